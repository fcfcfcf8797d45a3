"""RangeEstimator's contracts that mutation testing found unpinned: keyword-only options, an
immutable result, the channel limit, the surface-reflectance correction with a coloured target,
``samples`` and the quantisation step on every kernel path, the 3σ rule of a background, and
range_frame's smoothing stages. Expected values are closed forms written out here (the noise
model σ² = read² + gain·(E + B) + q²/12 and the two-channel transform of docs/physics.md), not
uwcam's helpers.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tests.synthetic import make_profile
from uwcam.fileio import UserInputError
from uwcam.optics import kernels
from uwcam.optics.validity import ChannelState
from uwcam.ranging.smoothing import smooth_frame, smooth_range_map
from uwcam.ranging.estimator import RangeEstimator, range_frame

C = np.array([0.46, 0.11, 0.06])  # 1/m
B = np.array([9.0, 9.6, 9.3])  # ln(K_k ρ_k)


def pair_closed_form(e: np.ndarray, var: np.ndarray, b: np.ndarray = B) -> tuple[np.ndarray, np.ndarray]:
    """Pair R–G, lamp at the camera: d_c = ln((E_R/E_G)·e^(b_G − b_R))/(c_G − c_R)/2 and
    Var d_c = ¼·(σ_R²/E_R² + σ_G²/E_G²)/(c_G − c_R)²."""
    v = C[1] - C[0]
    d = np.log(e[..., 0] / e[..., 1] * np.exp(b[1] - b[0])) / v / 2
    var_d = 0.25 * (var[..., 0] / e[..., 0] ** 2 + var[..., 1] / e[..., 1] ** 2) / v**2
    return d, var_d


def signals(paths) -> np.ndarray:
    return np.stack([np.exp(B - C * p) for p in paths])[None]  # (1, len(paths), 3)


def test_the_result_is_immutable_and_options_are_keyword_only():
    profile = make_profile(C, B, read_noise=2.0)
    result = RangeEstimator(profile)(signals([2.0]).astype(np.float32))
    with pytest.raises(dataclasses.FrozenInstanceError):
        result.range = result.variance  # type: ignore[misc]
    with pytest.raises(TypeError):
        RangeEstimator(profile, ("R", "G"))  # type: ignore[misc]


def test_the_channel_limit_is_inclusive():
    n = kernels.MAX_CHANNELS
    c = np.linspace(0.05, 0.5, n + 1)
    RangeEstimator(make_profile(c[:n], np.zeros(n)))  # exactly the limit: accepted
    with pytest.raises(UserInputError, match=f"at most {n}"):
        RangeEstimator(make_profile(c, np.zeros(n + 1)))


def test_a_surface_of_the_targets_own_hue_changes_nothing_even_for_a_coloured_target():
    """U(surface) = U(target)·(ρ_s,j/ρ_s,i)/(ρ_t,j/ρ_t,i): a surface whose reflectances are the
    target's gives back the profile's constants, whatever the target's colour."""
    rho_t = np.array([0.9, 0.5, 0.3])
    profile = make_profile(C, B, read_noise=2.0)
    channels = [ch.model_copy(update={"target_reflectance": float(r)}) for ch, r in zip(profile.channels, rho_t)]
    profile = profile.model_copy(update={"channels": channels})
    frame = signals([1.5, 2.5, 4.0]).astype(np.float32)
    plain = RangeEstimator(profile)(frame)
    same_hue = RangeEstimator(profile, surface_reflectance=2 * rho_t)(frame)  # only ratios matter
    np.testing.assert_allclose(same_hue.range, plain.range, rtol=1e-6)
    np.testing.assert_allclose(plain.range, [[1.5 / 2, 2.5 / 2, 4.0 / 2]], rtol=1e-4)


def test_one_sample_per_value_is_no_sample_count_at_all():
    profile = make_profile(C, B, read_noise=3.0, shot_gain=0.4)
    est = RangeEstimator(profile, pair=("R", "G"))
    frame = signals([1.0, 2.0, 3.0])
    with_ones = est(frame, samples=np.ones(frame.shape))
    plain = est(frame)
    np.testing.assert_allclose(with_ones.variance, plain.variance, rtol=1e-6)
    np.testing.assert_allclose(with_ones.range, plain.range, rtol=1e-6)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
@pytest.mark.parametrize("with_background", [False, True])
def test_values_averaged_over_n_samples_have_the_variance_divided_by_n(dtype, with_background):
    """Whatever the pixel type and whether a background is given, samples=n divides σ² by n."""
    read, gain, q = 1.5, 0.05, 1.0
    b = np.array([4.6, 4.9, 4.8])  # codes of 50–130: fits uint8
    profile = make_profile(C, b, read_noise=read, shot_gain=gain, quantisation_step=q, saturation_level=250.0)
    est = RangeEstimator(profile, pair=("R", "G"))
    e = np.rint(np.stack([np.exp(b - C * p) for p in (0.5, 1.0, 1.5)])[None])
    bg = np.full(e.shape, 4.0) if with_background else None
    raw = e + (0.0 if bg is None else bg)
    samples = np.full(e.shape, 9.0)
    out = est(raw.astype(dtype), background=bg, samples=samples)
    total = raw
    var = (read**2 + gain * total + q * q / 12) / 9.0
    d, var_d = pair_closed_form(e, var, b)
    np.testing.assert_allclose(out.range, d, rtol=1e-4)
    np.testing.assert_allclose(out.variance, var_d, rtol=1e-4)


