"""In-situ calibration from a target imaged at known distances (docs/physics.md §4).

The fitting functions are pure and work on per-image region statistics; :func:`calibrate`
measures those statistics on frames and assembles a :class:`CalibrationProfile`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from uwcam.fileio import UserInputError
from uwcam.optics.geometry import Intrinsics, pixel_rays, plane_camera_range
from uwcam.optics.noise import signal_variance
from uwcam.profile import (
    BackscatterSamples,
    CalibrationCovariance,
    CalibrationProfile,
    ChannelCalibration,
    Provenance,
    now_iso,
)

# A target region with more clipped pixels than this is refused rather than averaged.
MAX_SATURATED_FRACTION = 0.01
# Noise floor = backscatter at the black patch + this many σ of its pixel noise.
FLOOR_SIGMAS = 3.0
# Side of the box average applied before taking logs of the target (pixels).
SMOOTHING = 5
# Backscatter more than this many σ from 0 at any distance counts as measured (see calibrate_with_details);
# at 5σ clean water is almost never taken for murky (6 tests per calibration: ~4e-6).
BACKSCATTER_SIGMAS = 5.0
BACKSCATTER_FRACTION = 1e-3
# Brightness bins of the plate, each a point of the noise-model fit.
NOISE_BINS = 4

Box = tuple[int, int, int, int]  # x, y, width, height in pixels


@dataclass(frozen=True)
class NoisePoint:
    """Noise observed in one region of one distance's frames, per channel (DN, dark-corrected)."""

    mean: NDArray[np.float64]
    """(N,) mean signal E over the region."""
    mean_square: NDArray[np.float64]
    """(N,) mean of E² over the region (the fixed-pattern term goes with E², not with Ē²)."""
    spatial_variance: NDArray[np.float64]
    """(N,) pixel-to-pixel variance of the frames' average (second differences along rows:
    smooth illumination cancels): fixed pattern + temporal/frames."""
    temporal_variance: NDArray[np.float64] | None
    """(N,) frame-to-frame variance from the differences between frames; None with one frame."""
    frames: int
    count: int


def _interior(mask: NDArray[np.bool_], margin: int) -> NDArray[np.bool_]:
    if margin <= 0:
        return mask
    kernel = np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)
    return cv2.erode(mask.astype(np.uint8), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)


def noise_point(frames: list[NDArray] | NDArray, mask: ArrayLike, dark_level: ArrayLike = 0.0) -> NoisePoint:
    """Noise statistics of ``frames`` (m frames (H, W, N) of one static scene) inside ``mask`` (H, W).

    Temporal variance: per pixel, the unbiased variance over the m frames, averaged over the
    region. Spatial variance: of the frames' average, from second differences along rows,
    x[i−1] − 2x[i] + x[i+1], whose variance is 6σ² for independent pixel noise while a
    linear gradient of illumination cancels exactly.
    """
    stack = np.asarray(frames, dtype=np.float64)
    if stack.ndim == 3:
        stack = stack[None]
    m_frames = stack.shape[0]
    x = stack.mean(axis=0) - np.asarray(dark_level, dtype=np.float64)
    m = np.asarray(mask, dtype=bool)
    triple = m[:, 2:] & m[:, 1:-1] & m[:, :-2]
    count = int(triple.sum())
    if count < 2:
        raise UserInputError("a noise region holds fewer than 2 usable pixels; check the target and black patch regions")
    centre = x[:, 1:-1][triple]
    second = (x[:, :-2] - 2.0 * x[:, 1:-1] + x[:, 2:])[triple]
    spatial = second.var(axis=0) / 6.0
    temporal = None
    if m_frames >= 2:
        temporal = stack[:, :, 1:-1][:, triple].var(axis=0, ddof=1).mean(axis=0)
    return NoisePoint(centre.mean(axis=0), (centre**2).mean(axis=0), spatial, temporal, m_frames, count)


def _nonnegative_least_squares(a: NDArray, y: NDArray, w: NDArray) -> NDArray:
    """argmin Σ w (a·p − y)² over p ≥ 0, by trying every set of free parameters (few columns)."""
    n_par = a.shape[1]
    best, best_cost = np.zeros(n_par), float(np.sum(w * y**2))
    sw = np.sqrt(w)
    for subset in range(1, 2**n_par):
        cols = [j for j in range(n_par) if subset >> j & 1]
        sol, *_ = np.linalg.lstsq(a[:, cols] * sw[:, None], y * sw, rcond=None)
        if np.all(sol >= 0):
            p = np.zeros(n_par)
            p[cols] = sol
            cost = float(np.sum(w * (a @ p - y) ** 2))
            if cost < best_cost - 1e-12 * abs(best_cost):
                best, best_cost = p, cost
    return best


@dataclass(frozen=True)
class NoiseFit:
    """Per-channel noise model: σ² = read² + shot_gain·E + (fixed_pattern·E)² + step²/12."""

    read_noise: NDArray[np.float64]
    """(N,) DN rms."""
    shot_gain: NDArray[np.float64]
    """(N,) DN per photo-electron."""
    fixed_pattern: NDArray[np.float64]
    """(N,) relative rms of the pixel response non-uniformity."""
    method: str


