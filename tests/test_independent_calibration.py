"""Calibration against closed forms (DESIGN.md §4), textbook least squares and a naive renderer.

Expected values come from numpy's lstsq/polyfit, the two-distance formulas written out here, and
frames rendered pixel by pixel with non-square pixels, an off-centre principal point and a lamp
off both axes; nothing is taken from uwcam's own geometry or fitting helpers.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from uwcam.calibration import (
    CalibrationInputs,
    absolute_attenuation,
    backscatter_at_black_patch,
    box_mask,
    calibrate,
    fit_attenuation_differences,
    fit_lines,
    fit_noise_model,
    noise_floor_from_black_patch,
    project_plate_box,
    region_statistics,
    spreading_log,
    surrounding_box,
)
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
    v = np.log((e1[1] / e2[1]) / (e1 / e2)) / (d[0] - d[1])  # DESIGN.md §4 with i = ref
    u = (e1 / e1[1]) * np.exp(v * d[0])  # E_k1/E_ref1 · exp(V·d_T1): exp(b_k)
    np.testing.assert_allclose(fit.attenuation_difference, C - C[1], atol=1e-12)
    np.testing.assert_allclose(fit.attenuation_difference, v, atol=1e-12)
    np.testing.assert_allclose(fit.log_constant, np.log(u), atol=1e-12)
    np.testing.assert_allclose(fit.log_constant, LOG_K - LOG_K[1], atol=1e-12)
    assert fit.attenuation_difference[1] == 0 and fit.log_constant[1] == 0 and fit.method == "two-distance closed form"


def test_several_distances_are_fitted_by_weighted_least_squares():
    rng = np.random.default_rng(11)
    d = np.array([1.0, 1.8, 2.5, 3.7, 5.0])
    ln_e = LOG_K[None, :] - C[None, :] * d[:, None] + rng.normal(0, 0.01, (5, 3))
    log_var = rng.uniform(1e-5, 4e-4, (5, 3))
    fit = fit_attenuation_differences(ln_e, d, 0, log_var)
    for k in (1, 2):
        (a, s), _ = weighted_fit(d, ln_e[:, k] - ln_e[:, 0], log_var[:, k] + log_var[:, 0])
        assert fit.attenuation_difference[k] == pytest.approx(-s, abs=1e-10)
        assert fit.log_constant[k] == pytest.approx(a, abs=1e-10)
    assert fit.method == "weighted least squares over 5 distances"
    with pytest.raises(UserInputError, match="all path lengths are equal"):
        fit_attenuation_differences(ln_e[:2], [2.0, 2.0])
    with pytest.raises(ValueError, match="n ≥ 2"):
        fit_attenuation_differences(ln_e[:1], d[:1])
    with pytest.raises(ValueError, match="need log_signal"):
        fit_attenuation_differences(ln_e[:, 0], d)
    with pytest.raises(ValueError, match="need log_signal"):
        fit_attenuation_differences(ln_e, d[:4])


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


def test_noise_model_recovers_read_noise_and_gain():
    means = np.array([[100.0, 50.0], [400.0, 200.0], [1600.0, 800.0]])
    read, gain, step = np.array([4.0, 9.0]), np.array([0.5, 0.0]), 3.0
    var = read**2 + gain * means + step**2 / 12
    got_read, got_gain = fit_noise_model(means, var, step)
    np.testing.assert_allclose(got_read, read, rtol=1e-9)
    np.testing.assert_allclose(got_gain, gain, atol=1e-12)
    # Variance falling with signal: no measurable shot noise, read noise from the mean variance.
    falling = np.array([[100.0], [200.0]]), np.array([[30.0], [20.0]])
    r, g = fit_noise_model(*falling, quantisation_step=0.0)
    assert g[0] == 0.0 and r[0] == pytest.approx(5.0)
    # Pure shot noise measured with a small negative intercept: gain through the origin.
    m = np.array([[100.0], [300.0]])
    r, g = fit_noise_model(m, np.array([[49.7], [150.7]]), quantisation_step=0.0)
    assert r[0] == 0.0 and g[0] == pytest.approx((100 * 49.7 + 300 * 150.7) / (100**2 + 300**2))
    # One image: all of the variance is put down to shot noise.
    r, g = fit_noise_model(np.array([[400.0]]), np.array([[100.0 + 1 / 12]]))
    assert r[0] == 0.0 and g[0] == pytest.approx(0.25)  # the default step is one code
    # Two images of equal brightness: no slope to fit, the variance is read noise.
    r, g = fit_noise_model(np.array([[400.0], [400.0]]), np.array([[9.0 + 1 / 12], [9.0 + 1 / 12]]))
    assert r[0] == pytest.approx(3.0) and g[0] == 0.0


def test_backscatter_and_noise_floor_from_the_black_patch():
    rho_p, rho_b = np.array([0.8, 0.8, 0.8]), np.array([0.04, 0.05, 0.03])
    lit, bs = np.array([1000.0, 3000.0, 2000.0]), np.array([20.0, 35.0, 50.0])
    black, surround = bs + rho_b * lit, bs + rho_p * lit
    np.testing.assert_allclose(backscatter_at_black_patch(black, surround, rho_b, rho_p), bs, rtol=1e-12)
    assert (backscatter_at_black_patch(black * 0, surround, rho_b, rho_p) == 0).all()  # clipped at 0
    floors = noise_floor_from_black_patch(np.array([[10.0, 20.0], [15.0, 18.0]]), np.array([[4.0, 1.0], [1.0, 9.0]]))
    np.testing.assert_allclose(floors, [max(10 + 3 * 2, 15 + 3 * 1), max(20 + 3 * 1, 18 + 3 * 3)])


def test_region_statistics_against_a_naive_loop():
    rng = np.random.default_rng(2)
    frame = rng.normal(500.0, 7.0, (12, 15, 2)) + np.arange(15)[None, :, None] * 3.0  # a gradient
    mask = np.zeros((12, 15), bool)
    mask[2:9, 3:13] = True
    mask[5, 6] = False
    stats = region_statistics(frame, mask, dark_level=[10.0, 20.0])
    values = [frame[i, j] - [10.0, 20.0] for i in range(12) for j in range(15) if mask[i, j]]
    diffs = [frame[i, j + 1] - frame[i, j] for i in range(12) for j in range(14) if mask[i, j] and mask[i, j + 1]]
    assert stats.count == len(values)
    np.testing.assert_allclose(stats.mean, np.mean(values, axis=0), rtol=1e-12)
    np.testing.assert_allclose(stats.noise_variance, np.var(diffs, axis=0) / 2, rtol=1e-12)
    with pytest.raises(UserInputError, match="no usable pixels"):
        region_statistics(frame, np.zeros((12, 15), bool))
    column = np.zeros((12, 15), bool)
    column[:, 4] = True  # no horizontal neighbours: no noise estimate, one NaN per channel
    lonely = region_statistics(frame, column)
    assert lonely.noise_variance.shape == (2,) and np.isnan(lonely.noise_variance).all() and lonely.count == 12


def test_boxes_project_with_non_square_pixels():
    box = project_plate_box((0.15, -0.08), (0.2, 0.1), 2.5, INTR)
    # Corners of the rectangle by the pinhole model: u = cx + fx·X/Z, v = cy + fy·Y/Z.
    u0, u1 = INTR.cx + INTR.fx * 0.05 / 2.5, INTR.cx + INTR.fx * 0.25 / 2.5
    v0, v1 = INTR.cy + INTR.fy * -0.13 / 2.5, INTR.cy + INTR.fy * -0.03 / 2.5
    x, y = math.ceil(u0), math.ceil(v0)
    assert box == (x, y, math.floor(u1) - x + 1, math.floor(v1) - y + 1)
    assert surrounding_box((10, 10, 8, 4), (30, 40)) == (6, 8, 16, 8)
    assert surrounding_box((1, 1, 8, 4), (12, 12)) == (0, 0, 12, 7)
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


def test_calibration_of_rendered_plates_recovers_the_water_and_the_geometry():
    distances = [1.0, 1.7, 2.6]
    frames = [render(d)[0] * 3000.0 for d in distances]
    inputs = CalibrationInputs(channel_names=["R", "G", "B"], wavelengths_nm=[675.0, 575.0, 475.0],
                               target_reflectance=np.array([0.5, 0.5, 0.5]), lamp_position_m=LAMP, intrinsics=INTR,
                               lamp_radius_m=0.2, saturation_level=1e12)
    profile = calibrate(frames, distances, inputs)
    v = profile.array("attenuation_difference")
    b = profile.array("log_constant")
    np.testing.assert_allclose(v, C - C[0], atol=2e-4)
    np.testing.assert_allclose(b, LOG_K - LOG_K[0], atol=5e-4)
    np.testing.assert_allclose([ch.attenuation for ch in profile.channels], C, atol=2e-3)
    assert profile.intrinsics == {"fx": INTR.fx, "fy": INTR.fy, "cx": INTR.cx, "cy": INTR.cy}
    assert profile.lamp_position_m == LAMP
    # The stored mean path lengths are those of the pixels' own rays (interior of the 5×5 box).
    inner = [render(d)[1] for d in distances]
    np.testing.assert_allclose(profile.provenance.path_lengths_m, inner, rtol=1e-12)


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


def test_calibration_without_intrinsics_uses_the_optical_axis_and_close_distances():
    distances = [2.0, 2.4]  # 40 cm apart is enough
    rng = np.random.default_rng(4)
    flat = [np.exp(LOG_K - C * (d + math.dist((0, 0, d), LAMP))) + 5.0 * rng.standard_normal((16, 16, 3))
            for d in distances]
    inputs = CalibrationInputs(channel_names=["R", "G", "B"], wavelengths_nm=[None] * 3, target_reflectance=np.ones(3),
                               lamp_position_m=LAMP, saturation_level=1e12)
    profile = calibrate(flat, distances, inputs)
    np.testing.assert_allclose(profile.provenance.path_lengths_m, [d + math.dist((0, 0, d), LAMP) for d in distances],
                               rtol=1e-12)
    np.testing.assert_allclose(profile.array("attenuation_difference"), C - C[0], atol=2e-3)
    assert profile.intrinsics is None and profile.quantisation_step == 1.0
    # Uncertainty of V_k from pixel noise, two images: Var = Σ over images of (σ²/(n·E²))_k + (…)_ref, / Δd_T².
    lv = []
    for f in flat:
        mean = f.reshape(-1, 3).mean(axis=0)
        diff = (f[:, 1:] - f[:, :-1]).reshape(-1, 3)
        lv.append(diff.var(axis=0) / 2 / (f.shape[0] * f.shape[1] * mean**2))
    paths = [d + math.dist((0, 0, d), LAMP) for d in distances]
    expected = np.sqrt(lv[0] + lv[0][0] + lv[1] + lv[1][0]) / (paths[1] - paths[0])
    np.testing.assert_allclose([ch.attenuation_difference_std for ch in profile.channels][1:], expected[1:], rtol=1e-9)


def test_black_patch_gives_backscatter_per_image_and_the_noise_floor():
    rng = np.random.default_rng(5)
    rho_p, rho_b = 0.8, 0.05
    distances, lit, bs = [1.0, 2.0, 3.0], [4000.0, 1500.0, 600.0], [np.array([30.0, 40.0, 50.0]) * k for k in (1, 2, 3)]
    black_boxes = [(4, 6, 12, 10), (5, 7, 10, 8), (6, 8, 8, 8)]
    frames = []
    for d, x, b, (bx, by, bw, bh) in zip(distances, lit, bs, black_boxes):
        signal = np.exp(LOG_K - C * 2 * d)
        level = np.full((32, 28, 3), 0.0) + b + rho_p * x * signal / signal[0]
        level[by:by + bh, bx:bx + bw] = b + rho_b * x * signal / signal[0]
        frames.append(level + rng.normal(0.0, 2.0, level.shape))
    inputs = CalibrationInputs(channel_names=["R", "G", "B"], wavelengths_nm=[None] * 3, target_reflectance=np.full(3, rho_p),
                               black_reflectance=np.full(3, rho_b), black_boxes=black_boxes, saturation_level=1e12)
    profile = calibrate(frames, distances, inputs)
    samples = profile.backscatter
    for k, name in enumerate("RGB"):
        np.testing.assert_allclose(samples.levels[name], [b[k] for b in bs], atol=3.0)
        assert samples.noise_sigma[name] == pytest.approx(2.0, rel=0.25)
    assert samples.distances_m == distances
    assert samples.patch_pixels == [(x + w / 2 - 0.5, y + h / 2 - 0.5) for x, y, w, h in black_boxes]
    # Floor: the largest backscatter plus 3σ of the patch's pixel noise.
    floors = profile.array("noise_floor")
    np.testing.assert_allclose(floors, bs[2] + 3 * 2.0, atol=5.0)


def test_black_patches_need_a_surround_and_a_reflectance_to_give_backscatter():
    frames = [np.full((12, 12, 3), 1000.0) + np.random.default_rng(k).normal(0, 1, (12, 12, 3)) for k in range(2)]
    for f in frames:
        f[2:6, 2:6] = 100.0
    base = dict(channel_names=["R", "G", "B"], wavelengths_nm=[None] * 3, target_reflectance=np.full(3, 0.8))
    plain = calibrate(frames, [1.0, 2.0], CalibrationInputs(**base, black_boxes=[(2, 2, 4, 4)] * 2))
    assert plain.backscatter is None and (plain.array("noise_floor") == 0).all()
    with pytest.raises(UserInputError, match="black patch of image 1 is not surrounded by target pixels"):
        calibrate(frames, [1.0, 2.0], CalibrationInputs(**base, target_box=(2, 2, 4, 4), black_boxes=[(2, 2, 4, 4)] * 2))
