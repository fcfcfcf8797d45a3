"""The calibration's small helpers against values written out here: noise statistics of a region
(noise_point), the interior and dilation of masks, box masks at the image edge, the temporal noise
model, the (mean, variance) noise fit with its default quantisation step, and the immutability of
the results. Found unpinned by mutation testing (bench/mutation_test.py)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from uwcam.calibration.fit import box_mask
from uwcam.calibration.black_patch import dilate_mask
from uwcam.calibration.line_fit import LineFit, fit_lines
from uwcam.calibration.noise_fit import NoiseFit, NoisePoint, mask_interior, fit_noise_model, noise_point, signal_variance_temporal
from uwcam.fileio import UserInputError


def test_the_interior_of_a_mask_keeps_pixels_a_margin_away_from_its_edge_and_the_image_border():
    mask = np.ones((7, 9), bool)
    mask[3, 4] = False  # a hole
    inner = mask_interior(mask, 1)
    expected = np.zeros((7, 9), bool)
    expected[1:6, 1:8] = True  # one pixel in from the border (outside the image is not the mask)
    expected[2:5, 3:6] = False  # and one pixel away from the hole, in every direction
    np.testing.assert_array_equal(inner, expected)
    np.testing.assert_array_equal(mask_interior(mask, 0), mask)
    np.testing.assert_array_equal(mask_interior(mask, -2), mask)


def test_dilation_grows_a_mask_by_its_radius_in_every_direction():
    mask = np.zeros((9, 9), bool)
    mask[4, 4] = True
    grown = dilate_mask(mask, 2)
    expected = np.zeros((9, 9), bool)
    expected[2:7, 2:7] = True
    np.testing.assert_array_equal(grown, expected)
    np.testing.assert_array_equal(dilate_mask(mask, 0), mask)


def test_boxes_on_the_image_edge_are_accepted_and_boxes_past_it_or_empty_are_refused():
    np.testing.assert_array_equal(box_mask((4, 6), (0, 0, 6, 4), "box"), np.ones((4, 6), bool))
    assert box_mask((4, 6), (5, 3, 1, 1), "box").sum() == 1  # one pixel, in the far corner
    for bad in [(0, -1, 2, 2), (-1, 0, 2, 2), (0, 0, 2, 0), (0, 0, 0, 2), (5, 0, 2, 2), (0, 3, 2, 2)]:
        with pytest.raises(UserInputError, match="does not lie inside the 6×4 image"):
            box_mask((4, 6), bad, "box")


def test_noise_point_statistics_are_those_written_out():
    rng = np.random.default_rng(11)
    frames = 100.0 + rng.normal(0.0, 2.0, size=(2, 6, 8, 2))
    mask = np.zeros((6, 8), bool)
    mask[1:5, 1:7] = True
    point = noise_point(list(frames), mask, dark_level=[10.0, 20.0])
    x = frames.mean(axis=0) - [10.0, 20.0]
    centres = [(i, j) for i in range(6) for j in range(1, 7) if mask[i, j - 1] and mask[i, j] and mask[i, j + 1]]
    assert point.count == len(centres) == 16 and point.frames == 2
    centre = np.array([x[i, j] for i, j in centres])
    second = np.array([x[i, j - 1] - 2 * x[i, j] + x[i, j + 1] for i, j in centres])
    temporal = np.array([(frames[0, i, j] - frames[1, i, j]) ** 2 / 2 for i, j in centres]).mean(axis=0)
    np.testing.assert_allclose(point.mean, centre.mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose(point.mean_square, (centre**2).mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose(point.spatial_variance, second.var(axis=0) / 6, rtol=1e-12)
    np.testing.assert_allclose(point.temporal_variance, temporal, rtol=1e-12)
    # One frame, as an array or a list of one: no temporal variance, no dark level by default.
    single = noise_point(frames[0], mask)
    assert single.temporal_variance is None and single.frames == 1
    np.testing.assert_allclose(single.mean, np.array([frames[0][i, j] for i, j in centres]).mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose(noise_point([frames[0]], mask).spatial_variance, single.spatial_variance, rtol=1e-12)


def test_noise_point_needs_two_rows_of_three_pixels():
    frame = np.random.default_rng(1).normal(100.0, 1.0, size=(5, 6, 1))
    mask = np.zeros((5, 6), bool)
    mask[1, 1:5] = True  # four in a row: two triples
    assert noise_point(frame, mask).count == 2
    mask[1, 4] = False  # three in a row: one triple
    with pytest.raises(UserInputError, match="fewer than 2 usable pixels"):
        noise_point(frame, mask)
    checker = np.indices((5, 6)).sum(axis=0) % 2 == 0  # no three in a row at all
    with pytest.raises(UserInputError):
        noise_point(frame, checker)


def test_the_temporal_noise_model_is_read_squared_plus_gain_times_the_signal():
    noise = NoiseFit(np.array([3.0, 0.5]), np.array([0.2, 0.1]), np.array([0.0, 0.0]), "test")
    signal = np.array([[100.0, 0.5], [-4.0, 2.0]])
    expected = np.array([[9.0 + 20.0, 0.25 + 0.05], [9.0 + 0.0, 0.25 + 0.2]])
    np.testing.assert_allclose(signal_variance_temporal(signal, noise), expected, rtol=1e-12)


def test_noise_model_fit_takes_a_quantisation_step_of_one_by_default():
    """σ² = read² + gain·E + 1/12 exactly, at five means of two channels: read and gain recovered."""
    means = np.array([[50.0, 80.0], [200.0, 300.0], [800.0, 1000.0], [2000.0, 2600.0], [5000.0, 6100.0]])
    read, gain = np.array([4.0, 7.0]), np.array([0.25, 0.6])
    variances = read**2 + gain * means + 1 / 12
    got_read, got_gain = fit_noise_model(means, variances)
    np.testing.assert_allclose(got_read, read, rtol=1e-6)
    np.testing.assert_allclose(got_gain, gain, rtol=1e-6)
    # Without any finite variance: zeros, one per channel (not per point).
    r0, g0 = fit_noise_model(means, np.full(means.shape, np.nan))
    assert r0.shape == g0.shape == (2,) and not r0.any() and not g0.any()


def test_results_are_immutable():
    point = NoisePoint(np.ones(1), np.ones(1), np.ones(1), None, 1, 2)
    with pytest.raises(dataclasses.FrozenInstanceError):
        point.count = 3  # type: ignore[misc]
    line = fit_lines([0.0, 1.0, 2.0], np.array([[0.0], [1.0], [2.1]]))
    assert isinstance(line, LineFit)
    with pytest.raises(dataclasses.FrozenInstanceError):
        line.slope = np.zeros(1)  # type: ignore[misc]


def test_attenuation_fit_checks_its_shapes_and_needs_two_different_paths():
    from uwcam.calibration.line_fit import fit_attenuation_differences

    ln_e = np.log(np.array([[900.0, 700.0, 400.0], [500.0, 450.0, 300.0]]))
    with pytest.raises(ValueError, match="n ≥ 2"):
        fit_attenuation_differences(ln_e[:1], [1.0])  # one distance, three channels
    with pytest.raises(ValueError, match="n ≥ 2"):
        fit_attenuation_differences(np.vstack([ln_e, ln_e[:1]]), [1.0, 2.0])  # three rows, two paths
    with pytest.raises(ValueError, match="n ≥ 2"):
        fit_attenuation_differences(ln_e[0], [1.0, 2.0, 3.0])  # not (n, N)
    with pytest.raises(UserInputError, match="all path lengths are equal"):
        fit_attenuation_differences(ln_e, [2.0, 2.0])
    fit = fit_attenuation_differences(ln_e, [1.0, 1.5])  # half a metre apart is enough
    v = (ln_e[0, 0] - ln_e[1, 0] - (ln_e[0] - ln_e[1])) / (1.0 - 1.5)
    np.testing.assert_allclose(fit.attenuation_difference, v, rtol=1e-12)


def test_attenuation_fit_residuals_are_observed_minus_fitted_log_ratios():
    """Four channels, four distances, noisy: GLS; the residuals are ln(E_k/E_ref) − (b_k − V_k d)."""
    from uwcam.calibration.line_fit import fit_attenuation_differences

    d = np.array([1.0, 2.0, 3.5, 5.0])
    c = np.array([0.46, 0.11, 0.06, 0.2])
    rng = np.random.default_rng(2)
    ln_e = 9.0 - d[:, None] * c + rng.normal(0.0, 0.01, size=(4, 4))
    fit = fit_attenuation_differences(ln_e, d, log_variance=np.full((4, 4), 1e-4))
    ratio = ln_e - ln_e[:, :1]
    expected = ratio - (fit.log_constant - np.outer(d, fit.attenuation_difference))
    np.testing.assert_allclose(fit.residuals, expected, atol=1e-12)
    assert np.abs(fit.residuals[:, 1:]).max() > 1e-3  # noisy: the residuals are not all 0
    # Ordinary least squares per channel on the ratios gives the same V when all variances are equal
    # within a distance (the reference's shared noise is the same for every ratio of that distance).
    for k in (1, 2, 3):
        slope, intercept = np.polyfit(d, ratio[:, k], 1)
        assert fit.attenuation_difference[k] == pytest.approx(-slope, rel=1e-9)
        assert fit.log_constant[k] == pytest.approx(intercept, rel=1e-9)


def _plate(shape=(40, 48), patch=(16, 24, 14, 12)):
    """A plate lit by a smooth (quadratic) field X with a black patch, and their masks."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    light = 1000.0 + 8.0 * xx - 5.0 * yy + 0.09 * xx * yy - 0.12 * (yy - 20.0) ** 2
    plate_mask = np.zeros(shape, bool)
    plate_mask[3:-3, 3:-3] = True
    x, y, bw, bh = patch
    black_mask = np.zeros(shape, bool)
    black_mask[y : y + bh, x : x + bw] = True
    return light, plate_mask, black_mask


