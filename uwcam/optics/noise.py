"""Camera noise model: variance of a pixel value as a function of its signal.

Per channel, for a dark-corrected signal E (DN):

    σ² = read² + shot_gain·E + (fixed_pattern·E)² + step²/12

* read: dark and read noise (DN rms), the same at every signal level;
* shot_gain·E: photon shot noise (shot_gain in DN per photo-electron);
* (fixed_pattern·E)²: pixel response non-uniformity, the same in every frame but different
  from pixel to pixel, so it is noise for a single pixel's value against the truth;
* step²/12: quantisation of codes of size ``step``.

Read, shot and quantisation noise change from frame to frame (temporal); the fixed pattern
does not, which is how calibration tells them apart (see :func:`temporal_variance`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray


def signal_variance(
    signal: ArrayLike,
    read_noise: ArrayLike,
    shot_gain: ArrayLike,
    quantisation_step: ArrayLike = 1.0,
    fixed_pattern: ArrayLike = 0.0,
    dtype: type = np.float64,
) -> NDArray[np.floating]:
    """Total variance σ² (DN²) of a dark-corrected signal E (DN) against its expected value.

    σ² = read_noise² + shot_gain·E + (fixed_pattern·E)² + quantisation_step²/12, with E
    clipped at 0. read_noise: rms in DN; shot_gain: DN per photo-electron; fixed_pattern:
    relative rms of the pixel response non-uniformity (0.01 = 1 %). Per-channel parameters
    broadcast against the last axis of ``signal`` when given as length-N arrays. dtype: the
    arithmetic's precision (float32 for a test statistic's scale over a whole frame: half the
    memory traffic of float64).
    """
    e = np.maximum(np.asarray(signal, dtype=dtype), 0.0)
    fpn = np.asarray(fixed_pattern, dtype=dtype)
    return temporal_variance(e, read_noise, shot_gain, quantisation_step, dtype) + (fpn * e) ** 2


def temporal_variance(
    signal: ArrayLike, read_noise: ArrayLike, shot_gain: ArrayLike, quantisation_step: ArrayLike = 1.0,
    dtype: type = np.float64,
) -> NDArray[np.floating]:
    """Frame-to-frame variance (DN²): read_noise² + shot_gain·E + step²/12, E clipped at 0, in ``dtype``."""
    e = np.maximum(np.asarray(signal, dtype=dtype), 0.0)
    read = np.asarray(read_noise, dtype=dtype)
    return read**2 + np.asarray(shot_gain, dtype=dtype) * e + np.asarray(quantisation_step, dtype=dtype) ** 2 / 12.0


@dataclass(frozen=True)
class NoiseModel:
    """Noise of one channel: read noise (DN rms), shot gain (DN/e⁻), fixed pattern (relative rms),
    quantisation step (DN)."""

    read_noise: float
    shot_gain: float
    quantisation_step: float = 1.0
    fixed_pattern: float = 0.0

    def variance(self, signal: ArrayLike) -> NDArray[np.floating]:
        """Total σ² in DN² at dark-corrected signal ``signal`` (DN)."""
        return signal_variance(signal, self.read_noise, self.shot_gain, self.quantisation_step, self.fixed_pattern)

    def temporal(self, signal: ArrayLike) -> NDArray[np.floating]:
        """Frame-to-frame σ² in DN² (no fixed pattern)."""
        return temporal_variance(signal, self.read_noise, self.shot_gain, self.quantisation_step)
