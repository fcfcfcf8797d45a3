"""Per-channel terms of the transform with a known background (backscatter) subtracted, against
the noise model written out by hand: σ² = read² + gain·(E + B) + (fpn·(E + B))² + q²/12, where
E is the signal left after the background B; a channel is usable only 3σ above the background."""

from __future__ import annotations

import numpy as np
import pytest

from tests.synthetic import RGB_ATTENUATION, make_profile
from uwcam.ranging.estimator import RangeEstimator

READ, GAIN, Q, DARK, FLOOR, SAT = 3.0, 0.4, 1.0, 60.0, 12.0, 4000.0
B = np.log([0.7, 1.0, 0.8])


def naive_terms(raw: np.ndarray, background: np.ndarray, b: np.ndarray):
    h, w, n = raw.shape
    y = np.zeros(raw.shape)
    weight = np.zeros(raw.shape)
    usable = np.zeros(raw.shape, bool)
    for i in range(h):
        for j in range(w):
            for k in range(n):
                e = float(raw[i, j, k]) - DARK - float(background[i, j, k])
                total = max(e + float(background[i, j, k]), 0.0)
                var = READ**2 + GAIN * total + Q**2 / 12
                ok = raw[i, j, k] < SAT and e > FLOOR and e > 3 * np.sqrt(var)
                if ok:
                    usable[i, j, k] = True
                    weight[i, j, k] = e * e / var
                    y[i, j, k] = np.log(e) - b[k]
    return y, weight, usable


def test_background_is_subtracted_but_still_counts_in_the_noise():
    profile = make_profile(RGB_ATTENUATION, B, read_noise=READ, shot_gain=GAIN, dark_level=DARK, noise_floor=FLOOR,
                           saturation_level=SAT, quantisation_step=Q)
    est = RangeEstimator(profile, calibration_variance=False)
    rng = np.random.default_rng(5)
    raw = rng.uniform(40, 4100, (6, 7, 3)).round()
    background = rng.uniform(0, 600, raw.shape)
    y, weight, state = est.channel_terms(raw, background)
    ref_y, ref_w, ref_ok = naive_terms(raw, background, np.array(profile.array("log_constant")))
    np.testing.assert_array_equal(state == 0, ref_ok)
    np.testing.assert_allclose(weight, ref_w, rtol=1e-9)
    np.testing.assert_allclose(y, ref_y, rtol=1e-9, atol=1e-12)
    assert 0 < ref_ok.mean() < 1  # both usable and unusable channels were exercised


def test_ranging_with_a_background_equals_ranging_the_background_free_frame_at_its_range():
    """A plate whose light is E_k plus a background B_k: subtracting B gives the range of E alone."""
    profile = make_profile(RGB_ATTENUATION, B, read_noise=READ, shot_gain=GAIN, dark_level=DARK, noise_floor=FLOOR,
                           saturation_level=65535.0, quantisation_step=Q)
    est = RangeEstimator(profile, calibration_variance=False)
    d_t = 5.0  # lamp at the camera: camera range 2.5 m
    e = 3000.0 * np.exp(B - RGB_ATTENUATION * d_t) / np.exp(B - RGB_ATTENUATION * d_t).max()
    background = np.broadcast_to(np.array([40.0, 300.0, 500.0]), (4, 5, 3)).copy()
    raw = DARK + e + background
    out = est(raw.astype(np.float32), background=background.astype(np.float32))
    np.testing.assert_allclose(out.range, 2.5, rtol=1e-4)
    plain = est(raw.astype(np.float32))  # the background left in: the water's colour biases the range
    assert np.all(np.abs(plain.range - 2.5) > 0.05)


def test_compiled_background_kernel_equals_the_numpy_terms_with_every_state():
    """Ranging with a background runs a compiled kernel; the terms written in numpy
    (channel_terms → pack_pairs → fuse_arrays) are the reference, on frames mixing usable,
    saturated, dark, backscatter-only channels, a pair selection and an open-water level."""
    import pytest

    from uwcam.optics import Intrinsics, kernels

    if kernels.fuse_background is None:
        pytest.skip("numba is not installed: ranging with a background runs the numpy terms themselves")
    rng = np.random.default_rng(9)
    intr = Intrinsics(150.0, 118.0, 71.3, 66.8)
    cases = ((None, None, 0.0, None, False), (("R", "B"), None, 0.0, None, False), (None, [30.0, 80.0, 60.0], 0.0, None, False),
             (None, None, 0.05, None, False), (None, None, 0.003, [0.002, 0.004, 0.0], True))
    for pair, levels, u, residual, doubted in cases:
        profile = make_profile(RGB_ATTENUATION, B, read_noise=READ, shot_gain=GAIN, dark_level=DARK, noise_floor=FLOOR,
                               saturation_level=SAT, quantisation_step=Q, lamp=(0.3, -0.2, 0.0), intrinsics=intr)
        profile = profile.model_copy(update={"channels": [c.model_copy(update={"fixed_pattern": 0.01}) for c in profile.channels]})
        est = RangeEstimator(profile, pair=pair, backscatter_level=levels, calibration_variance=False, background_uncertainty=u,
                             background_fixed_pattern=residual)
        raw = rng.uniform(40, 4100, (40, 56, 3)).round().astype(np.uint16)
        background = rng.uniform(0, 400, raw.shape).astype(np.float32)
        doubt = rng.uniform(0, 900, raw.shape).astype(np.float32) if doubted else None
        got = est(raw, background=background, background_variance=doubt)
        y, weight, state = est.channel_terms(raw, background, background_variance=doubt)
        pairs = kernels.pack_pairs(y, weight, state, 2, 3)
        h, w = raw.shape[:2]
        ref = [np.empty((h, w), np.float32), np.empty((h, w), np.float32), np.empty((h, w), np.uint8)]
        kernels.fuse_arrays(pairs, est._c, (0.0,) * 3, est._cv, est._geo, est.bounds, *ref)
        np.testing.assert_array_equal(got.reasons, ref[2])
        # The kernel's terms are float32 (numpy's float64): ln E's rounding, ~1e-6, over attenuation
        # differences of ~0.1–0.5 1/m is ~1e-5 m of range.
        np.testing.assert_allclose(got.range, ref[0], rtol=2e-6, atol=3e-5, equal_nan=True)
        np.testing.assert_allclose(got.variance, ref[1], rtol=2e-5, equal_nan=True)
        assert len(set(np.unique(ref[2]))) >= 3  # several reasons exercised


