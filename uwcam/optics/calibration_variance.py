"""How the calibration's own uncertainty reaches every pixel's range.

The fused path length of DESIGN.md §5 is d_T = −Σ w_k (c_k − c̄)(y_k − ȳ) / S with
y_k = ln E_k − b_k and S = Σ w_k (c_k − c̄)². Its sensitivity to the calibration is

    ∂d_T/∂b_k = h_k,   ∂d_T/∂V_k = −d_T·h_k,   h_k = w_k (c_k − c̄) / S

(a change δ in c_k acts like a change δ·d_T in y_k; the reference's c and b are fixed by
definition, and Σ h_k = 0 so a common shift changes nothing). With Cvv, Cvb, Cbb the
calibration's covariances of attenuation differences V and log constants b,

    Var_cal(d_T) = hᵀ (Cbb − d_T (Cvb + Cvbᵀ) + d_T² Cvv) h.

Unlike pixel noise, this error is the same for every frame and every neighbouring pixel:
averaging does not reduce it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray


def calibration_path_variance(
    weight: ArrayLike,
    attenuation: ArrayLike,
    path_length: ArrayLike,
    cvv: ArrayLike,
    cvb: ArrayLike,
    cbb: ArrayLike,
) -> NDArray[np.float64]:
    """Var_cal(d_T) in m² for pixels (...) from their fusion weights.

    weight: (..., N) w_k = E_k²/σ_k² (0 for unusable channels); attenuation: (N,) c_k in 1/m
    (any offset); path_length: (...) d_T in metres; cvv, cvb, cbb: (N, N) covariances of
    attenuation differences (1/m)², of attenuation differences with log constants (1/m, row V,
    column b) and of log constants. NaN where the pixel has no spread of attenuation.
    """
    w = np.asarray(weight, dtype=np.float64)
    c = np.asarray(attenuation, dtype=np.float64)
    d = np.asarray(path_length, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        sw = w.sum(axis=-1, keepdims=True)
        c_mean = (w * c).sum(axis=-1, keepdims=True) / sw
        dc = c - c_mean
        spread = (w * dc * dc).sum(axis=-1, keepdims=True)
        h = w * dc / spread
    vv = np.einsum("...k,kl,...l->...", h, np.asarray(cvv, dtype=np.float64), h)
    vb = np.einsum("...k,kl,...l->...", h, np.asarray(cvb, dtype=np.float64), h)
    bb = np.einsum("...k,kl,...l->...", h, np.asarray(cbb, dtype=np.float64), h)
    return bb - 2.0 * d * vb + d * d * vv