def test_backscatter_at_the_black_patch_is_exact_for_a_smooth_lamp_field():
    """black = bs + ρb·X and plate = bs + ρp·X with X quadratic: the fit recovers bs and ln(ρp·X̄)."""
    from uwcam.calibration.black_patch import backscatter_at_black_patch

    light, plate_mask, black_mask = _plate()
    bs, rho_p, rho_b = np.array([40.0, 90.0]), np.array([0.8, 0.6]), np.array([0.05, 0.04])
    reflect = np.where(black_mask[..., None], rho_b, rho_p)
    signal = bs + reflect * light[..., None]
    est = backscatter_at_black_patch(signal, black_mask, plate_mask, rho_b, rho_p)
    inner = np.zeros_like(black_mask)
    inner[26:34, 18:28] = True  # the patch (rows 24–35, columns 16–29) without its 2-pixel edge
    np.testing.assert_array_equal(est.pixels, inner)
    np.testing.assert_allclose(est.level, bs, rtol=1e-9)
    np.testing.assert_allclose(est.black_mean, (bs + rho_b * light[inner][:, None]).mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose(est.plate_log, np.log(rho_p * light[inner].mean()), rtol=1e-9)
    assert est.variance.shape == est.plate_log_variance.shape == (2,)
    assert not est.variance.any() and not est.plate_log_variance.any()  # no pixel variance given


def test_a_black_patch_projected_pixels_off_is_measured_where_the_image_shows_it():
    """A pose from a few markers put the projected patch 4 px off (the simulated tank at 1 m): the
    box then reached over the grey plate, which read as backscatter hundreds of times the true
    level. The patch is located in the image near the projection; the level is then the true one."""
    from uwcam.calibration.black_patch import backscatter_at_black_patch, locate_black_patch

    shape, true_patch = (60, 72), (24, 20, 20, 18)
    light, plate_mask, patch = _plate(shape, true_patch)
    bs, rho_p, rho_b = np.array([1.5, 6.0, 9.0]), np.array([0.18, 0.18, 0.18]), np.array([0.03, 0.03, 0.03])
    signal = bs + np.where(patch[..., None], rho_b, rho_p) * light[..., None]
    x, y, w, h = true_patch
    for dx, dy in ((4, 0), (-3, 2), (0, -4)):
        projected = np.zeros(shape, bool)
        projected[y + dy : y + dy + h, x + dx : x + dx + w] = True
        target = plate_mask & ~projected
        located = locate_black_patch(signal, projected, target)
        np.testing.assert_array_equal(located, patch)
        est = backscatter_at_black_patch(signal, located, plate_mask & ~located, rho_b, rho_p)
        np.testing.assert_allclose(est.level, bs, rtol=1e-6)
        # What the projected box alone gives: grey plate inside the "black" (why the patch is located).
        off = backscatter_at_black_patch(signal, projected, target, rho_b, rho_p)
        assert np.all(np.abs(off.level - bs) > 10.0), off.level
    # An unlit frame (nothing to tell patch from plate by): the projection is kept.
    dim = np.full(shape + (3,), 5.0)
    np.testing.assert_array_equal(locate_black_patch(dim, projected, plate_mask & ~projected), projected)


def test_backscatter_variances_are_those_of_the_linear_estimate():
    """The level and the plate's light are linear in the pixel values: their variances for
    independent pixel noise σ² are σ²·Σ_p (∂/∂s_p)², the derivatives taken here by giving each
    pixel a unit value in its own channel (the estimate treats channels independently)."""
    from uwcam.calibration.black_patch import backscatter_at_black_patch

    light, plate_mask, black_mask = _plate()
    h, w = light.shape
    rho_p, rho_b, sigma2 = 0.8, 0.05, 30.0
    reflect = np.where(black_mask, rho_b, rho_p)
    signal = 40.0 + reflect * light
    est = backscatter_at_black_patch(signal[..., None], black_mask, plate_mask, [rho_b], [rho_p],
                                     pixel_variance=np.full((h, w, 1), sigma2))
    impulses = np.eye(h * w).reshape(h, w, h * w)
    unit = backscatter_at_black_patch(impulses, black_mask, plate_mask, np.full(h * w, rho_b), np.full(h * w, rho_p))
    d_level, d_black = unit.level, unit.black_mean
    alpha, beta = rho_p / (rho_p - rho_b), rho_b / (rho_p - rho_b)
    d_plate = (alpha * d_black - d_level) / beta  # level = α·mean(black) − β·mean(plate fit)
    d_difference = d_plate - d_black
    difference = rho_p * light[est.pixels].mean() * (rho_p - rho_b) / rho_p
    np.testing.assert_allclose(est.variance, sigma2 * (d_level**2).sum(), rtol=1e-9)
    np.testing.assert_allclose(est.plate_log_variance, sigma2 * (d_difference**2).sum() / difference**2, rtol=1e-9)


def _wls(a: np.ndarray, y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted least squares written out: the normal equations AᵀWA p = AᵀWy."""
    return np.linalg.solve(a.T @ (a * w[:, None]), a.T @ (w * y))


def _points(e, t, s, frames):
    return [NoisePoint(np.array([ei]), np.array([ei * ei * 1.02]), np.array([si]), None if ti is None else np.array([ti]),
                       frames, 400) for ei, ti, si in zip(e, t, s)]


def test_noise_fit_from_repeated_frames_is_weighted_by_one_over_variance_squared():
    """Points off the model (±4 %): the fit is the weighted least-squares one, with weights
    1/t² for read and shot noise (t − q²/12 = read² + gain·E) and 1/s² for the fixed pattern
    (s − t_model/m = fpn²·mean(E²)); step 2 DN, so q²/12 = 1/3 DN²."""
    from uwcam.calibration.noise_fit import fit_noise

    q = 4.0 / 12.0
    e = np.array([60.0, 300.0, 1500.0, 6000.0])
    t = (20.0 + 0.4 * e + q) * np.array([1.04, 0.97, 1.03, 0.98])
    m = 4
    s = (t / m + 2e-5 * e * e * 1.02) * np.array([0.96, 1.05, 0.98, 1.02])
    fit = fit_noise(_points(e, t, s, m), quantisation_step=2.0)
    read2, gain = _wls(np.stack([np.ones_like(e), e], 1), t - q, 1 / t**2)
    assert read2 > 0 and gain > 0
    np.testing.assert_allclose([fit.read_noise[0] ** 2, fit.shot_gain[0]], [read2, gain], rtol=1e-9)
    e2 = e * e * 1.02
    residual = s - (read2 + gain * e + q) / m
    fpn2 = np.sum(residual * e2 / s**2) / np.sum(e2 * e2 / s**2)
    assert fpn2 > 0
    assert fit.fixed_pattern[0] ** 2 == pytest.approx(fpn2, rel=1e-9)


def test_noise_fit_from_single_frames_is_weighted_by_one_over_variance_squared():
    from uwcam.calibration.noise_fit import fit_noise

    e = np.array([50.0, 200.0, 900.0, 3000.0, 9000.0])
    e2 = e * e * 1.02
    s = (16.0 + 0.5 * e + 3e-5 * e2 + 1 / 12) * np.array([1.03, 0.96, 1.04, 0.97, 1.02])
    fit = fit_noise(_points(e, [None] * 5, s, 1))  # default step: 1 DN
    expected = _wls(np.stack([np.ones_like(e), e, e2], 1), s - 1 / 12, 1 / s**2)
    assert np.all(expected > 0)
    got = [fit.read_noise[0] ** 2, fit.shot_gain[0], fit.fixed_pattern[0] ** 2]
    np.testing.assert_allclose(got, expected, rtol=1e-8)


def test_noise_fit_of_tiny_variances_is_not_clipped_at_one():
    """Float data (step 0) with variances of 0.02–0.4 DN²: weights 1/t², not 1/max(t, 1)²."""
    from uwcam.calibration.noise_fit import fit_noise

    e = np.array([2.0, 10.0, 40.0])
    t = (0.01 + 0.009 * e) * np.array([1.1, 0.9, 1.05])
    s = t * np.array([1.0, 1.0, 1.0])
    fit = fit_noise(_points(e, t, s, 1), quantisation_step=0.0)
    read2, gain = _wls(np.stack([np.ones_like(e), e], 1), t, 1 / t**2)
    assert read2 > 0 and gain > 0
    np.testing.assert_allclose([fit.read_noise[0] ** 2, fit.shot_gain[0]], [read2, gain], rtol=1e-9)
    single = fit_noise(_points(e, [None] * 3, s * np.array([1.0, 1.2, 0.9]), 1), quantisation_step=0.0)
    s1 = s * np.array([1.0, 1.2, 0.9])
    a = np.stack([np.ones_like(e), e, e * e * 1.02], 1)
    # Non-negative: check optimality (KKT) of the fit with weights 1/s² directly.
    p = np.array([single.read_noise[0] ** 2, single.shot_gain[0], single.fixed_pattern[0] ** 2])
    grad = a.T @ ((a @ p - s1) / s1**2)
    scale = np.abs(a.T @ (s1 / s1**2))
    assert np.all(np.where(p > 0, np.abs(grad) <= 1e-9 * scale, grad >= -1e-9 * scale)), (p, grad)


def test_non_negative_least_squares_keeps_a_small_positive_solution():
    """One parameter: p = max(0, Σwy/Σw). For y = (0.5, −0.4): p = 0.05, better than 0."""
    from uwcam.calibration.noise_fit import _nonnegative_least_squares

    p = _nonnegative_least_squares(np.ones((2, 1)), np.array([0.5, -0.4]), np.ones(2))
    assert p[0] == pytest.approx(0.05, rel=1e-12)
    p = _nonnegative_least_squares(np.ones((2, 1)), np.array([0.3, -0.4]), np.ones(2))
    assert p[0] == 0.0


def test_log_mean_variance_is_the_sum_over_pixels_of_their_share_squared():
    """Written out: each used pixel's 5×5 box spreads 1/(25·P) to every pixel in it; the variance of
    the mean of ln(box average) is Σ share² σ²/E² (E clipped at 1e-30 only, not at 1 DN)."""
    from uwcam.calibration.line_fit import SMOOTHING, log_mean_variance

    assert SMOOTHING == 5
    h, w = 12, 14
    pixels = np.zeros((h, w), bool)
    pixels[4:8, 3:10] = True
    pixels[5, 3] = False
    rng = np.random.default_rng(4)
    signal = rng.uniform(0.3, 50.0, size=(h, w, 2))  # some pixels under 1 DN
    variance = rng.uniform(1.0, 9.0, size=(h, w, 2))
    count = pixels.sum()
    share = np.zeros((h, w))
    for i, j in zip(*np.nonzero(pixels)):
        share[max(i - 2, 0) : i + 3, max(j - 2, 0) : j + 3] += 1.0 / (25 * count)
    expected = (share[..., None] ** 2 * variance / signal**2).sum(axis=(0, 1))
    np.testing.assert_allclose(log_mean_variance(pixels, signal, variance), expected, rtol=1e-9)
    assert (signal[share > 0] < 1).any()


def test_log_signal_leaves_out_pixels_without_signal_in_every_channel():
    from uwcam.calibration.line_fit import smoothed_log_signal

    frame = np.full((14, 14, 2), 100.0)
    frame[3:10, 3:10, 1] = 0.0  # a 7×7 block dark in one channel: its centre's 5×5 average is 0
    mask = np.ones((14, 14), bool)
    logs, used = smoothed_log_signal(frame, mask)
    assert not used[5:8, 5:8].any() and used[2, 2] and np.all(np.isfinite(logs))


def test_backscatter_log_variance_of_a_faint_plate_is_not_clipped_at_one():
    from uwcam.calibration.black_patch import backscatter_at_black_patch

    light, plate_mask, black_mask = _plate()
    light = light / 2000.0  # about 0.5: the plate gives under 1 DN more than the patch
    signal = (5.0 + np.where(black_mask, 0.05, 0.8) * light)[..., None]
    est = backscatter_at_black_patch(signal, black_mask, plate_mask, [0.05], [0.8],
                                     pixel_variance=np.full(signal.shape, 0.01))
    difference = 0.75 * light[est.pixels].mean()
    assert difference < 1.0 and est.plate_log_variance[0] > 0
    assert est.plate_log[0] == pytest.approx(np.log(0.8 * light[est.pixels].mean()), rel=1e-9)  # not clipped at 1 DN
    brighter = backscatter_at_black_patch(signal * 100.0, black_mask, plate_mask, [0.05], [0.8],
                                          pixel_variance=np.full(signal.shape, 0.01))
    # ln-variance is var/difference²: a hundred times the light, the same noise: 10⁴ times less.
    assert est.plate_log_variance[0] == pytest.approx(1e4 * brighter.plate_log_variance[0], rel=1e-9)


def test_more_results_are_immutable_and_image_size_errors_say_width_by_height():
    from uwcam.calibration.fit import CalibrationInputs, calibrate
    from uwcam.calibration.black_patch import BackscatterEstimate

    est = BackscatterEstimate(np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1), np.zeros((2, 2), bool))
    with pytest.raises(dataclasses.FrozenInstanceError):
        est.level = np.ones(1)  # type: ignore[misc]
    inputs = CalibrationInputs(channel_names=["R", "G"], wavelengths_nm=[None, None], target_reflectance=np.ones(2))
    with pytest.raises(dataclasses.FrozenInstanceError):
        inputs.reference = 1  # type: ignore[misc]
    frames = [np.ones((4, 6, 2)), np.ones((5, 6, 2))]
    with pytest.raises(UserInputError, match="image 2 is 6×5 but the first image is 6×4"):
        calibrate(frames, [1.0, 2.0], inputs)


def test_noise_model_fit_with_fewer_points_than_channels():
    means = np.array([[100.0, 80.0, 60.0], [900.0, 700.0, 500.0]])
    read, gain = np.array([3.0, 4.0, 5.0]), np.array([0.2, 0.3, 0.4])
    got_read, got_gain = fit_noise_model(means, read**2 + gain * means + 1 / 12)
    np.testing.assert_allclose(got_read, read, rtol=1e-6)
    np.testing.assert_allclose(got_gain, gain, rtol=1e-6)


def test_variance_floor_of_float_values_under_one():
    from uwcam.calibration.noise_fit import variance_floor

    e = np.array([0.25, 3.0])
    np.testing.assert_allclose(variance_floor(e, 0.0), (e * 2.0**-23) ** 2 / 12, rtol=1e-12)


def test_log_signal_takes_off_the_dark_level_keeps_dim_pixels_and_stays_inside_the_image():
    from uwcam.calibration.line_fit import smoothed_log_signal

    frame = np.full((10, 10, 2), [10.5, 40.0])
    logs, used = smoothed_log_signal(frame, np.ones((10, 10), bool), dark_level=[10.0, 20.0])
    expected = np.zeros((10, 10), bool)
    expected[2:8, 2:8] = True  # whole 5×5 boxes inside the image only
    np.testing.assert_array_equal(used, expected)
    np.testing.assert_allclose(logs, np.log([[0.5, 20.0]] * 36), rtol=1e-12)  # 0.5 DN still counts


def test_calibration_results_are_immutable():
    from tests.test_calibration import frames, inputs
    from uwcam.calibration.fit import calibrate_with_details

    details = calibrate_with_details(frames([1.0, 2.0]), [1.0, 2.0], inputs())
    for obj, field in [(details, "profile"), (details.noise, "method"), (details.fit, "method"), (details.groups[0], "images")]:
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(obj, field, None)


@pytest.mark.parametrize("frames", [2, 4])
def test_few_frames_per_distance_give_the_cameras_read_noise(frames):
    """Fitted from the plate's bins (thousands of DN, where read noise is a few percent of the
    variance) and a small black patch, 2-4 frames per distance gave a read noise of 0-50 DN for
    the simulated camera's 26.4 (σ of dim pixels then too small). The light beside the plate pins
    it. Expected: the simulator's camera, gain·√(read² + dark electrons) DN, and its gain."""
    from uwcam.simulation import CameraModel, Lamp, water_preset
    from uwcam.simulation.tank import calibrate_in_simulation

    camera = CameraModel()
    water = water_preset("jerlov-IB", [675.0, 575.0, 475.0])
    profile = calibrate_in_simulation(water, Lamp(position=(0.3, 0.0, 0.0)), (320, 240), camera,
                                      frames_per_distance=frames)
    read = camera.gain_dn_per_e * np.sqrt(camera.read_noise_e**2 + camera.dark_current_e)
    np.testing.assert_allclose(profile.array("read_noise"), read, rtol=0.06)
    np.testing.assert_allclose(profile.array("shot_gain"), camera.gain_dn_per_e, rtol=0.06)


def _located(dark_boxes, box, shape=(80, 90), dark=50.0, plate=1000.0, plate_mask=None):
    """locate_black_patch on a frame of lit plate (``plate`` DN summed over three channels) with
    these dark rectangles ((x, y, w, h), ``dark`` DN summed), the pose's patch at ``box``: the
    located mask and the projected one."""
    from uwcam.calibration.black_patch import locate_black_patch

    light = np.full(shape, plate)
    for x, y, w, h in dark_boxes:
        light[y : y + h, x : x + w] = dark
    projected = np.zeros(shape, bool)
    x, y, w, h = box
    projected[y : y + h, x : x + w] = True
    mask = np.ones(shape, bool) if plate_mask is None else plate_mask
    signal = np.repeat(light[..., None] / 3.0, 3, axis=-1)
    return locate_black_patch(signal, projected, mask & ~projected), projected


def _box_mask(shape, box):
    x, y, w, h = box
    out = np.zeros(shape, bool)
    out[y : y + h, x : x + w] = True
    return out


@pytest.mark.parametrize("side, margin", [(18, 5), (28, 7)])
def test_the_patch_is_found_as_far_off_as_the_search_margin_and_no_farther(side, margin):
    """The search reaches a quarter of the projected box's smaller side beyond it, at least 5 px:
    a patch off by exactly that much is found whole; one pixel more and the part beyond is cut
    off, so what is found is not the patch."""
    box = (30, 25, side + 4, side)
    for off in (margin, margin + 1):
        true = (box[0] + off, box[1], box[2], box[3])
        located, projected = _located([true], box)
        assert np.array_equal(located, _box_mask(projected.shape, true)) == (off == margin), off


def test_a_patch_that_barely_stands_out_is_not_searched_for():
    """The plate beside the patch must be brighter than 1.5 times the patch's light (in the
    sums of the channels) for the image to tell where the patch is: at exactly 1.5 the
    projection is kept; just above it the patch is located."""
    box, true = (30, 25, 20, 18), (32, 25, 20, 18)
    kept, projected = _located([true], box, dark=100.0, plate=150.0)
    np.testing.assert_array_equal(kept, projected)
    found, _ = _located([true], box, dark=100.0, plate=150.5)
    np.testing.assert_array_equal(found, _box_mask(projected.shape, true))


def test_a_dark_region_of_implausible_size_leaves_the_projection():
    """The dark region found must hold from half to 1.6 times the projected box's pixels: a
    box of 20×20 (400 px) with a dark region of 630 or 640 px inside the search is taken, 660 px
    is not; of two dark regions inside the box, split by a stripe of plate, the larger is taken
    when it holds half the box (200 px), not when it holds 180."""
    box = (35, 30, 20, 20)
    for regions, taken in (([(30, 30, 30, 21)], True), ([(30, 30, 30, 21), (30, 51, 10, 1)], True),
                           ([(30, 30, 30, 22)], False)):
        # 30 wide: the box and the 5-px margin either side; 630, 640 (1.6 × 400 exactly) and 660 px
        located, projected = _located(regions, box)
        expected = np.any([_box_mask(projected.shape, r) for r in regions], axis=0) if taken else projected
        np.testing.assert_array_equal(located, expected)
    for first, taken in ((8, True), (9, False)):
        second = 18 - first  # rows: first, a stripe of 2 rows of plate, the rest
        a, b = (35, 30, 20, first), (35, 30 + first + 2, 20, second)
        located, projected = _located([a, b], box)
        expected = _box_mask(projected.shape, b) if taken else projected
        np.testing.assert_array_equal(located, expected)


def test_too_little_plate_around_the_box_leaves_the_projection():
    """The plate's light is measured on a ring around the box (from 2 px beyond the margin to
    twice the margin and 2 px): with only 15 of its pixels on the plate, the projection is kept;
    with 16 the patch is located."""
    shape, box, true = (80, 90), (30, 25, 20, 18), (32, 25, 20, 18)
    # margin 5: the ring spans 7 to 12 px beyond the box; its pixels on one row above the box.
    for count, located_patch in ((15, False), (16, True)):
        plate_mask = np.zeros(shape, bool)
        plate_mask[25 - 8, 30 : 30 + count] = True
        located, projected = _located([true], box, plate_mask=plate_mask)
        expected = _box_mask(shape, true) if located_patch else projected
        np.testing.assert_array_equal(located, expected)
