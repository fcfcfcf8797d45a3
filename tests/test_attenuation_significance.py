"""A range needs channels whose attenuations differ by more than the calibration's doubt about it.

With red lost, green and blue carry the range alone; where they attenuate nearly alike (Jerlov III),
the calibration's G−B difference may be mostly its own error, and dividing by it gives ranges
anything (the water study saw +581 % kept). The rule, from outside the code: two channels give a
range only where |c_G − c_B| > 3·σ(c_G − c_B), σ² = σ_G² + σ_B² − 2·cov(G, B). Each path
(lookup tables, background kernel, float pairs, numpy) and the float64 reference must apply it.
"""

import numpy as np
import pytest

from tests.synthetic import make_profile
from uwcam.calibration.profile import CalibrationCovariance
from uwcam.optics import Reason, fused_path_length, kernels
from uwcam.ranging.estimator import RangeEstimator

C = np.array([0.45, 0.07, 0.04])  # R, G, B attenuation, 1/m: G − B = 0.03
B = np.log([30000.0, 40000.0, 35000.0])
NOISE = {"read_noise": 2.0, "shot_gain": 0.5, "noise_floor": 20.0, "quantisation_step": 0.0}


def profile_with(sigma: float, correlation: float):
    """R, G, B with σ(V_G) = σ(V_B) = sigma (1/m) correlated by ``correlation``; R the reference."""
    base = make_profile(C, B, **NOISE)
    cov = correlation * sigma * sigma
    matrix = [[sigma**2, cov, 0.0, 0.0], [cov, sigma**2, 0.0, 0.0], [0.0, 0.0, 1e-6, 0.0], [0.0, 0.0, 0.0, 1e-6]]
    return base.model_copy(update={"covariance": CalibrationCovariance(
        parameters=["V:G", "V:B", "b:G", "b:B"], matrix=matrix)})


def frame(red: bool) -> np.ndarray:
    """(8, 10, 3) float DN: path lengths 2-10 m, red's light present or gone (0)."""
    d = np.linspace(2.0, 10.0, 80).reshape(8, 10)
    e = np.exp(B[None, None, :] - C[None, None, :] * d[..., None])
    if not red:
        e[..., 0] = 0.0
    return e


# (σ of each V, correlation): |G − B| / σ(G − B) = 0.03 / (σ·√(2 − 2ρ)), from outside the code.
CASES = {
    "uncorrelated, 3.1 sigma": (0.0068, 0.0, True),
    "uncorrelated, 2.9 sigma": (0.0074, 0.0, False),
    "correlated, 3.3 sigma (1.0 if taken as independent)": (0.0205, 0.9, True),
    "correlated, 2.8 sigma": (0.0240, 0.9, False),
}


def by_path(est: RangeEstimator, e: np.ndarray, path: str, monkeypatch):
    if path == "numpy":
        monkeypatch.setattr(kernels, "fuse_lookup", kernels.fuse_lookup_numpy)
        monkeypatch.setattr(kernels, "fuse_arrays", kernels.fuse_arrays_numpy)
        monkeypatch.setattr(kernels, "fuse_background", None)
        return est(e.astype(np.float32), background=np.zeros(e.shape, np.float32))
    if path == "lookup":
        return est(np.round(e).astype(np.uint16))
    if path == "background":
        if kernels.fuse_background is None:
            pytest.skip("numba is not installed: no compiled background kernel")
        return est(e.astype(np.float32), background=np.zeros(e.shape, np.float32))
    return est(e.astype(np.float64))  # float pairs


@pytest.mark.parametrize("path", ["lookup", "background", "pairs", "numpy"])
@pytest.mark.parametrize("case", list(CASES))
def test_green_and_blue_range_only_where_their_difference_exceeds_three_sigma(case, path, monkeypatch):
    sigma, rho, significant = CASES[case]
    est = RangeEstimator(profile_with(sigma, rho))
    expected = 0.03 / (sigma * np.sqrt(2 - 2 * rho)) > 3.0
    assert expected == significant  # the case's premise
    out = by_path(est, frame(red=False), path, monkeypatch)
    if significant:
        assert (out.reasons == Reason.VALID).all()
        np.testing.assert_allclose(out.range, np.linspace(1.0, 5.0, 80).reshape(8, 10), rtol=2e-3)
    else:
        assert (out.reasons == Reason.TOO_FEW_CHANNELS).all()
        assert np.isnan(out.range).all() and np.isnan(out.variance).all()
    # With red's light the spread is red's, far beyond any of these doubts: every pixel ranges.
    with_red = by_path(est, frame(red=True), path, monkeypatch)
    assert (with_red.reasons == Reason.VALID).all()


