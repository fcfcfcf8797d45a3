"""The calibration's small helpers against values written out here: noise statistics of a region
(noise_point), the interior and dilation of masks, box masks at the image edge, the temporal noise
model, the (mean, variance) noise fit with its default quantisation step, and the immutability of
the results. Found unpinned by mutation testing (bench/mutation_test.py)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from uwcam.calibration import (
    LineFit,
    NoiseFit,
    NoisePoint,
    _dilate,
    _interior,
    box_mask,
    fit_lines,
    fit_noise_model,
    noise_point,
    signal_variance_temporal,
)
from uwcam.fileio import UserInputError


def test_the_interior_of_a_mask_keeps_pixels_a_margin_away_from_its_edge_and_the_image_border():
    mask = np.ones((7, 9), bool)
    mask[3, 4] = False  # a hole
    inner = _interior(mask, 1)
    expected = np.zeros((7, 9), bool)
    expected[1:6, 1:8] = True  # one pixel in from the border (outside the image is not the mask)
    expected[2:5, 3:6] = False  # and one pixel away from the hole, in every direction
    np.testing.assert_array_equal(inner, expected)
    np.testing.assert_array_equal(_interior(mask, 0), mask)
    np.testing.assert_array_equal(_interior(mask, -2), mask)


def test_dilation_grows_a_mask_by_its_radius_in_every_direction():
    mask = np.zeros((9, 9), bool)
    mask[4, 4] = True
    grown = _dilate(mask, 2)
    expected = np.zeros((9, 9), bool)
    expected[2:7, 2:7] = True
    np.testing.assert_array_equal(grown, expected)
    np.testing.assert_array_equal(_dilate(mask, 0), mask)


def test_boxes_on_the_image_edge_are_accepted_and_boxes_past_it_or_empty_are_refused():
    np.testing.assert_array_equal(box_mask((4, 6), (0, 0, 6, 4), "box"), np.ones((4, 6), bool))
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
    from uwcam.calibration import fit_attenuation_differences

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
    """Three channels, four distances, noisy: GLS; the residuals are ln(E_k/E_ref) − (b_k − V_k d)."""
    from uwcam.calibration import fit_attenuation_differences

    d = np.array([1.0, 2.0, 3.5, 5.0])
    c = np.array([0.46, 0.11, 0.06])
    rng = np.random.default_rng(2)
    ln_e = 9.0 - d[:, None] * c + rng.normal(0.0, 0.01, size=(4, 3))
    fit = fit_attenuation_differences(ln_e, d, log_variance=np.full((4, 3), 1e-4))
    ratio = ln_e - ln_e[:, :1]
    expected = ratio - (fit.log_constant - np.outer(d, fit.attenuation_difference))
    np.testing.assert_allclose(fit.residuals, expected, atol=1e-12)
    assert np.abs(fit.residuals[:, 1:]).max() > 1e-3  # noisy: the residuals are not all 0
    # Ordinary least squares per channel on the ratios gives the same V when all variances are equal
    # within a distance (the reference's shared noise is the same for every ratio of that distance).
    for k in (1, 2):
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
    from uwcam.calibration import backscatter_at_black_patch

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


def test_backscatter_variances_are_those_of_the_linear_estimate():
    """The level and the plate's light are linear in the pixel values: their variances for
    independent pixel noise σ² are σ²·Σ_p (∂/∂s_p)², the derivatives taken here by giving each
    pixel a unit value in its own channel (the estimate treats channels independently)."""
    from uwcam.calibration import backscatter_at_black_patch

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
