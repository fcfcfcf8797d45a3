"""The calibration's share of a range's variance: how the profile's own uncertainty (the
covariance of its attenuation differences and log constants) carries to each pixel's range.

Smooth across the image, so computed on blocks of pixels with the fusion weights of the noise
model (:mod:`uwcam.optics.calibration_variance`) and interpolated; :class:`uwcam.ranging.estimator.RangeEstimator`
adds it to every range's variance and keeps it as the range's common variance.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np
from numpy.typing import NDArray

from uwcam.optics.calibration_variance import calibration_path_variance
from uwcam.optics.geometry import camera_range_derivative, pixel_rays
from uwcam.optics.noise import signal_variance
from uwcam.ranging.smoothing import block_means

if TYPE_CHECKING:
    from uwcam.ranging.estimator import RangeEstimator


def calibration_variance_map(estimator: RangeEstimator, frame: NDArray, background: NDArray | None = None,
                             block: int = 8) -> NDArray[np.float32]:
    """(H, W) variance of camera range (m²) due to the calibration's uncertainty, for ``frame``
    (H, W, N) ranged by ``estimator`` (a :class:`uwcam.ranging.estimator.RangeEstimator`).

    Computed on block averages (``block`` pixels a side; 1: every pixel) with the fusion
    weights of the noise model (see :mod:`uwcam.optics.calibration_variance`), then
    interpolated bilinearly; blocks without a range take their neighbours' largest value.
    """
    h, w = frame.shape[:2]
    if estimator.response is not None and np.issubdtype(frame.dtype, np.integer):
        frame = estimator.response.linearise(frame)
    gh, gw = max(h // block, 1), max(w // block, 1)
    if block > 1:
        small = block_means(frame, (gw, gh)).astype(np.float64)
        if small.ndim == 2:
            small = small[:, :, None]
        bg = None if background is None else cv2.resize(np.asarray(background, np.float32), (gw, gh),
                                                        interpolation=cv2.INTER_AREA).reshape(gh, gw, -1)
    else:
        small, bg = frame.astype(np.float64), background
    # Channel planes (N, gh, gw): every operation below runs over whole planes.
    raw = np.moveaxis(small, -1, 0)
    e = raw - estimator.dark[:, None, None]
    if bg is not None:
        e = e - np.moveaxis(bg, -1, 0)
    n = estimator.n_channels
    q = estimator.profile.quantisation_step
    total = e if bg is None else e + np.moveaxis(bg, -1, 0)
    # Each value's variance as the estimator counts it (channels last there), back to planes.
    if bg is None:
        variance = signal_variance(np.moveaxis(total, 0, -1), estimator.read_noise, estimator.shot_gain, q,
                                   estimator.fixed_pattern)
    else:
        variance = estimator.background_signal_variance(np.moveaxis(total, 0, -1), np.moveaxis(e, 0, -1))
    variance = np.moveaxis(variance, -1, 0)
    weight, y = [], []
    for k in range(n):
        ek, var = e[k], variance[k]
        usable = (ek > max(estimator.floor[k], 0.0)) & (raw[k] < estimator.profile.saturation_level) & bool(estimator.active[k])
        with np.errstate(divide="ignore", invalid="ignore"):
            weight.append(np.where(usable, ek * ek / np.where(var > 0, var, 1.0), 0.0))
            y.append(np.where(usable, np.log(np.where(usable, ek, 1.0)) - estimator.effective_log_constant[k], 0.0))
    c = estimator.attenuation
    with np.errstate(divide="ignore", invalid="ignore"):
        sw = sum(weight)
        c_mean = sum(weight[k] * c[k] for k in range(n)) / sw
        y_mean = sum(weight[k] * y[k] for k in range(n)) / sw
        spread = sum(weight[k] * (c[k] - c_mean) ** 2 for k in range(n))
        path = -sum(weight[k] * (c[k] - c_mean) * (y[k] - y_mean) for k in range(n)) / spread
    cvv, cvb, cbb = estimator.covariance
    var_path = calibration_path_variance(np.stack(weight, axis=-1), c, path, cvv, cvb, cbb)
    deriv = camera_range_derivative(path, estimator.profile.lamp_position_m, block_rays(estimator, gh, gw, h, w))
    # A path length at the lamp's own distance makes the derivative, hence the variance, exceed
    # float32: it stays the largest float32 (still no range worth the name), not inf, which the
    # filling below would take for a block without a range and give its neighbours' value.
    cal = np.minimum(deriv * deriv * var_path, np.finfo(np.float32).max).astype(np.float32)
    bad = ~np.isfinite(cal)
    if bad.all():
        return np.zeros((h, w), np.float32)
    if bad.any():
        # Blocks without a range (dark, saturated, out of bounds) take their neighbours' largest value, so no
        # valid pixel next to them gets less than its share or a NaN from the interpolation.
        filled = np.where(bad, 0.0, cal).astype(np.float32)
        for _ in range(3):
            grown = cv2.dilate(filled, np.ones((3, 3), np.uint8))
            filled = np.where(bad & (filled == 0), grown, filled)
        cal = filled
    if block == 1:
        return cal
    return cv2.resize(cal, (w, h), interpolation=cv2.INTER_LINEAR)


def block_rays(estimator: RangeEstimator, gh: int, gw: int, h: int, w: int) -> NDArray | None:
    """Unit rays of the centres of (gh, gw) blocks of frames (h, w) (gh, gw, 3), or None (optical
    axis) without intrinsics; kept in the estimator's cache."""
    key = (gh, gw, h, w)
    if key not in estimator._low_res_rays:
        intr = estimator.profile.camera_intrinsics()
        rays = None
        if intr is not None and np.any(estimator.profile.lamp_position_m):
            rays = pixel_rays(intr.reduced(w / gw, h / gh), gh, gw)
        estimator._low_res_rays[key] = rays
    return estimator._low_res_rays[key]
