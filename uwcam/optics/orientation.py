"""Surface orientation: Kirlin's multichannel Gauss–Newton step, and normals from a range map.

Kirlin's model (lamp at the camera) of the irradiance a pixel receives in channel k from a
Lambertian surface at range d (metres) whose normal makes the angle γ with the line of sight:

    T_k(d, cos γ) = s_k · cos γ · exp(−2 α_k d) / d²

with α_k the channel's absolute attenuation (1/m) and s_k its scale (K_k ρ_k f / (π m²), in the
irradiance's units). Expanding about a nominal (d0, cos γ0) to second order in d,

    E_k − T_k(d0, cos γ0) ≈ ∂T_k/∂cos γ · δcos γ + ∂T_k/∂d · δd + ½ ∂²T_k/∂d² · δd²

is linear in [δcos γ, δd, δd²] (δd² taken as a third unknown, as Kirlin does), solved by
(weighted) least squares over the N ≥ 3 channels. Iterated from the range that the attenuation
ratios give, it returns the incidence angle of every surface patch; it needs the absolute
radiometric calibration (α_k and s_k). :func:`normals_from_range` is the calibration-free
complement: surface normals from the gradient of the range map.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from uwcam.optics.geometry import Intrinsics, pixel_rays


def transfer(attenuation: ArrayLike, scale: ArrayLike, range_m: ArrayLike, cos_incidence: ArrayLike) -> NDArray[np.float64]:
    """T_k(d, cos γ), shape (..., N): ``attenuation`` (N,) 1/m, ``scale`` scalar or (N,),
    ``range_m`` and ``cos_incidence`` broadcasting over the leading axes."""
    a = np.asarray(attenuation, dtype=np.float64)
    d = np.asarray(range_m, dtype=np.float64)[..., None]
    c = np.asarray(cos_incidence, dtype=np.float64)[..., None]
    return np.asarray(scale, dtype=np.float64) * c * np.exp(-2.0 * a * d) / d**2


def sensitivity(attenuation: ArrayLike, scale: ArrayLike, range_m: ArrayLike, cos_incidence: ArrayLike) -> NDArray[np.float64]:
    """Kirlin's sensitivity matrix G, shape (..., N, 3): columns ∂T/∂cos γ, ∂T/∂d, ½ ∂²T/∂d²."""
    a = np.asarray(attenuation, dtype=np.float64)
    d = np.asarray(range_m, dtype=np.float64)[..., None]
    c = np.asarray(cos_incidence, dtype=np.float64)[..., None]
    s = np.asarray(scale, dtype=np.float64)
    e = s * np.exp(-2.0 * a * d)
    g = np.empty(np.broadcast_shapes(e.shape, c.shape) + (3,))
    g[..., 0] = e / d**2
    g[..., 1] = -2.0 * c * e * (a * d + 1.0) / d**3
    g[..., 2] = c * e * (2.0 * a**2 / d**2 + 4.0 * a / d**3 + 3.0 / d**4)
    return g


def kirlin_step(irradiance: ArrayLike, attenuation: ArrayLike, scale: ArrayLike, range_m: ArrayLike,
                incidence_deg: ArrayLike, weights: ArrayLike | None = None) -> NDArray[np.float64]:
    """One Gauss–Newton step about (range_m, incidence_deg): array (..., 3) = [δcos γ, δd, δd²].

    ``irradiance`` (..., N) in the units of ``scale``; ``attenuation`` (N,) absolute, 1/m;
    ``scale`` scalar or (N,); ``range_m`` (metres) and ``incidence_deg`` (degrees) scalars or
    arrays broadcasting over the leading axes; ``weights`` (..., N) optional, e.g. 1/σ_k² (the
    D_I⁻¹ of the method); by default every channel counts by its relative error, 1/T_k².
    """
    e = np.asarray(irradiance, dtype=np.float64)
    cos0 = np.cos(np.radians(np.asarray(incidence_deg, dtype=np.float64)))
    t0 = transfer(attenuation, scale, range_m, cos0)
    g = sensitivity(attenuation, scale, range_m, cos0)
    w = 1.0 / t0**2 if weights is None else np.asarray(weights, dtype=np.float64)
    shape = np.broadcast_shapes(e.shape, t0.shape, w.shape)
    residual = np.broadcast_to(e - t0, shape)
    w = np.broadcast_to(w, shape)
    g = np.broadcast_to(g, shape + (3,))
    gtw = np.swapaxes(g, -1, -2) * w[..., None, :]
    normal = gtw @ g
    rhs = (gtw @ residual[..., None])[..., 0]
    return np.linalg.solve(normal, rhs[..., None])[..., 0]


