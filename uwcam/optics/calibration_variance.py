"""How the calibration's own uncertainty reaches every pixel's range.

The fused path length of docs/physics.md §5 is d_T = −Σ w_k (c_k − c̄)(y_k − ȳ) / S with
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
    w = np.moveaxis(np.asarray(weight, dtype=np.float64), -1, 0)  # (N, ...): whole planes per channel
    c = np.asarray(attenuation, dtype=np.float64)
    d = np.asarray(path_length, dtype=np.float64)
    cvv, cvb, cbb = (np.asarray(m, dtype=np.float64) for m in (cvv, cvb, cbb))
    n = w.shape[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        sw = sum(w[k] for k in range(n))
        c_mean = sum(w[k] * c[k] for k in range(n)) / sw
        dc = [c[k] - c_mean for k in range(n)]
        h = [w[k] * dc[k] for k in range(n)]
        inv_spread = 1.0 / sum(h[k] * dc[k] for k in range(n))
    # Σ_kl h_k h_l (Cbb − d(Cvb + Cvbᵀ) + d² Cvv)_kl over the pairs with a non-zero coefficient.
    bb = vb = vv = 0.0
    for k in range(n):
        for m in range(k, n):
            twice = 1.0 if k == m else 2.0
            coef_b, coef_v = twice * cbb[k, m], twice * cvv[k, m]
            coef_bv = twice * (cvb[k, m] + cvb[m, k])
            if coef_b == 0 and coef_v == 0 and coef_bv == 0:
                continue
            pair = h[k] * h[m]
            bb = bb + coef_b * pair
            vb = vb + coef_bv * pair
            vv = vv + coef_v * pair
    with np.errstate(invalid="ignore"):
        return (bb - d * vb + d * d * vv) * inv_spread * inv_spread