def fit_noise(points: list[NoisePoint], quantisation_step: float = 1.0) -> NoiseFit:
    """Read noise, shot gain and fixed pattern per channel from region noise points.

    With repeated frames, the temporal variances give read and shot noise
    (t − step²/12 = read² + gain·E) and the spatial variance beyond temporal/frames gives the
    fixed pattern (s − t/m = fpn²·mean(E²)). With single frames, the spatial variances alone
    are fitted with all three terms. Every term is kept non-negative; a variance of 0 (noise-free
    frames) gives all terms 0, and users of the model fall back to the quantisation floor.
    Weights are 1/variance², so every point counts by its relative error.
    """
    if not points:
        raise ValueError("fit_noise needs at least one noise point")
    n = points[0].mean.shape[0]
    q = quantisation_step**2 / 12.0
    read2, gain, fpn2 = np.zeros(n), np.zeros(n), np.zeros(n)
    temporal = [p for p in points if p.temporal_variance is not None]
    for k in range(n):
        if temporal:
            e = np.array([p.mean[k] for p in temporal])
            t = np.array([p.temporal_variance[k] for p in temporal])
            w = 1.0 / np.maximum(t, q + 1e-12) ** 2
            read2[k], gain[k] = _nonnegative_least_squares(np.stack([np.ones_like(e), e], 1), t - q, w)
            e2 = np.array([p.mean_square[k] for p in temporal])
            s = np.array([p.spatial_variance[k] for p in temporal])
            t_model = read2[k] + gain[k] * np.maximum(e, 0) + q
            m = np.array([p.frames for p in temporal], dtype=np.float64)
            ws = 1.0 / np.maximum(s, q + 1e-12) ** 2
            fpn2[k] = _nonnegative_least_squares(e2[:, None], s - t_model / m, ws)[0]
        else:
            e = np.array([p.mean[k] for p in points])
            e2 = np.array([p.mean_square[k] for p in points])
            s = np.array([p.spatial_variance[k] for p in points])
            w = 1.0 / np.maximum(s, q + 1e-12) ** 2
            read2[k], gain[k], fpn2[k] = _nonnegative_least_squares(np.stack([np.ones_like(e), e, e2], 1), s - q, w)
    method = "temporal from repeated frames, fixed pattern beyond it" if temporal else "spatial spread of single frames"
    return NoiseFit(np.sqrt(read2), gain, np.sqrt(fpn2), method)


