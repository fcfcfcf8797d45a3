"""A known range fixes an unknown surface reflectance ratio (docs/physics.md §8)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray


def surface_log_constant(
    signal: ArrayLike,
    path_length: ArrayLike,
    attenuation: ArrayLike,
    reference: int = 0,
) -> NDArray[np.float64]:
    """Per-channel log constant b_k = ln(K_k ρ_k / K_ref ρ_ref) of a surface of known range.

    Inverts y_k = b_k − (c_k − c_ref)·d_T: b_k = ln(E_k/E_ref) + (c_k − c_ref)·d_T.
    signal: (M, N) dark-corrected signals at M pixels with known path length
    (M,) in metres; attenuation: (N,) c_k in 1/m (or differences). Returns the
    (N,) estimate pooled over the M pixels as the log of the summed ratios, which
    weights bright pixels more and is robust to noise in dim ones.
    """
    e = np.asarray(signal, dtype=np.float64)
    d = np.asarray(path_length, dtype=np.float64)
    c = np.asarray(attenuation, dtype=np.float64)
    if e.ndim != 2 or d.shape != (e.shape[0],) or c.shape != (e.shape[1],):
        raise ValueError(f"need signal (M, N), path_length (M,), attenuation (N,); got {e.shape}, {d.shape}, {c.shape}")
    ok = np.all(e > 0, axis=1) & np.isfinite(d)
    if not ok.any():
        raise ValueError("no pixel with a positive signal in every channel and a finite path length")
    e, d = e[ok], d[ok]
    dc = c - c[reference]
    # E_k·exp(dc_k·d) removes attenuation pixel by pixel; sum before the log.
    corrected = e * np.exp(dc[None, :] * d[:, None])
    total = corrected.sum(axis=0)
    return np.log(total / total[reference])


def reflectance_ratio_from_range(
    signal: ArrayLike,
    path_length: ArrayLike,
    attenuation: ArrayLike,
    target_log_constant: ArrayLike,
    reference: int = 0,
) -> NDArray[np.float64]:
    """(ρ_k/ρ_ref)(surface) / (ρ_k/ρ_ref)(target), per channel, from a known range.

    Multiply a profile's target reflectance ratios by this to describe the surface.
    """
    b_surface = surface_log_constant(signal, path_length, attenuation, reference)
    b_target = np.asarray(target_log_constant, dtype=np.float64)
    return np.exp(b_surface - (b_target - b_target[reference]))