@pytest.mark.parametrize("case", list(CASES))
def test_the_float64_reference_applies_the_same_rule(case):
    sigma, rho, significant = CASES[case]
    profile = profile_with(sigma, rho)
    cvv = profile.covariance_blocks()[0]
    e = frame(red=False)
    var = 4.0 + 0.5 * e
    path, var_path = fused_path_length(e, C, B, var, attenuation_covariance=cvv)
    assert np.isfinite(path).all() == significant and np.isnan(path).all() != significant
    assert np.isfinite(var_path).all() == significant
    plain, _ = fused_path_length(e, C, B, var)  # without the calibration's doubt: any difference counts
    assert np.isfinite(plain).all()
    with pytest.raises(ValueError, match=r"shape \(3, 3\)"):
        fused_path_length(e, C, B, var, attenuation_covariance=np.eye(2))


def test_pair_noise_is_the_variance_of_each_difference_times_nine():
    cvv = np.array([[0.0, 0.0, 0.0], [0.0, 4e-4, 1e-4], [0.0, 1e-4, 9e-4]])
    got = kernels.pair_noise(cvv)
    want = 9.0 * np.array([[0.0, 4e-4, 9e-4], [4e-4, 0.0, 4e-4 + 9e-4 - 2e-4], [9e-4, 11e-4, 0.0]])
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-18)


def test_a_pair_the_calibration_cannot_tell_apart_is_refused_in_one_line():
    """--pair G,B where G − B (0.03 1/m) is within 3σ of the calibration's doubt: every pixel would
    be reason 4, so the estimator refuses the pair and says why, with the figures."""
    from uwcam.fileio import UserInputError

    with pytest.raises(UserInputError, match=r"^channels G and B differ in attenuation by \+0\.0300 ± 0\.0105 1/m.*3σ.*leave out --pair"):
        RangeEstimator(profile_with(0.0074, 0.0), pair=("G", "B"))
    out = RangeEstimator(profile_with(0.0068, 0.0), pair=("G", "B"))(frame(red=True))  # 3.1σ: taken
    assert (out.reasons == Reason.VALID).all()
    assert (RangeEstimator(profile_with(0.0074, 0.0), pair=("R", "G"))(frame(red=True)).reasons == Reason.VALID).all()


def two_channel_profile(sigma_b: float):
    """G (reference) and B with c_G − c_B = 0.75 1/m and σ(V_B) = sigma_b: binary fractions, so
    that 3σ can equal the difference exactly."""
    base = make_profile([0.75, 0.0], np.log([40000.0, 35000.0]), names=["G", "B"], **NOISE)
    return base.model_copy(update={"covariance": CalibrationCovariance(
        parameters=["V:B", "b:B"], matrix=[[sigma_b**2, 0.0], [0.0, 0.0]])})


@pytest.mark.parametrize("path", ["lookup", "background", "pairs", "numpy"])
def test_a_difference_of_exactly_three_sigma_is_not_clearly_above_it(path, monkeypatch):
    e = np.exp(np.log([40000.0, 35000.0]) - np.array([0.75, 0.0]) * 2.0)[None, None, :].repeat(3, axis=1)
    at = by_path(RangeEstimator(two_channel_profile(0.25)), e, path, monkeypatch)  # 0.75 = 3 × 0.25 exactly
    assert (at.reasons == Reason.TOO_FEW_CHANNELS).all()
    within = by_path(RangeEstimator(two_channel_profile(0.2499)), e, path, monkeypatch)
    assert (within.reasons == Reason.VALID).all()
    np.testing.assert_allclose(within.range, 1.0, rtol=1e-3)
    cvv = lambda s: [[0.0, 0.0], [0.0, s * s]]  # noqa: E731
    ref_at, _ = fused_path_length(e, [0.75, 0.0], np.log([40000.0, 35000.0]), 1.0, attenuation_covariance=cvv(0.25))
    ref_within, _ = fused_path_length(e, [0.75, 0.0], np.log([40000.0, 35000.0]), 1.0, attenuation_covariance=cvv(0.2499))
    assert np.isnan(ref_at).all() and np.isfinite(ref_within).all()


