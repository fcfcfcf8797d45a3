"""The estimator's exposure correction where the calibration's own gain is not 0 dB, for a gain
that lifts the noise floor, and for exposures shorter than 1 µs (docs: channel k holds
m_k = (t_k/t_k,cal)·10^((g_k − g_k,cal)/20) times its calibrated signal; read and shot noise and
the floor are amplified with the signal; exposure times need only be positive)."""

from __future__ import annotations

import numpy as np

from tests.test_exposure import DARK, READ, SHOT, C, profile_with, scene
from uwcam.optics import ChannelState
from uwcam.ranging.estimator import RangeEstimator


def test_gain_is_taken_relative_to_the_calibrations_own_gain():
    """Calibrated at 6 dB in every channel; red now at 6 dB + ×2: only red's signal doubles."""
    profile = profile_with((1000.0,) * 3, (6.0,) * 3, read_noise=READ, shot_gain=SHOT)
    light, truth = scene(3.0)
    raw = light * np.array([2.0, 1.0, 1.0])
    est = RangeEstimator(profile, pair=("R", "B"))
    est.set_exposure((1000.0,) * 3, (6.0 + 20 * np.log10(2.0), 6.0, 6.0))
    out = est(raw + DARK)
    np.testing.assert_allclose(out.range, truth, rtol=1e-5)
    sigma2_r = (2 * READ) ** 2 + 2 * SHOT * raw[..., 0] + 1.0 / 12.0  # read and shot noise amplified ×2
    sigma2_b = READ**2 + SHOT * raw[..., 2] + 1.0 / 12.0
    expected = (sigma2_r / raw[..., 0] ** 2 + sigma2_b / raw[..., 2] ** 2) / (C[0] - C[2]) ** 2 / 4.0
    np.testing.assert_allclose(out.variance, expected, rtol=1e-4)


def test_gain_lifts_the_noise_floor_in_counts():
    """A floor of 50 DN at the calibration's gain is 100 DN at twice the gain: 80 DN is below it."""
    est = RangeEstimator(profile_with((1000.0,) * 3, (0.0,) * 3, read_noise=1.0, noise_floor=50.0))
    raw = np.array([[[DARK + 80.0, DARK + 80.0, DARK + 120.0]]])
    est.set_exposure((1000.0,) * 3, (20 * np.log10(2.0), 0.0, 20 * np.log10(2.0)))
    _, _, state = est.channel_terms(raw)
    assert list(state[0, 0]) == [ChannelState.BELOW_NOISE_FLOOR, ChannelState.USABLE, ChannelState.USABLE]


def test_exposures_shorter_than_a_microsecond_are_accepted():
    profile = profile_with((1.0,) * 3, None, read_noise=READ, shot_gain=SHOT)  # calibrated at 1 µs
    light, truth = scene(3.0)
    est = RangeEstimator(profile)
    est.set_exposure((0.5, 0.25, 0.5))  # half and a quarter of the calibration's light
    out = est(light * np.array([0.5, 0.25, 0.5]) + DARK)
    np.testing.assert_allclose(out.range, truth, rtol=1e-4)


def test_gains_of_a_profile_without_its_own_gain_are_taken_as_ratios_between_channels():
    """Gain not recorded at calibration: only the channels' gain differences count, 20·log10(2) dB
    more in red is twice red's signal (the noise model stays as measured)."""
    profile = profile_with((1000.0,) * 3, None, read_noise=READ, shot_gain=SHOT)
    light, truth = scene(3.0)
    est = RangeEstimator(profile)
    est.set_exposure((1000.0,) * 3, (20 * np.log10(2.0) + 3.0, 3.0, 3.0))
    out = est(light * np.array([2.0, 1.0, 1.0]) + DARK)
    np.testing.assert_allclose(out.range, truth, rtol=1e-4)
