"""The frame estimator against closed forms written out here, not against uwcam's own helpers.

Every expected value below is computed in this file from docs/physics.md's formulas with plain numpy:
the camera noise model σ² = read² + gain·E + step²/12, the two-channel transform and its
variance, and the weighted least-squares fusion solved by ``numpy.linalg.lstsq`` (a different
algorithm from the one under test). Nothing is taken from ``uwcam.optics``.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.synthetic import make_profile
from uwcam.optics import fused_path_length, pair_path_length, pair_path_variance, surface_log_constant
from uwcam.optics.reflectance import reflectance_ratio_from_range
from uwcam.optics.validity import Reason
from uwcam.ranging.estimator import RangeEstimator

C = np.array([0.46, 0.11, 0.06])  # 1/m
B = np.array([9.0, 9.6, 9.3])  # ln(K_k ρ_k)
READ, GAIN, STEP, DARK = 12.0, 0.5, 2.0, 64.0


def sigma2(e: np.ndarray) -> np.ndarray:
    """The camera noise model, written out (DN²)."""
    return READ * READ + GAIN * e + STEP * STEP / 12.0


def wls(e: np.ndarray, c: np.ndarray, b: np.ndarray, var: np.ndarray) -> tuple[float, float]:
    """Weighted least squares for y_k = a − c_k·d with weights E_k²/σ_k², by lstsq: (d, Var d)."""
    y = np.log(e) - b
    w = e * e / var
    design = np.stack([np.ones_like(c), -c], axis=1)
    sw = np.sqrt(w)
    (a, d), *_ = np.linalg.lstsq(design * sw[:, None], y * sw, rcond=None)
    cov = np.linalg.inv(design.T @ (design * w[:, None]))
    return float(d), float(cov[1, 1])


def signals_at(path_length: float, c=C, b=B) -> np.ndarray:
    return np.exp(b - c * path_length)


@pytest.mark.parametrize("dtype", [np.uint16, np.float64])
def test_two_channel_range_and_variance_follow_the_closed_form(dtype):
    """Pair R–G, lamp beside the camera: d_c = ln((E_i/E_j)·U)/V / 2,
    Var d_c = ¼·(σ_i²/E_i² + σ_j²/E_j²)/V², σ² with the read noise squared."""
    profile = make_profile(C, B, read_noise=READ, shot_gain=GAIN, dark_level=DARK, quantisation_step=STEP)
    est = RangeEstimator(profile, pair=("R", "G"))
    e_true = np.array([[signals_at(2.0), signals_at(3.3), signals_at(5.1)]])  # (1, 3, 3)
    raw = np.rint(e_true + DARK) if dtype == np.uint16 else e_true + DARK
    out = est(raw.astype(dtype))
    e = raw - DARK
    v = C[1] - C[0]
    u = np.exp(B[1] - B[0])
    d_t = np.log(e[..., 0] / e[..., 1] * u) / v
    var_t = (sigma2(e[..., 0]) / e[..., 0] ** 2 + sigma2(e[..., 1]) / e[..., 1] ** 2) / v**2
    np.testing.assert_allclose(out.range, d_t / 2, rtol=2e-5)
    np.testing.assert_allclose(out.variance, var_t / 4, rtol=2e-5)
    assert (out.reasons == Reason.VALID).all()
    # The same numbers from the pure two-channel functions.
    np.testing.assert_allclose(pair_path_length(e[..., 0], e[..., 1], v, u), d_t, rtol=1e-12)
    np.testing.assert_allclose(pair_path_variance(e[..., 0], e[..., 1], sigma2(e[..., 0]), sigma2(e[..., 1]), v), var_t, rtol=1e-12)


def test_read_noise_enters_squared():
    """Dim pixels, where read noise dominates: read² (144) and read (12) differ by a factor ~5."""
    profile = make_profile(C, B, read_noise=READ, shot_gain=0.0, quantisation_step=STEP)
    est = RangeEstimator(profile, pair=("R", "G"))
    e = np.array([[[40.0, 90.0, 70.0]]])
    out = est(e)
    v = C[1] - C[0]
    expected = 0.25 * (READ**2 + STEP**2 / 12) * (1 / 40.0**2 + 1 / 90.0**2) / v**2
    assert out.variance[0, 0] == pytest.approx(expected, rel=1e-5)


@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_fused_range_and_variance_equal_weighted_least_squares(dtype):
    profile = make_profile(C, B, read_noise=READ, shot_gain=GAIN, dark_level=DARK, quantisation_step=STEP)
    est = RangeEstimator(profile)
    paths = [1.5, 4.0, 7.5, 11.0]
    raw = np.array([[np.rint(signals_at(p) + DARK) for p in paths]]).astype(dtype)
    out = est(raw)
    for k, p in enumerate(paths):
        e = raw[0, k].astype(np.float64) - DARK
        d, var = wls(e, C, B, sigma2(e))
        assert d == pytest.approx(p, abs=0.02)  # rounding to codes moves the truth a little
        assert out.range[0, k] == pytest.approx(d / 2, rel=2e-5)
        assert out.variance[0, k] == pytest.approx(var / 4, rel=2e-5)
        fused, fused_var = fused_path_length(e, C, B, sigma2(e))
        assert fused == pytest.approx(d, rel=1e-10) and fused_var == pytest.approx(var, rel=1e-10)


def test_fusion_of_many_channels_with_unequal_weights_and_an_unusable_one():
    rng = np.random.default_rng(3)
    c = np.array([0.9, 0.46, 0.2, 0.11, 0.06])
    b = rng.uniform(8.0, 10.0, 5)
    e = np.exp(b - c * 3.0) * rng.uniform(0.97, 1.03, 5)
    var = rng.uniform(5.0, 500.0, 5)
    usable = np.array([True, True, False, True, True])
    d, v = wls(e[usable], c[usable], b[usable], var[usable])
    got, got_var = fused_path_length(e, c, b, var, usable)
    assert got == pytest.approx(d, rel=1e-10) and got_var == pytest.approx(v, rel=1e-10)
    # Only differences of c and b matter.
    shifted, shifted_var = fused_path_length(e, c - 0.3, b + 5.0, var, usable)
    assert shifted == pytest.approx(d, rel=1e-10) and shifted_var == pytest.approx(v, rel=1e-10)


def test_fusion_needs_two_usable_channels_of_different_attenuation():
    e = np.array([[100.0, 50.0, 30.0], [100.0, 50.0, 30.0], [100.0, 50.0, 30.0], [0.0, 50.0, 30.0]])
    c = np.array([0.46, 0.11, 0.11])
    usable = np.array([[True, False, False], [False, True, True], [True, True, False], [True, True, False]])
    d, v = fused_path_length(e, c, np.zeros(3), np.ones(3), usable)
    assert np.isnan(d[0]) and np.isnan(d[1]) and np.isnan(v[0]) and np.isnan(v[1])
    assert d[2] == pytest.approx(np.log(50.0 / 100.0) / (0.46 - 0.11)) and v[2] == pytest.approx(
        1.0 / (100.0**2 * 50.0**2 / (100.0**2 + 50.0**2) * (0.46 - 0.11) ** 2))
    assert np.isnan(d[3])  # a zero signal is not usable
    with pytest.raises(ValueError, match="at least 2 channels"):
        fused_path_length(np.ones((2, 1)), [0.1], [0.0], [1.0])
    with pytest.raises(ValueError, match="must have shape"):
        fused_path_length(np.ones((2, 3)), [0.1, 0.2], [0.0, 0.0], [1.0])


def test_pair_transform_refuses_meaningless_constants():
    with pytest.raises(ValueError, match="equal attenuation"):
        pair_path_length(1.0, 2.0, 0.0, 1.0)
    with pytest.raises(ValueError, match="constant_ratio must be positive"):
        pair_path_length(1.0, 2.0, 0.3, 0.0)
    assert np.isnan(pair_path_length(0.0, 2.0, 0.3, 1.0)) and np.isnan(pair_path_length(2.0, -1.0, 0.3, 1.0))
    # Only signals that are not positive are refused: a zero denominator too, small ones are fine.
    e = np.array([0.0, 2.0, 0.5, 2.0, -0.5])
    f = np.array([2.0, 0.0, 2.0, 0.5, 2.0])
    got = pair_path_length(e, f, 0.3, 1.5)
    assert np.isnan(got[[0, 1, 4]]).all()
    np.testing.assert_allclose(got[[2, 3]], np.log([0.5 / 2.0 * 1.5, 2.0 / 0.5 * 1.5]) / 0.3, rtol=1e-12)


def test_surface_reflectance_shifts_the_log_constants_by_the_hue_ratio():
    """A surface twice as red (relative to green) as the target reads as if U_RG halved."""
    profile = make_profile(C, B)
    plain = RangeEstimator(profile, pair=("R", "G"))
    rho_target = np.array(profile.array("target_reflectance"))
    rho_surface = rho_target * np.array([2.0, 1.0, 1.0])
    redder = RangeEstimator(profile, pair=("R", "G"), surface_reflectance=rho_surface)
    e = np.array([[[300.0, 900.0, 700.0]]])
    v = C[1] - C[0]
    base = np.log(300.0 / 900.0 * np.exp(B[1] - B[0])) / v
    assert plain(e).range[0, 0] == pytest.approx(base / 2, rel=1e-6)
    assert redder(e).range[0, 0] == pytest.approx(np.log(300.0 / 900.0 * np.exp(B[1] - B[0]) / 2.0) / v / 2, rel=1e-6)


def test_surface_log_constant_inverts_a_known_range():
    c = np.array([0.46, 0.11, 0.06])
    b_true = np.array([0.0, 0.7, 0.2])
    d = np.array([2.0, 2.5, 3.0, 3.5])
    e = np.exp(b_true[None, :] - c[None, :] * d[:, None]) * np.array([1.0, 0.5, 2.0, 0.8])[:, None]  # g varies
    np.testing.assert_allclose(surface_log_constant(e, d, c), b_true - b_true[0], atol=1e-12)
    np.testing.assert_allclose(surface_log_constant(e, d, c, reference=1), b_true - b_true[1], atol=1e-12)
    # Pooled as the log of summed, attenuation-corrected signals: bright pixels weigh more.
    noisy = e.copy()
    noisy[0, 1] *= 1.1
    corrected = noisy * np.exp((c - c[0])[None, :] * d[:, None])
    expected = np.log(corrected.sum(axis=0) / corrected.sum(axis=0)[0])
    np.testing.assert_allclose(surface_log_constant(noisy, d, c), expected, rtol=1e-12)
    target = np.array([0.4, 0.75, 0.6])  # only differences to the reference channel count
    np.testing.assert_allclose(reflectance_ratio_from_range(e, d, c, target), np.exp((b_true - b_true[0]) - (target - 0.4)),
                               rtol=1e-12)
    np.testing.assert_allclose(reflectance_ratio_from_range(e, d, c, target, reference=2),
                               np.exp((b_true - b_true[2]) - (target - 0.6)), rtol=1e-12)
    with pytest.raises(ValueError, match="no pixel with a positive signal"):
        surface_log_constant(np.zeros((2, 3)), d[:2], c)
    with pytest.raises(ValueError, match="need signal"):
        surface_log_constant(e, d[:2], c)


def test_fusion_of_two_channels_is_the_pair_transform():
    e = np.array([[300.0, 900.0], [0.5, 2.0], [300.0, 900.0]])  # small signals are as good as large ones
    c, b = np.array([0.46, 0.11]), np.array([9.0, 9.6])
    var = np.array([[40.0, 60.0], [0.01, 0.02], [1e6, 1e7]])  # and very noisy ones, with a large variance
    d, v = fused_path_length(e, c, b, var)
    u = np.exp(b[1] - b[0])
    np.testing.assert_allclose(d, pair_path_length(e[:, 0], e[:, 1], c[1] - c[0], u), rtol=1e-12)
    np.testing.assert_allclose(v, pair_path_variance(e[:, 0], e[:, 1], var[:, 0], var[:, 1], c[1] - c[0]), rtol=1e-12)


def test_fusion_ignores_unusable_and_weightless_channels():
    c, b = np.array([0.46, 0.11, 0.06]), np.zeros(3)
    # A zero signal is left out; the other two still give a range.
    d, v = fused_path_length(np.array([0.0, 50.0, 30.0]), c, b, np.ones(3))
    assert d == pytest.approx(np.log(30.0 / 50.0) / (0.11 - 0.06)) and np.isfinite(v)
    # Usable channels whose weights vanish (infinite variance) leave one channel: no range, no variance.
    d, v = fused_path_length(np.array([100.0, 50.0, 30.0]), c, b, np.array([1.0, np.inf, np.inf]))
    assert np.isnan(d) and np.isnan(v)
    with pytest.raises(ValueError, match="must have shape"):
        fused_path_length(np.ones((2, 3)), [0.1, 0.2, 0.3], [0.0, 0.0], [1.0])
    with pytest.raises(ValueError, match="must have shape"):
        fused_path_length(np.ones((2, 3)), [0.1, 0.2], [0.0, 0.0, 0.0], [1.0])


def test_estimator_checks_its_inputs():
    from uwcam.fileio import UserInputError

    profile = make_profile(C, B)
    est = RangeEstimator(profile)
    for bad in ([0.1, 0.2], [0.1, np.nan, 0.3]):
        with pytest.raises(ValueError, match="finite log constants"):
            est.set_log_constants(bad)
        with pytest.raises(ValueError, match="finite attenuation differences"):
            est.set_attenuation_differences(bad)
    for pair in (("R", "R"), ("R", "X"), ("R", "G", "B")):
        with pytest.raises(UserInputError, match="--pair needs two different channel names"):
            RangeEstimator(profile, pair=pair)
    for rho in ([0.5, 0.0, 0.5], [0.5, -0.1, 0.5], [0.5, 0.5]):
        with pytest.raises(UserInputError, match="surface reflectance needs 3 positive values"):
            RangeEstimator(profile, surface_reflectance=rho)


def test_a_profile_without_any_noise_counts_one_code_of_noise():
    profile = make_profile(C, B, quantisation_step=0.0)
    e = np.array([[[300.0, 900.0, 700.0]]])
    out = RangeEstimator(profile, pair=("R", "G"))(e)
    v = C[1] - C[0]
    assert out.range[0, 0] == pytest.approx(np.log(300.0 / 900.0 * np.exp(B[1] - B[0])) / v / 2, rel=1e-6)
    assert out.variance[0, 0] == pytest.approx(0.25 * (1 / 300.0**2 + 1 / 900.0**2) / v**2, rel=1e-5)


def test_a_known_background_is_taken_off_integer_frames_too():
    profile = make_profile(C, B, read_noise=2.0, shot_gain=0.1)
    est = RangeEstimator(profile)
    raw = np.rint(np.stack([signals_at(p) for p in (2.0, 3.0)])[None] + 50.0)
    background = np.full(raw.shape, 50.0)
    as_int = est(raw.astype(np.uint16), background=background)
    as_float = est(raw.astype(np.float64), background=background)
    np.testing.assert_allclose(as_int.range, as_float.range, rtol=1e-6)
    np.testing.assert_allclose(as_int.range, [[1.0, 1.5]], atol=0.01)  # the truth, without the 50 DN of background
