"""Camera noise model: variance of a pixel value as a function of its signal."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray


def signal_variance(
    signal: ArrayLike,
    read_noise: ArrayLike,
    shot_gain: ArrayLike,
    quantisation_step: ArrayLike = 1.0,
) -> NDArray[np.floating]:
    """Variance σ² (DN²) of a dark-corrected signal E (DN).

    σ² = read_noise² + shot_gain·E + quantisation_step²/12, with E clipped at 0.
    read_noise: rms read noise in DN; shot_gain: DN per photo-electron (shot-noise
    variance per DN of signal). Per-channel parameters broadcast against the
    last axis of ``signal`` when given as length-N arrays.
    """
    e = np.maximum(np.asarray(signal, dtype=np.float64), 0.0)
    read = np.asarray(read_noise, dtype=np.float64)
    return read**2 + np.asarray(shot_gain, dtype=np.float64) * e + np.asarray(quantisation_step, dtype=np.float64) ** 2 / 12.0


@dataclass(frozen=True)
class NoiseModel:
    """Noise of one channel: read noise (DN rms), shot gain (DN/e⁻), quantisation step (DN)."""

    read_noise: float
    shot_gain: float
    quantisation_step: float = 1.0

    def variance(self, signal: ArrayLike) -> NDArray[np.floating]:
        """σ² in DN² at dark-corrected signal ``signal`` (DN)."""
        return signal_variance(signal, self.read_noise, self.shot_gain, self.quantisation_step)
