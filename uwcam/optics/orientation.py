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

import math

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


def plane_normal(range_m: ArrayLike, rays: ArrayLike) -> NDArray[np.float64] | None:
    """Unit normal (3,) in the camera frame, facing the camera, of the plane that best fits ranges
    (N,) metres along unit rays (N, 3); pixels with a NaN are left out. None with fewer than three
    ranges or a degenerate fit.

    A plane n·P = d meets the ray u at r = d / (n·u), so 1/r = (n/d)·u is linear in the ray and
    the fit is ordinary least squares with the noise where it is, in the range. (A fit of the
    points' least spread would count the range noise, which runs along the line of sight, as
    spread of the surface and tilt the plane away from the camera.) Far steadier than averaging
    per-pixel normals, each of which differentiates noise over a few pixels."""
    r = np.asarray(range_m, dtype=np.float64).reshape(-1)
    u = np.asarray(rays, dtype=np.float64).reshape(-1, 3)
    ok = np.isfinite(r) & (r > 0) & np.all(np.isfinite(u), axis=1)
    if ok.sum() < 3:
        return None
    p, _, rank, _ = np.linalg.lstsq(u[ok], 1.0 / r[ok], rcond=None)
    norm = float(np.linalg.norm(p))
    if rank < 3 or not np.isfinite(norm) or norm == 0.0:
        return None
    return -p / norm  # p = n/d points away from the camera


def beam_pattern(rays: ArrayLike, half_angle_deg: float | None) -> NDArray[np.float64]:
    """Relative lamp intensity exp(−k(1 − cos θ)) toward unit rays (..., 3), θ off the camera's z
    axis, half power at ``half_angle_deg`` (k = ln 2 / (1 − cos θ½)); 1 everywhere for None."""
    u = np.asarray(rays, dtype=np.float64)
    if half_angle_deg is None:
        return np.ones(u.shape[:-1])
    k = np.log(2.0) / (1.0 - np.cos(np.radians(half_angle_deg)))
    return np.exp(-k * (1.0 - u[..., 2]))