def test_a_background_that_knows_each_pixels_response_leaves_only_its_residual_fixed_pattern():
    """With the fixed pattern f of the profile and r of the background (the part of each pixel's
    response the background's model did not take out), a value's fixed-pattern variance is
    r²·(E + B)² + (f² − r²)·E² (E the surface's light, B the background), and a per-value
    background variance adds as it is: written out here by hand."""
    f, r = np.array([0.01, 0.01, 0.02]), np.array([0.002, 0.01, 0.0])
    profile = make_profile(RGB_ATTENUATION, B, read_noise=READ, shot_gain=GAIN, dark_level=DARK, noise_floor=FLOOR,
                           saturation_level=65535.0, quantisation_step=Q)
    profile = profile.model_copy(update={"channels": [c.model_copy(update={"fixed_pattern": float(v)})
                                                      for c, v in zip(profile.channels, f)]})
    est = RangeEstimator(profile, calibration_variance=False, background_fixed_pattern=r, background_uncertainty=0.003)
    background = np.array([[[20000.0, 30000.0, 10000.0]]])
    e = np.array([3000.0, 6000.0, 4000.0])
    doubt = np.array([[[400.0, 0.0, 2500.0]]])
    raw = DARK + e + background
    _, weight, state = est.channel_terms(raw, background, background_variance=doubt)
    total = e + background[0, 0]
    var = (READ**2 + GAIN * total + Q**2 / 12 + (r * total) ** 2 + (f**2 - r**2) * e**2
           + (0.003 * background[0, 0]) ** 2 + doubt[0, 0])
    assert np.all(state[0, 0] == 0)
    np.testing.assert_allclose(weight[0, 0], e**2 / var, rtol=1e-12)
    with pytest.raises(ValueError, match="background_fixed_pattern"):
        RangeEstimator(profile, background_fixed_pattern=[0.01, float("nan"), 0.0])
    with pytest.raises(ValueError, match="pass the background too"):
        est(raw.astype(np.float32), background_variance=doubt.astype(np.float32))


def test_an_uncertain_background_adds_its_share_to_the_noise():
    """With a background known to 10 %: σ² = (noise model) + (0.1·B)², in the weights and in the
    3σ test; a channel whose light is not 3σ above the background is left out."""
    profile = make_profile(RGB_ATTENUATION, B, read_noise=READ, shot_gain=GAIN, dark_level=DARK, noise_floor=FLOOR,
                           saturation_level=SAT, quantisation_step=Q)
    est = RangeEstimator(profile, calibration_variance=False, background_uncertainty=0.1)
    raw = np.array([[[DARK + 1000 + 100, DARK + 200 + 1000, DARK + 600 + 3000]]])
    background = np.array([[[100.0, 1000.0, 3000.0]]])
    _, weight, state = est.channel_terms(raw, background)
    e = np.array([1000.0, 200.0, 600.0])
    var = READ**2 + GAIN * (e + background[0, 0]) + Q**2 / 12 + (0.1 * background[0, 0]) ** 2
    ok = e > 3 * np.sqrt(var)  # R: 1000 > 3·32 yes; G: 200 > 3·104 no; B: 600 > 3·302 no
    assert list(ok) == [True, False, False]
    np.testing.assert_array_equal(state[0, 0] == 0, ok)
    assert weight[0, 0, 0] == pytest.approx(e[0] ** 2 / var[0], rel=1e-12)
    with pytest.raises(ValueError, match="background_uncertainty"):
        RangeEstimator(profile, background_uncertainty=float("nan"))


@pytest.mark.parametrize("u", [-0.01, 10.5, float("inf"), float("nan")])
def test_background_uncertainty_out_of_range_is_refused(u):
    profile = make_profile(RGB_ATTENUATION, B)
    with pytest.raises(ValueError, match="background_uncertainty must be a relative uncertainty from 0 to 10"):
        RangeEstimator(profile, background_uncertainty=u)
    RangeEstimator(profile, background_uncertainty=10.0)  # the bounds themselves are allowed
    RangeEstimator(profile, background_uncertainty=0.0)
