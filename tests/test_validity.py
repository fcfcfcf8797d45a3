"""Every pixel carries the reason it has, or has no, range (docs/physics.md §7)."""

import numpy as np

from tests.synthetic import make_profile
from uwcam.optics import ChannelState, Reason, channel_states, pixel_reasons
from uwcam.ranging.estimator import RangeEstimator


def test_each_reason_arises_where_expected():
    # Columns: valid, below floor, saturated, backscatter only, one channel left, path out of bounds.
    raw = np.array([[
        [2000, 6000, 9000],
        [5, 8, 9],
        [65535, 70, 9],
        [30, 35, 9000],
        [2000, 9, 9],
        [9000, 2000, 1000],  # red brighter than blue here means a negative path length
    ]], dtype=np.uint16)
    profile = make_profile([0.46, 0.11, 0.06], [0.0, 0.0, 0.0], noise_floor=10.0, read_noise=2.0, shot_gain=0.3)
    est = RangeEstimator(profile, backscatter_level=[40.0, 40.0, 40.0])
    result = est(raw)
    assert list(result.reasons[0]) == [
        Reason.VALID, Reason.BELOW_NOISE_FLOOR, Reason.SATURATED, Reason.BACKSCATTER_ONLY,
        Reason.TOO_FEW_CHANNELS, Reason.PATH_OUT_OF_BOUNDS,
    ]
    assert np.isfinite(result.range[0, 0]) and np.isnan(result.range[0, 1:]).all()
    assert np.isfinite(result.variance[0, 0]) and np.isnan(result.variance[0, 1:]).all()


def test_without_a_measured_floor_every_positive_value_is_usable():
    profile = make_profile([0.46, 0.11, 0.06], [0.0, 0.0, 0.0])
    result = RangeEstimator(profile)(np.array([[[1, 2, 3]]], dtype=np.uint16))
    assert result.reasons[0, 0] == Reason.VALID
    zero = RangeEstimator(profile)(np.array([[[0, 2, 3]]], dtype=np.uint16))
    assert zero.reasons[0, 0] == Reason.VALID  # two usable channels remain
    assert RangeEstimator(profile)(np.array([[[0, 0, 3]]], dtype=np.uint16)).reasons[0, 0] == Reason.TOO_FEW_CHANNELS


def test_channel_states_judge_saturation_on_raw_and_floor_on_corrected():
    raw = np.array([[100, 100]])
    corrected = raw - np.array([95, 0])
    states = channel_states(raw, corrected, noise_floor=[10, 10], saturation_level=100)
    assert list(states[0]) == [ChannelState.SATURATED, ChannelState.SATURATED]
    states = channel_states(raw, corrected, noise_floor=[10, 10], saturation_level=101)
    assert list(states[0]) == [ChannelState.BELOW_NOISE_FLOOR, ChannelState.USABLE]


def test_pixel_reasons_bounds_and_equal_attenuation():
    states = np.zeros((1, 3, 2), np.uint8)
    path = np.array([[1.0, 50.0, np.nan]])
    assert list(pixel_reasons(states, path, 0.0, 30.0)[0]) == [Reason.VALID, Reason.PATH_OUT_OF_BOUNDS, Reason.TOO_FEW_CHANNELS]
    assert Reason.describe()[5] == "path out of bounds"


def test_one_usable_channel_is_no_range_whatever_path_length_it_is_handed():
    """A range needs two usable channels: a single one with a finite path length beside it (a
    caller's mistake) is still too few, and two with NaN (no clear difference) say what is missing."""
    from uwcam.optics.validity import ChannelState as S, Reason, pixel_reasons

    states = [[S.USABLE, S.BELOW_NOISE_FLOOR, S.BELOW_NOISE_FLOOR],
              [S.USABLE, S.USABLE, S.BACKSCATTER_ONLY],
              [S.USABLE, S.USABLE, S.SATURATED],
              [S.USABLE, S.USABLE, S.BELOW_NOISE_FLOOR],
              [S.USABLE, S.USABLE, S.BELOW_NOISE_FLOOR]]
    got = pixel_reasons(states, [2.0, float("nan"), float("nan"), float("nan"), 2.0])
    assert list(got) == [Reason.TOO_FEW_CHANNELS, Reason.BACKSCATTER_ONLY, Reason.SATURATED,
                         Reason.TOO_FEW_CHANNELS, Reason.VALID]