def block_means(values: NDArray, valid: NDArray[np.bool_], block: int,
                min_fraction: float = 0.5) -> NDArray[np.float32]:
    """Means of ``values`` (H, W) or (H, W, C) over ``block`` × ``block`` pixel blocks, counting only
    ``valid`` pixels: (H // block, W // block[, C]), NaN where fewer than ``min_fraction`` of a
    block's pixels are valid. Pixels beyond the last whole block are left out; ``valid`` may
    already be cropped to the whole blocks."""
    h, w = values.shape[:2]
    bh, bw = h // block, w // block
    if bh == 0 or bw == 0:
        raise ValueError(f"an image of {w}×{h} pixels holds no whole block of {block}×{block}")
    hh, ww = bh * block, bw * block
    v = np.ascontiguousarray(values[:hh, :ww], dtype=np.float32)
    m = np.ascontiguousarray(valid[:hh, :ww], dtype=bool)
    # Zero the pixels left out bit by bit (NaN · 0 would stay NaN); INTER_AREA with a whole factor
    # is then the exact block sum over block² (OpenCV, a fraction of numpy's time).
    v = cv2.bitwise_and(v, v, mask=m.view(np.uint8))
    size = (bw, bh)
    total = cv2.resize(v, size, interpolation=cv2.INTER_AREA).reshape((bh, bw) + values.shape[2:])
    fraction = cv2.resize(m.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    f = fraction if total.ndim == 2 else fraction[..., None]
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = total / f
    mean[fraction < min_fraction] = np.nan
    return mean.astype(np.float32, copy=False)


def block_irradiance(data: NDArray, range_map: NDArray, dark: ArrayLike, floor: ArrayLike, saturation: float,
                     block: int, background: NDArray | None = None,
                     min_fraction: float = 0.5) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.bool_]]:
    """Per ``block`` × ``block`` block, over the pixels that have a range and every channel above its
    floor and below saturation: the mean dark-corrected irradiance (bh, bw, N), the usable pixels'
    share (bh, bw) and the mask (H', W') of those pixels (H', W' whole blocks only); NaN irradiance
    where the share is below ``min_fraction``.

    ``data`` (H, W, N) raw; ``range_map`` (H, W), NaN where none; ``dark`` and ``floor`` (N,) DN;
    ``background`` (H, W, N) light not from the lamp, subtracted first. Raw integer frames of up
    to four channels without a background are masked and summed by OpenCV on the raw codes (a
    few ms at 720p); anything else takes the same steps in numpy."""
    h, w = range_map.shape
    bh, bw = h // block, w // block
    if bh == 0 or bw == 0:
        raise ValueError(f"an image of {w}×{h} pixels holds no whole block of {block}×{block}")
    hh, ww = bh * block, bw * block
    raw = data[:hh, :ww]
    dark = np.asarray(dark, np.float64)
    floor = np.asarray(floor, np.float64)
    n = raw.shape[-1]
    fast = background is None and raw.dtype in (np.uint8, np.uint16) and n <= 4
    if fast:
        raw = np.ascontiguousarray(raw)
        # Integer codes: E > dark + floor ⇔ code ≥ ⌊dark + floor⌋ + 1; code < saturation ⇔ ≤ ⌈saturation⌉ − 1.
        low = np.floor(dark + np.maximum(floor, 0.0)) + 1.0
        high = np.full(n, float(np.ceil(saturation) - 1.0))
        mask = cv2.inRange(raw, tuple(low.tolist()), tuple(high.tolist())) > 0
        mask &= np.isfinite(range_map[:hh, :ww])
        summed = cv2.bitwise_and(raw, raw, mask=mask.view(np.uint8)).astype(np.float32)
    else:
        e = raw.astype(np.float32) - dark.astype(np.float32)
        if background is not None:
            e -= background[:hh, :ww]
        mask = np.isfinite(range_map[:hh, :ww]) & np.all((e > floor.astype(np.float32)) & (raw < saturation), axis=-1)
        summed = np.where(mask[..., None], e, 0.0).astype(np.float32)
    share = cv2.resize(mask.astype(np.float32), (bw, bh), interpolation=cv2.INTER_AREA)
    total = cv2.resize(summed, (bw, bh), interpolation=cv2.INTER_AREA).reshape(bh, bw, n)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = total / share[..., None]
    if fast:
        mean -= dark.astype(np.float32)
    mean[share < min_fraction] = np.nan
    return mean.astype(np.float32), share, mask


def surface_scale(irradiance: ArrayLike, camera_range: ArrayLike, attenuation: ArrayLike,
                  cos_incidence: ArrayLike, lamp_radius: float = 0.0, beam: ArrayLike = 1.0) -> NDArray[np.float64]:
    """The scale s_k (N,) of Kirlin's model at pixels of known range and incidence: the inverse of
    E_k = s_k · B · cos γ · exp(−2 α_k d) / (d + r)², pooled over the M pixels as
    Σ E_k / Σ B cos γ exp(−2 α_k d)/(d + r)² (bright pixels count most).

    ``irradiance`` (M, N) dark-corrected; ``camera_range`` d (M,) metres along each pixel's ray;
    ``attenuation`` α (N,) absolute, 1/m; ``cos_incidence`` (M,) or scalar; ``lamp_radius`` r in
    metres (0: a point source, Kirlin's 1/d²); ``beam`` B (M,) or scalar, the lamp's relative
    intensity toward each pixel."""
    e = np.asarray(irradiance, dtype=np.float64)
    d = np.asarray(camera_range, dtype=np.float64)
    a = np.asarray(attenuation, dtype=np.float64)
    if e.ndim != 2 or d.shape != (e.shape[0],) or a.shape != (e.shape[1],):
        raise ValueError(f"need irradiance (M, N), camera_range (M,), attenuation (N,); got {e.shape}, {d.shape}, {a.shape}")
    geometric = np.broadcast_to(np.asarray(beam, np.float64) * np.asarray(cos_incidence, np.float64), d.shape)
    model = geometric[:, None] * np.exp(-2.0 * a[None, :] * d[:, None]) / (d[:, None] + lamp_radius) ** 2
    ok = np.all(np.isfinite(e) & np.isfinite(model), axis=1) & (geometric > 0)
    if not ok.any():
        raise ValueError("no pixel with a finite signal, range and a surface facing the lamp")
    return e[ok].sum(axis=0) / model[ok].sum(axis=0)


