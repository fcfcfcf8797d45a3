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
    got = np.array(kernels.pair_noise(cvv)).reshape(3, 3)
    want = 9.0 * np.array([[0.0, 4e-4, 9e-4], [4e-4, 0.0, 4e-4 + 9e-4 - 2e-4], [9e-4, 11e-4, 0.0]])
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-18)
