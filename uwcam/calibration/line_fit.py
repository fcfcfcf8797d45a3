"""Attenuation from the target's log signal against distance: smoothed logs and their variance,
weighted line fits, attenuation differences with their covariance, absolute attenuation
(docs/physics.md §4)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from uwcam.fileio import UserInputError


# Side of the box average applied before taking logs of the target (pixels).
SMOOTHING = 5


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


def common_pixel_means(parts: list[tuple[NDArray[np.bool_], NDArray, NDArray]],
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