def channel_reach_m(attenuation: float, scale: float, floor: float, lamp_radius: float = 0.0) -> float:
    """The camera range (m) beyond which a surface square to the lamp returns no more than ``floor``
    in a channel: the root of s · exp(−2 α d) / (d + r)² = floor, which falls monotonically in d.
    inf for a floor of 0 (never reached); 0 when even 1 mm away the signal is at the floor."""
    if floor <= 0:
        return math.inf
    if not (scale > 0 and attenuation >= 0 and math.isfinite(scale)):
        return 0.0

    def excess(d: float) -> float:  # ln T(d) − ln floor
        return math.log(scale) - 2.0 * attenuation * d - 2.0 * math.log(d + lamp_radius) - math.log(floor)

    near, far = 1e-3, 1e4
    if excess(near) <= 0:
        return 0.0
    if excess(far) > 0:
        return math.inf
    for _ in range(100):  # bisection to well below a millimetre
        mid = 0.5 * (near + far)
        near, far = (mid, far) if excess(mid) > 0 else (near, mid)
    return near


def measurable_range_m(attenuation: ArrayLike, scale: ArrayLike, floor: ArrayLike, lamp_radius: float = 0.0) -> float:
    """The longest camera range (m) at which ranging can still work: at least two channels of
    different attenuation return more than their noise floor from a surface like the one whose
    scale s_k was measured, square to the lamp (Kirlin's model, lamp at the camera). The second
    longest reach among channels of distinct attenuation; inf where no floor limits two of them."""
    a = np.asarray(attenuation, dtype=np.float64)
    reach: dict[float, float] = {}
    for alpha, s, f in zip(a, np.asarray(scale, dtype=np.float64), np.asarray(floor, dtype=np.float64)):
        r = channel_reach_m(float(alpha), float(s), float(f), lamp_radius)
        reach[float(alpha)] = max(reach.get(float(alpha), 0.0), r)
    ranked = sorted(reach.values(), reverse=True)
    return ranked[1] if len(ranked) >= 2 else 0.0


