"""Reasons for every combination of channel states, against the rule of docs/physics.md §7 written out.

Three channels, each usable, below the noise floor, saturated or backscatter only: all 64
combinations, through the pure ``pixel_reasons`` and through the estimator's compiled kernels
(integer and float frames)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from tests.synthetic import make_profile
from uwcam.optics import ChannelState, Reason, channel_states, pixel_reasons
from uwcam.ranging.estimator import RangeEstimator

USABLE, BELOW, SATURATED, BACKSCATTER = (ChannelState.USABLE, ChannelState.BELOW_NOISE_FLOOR, ChannelState.SATURATED,
                                         ChannelState.BACKSCATTER_ONLY)
# Raw codes giving each state with floor 10, backscatter level 40, saturation at 65535, no dark level.
CODE = {BELOW: (5, 5, 5), BACKSCATTER: (30, 30, 30), SATURATED: (65535, 65535, 65535), USABLE: (2000, 6000, 9000)}
COMBOS = list(itertools.product([USABLE, BELOW, SATURATED, BACKSCATTER], repeat=3))


def expected_reason(states) -> Reason:
    usable = sum(s == USABLE for s in states)
    if usable >= 2:
        return Reason.VALID
    if any(s == SATURATED for s in states):
        return Reason.SATURATED
    if usable + sum(s == BACKSCATTER for s in states) >= 2:
        return Reason.BACKSCATTER_ONLY
    if usable == 1:
        return Reason.TOO_FEW_CHANNELS
    return Reason.BELOW_NOISE_FLOOR


def frame(dtype) -> np.ndarray:
    return np.array([[[CODE[s][k] for k, s in enumerate(combo)] for combo in COMBOS]], dtype=dtype)


def test_channel_states_of_the_codes():
    raw = frame(np.uint16)
    states = channel_states(raw, raw.astype(float), [10.0] * 3, 65535, [40.0] * 3)
    np.testing.assert_array_equal(states[0], np.array(COMBOS, np.uint8))
    # Boundaries: the floor and the backscatter level belong to the state below them.
    edge = channel_states(np.array([10, 11, 40, 41, 65534, 65535]), np.array([10, 11, 40, 41, 65534, 65535.0]),
                          10.0, 65535, 40.0)
    assert list(edge) == [BELOW, BACKSCATTER, BACKSCATTER, USABLE, USABLE, SATURATED]
    assert channel_states(np.array([1.0]), np.array([np.nan]), 0.0, 10.0)[0] == BELOW
    assert channel_states(np.array([20.0]), np.array([20.0]), 10.0, 100.0)[0] == USABLE  # no backscatter level


def test_pixel_reasons_for_every_combination():
    states = np.array([COMBOS], np.uint8)
    path = np.where([[sum(s == USABLE for s in c) >= 2 for c in COMBOS]], 3.0, np.nan)
    got = pixel_reasons(states, path)
    assert [Reason(r) for r in got[0]] == [expected_reason(c) for c in COMBOS]
    # Two usable channels but no path (equal attenuation): too few channels; outside the bounds: so.
    two = np.array([[USABLE, USABLE, BELOW]] * 4, np.uint8)
    assert list(pixel_reasons(two, np.array([np.nan, 0.5, 3.0, 9.0]), 1.0, 8.0)) == [
        Reason.TOO_FEW_CHANNELS, Reason.PATH_OUT_OF_BOUNDS, Reason.VALID, Reason.PATH_OUT_OF_BOUNDS]
    assert list(pixel_reasons(two[:2], np.array([1.0, 8.0]), 1.0, 8.0)) == [Reason.VALID, Reason.VALID]  # inclusive


@pytest.mark.parametrize("dtype", [np.uint16, np.float64])
def test_estimator_names_the_reason_of_every_combination(dtype):
    profile = make_profile([0.46, 0.11, 0.06], [0.0, 0.0, 0.0], noise_floor=10.0, read_noise=2.0, shot_gain=0.3)
    out = RangeEstimator(profile, backscatter_level=[40.0] * 3)(frame(dtype))
    expected = [expected_reason(c) for c in COMBOS]
    assert [Reason(r) for r in out.reasons[0]] == expected
    valid = np.array(expected) == Reason.VALID
    assert np.isfinite(out.range[0, valid]).all() and np.isnan(out.range[0, ~valid]).all()
    assert (out.variance[0, valid] > 0).all() and np.isnan(out.variance[0, ~valid]).all()


def test_equal_attenuations_leave_too_few_channels():
    profile = make_profile([0.46, 0.11, 0.11], [0.0, 0.0, 0.0])
    out = RangeEstimator(profile)(np.array([[[0, 6000, 9000], [2000, 6000, 0], [2000, 6000, 9000]]], np.uint16))
    assert list(out.reasons[0]) == [Reason.TOO_FEW_CHANNELS, Reason.VALID, Reason.VALID]
    pair = RangeEstimator(profile, pair=("R", "G"))(np.array([[[2000, 6000, 0], [0, 6000, 9000]]], np.uint16))
    # With a pair chosen, the third channel neither helps nor counts.
    assert list(pair.reasons[0]) == [Reason.VALID, Reason.TOO_FEW_CHANNELS]


def test_default_bounds_accept_every_positive_path_and_refuse_negative_ones():
    two = np.zeros((3, 2), np.uint8)
    assert list(pixel_reasons(two, np.array([0.5, 1e9, -0.5]))) == [Reason.VALID, Reason.VALID, Reason.PATH_OUT_OF_BOUNDS]
