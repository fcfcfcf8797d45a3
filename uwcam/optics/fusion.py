"""Multichannel fusion by weighted least squares (docs/physics.md §5).

Per pixel, y_k = ln E_k − b_k = a − c_k·d_T with an unknown common offset a.
With weights w_k = E_k²/σ_k² the estimate and its variance are

    d_T = −Σ w_k (c_k − c̄)(y_k − ȳ) / Σ w_k (c_k − c̄)²,   Var(d_T) = 1 / Σ w_k (c_k − c̄)².

The calibration knows each c_k only to its uncertainty: where the usable channels' spread of
attenuation, Σ_{k<l} w_k w_l (c_k − c_l)², is not above 3² times what that uncertainty alone gives
it, Σ_{k<l} w_k w_l Var(c_k − c_l), the pixel has no range (for two channels: |c_k − c_l| ≤ 3σ).

This module is the readable float64 reference; ``uwcam.optics.kernels`` computes the
same thing in one compiled pass for the frame loop.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

def fused_path_length(
    signal: ArrayLike,
    attenuation: ArrayLike,
    log_constant: ArrayLike,
    variance: ArrayLike,
    usable: ArrayLike | None = None,
    attenuation_covariance: ArrayLike | None = None,
    significance: float = 3.0,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Fused path length d_T (m) and its variance (m²) from N ≥ 2 channels.

    signal: (..., N) dark-corrected linear signals E_k (any numeric dtype).
    attenuation: (N,) c_k in 1/m; only differences matter, so c_k − c_ref works.
    log_constant: (N,) b_k = ln(K_k ρ_k), likewise only differences matter.
    variance: (..., N) or (N,) σ_k² of E_k in the same units squared.
    usable: optional (..., N) bool; False channels get weight 0 (below floor, saturated).
    attenuation_covariance: optional (N, N) covariance of the c_k, (1/m)²: the usable channels'
    attenuations must differ by more than ``significance`` of its standard deviations.

    Returns (path_length, path_variance), each of shape (...). Pixels without two
    usable channels of different attenuation get NaN in both.
    """
    e = np.asarray(signal, dtype=np.float64)
    c = np.asarray(attenuation, dtype=np.float64)
    b = np.asarray(log_constant, dtype=np.float64)
    n = e.shape[-1]
    if n < 2:
        raise ValueError(f"fusion needs at least 2 channels, got {n}")
    if c.shape != (n,) or b.shape != (n,):
        raise ValueError(f"attenuation and log_constant must have shape ({n},), got {c.shape} and {b.shape}")
    ok = e > 0
    if usable is not None:
        ok &= np.asarray(usable, dtype=bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(ok, e * e / np.asarray(variance, dtype=np.float64), 0.0)
        y = np.where(ok, np.log(np.where(ok, e, 1.0)) - b, 0.0)
    # Two passes (weighted means first, then centred sums), in coordinates shifted to
    # the heaviest channel's (c, y): the common offset a of y then cannot cancel digits
    # away, and a channel whose weight dwarfs the others sits exactly at the origin.
    sw = w.sum(axis=-1)
    heaviest = np.argmax(w, axis=-1)[..., None]
    c_rel = c - c[heaviest]
    y_rel = y - np.take_along_axis(y, heaviest, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        c_mean = (w * c_rel).sum(axis=-1) / sw
        y_mean = (w * y_rel).sum(axis=-1) / sw
        dc = c_rel - c_mean[..., None]
        spread = (w * dc * dc).sum(axis=-1)
        cov = (w * dc * (y_rel - y_mean[..., None])).sum(axis=-1)
        # A range needs two usable channels of different attenuation, tested exactly.
        distinct = np.where(ok, c, -np.inf).max(axis=-1) > np.where(ok, c, np.inf).min(axis=-1)
        bad = ~distinct | ~(spread > 0)
        if attenuation_covariance is not None:
            cvv = np.asarray(attenuation_covariance, dtype=np.float64)
            if cvv.shape != (n, n):
                raise ValueError(f"attenuation_covariance must have shape ({n}, {n}), got {cvv.shape}")
            pairs = [(k, m) for k in range(n) for m in range(k + 1, n)]
            between = sum(w[..., k] * w[..., m] * (c[k] - c[m]) ** 2 for k, m in pairs)
            by_chance = sum(w[..., k] * w[..., m] * (cvv[k, k] + cvv[m, m] - 2 * cvv[k, m]) for k, m in pairs)
            bad |= ~(between > significance**2 * by_chance)
        path = np.where(bad, np.nan, -cov / spread)
        var = np.where(bad, np.nan, 1.0 / spread)
    return path, var