def kirlin_estimate(irradiance: ArrayLike, attenuation: ArrayLike, scale: ArrayLike, range_m: ArrayLike,
                    incidence_deg: ArrayLike, weights: ArrayLike | None = None, iterations: int = 20,
                    tolerance_m: float = 1e-6) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """Iterate :func:`kirlin_step` from (range_m, incidence_deg), seeded e.g. with the fused range.

    Returns (range_m, incidence_deg, converged), each shaped like the leading axes: converged is
    False where the range step was still above ``tolerance_m`` after ``iterations`` steps or the
    estimate left the physical domain (range ≤ 0); there the estimates are NaN.
    """
    e = np.asarray(irradiance, dtype=np.float64)
    lead = e.shape[:-1]
    d = np.array(np.broadcast_to(np.asarray(range_m, dtype=np.float64), lead))
    cos = np.array(np.broadcast_to(np.cos(np.radians(np.asarray(incidence_deg, dtype=np.float64))), lead))
    converged = np.zeros(lead, dtype=bool)
    for _ in range(iterations):
        step = kirlin_step(e, attenuation, scale, d, np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))), weights)
        d = d + step[..., 1]
        # A surface seen at all faces the camera: cos γ stays within (0, 1].
        cos = np.clip(cos + step[..., 0], 1e-6, 1.0)
        converged = np.abs(step[..., 1]) < tolerance_m
        bad = ~(d > 0) | ~np.isfinite(d)
        d = np.where(bad, np.nan, d)
        if np.all(converged | bad):
            break
    converged &= np.isfinite(d)
    incidence = np.where(converged, np.degrees(np.arccos(cos)), np.nan)
    return np.where(converged, d, np.nan), incidence, converged


def normals_from_range(range_m: ArrayLike, intrinsics: Intrinsics, window: int = 7) -> NDArray[np.float32]:
    """Unit surface normals (H, W, 3) in the camera frame (x right, y down, z forward), facing
    the camera, from the gradient of a range map (metres along each pixel's ray). Needs no
    radiometric calibration.

    A single frame's range is noisy from pixel to pixel, so the surface points are averaged over
    ``window`` × ``window`` pixels (pixels without range left out) and differentiated across the
    window (1: plain central differences). NaN where the pixel has no range or the window reaches
    outside the image or holds no range on one side."""
    if window < 1 or window % 2 == 0:
        raise ValueError(f"window must be an odd number of pixels ≥ 1, got {window}")
    r = np.asarray(range_m, dtype=np.float64)
    h, w = r.shape
    valid = np.isfinite(r)
    points = np.where(valid, r, 0.0)[..., None] * pixel_rays(intrinsics, h, w)
    if window > 1:
        # Counts of valid pixels; OpenCV's running sums leave rounding residue (1e-16 where the
        # window holds none), which would divide into an infinite point.
        weight = np.rint(cv2.boxFilter(valid.astype(np.float64), -1, (window, window), normalize=False,
                                       borderType=cv2.BORDER_CONSTANT))
        summed = cv2.boxFilter(points, -1, (window, window), normalize=False, borderType=cv2.BORDER_CONSTANT)
        with np.errstate(invalid="ignore", divide="ignore"):
            points = np.where(weight[..., None] > 0, summed / weight[..., None], np.nan)
    else:
        points[~valid] = np.nan
    k = max(window // 2, 1)
    du = np.full_like(points, np.nan)
    dv = np.full_like(points, np.nan)
    du[:, k:-k] = points[:, 2 * k:] - points[:, : -2 * k]
    dv[k:-k] = points[2 * k:] - points[: -2 * k]
    n = np.cross(du, dv)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    # Face the camera: the normal points back along the line of sight.
    flip = np.sum(n * points, axis=-1) > 0
    n[flip] *= -1.0
    n[~valid] = np.nan
    return n.astype(np.float32)