def fit_noise_model(
    means: ArrayLike, noise_variances: ArrayLike, quantisation_step: float = 1.0
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Read noise (DN rms) and shot gain (DN/e⁻) per channel from (mean, temporal variance) pairs (n, N).

    σ² − step²/12 = read² + gain·E by weighted non-negative least squares (see :func:`fit_noise`).
    """
    mu = np.asarray(means, dtype=np.float64)
    var = np.asarray(noise_variances, dtype=np.float64)
    pts = [NoisePoint(mu[i], mu[i] ** 2, var[i], var[i], 1, 2) for i in range(mu.shape[0]) if np.all(np.isfinite(var[i]))]
    if not pts:
        return np.zeros(mu.shape[1]), np.zeros(mu.shape[1])
    fit = fit_noise(pts, quantisation_step)
    return fit.read_noise, fit.shot_gain


def variance_floor(signal: ArrayLike, quantisation_step: float) -> NDArray[np.float64]:
    """The least variance (DN²) a value can have: its quantisation, step²/12, or for float data
    (step 0) the float32 rounding of the value itself (relative step 2⁻²³). Never 0 for E > 0."""
    e = np.abs(np.asarray(signal, dtype=np.float64))
    step = np.where(quantisation_step > 0, quantisation_step, np.maximum(e, 1e-30) * 2.0**-23)
    return step**2 / 12.0


def smoothed_log_signal(frame: ArrayLike, mask: ArrayLike, dark_level: ArrayLike = 0.0) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """ln E per pixel of a region after a 5×5 box average, and the (H, W) mask of pixels used.

    Averaging ln E per pixel keeps the calibration exactly linear in each pixel's own
    path length, however much d_T varies over a large target. The box average first
    divides the noise variance by 25, which makes the log's small-signal bias
    (−σ²/2E²) negligible; only pixels whose whole 5×5 box lies in the region are used,
    so nothing from outside it leaks in.
    """
    m = np.asarray(mask, dtype=bool)
    x = np.asarray(frame, dtype=np.float64) - np.asarray(dark_level, dtype=np.float64)
    kernel = np.ones((SMOOTHING, SMOOTHING), np.uint8)
    interior = cv2.erode(m.astype(np.uint8), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)
    if not interior.any():
        interior = m  # a region thinner than the box: use it unsmoothed
        smooth = x
    else:
        smooth = cv2.blur(x, (SMOOTHING, SMOOTHING), borderType=cv2.BORDER_REFLECT)
    values = smooth[interior]
    positive = np.all(values > 0, axis=-1)
    if not positive.any():
        raise UserInputError("the target region has no pixel with signal in every channel; check the lamp and the region")
    pixels = interior.copy()
    pixels[interior] = positive
    return np.log(values[positive]), pixels


def mean_weights(pixels: NDArray[np.bool_]) -> NDArray[np.float64]:
    """(H, W) the weight a_p with which each pixel's value enters the mean over ``pixels`` of the
    5×5 box averages: (interior boxes holding p)/(25·P)."""
    count = int(pixels.sum())
    if SMOOTHING > 1 and count and not np.array_equal(pixels, np.zeros_like(pixels)):
        return cv2.boxFilter(pixels.astype(np.float64), -1, (SMOOTHING, SMOOTHING), normalize=True,
                             borderType=cv2.BORDER_CONSTANT) / count
    return pixels / max(count, 1)


def log_mean_variance(pixels: NDArray[np.bool_], signal: NDArray, pixel_variance: NDArray) -> NDArray[np.float64]:
    """Variance (N,) of the mean over ``pixels`` of ln(5×5 box average of E), from independent pixel noise.

    Pixel p enters the mean with weight a_p (:func:`mean_weights`); the variance is
    Σ a_p² σ_p²/E_p² (σ_p², E_p: (H, W, N) per-pixel noise variance and signal).
    """
    share = mean_weights(pixels)
    e = np.maximum(np.asarray(signal, dtype=np.float64), 1e-30)
    rel = np.asarray(pixel_variance, dtype=np.float64) / e**2
    used = share > 0
    return np.einsum("p,pn->n", share[used] ** 2, rel[used])


@dataclass(frozen=True)
class LineFit:
    """y = intercept + slope·x fitted per channel, with standard uncertainties."""

    intercept: NDArray[np.float64]
    slope: NDArray[np.float64]
    intercept_std: NDArray[np.float64]
    slope_std: NDArray[np.float64]
    residuals: NDArray[np.float64]  # (n, N)


@dataclass(frozen=True)
class AttenuationFit:
    """Relative calibration: y_k = ln(E_k/E_ref) = b_k − V_k·d_T."""

    attenuation_difference: NDArray[np.float64]  # V_k = c_k − c_ref, 1/m
    attenuation_difference_std: NDArray[np.float64]
    log_constant: NDArray[np.float64]  # b_k
    log_constant_std: NDArray[np.float64]
    residuals: NDArray[np.float64]  # (n, N), natural-log units
    method: str
    covariance: NDArray[np.float64] | None = None
    """(2(N−1), 2(N−1)) joint covariance of [V_k…, b_k…] over the non-reference channels."""


def fit_lines(x: ArrayLike, y: ArrayLike, variance: ArrayLike | None = None) -> LineFit:
    """Weighted least squares y[:, k] = a_k + s_k·x per column k.

    x: (n,), y: (n, N), variance: (n, N) of y or None (equal weights). With n = 2 the
    fit is exact and uncertainties come from ``variance`` alone; with n ≥ 3 they are
    scaled up by the reduced χ² when the scatter exceeds the stated variances, so a
    bad distance or scattering shows up as uncertainty, not false confidence.
    """
    xv = np.asarray(x, dtype=np.float64)
    yv = np.asarray(y, dtype=np.float64)
    n = xv.shape[0]
    var = np.ones_like(yv) if variance is None else np.asarray(variance, dtype=np.float64)
    w = 1.0 / var
    sw, swx, swxx = w.sum(0), (w * xv[:, None]).sum(0), (w * xv[:, None] ** 2).sum(0)
    swy, swxy = (w * yv).sum(0), (w * xv[:, None] * yv).sum(0)
    det = sw * swxx - swx**2
    slope = (sw * swxy - swx * swy) / det
    intercept = (swxx * swy - swx * swxy) / det
    residuals = yv - (intercept + slope * xv[:, None])
    var_slope, var_intercept = sw / det, swxx / det
    dof = n - 2
    if dof > 0:
        chi2 = (w * residuals**2).sum(0) / dof
        scale = chi2 if variance is None else np.maximum(1.0, chi2)
    else:
        scale = np.full(yv.shape[1], np.nan if variance is None else 1.0)
    return LineFit(intercept, slope, np.sqrt(var_intercept * scale), np.sqrt(var_slope * scale), residuals)


def chi2_upper(dof: int, z: float = 1.645) -> float:
    """Reduced χ² exceeded with probability ~5 % (z = 1.645) by chance, Wilson–Hilferty approximation."""
    k = float(dof)
    return (1.0 - 2.0 / (9.0 * k) + z * np.sqrt(2.0 / (9.0 * k))) ** 3


def fit_attenuation_differences(
    log_signal: ArrayLike,
    path_lengths: ArrayLike,
    reference: int = 0,
    log_variance: ArrayLike | None = None,
    log_covariance: ArrayLike | None = None,
) -> AttenuationFit:
    """Attenuation differences V_k = c_k − c_ref (1/m) and log constants b_k from n ≥ 2 distances.

    log_signal: (n, N) mean of ln E_k over the target in each image; path_lengths: (n,)
    mean d_T over the same pixels, metres; log_variance: (n, N) variance of each
    log_signal entry, if known (independent between channels); log_covariance: (n, n, N) covariance
    of one channel's entries between distances (its diagonal unused: ``log_variance``), e.g. from
    the same pixels' fixed pattern, which cancels between distances; None: independent. Two distances
    use the closed form of docs/physics.md §4, more use generalised least squares on
    ln(E_k/E_ref) = b_k − V_k·d_T for all channels jointly: the ratios of one distance share the
    reference channel's noise, so they are correlated, and the joint fit gives the covariance of
    every V and b with every other (``covariance``). With spare degrees of freedom it is scaled by
    the reduced χ² when the scatter is significantly (5 % level) more than the stated variances
    allow (a bad distance or scattering shows up as uncertainty, not false confidence); without
    variances the scatter alone sets it.
    """
    ln_e = np.asarray(log_signal, dtype=np.float64)
    d = np.asarray(path_lengths, dtype=np.float64)
    if ln_e.ndim != 2 or ln_e.shape[0] != d.shape[0] or ln_e.shape[0] < 2:
        raise ValueError(f"need log_signal (n, N) and path_lengths (n,) with n ≥ 2, got {ln_e.shape} and {d.shape}")
    if np.ptp(d) <= 0:
        raise UserInputError("all path lengths are equal; image the target at two or more different distances")
    n_img, n_ch = ln_e.shape
    others = [k for k in range(n_ch) if k != reference]
    q = len(others)
    lv = np.ones_like(ln_e) if log_variance is None else np.asarray(log_variance, dtype=np.float64)
    # Observations y[i, j] = ln E_{others[j]} − ln E_ref at distance i, stacked distance-major.
    y = (ln_e[:, others] - ln_e[:, reference : reference + 1]).reshape(-1)
    cov_y = np.zeros((n_img * q, n_img * q))
    for i in range(n_img):
        block = np.diag(lv[i, others]) + lv[i, reference]
        cov_y[i * q : (i + 1) * q, i * q : (i + 1) * q] = block
    if log_covariance is not None:
        lc = np.asarray(log_covariance, dtype=np.float64)
        for i in range(n_img):
            for i2 in range(n_img):
                if i != i2:
                    cov_y[i * q : (i + 1) * q, i2 * q : (i2 + 1) * q] = np.diag(lc[i, i2, others]) + lc[i, i2, reference]
    # Parameters θ = [V_others..., b_others...]: y = b − V·d.
    x = np.zeros((n_img * q, 2 * q))
    for i in range(n_img):
        for j in range(q):
            x[i * q + j, j] = -d[i]
            x[i * q + j, q + j] = 1.0
    inv = np.linalg.inv(cov_y)
    info = x.T @ inv @ x
    cov = np.linalg.inv(info)
    theta = cov @ (x.T @ inv @ y)
    resid = y - x @ theta
    dof = n_img * q - 2 * q
    if dof > 0:
        chi2 = float(resid @ inv @ resid) / dof
        if log_variance is None:
            cov = cov * chi2
        elif chi2 > chi2_upper(dof):
            # More scatter than the stated noise allows (a wrong distance, scattering): say so in the
            # uncertainty. Scaling whenever χ² > 1 would inflate honest fits on average.
            cov = cov * chi2
    elif log_variance is None:
        cov = np.full_like(cov, np.nan)  # nothing says how noisy equal-weight data with no spare degree are
    cov = 0.5 * (cov + cov.T)
    v, b = np.zeros(n_ch), np.zeros(n_ch)
    if n_img == 2:
        # Closed form (docs/physics.md §4): V = ln((E_ref1/E_ref2)/(E_k1/E_k2)) / (d1 − d2),
        # b = ln(E_k1/E_ref1) + V·d1. Identical to the fit, stated as the design states it.
        v = ((ln_e[0, reference] - ln_e[1, reference]) - (ln_e[0] - ln_e[1])) / (d[0] - d[1])
        b = (ln_e[0] - ln_e[0, reference]) + v * d[0]
        method = "two-distance closed form"
    else:
        v[others], b[others] = theta[:q], theta[q:]
        method = f"generalised least squares over {n_img} distances"
    v[reference] = b[reference] = 0.0
    v_std, b_std = np.zeros(n_ch), np.zeros(n_ch)
    v_std[others] = np.sqrt(np.diag(cov)[:q])
    b_std[others] = np.sqrt(np.diag(cov)[q:])
    residuals = np.zeros((n_img, n_ch))
    residuals[:, others] = (ln_e[:, others] - ln_e[:, reference : reference + 1]) - (b[others] - np.outer(d, v[others]))
    return AttenuationFit(v, v_std, b, b_std, residuals, method, cov)


def absolute_attenuation(
    spread_corrected_log_signal: ArrayLike,
    path_lengths: ArrayLike,
    log_variance: ArrayLike | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Absolute beam attenuation c_k (1/m) and its uncertainty, given the lamp spreading model.

    Irradiance from a lamp of effective radius r = sqrt(A0/Ω) falls as (r/(d_s + r))²
    (r = 0: a point source), so y_k = ln E_k + 2 ln(d_s + r) = a_k − c_k·d_T.
    spread_corrected_log_signal: (n, N) mean of y_k over the target per image (see
    :func:`spreading_log`); path_lengths: (n,) mean d_T in metres. With two distances
    this is c_k = [ln(E_k1/E_k2) − 2 ln((d_s2 + r)/(d_s1 + r))] / (d_T2 − d_T1).
    """
    fit = fit_lines(path_lengths, spread_corrected_log_signal, log_variance)
    return -fit.slope, fit.slope_std


def _common_pixel_means(parts: list[tuple[NDArray[np.bool_], NDArray, NDArray]],
                        path_lengths: list[float]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per distance, the mean spread-corrected log signal (n, N) and the mean path length (n,) over the
    pixels that every distance measured.

    ``parts``: per distance (pixel mask (H, W), spread-corrected ln E (M, N) of the mask's pixels in
    order, path length (M,) or (1,)). The lamp's beam pattern (unknown here) and the camera's
    vignetting weigh each pixel by a factor of its direction alone, which only the same pixels at
    every distance cancel: a nearer plate fills more of the view, toward the beam's dim edge, and
    would read the water as clearer than it is. Without pixels in common (or without per-pixel
    rays), each distance's own pixels and ``path_lengths`` are used."""
    common = np.logical_and.reduce([m for m, _, _ in parts])
    if common.sum() >= 16 and all(len(p) == m.sum() for m, _, p in parts):
        means, paths = [], []
        for mask, y, path in parts:
            rows = common[mask]
            means.append(y[rows].mean(axis=0))
            paths.append(float(path[rows].mean()))
        return np.array(means), np.array(paths)
    return np.array([y.mean(axis=0) for _, y, _ in parts]), np.asarray(path_lengths, np.float64)


def spreading_log(lamp_distance: ArrayLike, lamp_radius: float) -> NDArray[np.float64]:
    """2·ln(d_s + r): the log of the inverse lamp spreading factor, up to a constant."""
    return 2.0 * np.log(np.asarray(lamp_distance, dtype=np.float64) + lamp_radius)


# Pixels kept clear of a region's edges (blur, partial pixels) when measuring noise or backscatter.
EDGE = 2


def _dilate(mask: NDArray[np.bool_], radius: int) -> NDArray[np.bool_]:
    if radius <= 0:
        return mask
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    return cv2.dilate(mask.astype(np.uint8), kernel).astype(bool)


@dataclass(frozen=True)
class BackscatterEstimate:
    level: NDArray[np.float64]
    """(N,) backscatter in DN (dark-corrected) at the black patch; may be slightly negative from noise."""
    variance: NDArray[np.float64]
    """(N,) its variance from pixel noise, DN²."""
    black_mean: NDArray[np.float64]
    """(N,) mean signal of the black patch, DN."""
    plate_log: NDArray[np.float64]
    """(N,) ln of the plate's own light (backscatter excluded pixel by pixel) at the patch's pixels."""
    plate_log_variance: NDArray[np.float64]
    """(N,) its variance from pixel noise."""
    pixels: NDArray[np.bool_]
    """(H, W) the patch pixels used."""


def backscatter_at_black_patch(
    signal: NDArray,
    black_mask: NDArray[np.bool_],
    plate_mask: NDArray[np.bool_],
    black_reflectance: ArrayLike,
    plate_reflectance: ArrayLike,
    pixel_variance: NDArray | None = None,
) -> BackscatterEstimate:
    """Backscatter (DN, dark-corrected) in front of a plate, per channel, from its black patch.

    signal: (H, W, N) dark-corrected average of the distance's frames; masks (H, W). At each patch
    pixel, black = bs + ρ_black·X and the plate would read bs + ρ_plate·X, where X (lamp light ×
    geometry) is *that pixel's own*: the lamp lights patch and surrounding plate differently
    (spreading, beam pattern, incidence), so X is not the surround's mean. The plate's signal is
    interpolated across the patch by a quadratic surface fitted to a ring of plate pixels around
    it, then X = (plate − black)/(ρ_plate − ρ_black) and bs = black − ρ_black·X per pixel, averaged.
    Edge pixels of patch and plate are left out (blur, partial pixels). ``pixel_variance``
    (H, W, N): each pixel's noise variance, for the estimate's variance (0 without it).
    """
    rho_b = np.asarray(black_reflectance, dtype=np.float64)
    rho_p = np.asarray(plate_reflectance, dtype=np.float64)
    if not black_mask.any():
        raise UserInputError("the black patch region holds no pixels; check the regions")
    patch = _interior(black_mask, EDGE)
    edge = EDGE
    if patch.sum() < 4:
        patch, edge = black_mask, 0  # a patch a few pixels wide (small or far): keep every pixel of it
    ys, xs = np.nonzero(black_mask)
    size = max(int(min(np.ptp(ys), np.ptp(xs)) + 1), 4)
    ring = _dilate(black_mask, max(size // 2, 4)) & ~_dilate(black_mask, edge) & _interior(plate_mask, edge)
    ring &= ~black_mask
    if ring.sum() < 6:
        raise UserInputError("the black patch is not surrounded by enough plate pixels to interpolate the plate's light across it; "
                             "check the regions (the patch must lie inside the plate, away from its edges)")
    cy, cx, scale = ys.mean(), xs.mean(), float(size)
    quadratic = ring.sum() >= 24  # a few ring pixels only support a plane

    def design(mask: NDArray[np.bool_]) -> NDArray:
        yy, xx = np.nonzero(mask)
        u, v = (xx - cx) / scale, (yy - cy) / scale
        terms = [np.ones_like(u), u, v] + ([u * u, u * v, v * v] if quadratic else [])
        return np.stack(terms, axis=1)

    a_ring, a_patch = design(ring), design(patch)
    plate_values = signal[ring]
    coef, *_ = np.linalg.lstsq(a_ring, plate_values, rcond=None)
    plate_at_patch = a_patch @ coef
    black = signal[patch]
    lit = (plate_at_patch - black) / (rho_p - rho_b)
    level = (black - rho_b * lit).mean(axis=0)
    # The plate's own light at these pixels, ρp·X, free of backscatter pixel by pixel whatever
    # its spatial pattern (it cancels in plate − black).
    difference = (plate_at_patch - black).mean(axis=0)
    plate_log = np.log(np.maximum(difference, 1e-30)) + np.log(rho_p / (rho_p - rho_b))
    variance = np.zeros(signal.shape[-1])
    log_variance = np.zeros(signal.shape[-1])
    if pixel_variance is not None:
        # bs = α·mean(black) − β·mean(plate fit), α = ρp/(ρp−ρb), β = ρb/(ρp−ρb).
        alpha, beta = rho_p / (rho_p - rho_b), rho_b / (rho_p - rho_b)
        var_black = pixel_variance[patch].mean(axis=0) / patch.sum()
        mean_row = a_patch.mean(axis=0)
        leverage = float(mean_row @ np.linalg.pinv(a_ring.T @ a_ring) @ mean_row)
        var_plate = pixel_variance[ring].mean(axis=0) * leverage
        variance = alpha**2 * var_black + beta**2 * var_plate
        log_variance = (var_black + var_plate) / np.maximum(difference, 1e-30) ** 2
    return BackscatterEstimate(level, variance, black.mean(axis=0), plate_log, log_variance, patch)


def project_plate_box(centre_m: tuple[float, float], size_m: tuple[float, float], distance: float, intrinsics: Intrinsics) -> Box:
    """Pixel box of a rectangle on a plate square to the optical axis at ``distance`` (m), centred on the axis."""
    x0 = intrinsics.cx + intrinsics.fx * (centre_m[0] - size_m[0] / 2) / distance
    x1 = intrinsics.cx + intrinsics.fx * (centre_m[0] + size_m[0] / 2) / distance
    y0 = intrinsics.cy + intrinsics.fy * (centre_m[1] - size_m[1] / 2) / distance
    y1 = intrinsics.cy + intrinsics.fy * (centre_m[1] + size_m[1] / 2) / distance
    xa, ya = int(np.ceil(x0)), int(np.ceil(y0))
    return xa, ya, int(np.floor(x1)) - xa + 1, int(np.floor(y1)) - ya + 1


def box_mask(shape: tuple[int, int], box: Box | None, what: str) -> NDArray[np.bool_]:
    """Boolean (H, W) mask of a pixel box; the whole image for None. Errors if it misses the image."""
    h, w = shape
    if box is None:
        return np.ones((h, w), dtype=bool)
    x, y, bw, bh = box
    if bw <= 0 or bh <= 0 or x < 0 or y < 0 or x + bw > w or y + bh > h:
        raise UserInputError(f"{what} {x},{y},{bw},{bh} (x,y,width,height) does not lie inside the {w}×{h} image")
    m = np.zeros((h, w), dtype=bool)
    m[y : y + bh, x : x + bw] = True
    return m


@dataclass(frozen=True)
class CalibrationInputs:
    """What a calibration needs besides the frames and distances; units in each name."""

    channel_names: list[str]
    wavelengths_nm: list[float | None]
    target_reflectance: NDArray[np.float64]  # (N,)
    black_reflectance: NDArray[np.float64] | None = None  # (N,), if the target has a black patch
    target_box: Box | None = None  # one box for all images, or per-image boxes below
    target_boxes: list[Box] | None = None
    black_boxes: list[Box] | None = None
    lamp_position_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    intrinsics: Intrinsics | None = None
    lamp_radius_m: float | None = None
    dark_level: NDArray[np.float64] | None = None  # (N,) DN
    saturation_level: float = 65535.0
    quantisation_step: float = 1.0
    reference: int = 0
    name: str = "uwcam calibration"
    target_description: str = "spectrally flat target"
    image_names: list[str] | None = None


@dataclass(frozen=True)
class DistanceGroup:
    """The frames taken at one distance and what was measured on their average."""

    distance_m: float
    images: list[str]
    mean_frame: NDArray[np.float64]
    """(H, W, N) average of the frames, dark-corrected, DN."""
    target: NDArray[np.bool_]
    """(H, W) plate pixels used for the fit."""
    black: NDArray[np.bool_] | None
    path_length_m: float = 0.0
    log_signal: NDArray[np.float64] | None = None
    log_variance: NDArray[np.float64] | None = None
    backscatter: BackscatterEstimate | None = None
    fit_pixels: NDArray[np.bool_] | None = None
    """(H, W) the pixels whose light entered the fit."""


@dataclass(frozen=True)
class CalibrationDetails:
    """Everything measured on the way to a profile: for reports and plots."""

    profile: CalibrationProfile
    groups: list[DistanceGroup]
    noise_points: list[tuple[str, NoisePoint]]
    noise: NoiseFit
    fit: AttenuationFit


def calibrate(frames: list[NDArray], distances_m: list[float], inputs: CalibrationInputs) -> CalibrationProfile:
    """Calibration profile from frames (H, W, N) of the target at camera distances (m, along the axis).

    Frames given the same distance are averaged; see :func:`calibrate_with_details`."""
    return calibrate_with_details(frames, distances_m, inputs).profile


def _check_frames(frames: list[NDArray], distances_m: list[float], inputs: CalibrationInputs, names: list[str]) -> None:
    n_img = len(frames)
    if len(distances_m) != n_img:
        raise UserInputError(f"got {n_img} images but {len(distances_m)} --distance values; give one distance per image, in order")
    if any(not (np.isfinite(d) and d > 0) for d in distances_m):
        raise UserInputError(f"distances must be positive metres, got {list(distances_m)}")
    if len(set(float(d) for d in distances_m)) < 2:
        raise UserInputError(f"calibration needs images at two or more different distances, got {sorted(set(distances_m))} m")
    n_ch = len(inputs.channel_names)
    for frame, label in zip(frames, names):
        if frame.ndim != 3 or frame.shape[-1] != n_ch:
            got = frame.shape[-1] if frame.ndim == 3 else 1
            raise UserInputError(f"{label} has {got} channel(s) but calibration expects {n_ch} ({','.join(inputs.channel_names)})")
    shape = frames[0].shape[:2]
    for frame, label in zip(frames, names):
        if frame.shape[:2] != shape:
            raise UserInputError(f"{label} is {frame.shape[1]}×{frame.shape[0]} but the first image is {shape[1]}×{shape[0]}; use images of one size")


def calibrate_with_details(frames: list[NDArray], distances_m: list[float], inputs: CalibrationInputs) -> CalibrationDetails:
    """Calibration profile and what was measured, from frames (H, W, N) at camera distances (m).

    Several frames at one distance (the same distance given repeatedly) are averaged for the
    fit, and their differences give the temporal noise; the spatial spread beyond it is the
    fixed pattern. With one frame per distance the noise model comes from the spatial spread
    of a region clear of the plate's edges and of the black patch. The variance of every
    distance's mean log signal follows from that model, and the fit's joint covariance of
    attenuation differences and log constants is stored in the profile.
    """
    n_img = len(frames)
    names = inputs.image_names or [f"image {i + 1}" for i in range(n_img)]
    if n_img < 2:
        raise UserInputError(f"calibration needs images at two or more distances, got {n_img}")
    _check_frames(frames, distances_m, inputs, names)
    n_ch = len(inputs.channel_names)
    shape = frames[0].shape[:2]
    dark = np.zeros(n_ch) if inputs.dark_level is None else np.asarray(inputs.dark_level, dtype=np.float64)
    lamp = np.asarray(inputs.lamp_position_m, dtype=np.float64)
    rays = pixel_rays(inputs.intrinsics, *shape) if inputs.intrinsics is not None else None
    step = float(inputs.quantisation_step)
    has_black = bool(inputs.black_boxes) and inputs.black_reflectance is not None

    # Group by distance, in order of first appearance.
    order: list[float] = []
    members: dict[float, list[int]] = {}
    for i, d in enumerate(distances_m):
        key = float(d)
        if key not in members:
            order.append(key)
            members[key] = []
        members[key].append(i)

    groups: list[DistanceGroup] = []
    noise_points: list[tuple[str, NoisePoint]] = []
    for distance in order:
        idx = members[distance]
        first = idx[0]
        label = names[first] if len(idx) == 1 else f"{len(idx)} images at {distance:g} m"
        box = inputs.target_boxes[first] if inputs.target_boxes else inputs.target_box
        target = box_mask(shape, box, f"target region of {names[first]}")
        black = None
        if inputs.black_boxes:
            black = box_mask(shape, inputs.black_boxes[first], f"black patch region of {names[first]}")
            target &= ~black
        for i in idx:
            frac = (np.asarray(frames[i])[target] >= inputs.saturation_level).mean(axis=0)
            if frac.max() > MAX_SATURATED_FRACTION:
                k = int(frac.argmax())
                raise UserInputError(
                    f"{frac[k]:.0%} of the target region of {names[i]} is saturated in channel {inputs.channel_names[k]}; "
                    "lower the exposure, gain or lamp intensity and capture it again"
                )
        stack = [np.asarray(frames[i]) for i in idx]
        clipped = np.any([np.any(f >= inputs.saturation_level, axis=-1) for f in stack], axis=0)
        usable = target & ~clipped
        mean_frame = np.mean([f.astype(np.float64) for f in stack], axis=0) - dark
        # Noise region: away from the plate's edges and from the black patch (and from anything,
        # like markers, outside the target region); on a plate only a few pixels across, as close as it takes.
        away = np.zeros(shape, bool) if black is None else black
        candidates = [_interior(usable, EDGE) & ~_dilate(away, EDGE + SMOOTHING), _interior(usable, 1) & ~_dilate(away, 1),
                      usable & ~away]
        region = next((r for r in candidates if (r[:, 2:] & r[:, 1:-1] & r[:, :-2]).sum() >= 2), None)
        if region is None:
            raise UserInputError(f"the target region of {label} is too small to measure its noise; check the regions")
        # The plate's light falls off toward its edges: bins of brightness give the noise model
        # several signal levels per distance.
        brightness = cv2.blur(mean_frame.sum(axis=-1), (SMOOTHING, SMOOTHING))
        edges = np.quantile(brightness[region], np.linspace(0, 1, NOISE_BINS + 1))
        before = len(noise_points)
        for j in range(NOISE_BINS):
            part = region & (brightness >= edges[j]) & (brightness <= edges[j + 1])
            if part.sum() >= 64:
                noise_points.append((f"plate {distance:g} m, level {j + 1}", noise_point(stack, part, dark)))
        if len(noise_points) == before:
            noise_points.append((f"plate {distance:g} m", noise_point(stack, region, dark)))
        if black is not None:
            patch = _interior(black, EDGE)
            triples = patch[:, 2:] & patch[:, 1:-1] & patch[:, :-2]
            if triples.sum() >= 2:  # a patch too small to measure its noise still gives backscatter
                noise_points.append((f"black patch {distance:g} m", noise_point(stack, patch, dark)))
        groups.append(DistanceGroup(distance, [names[i] for i in idx], mean_frame, usable, black))

    noise = fit_noise([p for _, p in noise_points], step)

    def pixel_variance(signal: NDArray, frames_averaged: int) -> NDArray:
        # Temporal noise averages down over the frames; the fixed pattern does not.
        temporal = signal_variance_temporal(signal, noise) / frames_averaged
        return np.maximum(temporal + (noise.fixed_pattern * np.maximum(signal, 0)) ** 2, variance_floor(signal, step))

    estimates: list[BackscatterEstimate | None] = []
    for g in groups:
        estimate = None
        if has_black and g.black is not None:
            estimate = backscatter_at_black_patch(g.mean_frame, g.black, g.target, inputs.black_reflectance,
                                                  inputs.target_reflectance, pixel_variance(g.mean_frame, len(g.images)))
        estimates.append(estimate)
    # Backscatter is not uniform over a plate (it follows the lamp's beam through the water), so a
    # level measured at the patch cannot be subtracted from the whole plate. Where backscatter is
    # measurable, the fit uses the plate's own light at the patch, which is free of it pixel by
    # pixel; where it is not (clean water, a tank), the whole plate, which has many more pixels.
    # Measured: more than 5σ from 0 and more than 0.1 % of the plate's light (below that its unevenness
    # over the plate moves ln E by less than 1e-4; noise-free frames have σ ≈ 0).
    patch_local = has_black and any(
        np.any((np.abs(e.level) > BACKSCATTER_SIGMAS * np.sqrt(e.variance))
               & (np.abs(e.level) > BACKSCATTER_FRACTION * np.exp(e.plate_log)))
        for e in estimates if e is not None)

    fitted: list[DistanceGroup] = []
    log_signal, log_variance, path_lengths, log_spread_corrected = [], [], [], []
    weights: list[NDArray | None] = []  # each distance's pixel weights in its mean (None: patch-local)
    for g, estimate in zip(groups, estimates):
        m = len(g.images)
        if patch_local:
            pixels = estimate.pixels
            ln_mean = estimate.plate_log
            lv = estimate.plate_log_variance
            ln_e = np.broadcast_to(ln_mean, (int(pixels.sum()), n_ch))
        else:
            if np.any(g.mean_frame[g.target].mean(axis=0) <= 0):
                k = int(np.argmin(g.mean_frame[g.target].mean(axis=0)))
                raise UserInputError(
                    f"the target region at {g.distance_m:g} m has no signal in channel {inputs.channel_names[k]} after dark "
                    "correction; check the lamp, the exposure and that the target is in the region"
                )
            ln_e, pixels = smoothed_log_signal(g.mean_frame, g.target)
            # Each pixel's expected signal, smoothed within the region only (a box reaching past the
            # plate's edge or into the black patch would make its pixels look dark and noisy).
            inside = g.target.astype(np.float64)
            weight = cv2.blur(inside, (SMOOTHING, SMOOTHING), borderType=cv2.BORDER_CONSTANT)
            smooth = cv2.blur(g.mean_frame * inside[..., None], (SMOOTHING, SMOOTHING), borderType=cv2.BORDER_CONSTANT)
            smooth = smooth / np.maximum(weight, 1e-12)[..., None]
            lv = log_mean_variance(pixels, np.maximum(smooth, 1e-30), pixel_variance(smooth, m))
            weights.append(mean_weights(pixels))
            ln_mean = ln_e.mean(axis=0)
        lv = np.maximum(lv, variance_floor(np.exp(ln_mean), step) / np.exp(ln_mean) ** 2)
        u = rays[pixels] if rays is not None else np.array([[0.0, 0.0, 1.0]])
        dc = plane_camera_range(g.distance_m, u)
        ds = np.linalg.norm(dc[:, None] * u - lamp, axis=-1)
        path = float(np.mean(dc + ds))
        log_signal.append(ln_mean)
        log_variance.append(lv)
        path_lengths.append(path)
        if inputs.lamp_radius_m is not None:
            # The plate (normal along −z) is lit at the angle θ from its normal: cos θ = (z − S_z)/d_s.
            lit = np.clip((dc * u[:, 2] - lamp[2]) / ds, 1e-6, 1.0)
            spread = spreading_log(ds, inputs.lamp_radius_m) - np.log(lit)
            log_spread_corrected.append((pixels, ln_e + spread[:, None], dc + ds))
        fitted.append(replace(g, path_length_m=path, log_signal=log_signal[-1], log_variance=lv, backscatter=estimate,
                              fit_pixels=pixels))

    ref = inputs.reference
    # The fixed pattern of pixels that two distances share is the same in both means: it cancels in
    # their difference (the attenuation differences), and counted as independent it would inflate
    # their σ several times. Its covariance between distances i and j: f_k²·Σ_p a_p(i)·a_p(j).
    covariance = None
    if not patch_local and np.any(noise.fixed_pattern > 0):
        cross = np.array([[float(np.sum(a * b)) for b in weights] for a in weights])
        covariance = cross[:, :, None] * np.asarray(noise.fixed_pattern, np.float64) ** 2
    fit = fit_attenuation_differences(np.array(log_signal), path_lengths, ref, np.array(log_variance), covariance)

    backscatter_samples = None
    floor = np.zeros(n_ch)
    if has_black:
        levels = np.array([g.backscatter.level for g in fitted])
        blacks = np.array([g.backscatter.black_mean for g in fitted])
        # The floor is for single frames: the black patch's signal plus 3σ of one pixel's noise.
        sigma = np.sqrt(np.maximum(signal_variance(blacks, noise.read_noise, noise.shot_gain, step, noise.fixed_pattern),
                                   variance_floor(blacks, step)))
        floor = np.max(np.maximum(levels, 0.0) + FLOOR_SIGMAS * sigma, axis=0)
        centres = [(x + w / 2 - 0.5, y + h / 2 - 0.5) for x, y, w, h in
                   (inputs.black_boxes[members[g.distance_m][0]] for g in fitted)]
        backscatter_samples = BackscatterSamples(
            distances_m=[g.distance_m for g in fitted],
            patch_pixels=centres,
            levels={inputs.channel_names[k]: [float(max(v, 0.0)) for v in levels[:, k]] for k in range(n_ch)},
            noise_sigma={inputs.channel_names[k]: float(np.max(sigma[:, k])) for k in range(n_ch)},
        )
    absolute: tuple[NDArray, NDArray] | None = None
    if inputs.lamp_radius_m is not None:
        absolute = absolute_attenuation(*_common_pixel_means(log_spread_corrected, path_lengths), np.array(log_variance))

    channels = [
        ChannelCalibration(
            name=inputs.channel_names[k],
            wavelength_nm=inputs.wavelengths_nm[k],
            attenuation_difference=float(fit.attenuation_difference[k]),
            attenuation_difference_std=float(fit.attenuation_difference_std[k]),
            log_constant=float(fit.log_constant[k]),
            log_constant_std=float(fit.log_constant_std[k]),
            attenuation=None if absolute is None else float(max(absolute[0][k], 0.0)),
            target_reflectance=float(inputs.target_reflectance[k]),
            dark_level=float(dark[k]),
            read_noise=float(noise.read_noise[k]),
            shot_gain=float(noise.shot_gain[k]),
            fixed_pattern=float(noise.fixed_pattern[k]),
            noise_floor=float(floor[k]),
        )
        for k in range(n_ch)
    ]
    others = [inputs.channel_names[k] for k in range(n_ch) if k != ref]
    covariance = CalibrationCovariance(parameters=[f"V:{c}" for c in others] + [f"b:{c}" for c in others],
                                       matrix=fit.covariance.tolist())
    residuals = {inputs.channel_names[k]: [float(r) for r in fit.residuals[:, k]] for k in range(n_ch)}
    provenance = Provenance(
        created=now_iso(),
        method=f"{fit.method}; {'plate light at the black patch (backscatter measured)' if patch_local else 'whole plate'}; "
               f"noise: {noise.method}",
        distances_m=[g.distance_m for g in fitted],
        frames_per_distance=[len(g.images) for g in fitted],
        path_lengths_m=path_lengths,
        images=list(names),
        target=inputs.target_description,
        roi=list(inputs.target_box) if inputs.target_box else None,
        residuals=residuals,
        rms_residual=float(np.sqrt(np.mean(fit.residuals**2))),
    )
    intr = inputs.intrinsics
    profile = CalibrationProfile(
        name=inputs.name,
        reference_channel=inputs.channel_names[ref],
        channels=channels,
        saturation_level=float(inputs.saturation_level),
        quantisation_step=float(inputs.quantisation_step),
        lamp_position_m=tuple(float(v) for v in lamp),
        lamp_radius_m=inputs.lamp_radius_m,
        intrinsics=None if intr is None else {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy},
        backscatter=backscatter_samples,
        covariance=covariance,
        provenance=provenance,
    )
    return CalibrationDetails(profile, fitted, noise_points, noise, fit)


def signal_variance_temporal(signal: NDArray, noise: NoiseFit) -> NDArray:
    """Frame-to-frame variance (DN²) of ``signal`` (…, N) under a fitted noise model, quantisation excluded
    (it is added by the floor)."""
    return noise.read_noise**2 + noise.shot_gain * np.maximum(signal, 0.0)