def test_four_channels_follow_the_pair_sums_written_out():
    """Four channels (two sharing an attenuation), random weights and a random covariance: a pixel
    keeps its range exactly where Σ_{k<l} w_k w_l (c_k − c_l)² > 9 Σ_{k<l} w_k w_l Var(c_k − c_l),
    each pair counted once, in the float64 reference and in the estimator's kernels."""
    import itertools

    rng = np.random.default_rng(5)
    c = np.array([0.40, 0.09, 0.06, 0.09])
    a = rng.normal(size=(3, 3)) * 0.004
    cov3 = a @ a.T
    cvv = np.zeros((4, 4))
    cvv[1:, 1:] = cov3  # channel 0 the reference
    e = rng.uniform(50.0, 3000.0, size=(40, 50, 4))
    e[..., 0] *= rng.uniform(0, 1, size=(40, 50)) < 0.3  # red mostly lost
    e[..., 3] *= rng.uniform(0, 1, size=(40, 50)) < 0.5
    var = 4.0 + 0.5 * e
    w = np.where(e > 20.0, e * e / var, 0.0)  # the estimator's floor (NOISE) and weights
    between = sum(w[..., k] * w[..., m] * (c[k] - c[m]) ** 2 for k, m in itertools.combinations(range(4), 2))
    chance = sum(w[..., k] * w[..., m] * (cvv[k, k] + cvv[m, m] - 2 * cvv[k, m])
                 for k, m in itertools.combinations(range(4), 2))
    ratio = between / np.where(chance > 0, 9 * chance, np.nan)
    clear = np.abs(ratio - 1) > 1e-3  # float32 kernels may round a pixel at the threshold either way
    assert 0.2 < np.mean(ratio[clear] > 1) < 0.8  # the premise: both sides are well populated
    ref, _ = fused_path_length(e, c, np.zeros(4), var, usable=e > 20.0, attenuation_covariance=cvv)
    np.testing.assert_array_equal(np.isfinite(ref)[clear], (ratio > 1)[clear])
    base = make_profile(c, np.zeros(4), names=["R", "G", "B", "N"], **NOISE)
    names = [f"V:{n}" for n in "GBN"] + [f"b:{n}" for n in "GBN"]
    matrix = np.zeros((6, 6))
    matrix[:3, :3] = cov3
    profile = base.model_copy(update={"covariance": CalibrationCovariance(parameters=names, matrix=matrix.tolist())})
    est = RangeEstimator(profile, calibration_variance=False)
    out = est(e, background=np.zeros(e.shape, np.float32)) if kernels.fuse_background is not None else est(e)
    kept = out.reasons != Reason.TOO_FEW_CHANNELS
    np.testing.assert_array_equal(kept[clear], (ratio > 1)[clear])


def test_pair_noise_is_never_negative_for_a_covariance_the_profile_accepts():
    """The profile accepts eigenvalues down to −1e-9 of the largest variance (rounding in a saved
    file): two channels almost perfectly correlated may then give Var(c_k − c_l) a hair below 0,
    which would make channels of one attenuation (D = 0) look distinct."""
    cvv = np.array([[0.0, 0.0, 0.0], [0.0, 1e-6, 1.0000005e-6], [0.0, 1.0000005e-6, 1e-6]])
    assert cvv[1, 1] + cvv[2, 2] - 2 * cvv[1, 2] < 0  # the premise
    assert kernels.pair_noise(cvv).min() == 0.0


@pytest.mark.parametrize("path", ["lookup", "background", "pairs", "numpy"])
def test_without_a_clear_difference_the_reason_names_the_missing_channel(path, monkeypatch):
    """Green and blue within 3σ of each other (2.9σ), red clipped: reason 2 (saturated), what the
    pilot can change, rather than 4; red dark: reason 4."""
    est = RangeEstimator(profile_with(0.0074, 0.0))
    e = frame(red=True)
    e[..., 0] = 70000.0  # above the profile's saturation level (65535)
    if path == "lookup":
        e[..., 0] = 65535.0
    clipped = by_path(est, e, path, monkeypatch)
    assert (clipped.reasons == Reason.SATURATED).all()
    dark = by_path(est, frame(red=False), path, monkeypatch)
    assert (dark.reasons == Reason.TOO_FEW_CHANNELS).all()


def test_a_pair_exactly_three_sigma_apart_is_refused_and_one_just_inside_taken():
    from uwcam.fileio import UserInputError

    with pytest.raises(UserInputError, match=r"^channels B and G differ in attenuation by -0\.7500 ± 0\.2500 1/m"):
        RangeEstimator(two_channel_profile(0.25), pair=("B", "G"))  # 0.75 = 3 × 0.25 exactly
    RangeEstimator(two_channel_profile(0.2499), pair=("B", "G"))
