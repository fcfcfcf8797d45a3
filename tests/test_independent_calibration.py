"""Calibration against closed forms (docs/physics.md §4), textbook least squares and a naive renderer.

Expected values come from numpy's lstsq/polyfit, the two-distance formulas written out here, and
frames rendered pixel by pixel with non-square pixels, an off-centre principal point and a lamp
off both axes; nothing is taken from uwcam's own geometry or fitting helpers.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from uwcam.calibration.fit import CalibrationInputs, box_mask, calibrate, project_plate_box
from uwcam.calibration.line_fit import absolute_attenuation, fit_attenuation_differences, fit_lines, spreading_log
from uwcam.fileio import UserInputError
from uwcam.optics import Intrinsics

C = np.array([0.46, 0.11, 0.06])
LOG_K = np.array([10.2, 10.6, 10.4])
LAMP = (0.3, -0.15, 0.05)
INTR = Intrinsics(fx=70.0, fy=52.0, cx=27.0, cy=18.5)
H, W = 40, 60


def weighted_fit(x, y, var):
    """Textbook WLS of y = a + s·x: ((a, s), covariance) by lstsq on whitened rows."""
    a = np.stack([np.ones_like(x), x], axis=1)
    sw = 1.0 / np.sqrt(var)
    coef, *_ = np.linalg.lstsq(a * sw[:, None], y * sw, rcond=None)
    cov = np.linalg.inv(a.T @ (a / var[:, None]))
    return coef, cov


def test_fit_lines_is_weighted_least_squares_with_stated_variances():
    x = np.array([1.0, 2.0, 3.5, 5.0])
    y = np.stack([0.3 - 0.4 * x, 1.2 + 0.05 * x], axis=1)  # exact lines
    var = np.array([[0.01, 0.04], [0.02, 0.01], [0.04, 0.02], [0.01, 0.09]])
    fit = fit_lines(x, y, var)
    for k in range(2):
        (a, s), cov = weighted_fit(x, y[:, k], var[:, k])
        assert fit.intercept[k] == pytest.approx(a, abs=1e-12) and fit.slope[k] == pytest.approx(s, abs=1e-12)
        # No scatter beyond the stated variances: uncertainties from them alone.
        assert fit.intercept_std[k] == pytest.approx(math.sqrt(cov[0, 0]), rel=1e-10)
        assert fit.slope_std[k] == pytest.approx(math.sqrt(cov[1, 1]), rel=1e-10)
    np.testing.assert_allclose(fit.residuals, 0.0, atol=1e-12)


def test_fit_lines_scales_uncertainty_by_reduced_chi2_when_the_scatter_is_larger():
    x = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    noise = np.array([0.3, -0.5, 0.4, 0.1, -0.3])
    y = (2.0 - 0.5 * x + noise)[:, None]
    var = np.full((5, 1), 0.01)
    fit = fit_lines(x, y, var)
    (a, s), cov = weighted_fit(x, y[:, 0], var[:, 0])
    resid = y[:, 0] - (a + s * x)
    chi2 = (resid**2 / var[:, 0]).sum() / 3
    assert chi2 > 1
    assert fit.slope[0] == pytest.approx(s, abs=1e-12)
    assert fit.slope_std[0] == pytest.approx(math.sqrt(cov[1, 1] * chi2), rel=1e-10)
    assert fit.intercept_std[0] == pytest.approx(math.sqrt(cov[0, 0] * chi2), rel=1e-10)
    np.testing.assert_allclose(fit.residuals[:, 0], resid, atol=1e-12)
    # Without stated variances: ordinary least squares, uncertainty from the scatter itself.
    plain = fit_lines(x, y)
    slope, intercept = np.polyfit(x, y[:, 0], 1)
    assert plain.slope[0] == pytest.approx(slope) and plain.intercept[0] == pytest.approx(intercept)
    s2 = ((y[:, 0] - intercept - slope * x) ** 2).sum() / 3
    assert plain.slope_std[0] == pytest.approx(math.sqrt(s2 / ((x - x.mean()) ** 2).sum()), rel=1e-10)
    # Three points, one degree of freedom: scaled too.
    three = fit_lines(x[:3], y[:3], var[:3])
    (a3, s3), cov3 = weighted_fit(x[:3], y[:3, 0], var[:3, 0])
    chi2_3 = ((y[:3, 0] - a3 - s3 * x[:3]) ** 2 / var[:3, 0]).sum() / 1
    assert chi2_3 > 1 and three.slope_std[0] == pytest.approx(math.sqrt(cov3[1, 1] * chi2_3), rel=1e-10)
    # Two points: an exact fit, and no uncertainty without stated variances.
    two = fit_lines(x[:2], y[:2])
    assert np.isnan(two.slope_std[0]) and two.slope[0] == pytest.approx((y[1, 0] - y[0, 0]) / (x[1] - x[0]))


def test_two_distance_calibration_is_the_closed_form():
    d = np.array([1.5, 3.0])
    g = np.array([0.8, 0.3])  # spreading and anything else common to the channels
    ln_e = np.log(g[:, None]) + LOG_K[None, :] - C[None, :] * d[:, None]
    fit = fit_attenuation_differences(ln_e, d, reference=1)
    e1, e2 = np.exp(ln_e[0]), np.exp(ln_e[1])
    v = np.log((e1[1] / e2[1]) / (e1 / e2)) / (d[0] - d[1])  # docs/physics.md §4 with i = ref
    u = (e1 / e1[1]) * np.exp(v * d[0])  # E_k1/E_ref1 · exp(V·d_T1): exp(b_k)
    np.testing.assert_allclose(fit.attenuation_difference, C - C[1], atol=1e-12)
    np.testing.assert_allclose(fit.attenuation_difference, v, atol=1e-12)
    np.testing.assert_allclose(fit.log_constant, np.log(u), atol=1e-12)
    np.testing.assert_allclose(fit.log_constant, LOG_K - LOG_K[1], atol=1e-12)
    assert fit.attenuation_difference[1] == 0 and fit.log_constant[1] == 0 and fit.method == "two-distance closed form"


def test_absolute_attenuation_is_the_two_distance_formula():
    r = 0.12
    ds = np.array([1.1, 2.4])
    dt = np.array([2.0, 4.5])
    e = np.exp(LOG_K[None, :] - C[None, :] * dt[:, None]) * ((r / (ds + r)) ** 2)[:, None]
    y = np.log(e) + spreading_log(ds, r)[:, None]
    c, _ = absolute_attenuation(y, dt)
    expected = (np.log(e[0] / e[1]) - 2 * np.log((ds[1] + r) / (ds[0] + r))) / (dt[1] - dt[0])
    np.testing.assert_allclose(c, expected, rtol=1e-12)
    np.testing.assert_allclose(c, C, rtol=1e-12)


def test_boxes_project_with_non_square_pixels():
    box = project_plate_box((0.15, -0.08), (0.2, 0.1), 2.5, INTR)
    # Corners of the rectangle by the pinhole model: u = cx + fx·X/Z, v = cy + fy·Y/Z.
    u0, u1 = INTR.cx + INTR.fx * 0.05 / 2.5, INTR.cx + INTR.fx * 0.25 / 2.5
    v0, v1 = INTR.cy + INTR.fy * -0.13 / 2.5, INTR.cy + INTR.fy * -0.03 / 2.5
    x, y = math.ceil(u0), math.ceil(v0)
    assert box == (x, y, math.floor(u1) - x + 1, math.floor(v1) - y + 1)
    m = box_mask((5, 6), (1, 2, 3, 2), "target")
    assert m.sum() == 6 and m[2, 1] and m[3, 3] and not m[4, 1] and not m[2, 4]
    for bad in [(0, 0, 0, 2), (-1, 0, 2, 2), (5, 0, 2, 2), (0, 4, 2, 2)]:
        with pytest.raises(UserInputError, match="does not lie inside the 6×5 image"):
            box_mask((5, 6), bad, "target")
    assert box_mask((2, 3), None, "x").all()


def ray(i, j):
    x, y = (j - INTR.cx) / INTR.fx, (i - INTR.cy) / INTR.fy
    n = math.sqrt(x * x + y * y + 1)
    return np.array([x / n, y / n, 1 / n])


def render(distance: float) -> tuple[np.ndarray, float]:
    """Noise-free plate square to the axis at ``distance``, pixel by pixel; also the mean path
    length over the pixels whose whole 5×5 box lies in the image (those the calibration uses)."""
    frame = np.empty((H, W, 3))
    paths = []
    for i in range(H):
        for j in range(W):
            u = ray(i, j)
            dc = distance / u[2]
            ds = np.linalg.norm(dc * u - np.array(LAMP))
            frame[i, j] = np.exp(LOG_K - C * (dc + ds)) * (0.2 / (ds + 0.2)) ** 2 * u[2]
            if 2 <= i < H - 2 and 2 <= j < W - 2:
                paths.append(dc + ds)
    return frame, float(np.mean(paths))


def test_calibration_refuses_bad_inputs_with_clear_messages():
    frame = np.full((8, 8, 3), 100.0)
    inputs = CalibrationInputs(channel_names=["R", "G", "B"], wavelengths_nm=[None] * 3, target_reflectance=np.ones(3))
    with pytest.raises(UserInputError, match="two or more distances, got 1"):
        calibrate([frame], [1.0], inputs)
    with pytest.raises(UserInputError, match="got 2 images but 3 --distance values"):
        calibrate([frame, frame], [1.0, 2.0, 3.0], inputs)
    for bad in ([1.0, 0.0], [1.0, -2.0], [1.0, float("nan")], [float("inf"), 1.0]):
        with pytest.raises(UserInputError, match="distances must be positive metres"):
            calibrate([frame, frame], bad, inputs)
    with pytest.raises(UserInputError, match="image 2 has 2 channel"):
        calibrate([frame, frame[..., :2]], [1.0, 2.0], inputs)
    with pytest.raises(UserInputError, match="image 2 is 4×8 but the first image is 8×8"):
        calibrate([frame, frame[:, :4]], [1.0, 2.0], inputs)
    sat = frame.copy()
    sat[:2] = 65535.0
    with pytest.raises(UserInputError, match="25% of the target region of image 1 is saturated in channel R"):
        calibrate([sat, frame], [1.0, 2.0], inputs)
    dark = frame.copy()
    dark[..., 1] = 0.0
    with pytest.raises(UserInputError, match="no signal in channel G"):
        calibrate([frame, dark], [1.0, 2.0], inputs)