def incidence_from_blocks(irradiance: ArrayLike, range_m: ArrayLike, attenuation: ArrayLike, scale: ArrayLike,
                          lamp_radius: float = 0.0, iterations: int = 8, tolerance_m: float = 1e-4,
                          irradiance_variance: ArrayLike | None = None,
                          range_variance: ArrayLike | None = None) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Kirlin's Gauss–Newton iteration, vectorised over many pixels or blocks, for the daemon's loop.

    The model is T_k = s_k · cos γ · exp(−2 α_k d) / (d + r)² (lamp at the camera; r = 0 is
    Kirlin's point source, :func:`kirlin_step`); each step solves the weighted (1/T_k²) normal
    equations of the columns ∂T/∂cos γ, ∂T/∂d, ½ ∂²T/∂d² for [δcos γ, δd, δd²].

    ``irradiance`` (..., N) dark-corrected; ``range_m`` (...) the seed (the fused camera range);
    ``attenuation`` α (N,) absolute, 1/m; ``scale`` (N,) or (..., N), s_k including the lamp's beam
    toward each block. The seed of cos γ is the model inverted at the seed range.

    ``irradiance_variance`` (..., N): the variance of each irradiance, which weighs the channels
    (D_I⁻¹); None: 1/T_k², equal relative errors. ``range_variance`` (...): the variance of the seed
    range, which then enters the least squares as a fourth observation of d (the fused range is a
    measurement, not only a start); None or infinite: Kirlin's three-channel solve alone. With
    three channels that solve is exactly determined and, the channels' attenuations being close
    beside the 2/d of spreading, ill-conditioned: relative errors of 10⁻³ in the irradiance move γ
    by degrees. The fused range steadies it. Returns (range_m,
    incidence_deg), NaN where the seed or the irradiance was missing, the iteration did not settle
    within ``tolerance_m`` or left the domain (d ≤ 0, cos γ outside (0, 1.05]: a brighter surface
    than any facing the lamp squarely means a wrong scale or reflectance there, not an angle).
    """
    e = np.asarray(irradiance, dtype=np.float64)
    a = np.asarray(attenuation, dtype=np.float64)
    s = np.broadcast_to(np.asarray(scale, dtype=np.float64), e.shape)
    d = np.array(np.broadcast_to(np.asarray(range_m, dtype=np.float64), e.shape[:-1]))
    r = float(lamp_radius)
    ok = np.all(np.isfinite(e) & (e > 0) & np.isfinite(s) & (s > 0), axis=-1) & np.isfinite(d) & (d > 0)
    var_e = None if irradiance_variance is None else np.broadcast_to(np.asarray(irradiance_variance, np.float64), e.shape)
    if var_e is not None:
        ok &= np.all(np.isfinite(var_e) & (var_e > 0), axis=-1)
        var_e = var_e[ok]
    prior_w = None
    if range_variance is not None:
        var_d = np.broadcast_to(np.asarray(range_variance, np.float64), d.shape)[ok]
        with np.errstate(divide="ignore"):
            prior_w = np.where(np.isfinite(var_d) & (var_d > 0), 1.0 / var_d, 0.0)
    e, s, d = e[ok], s[ok], d[ok]
    measured = d.copy()
    # Seed cos γ: the model inverted at the seed range, channel by channel, in the mean.
    cos = np.mean(e * (d[:, None] + r) ** 2 * np.exp(2.0 * a * d[:, None]) / s, axis=-1)
    cos = np.clip(cos, 1e-3, 1.0)
    settled = np.zeros(d.shape, bool)
    dead = np.zeros(d.shape, bool)
    # Blocks that run off the domain overflow or divide by zero on the way; they are marked dead.
    with np.errstate(all="ignore"):
        for _ in range(iterations):
            q = d[:, None] + r
            shape = s * np.exp(-2.0 * a * d[:, None]) / q**2  # ∂T/∂cos γ
            t0 = cos[:, None] * shape
            g = np.empty(e.shape + (3,))
            g[..., 0] = shape
            slope = 2.0 * a + 2.0 / q  # −(∂T/∂d)/T
            g[..., 1] = -t0 * slope
            g[..., 2] = 0.5 * t0 * (slope**2 + 2.0 / q**2)
            w = 1.0 / t0**2 if var_e is None else 1.0 / var_e
            gtw = np.swapaxes(g, -1, -2) * w[:, None, :]
            normal = gtw @ g
            rhs = gtw @ (e - t0)[..., None]
            if prior_w is not None:  # the fused range observed directly: a row [0, 1, 0]
                normal[:, 1, 1] += prior_w
                rhs[:, 1, 0] += prior_w * (measured - d)
            try:
                step = np.linalg.solve(normal, rhs)[..., 0]
            except np.linalg.LinAlgError:  # a singular block: solve one by one, NaN where singular
                step = np.stack([_solve_or_nan(m, v) for m, v in zip(normal, rhs)])
            d = d + step[:, 1]
            cos = cos + step[:, 0]
            settled = np.abs(step[:, 1]) < tolerance_m
            dead |= ~(np.isfinite(d) & (d > 0) & np.isfinite(cos))
            d[dead], cos[dead] = 1.0, 0.5  # parked; reported NaN
            settled &= ~dead
            if np.all(settled | dead):
                break
    good = settled & (cos > 0) & (cos <= 1.05)
    out_d = np.full(ok.shape, np.nan)
    out_g = np.full(ok.shape, np.nan)
    out_d[ok] = np.where(good, d, np.nan)
    out_g[ok] = np.where(good, np.degrees(np.arccos(np.clip(cos, 0.0, 1.0))), np.nan)
    return out_d, out_g


def _solve_or_nan(matrix: NDArray, rhs: NDArray) -> NDArray:
    try:
        return np.linalg.solve(matrix, rhs)[..., 0]
    except np.linalg.LinAlgError:
        return np.full(3, np.nan)
