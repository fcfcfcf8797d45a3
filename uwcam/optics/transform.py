"""The two-channel intensity–range transform (docs/physics.md §3)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray


def pair_path_length(
    signal_i: ArrayLike,
    signal_j: ArrayLike,
    attenuation_difference: float,
    constant_ratio: float,
) -> NDArray[np.floating]:
    """Optical path length d_T (m) from two channels: ln((E_i/E_j)·U_ij) / V_ij.

    signal_i, signal_j: dark-corrected linear signals E_i, E_j, any equal shape.
    attenuation_difference: V_ij = c_j − c_i in 1/m (must be non-zero).
    constant_ratio: U_ij = (K_j ρ_j) / (K_i ρ_i), dimensionless, > 0.
    Pixels where either signal is not positive give NaN.
    """
    if attenuation_difference == 0:
        raise ValueError("attenuation_difference is 0: two channels with equal attenuation carry no range")
    if not constant_ratio > 0:
        raise ValueError(f"constant_ratio must be positive, got {constant_ratio}")
    e_i = np.asarray(signal_i, dtype=np.float64)
    e_j = np.asarray(signal_j, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where((e_i > 0) & (e_j > 0), e_i / e_j, np.nan)
        return np.log(ratio * constant_ratio) / attenuation_difference


def pair_path_variance(
    signal_i: ArrayLike,
    signal_j: ArrayLike,
    variance_i: ArrayLike,
    variance_j: ArrayLike,
    attenuation_difference: float,
) -> NDArray[np.floating]:
    """Variance of d_T (m²) for one pair: (σ_i²/E_i² + σ_j²/E_j²) / V_ij² (docs/physics.md §5)."""
    e_i = np.asarray(signal_i, dtype=np.float64)
    e_j = np.asarray(signal_j, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return (np.asarray(variance_i) / e_i**2 + np.asarray(variance_j) / e_j**2) / attenuation_difference**2
