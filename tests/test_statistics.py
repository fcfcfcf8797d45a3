"""Monte-Carlo: the fused estimator is unbiased, its predicted variance is right, and it
is never worse than the best single pair (docs/physics.md §5)."""

import itertools

import numpy as np
import pytest

from tests.synthetic import make_profile
from uwcam.optics import fused_path_length, pair_path_length
from uwcam.ranging.estimator import RangeEstimator

ATTENUATION = np.array([0.46, 0.11, 0.06])
SAMPLES = (500, 400)


@pytest.mark.parametrize("path_length", [1.0, 4.0, 10.0])
def test_fusion_unbiased_with_predicted_variance_and_beats_every_pair(path_length):
    rng = np.random.default_rng(int(path_length * 10))
    log_constant = np.log([3e4, 2e4, 1.5e4])
    truth = np.exp(log_constant - ATTENUATION * path_length)  # E_k with g = 1
    sigma = np.array([0.02, 0.015, 0.01]) * truth + 3.0  # known per-channel σ
    signal = truth + sigma * rng.standard_normal((*SAMPLES, 3))
    d_t, predicted = fused_path_length(signal, ATTENUATION, log_constant, sigma**2)
    assert np.isfinite(d_t).all()
    bias = d_t.mean() - path_length
    assert abs(bias) < 0.003 * path_length
    ratio = d_t.var() / predicted.mean()
    assert 0.9 < ratio < 1.1, f"empirical/predicted variance {ratio:.3f}"
    pair_vars = []
    for i, j in itertools.combinations(range(3), 2):
        u = np.exp(log_constant[j] - log_constant[i])
        pair_vars.append(pair_path_length(signal[..., i], signal[..., j], ATTENUATION[j] - ATTENUATION[i], u).var())
    assert d_t.var() <= min(pair_vars) * 1.01


def test_frame_estimator_statistics_with_camera_noise_model():
    """Same, end to end through the uint16 lookup tables, quantisation and the profile's noise model."""
    rng = np.random.default_rng(11)
    read, gain = 4.0, 0.25
    log_constant = np.log([5e4, 4e4, 3e4])
    path_length = 5.0
    truth = np.exp(log_constant - ATTENUATION * path_length)
    noisy = truth + np.sqrt(read**2 + gain * truth) * rng.standard_normal((*SAMPLES, 3))
    frame = np.clip(np.rint(noisy), 0, 65535).astype(np.uint16)
    profile = make_profile(ATTENUATION, log_constant, read_noise=read, shot_gain=gain)
    result = RangeEstimator(profile)(frame)
    camera_range = result.range.astype(np.float64)
    assert np.isfinite(camera_range).all()
    assert abs(camera_range.mean() - path_length / 2) < 0.003 * path_length / 2
    ratio = camera_range.var() / result.variance.mean()
    assert 0.9 < ratio < 1.1, f"empirical/predicted variance {ratio:.3f}"