def test_the_background_kernel_counts_the_quantisation_step_squared():
    read, gain, q = 0.5, 0.0, 6.0  # the step dominates: q²/12 = 3 DN² against 0.25
    profile = make_profile(C, B, read_noise=read, shot_gain=gain, quantisation_step=q)
    est = RangeEstimator(profile, pair=("R", "G"))
    e = np.rint(signals([1.0, 2.0, 3.0]))
    bg = np.full(e.shape, 100.0)
    for dtype in (np.uint16, np.float32):
        out = est((e + bg).astype(dtype), background=bg.astype(np.float32))
        var = np.full(e.shape, read**2 + q * q / 12)
        d, var_d = pair_closed_form(e, var)
        np.testing.assert_allclose(out.range, d, rtol=1e-4)
        np.testing.assert_allclose(out.variance, var_d, rtol=1e-4)


def test_an_uncertain_background_setting_changes_nothing_without_a_background():
    profile = make_profile(C, B, read_noise=2.0, shot_gain=0.3)
    frame = np.rint(signals([1.0, 2.0, 3.0])).astype(np.uint16)
    uncertain = RangeEstimator(profile, background_uncertainty=0.05)
    for f in (frame, frame.astype(np.float32)):  # the lookup-table and the numpy paths
        plain = RangeEstimator(profile)(f)
        out = uncertain(f)
        np.testing.assert_array_equal(out.range, plain.range)
        np.testing.assert_array_equal(out.variance, plain.variance)
        y, w, state = uncertain.channel_terms(f)
        assert np.all(state == ChannelState.USABLE)


def test_a_signal_exactly_three_sigma_above_the_background_is_not_usable():
    """σ² = read² = 1 DN² (no shot noise, no step): 3σ = 3 DN exactly. A channel whose signal
    is not *above* 3σ after the background is taken off carries no surface signal."""
    profile = make_profile(C, B, read_noise=1.0, quantisation_step=0.0)
    est = RangeEstimator(profile)
    background = np.array([[[50.0, 50.0, 50.0]]])
    raw = background + np.array([[[3.0, 3.0 + 1e-9, 10.0]]])
    _, _, state = est.channel_terms(raw, background)
    assert state.tolist() == [[[ChannelState.BACKSCATTER_ONLY, ChannelState.USABLE, ChannelState.USABLE]]]


def test_range_frame_smooths_at_the_stage_asked_for_and_not_at_the_other():
    profile = make_profile(C, B, read_noise=2.0, shot_gain=0.3)
    est = RangeEstimator(profile)
    rng = np.random.default_rng(5)
    paths = rng.uniform(1.0, 4.0, size=(6, 7))
    frame = np.exp(B - C * paths[..., None]).astype(np.float32)
    plain = est(frame)
    for stage in ("before", "after"):
        none = range_frame(est, frame, smoothing="none", stage=stage)
        np.testing.assert_array_equal(none.range, plain.range)
    after = range_frame(est, frame, smoothing="mean", stage="after")
    np.testing.assert_array_equal(after.range, smooth_range_map(plain, "mean").range)
    smoothed, samples = smooth_frame(frame, "mean", profile.saturation_level)
    before = range_frame(est, frame, smoothing="mean", stage="before")
    np.testing.assert_array_equal(before.range, est(smoothed, samples=samples).range)


def test_a_noise_model_below_one_code_squared_is_used_as_it_is():
    """σ² = 0.01 DN² (read 0.1, no step): the variance is that, not σ² clipped at 1 DN²."""
    profile = make_profile(C, B, read_noise=0.1, quantisation_step=0.0)
    e = signals([1.0, 2.5])
    out = RangeEstimator(profile, pair=("R", "G"))(e)
    d, var_d = pair_closed_form(e, np.full(e.shape, 0.01))
    np.testing.assert_allclose(out.range, d, rtol=1e-5)
    np.testing.assert_allclose(out.variance, var_d, rtol=1e-5)


def test_lookup_tables_keep_channels_with_a_signal_below_its_noise():
    """A channel at 3 DN with σ = 5 DN (weight E²/σ² < 1) still counts, with its own ln E: the
    uint8 lookup-table path equals weighted least squares written out (numpy.linalg.lstsq)."""
    from tests.test_independent_estimator import wls

    read = 5.0
    e = np.array([200.0, 150.0, 3.0])
    b = np.log(e) + C * 2.4  # these codes at a path of 2.4 m
    profile = make_profile(C, b, read_noise=read, quantisation_step=1.0, saturation_level=255.0)
    out = RangeEstimator(profile)(e[None, None].astype(np.uint8))
    var = read**2 + np.full(3, 1 / 12)
    assert e[2] ** 2 / var[2] < 1
    d, var_d = wls(e, C, b, var)
    assert d == pytest.approx(2.4, rel=1e-9)
    assert out.range[0, 0] == pytest.approx(d / 2, rel=1e-5)
    assert out.variance[0, 0] == pytest.approx(var_d / 4, rel=1e-4)
