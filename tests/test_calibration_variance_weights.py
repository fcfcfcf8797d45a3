"""The calibration's share of a pixel's variance (RangeEstimator.calibration_variance) for the
channels that must not count (saturated, at or below the floor, outside the pair), for noise
models below 1 DN², a dark level, blocks of 2 pixels, and the filling of blocks without a range.

The reference below is written out from docs/physics.md: weights w_k = E_k²/σ_k² over the usable
channels with σ² = read² + gain·(E + B) + q²/12, the fusion's sensitivity
h_k = w_k (c_k − c̄)/Σ w (c − c̄)², and Var d_T = hᵀ(Σbb − d (Σvb + Σvbᵀ) + d² Σvv) h; lamp at the
camera: d_c = d_T/2, so the share of d_c is a quarter of it.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.synthetic import make_profile
from uwcam.calibration.profile import CalibrationCovariance
from uwcam.ranging.estimator import RangeEstimator

C = np.array([0.46, 0.11, 0.06])
B = np.array([0.0, 0.4, -0.3])  # log constants b_k (reference R)


def covariance_profile(**noise):
    a = np.random.default_rng(3).normal(size=(4, 4)) * np.array([3e-4, 3e-4, 2e-3, 2e-3])
    base = make_profile(C, B, **noise)
    return base.model_copy(update={"covariance": CalibrationCovariance(parameters=["V:G", "V:B", "b:G", "b:B"],
                                                                      matrix=(a @ a.T).tolist())})


def reference(profile, e, total, usable, read2, gain, q):
    """(…) calibration share of d_c for signals e (…, 3), total light, usable mask (…, 3)."""
    var = read2 + gain * total + q * q / 12
    w = np.where(usable, e * e / np.where(usable, var, 1.0), 0.0)
    cw = (w * C).sum(-1, keepdims=True) / w.sum(-1, keepdims=True)
    h = w * (C - cw) / (w * (C - cw) ** 2).sum(-1, keepdims=True)
    # The path of the usable channels, by weighted least squares on y = ln E − b.
    y = np.log(np.where(usable, e, 1.0)) - B
    yw = (w * y).sum(-1, keepdims=True) / w.sum(-1, keepdims=True)
    d = (-(w * (C - cw) * (y - yw)).sum(-1) / (w * (C - cw) ** 2).sum(-1))[..., None, None]
    cvv, cvb, cbb = profile.covariance_blocks()
    hv = np.einsum("...k,...kl->...l", h, cbb - d * (cvb + cvb.T) + d**2 * cvv)
    return 0.25 * (hv * h).sum(-1)


def test_saturated_and_floor_channels_and_channels_outside_the_pair_do_not_count():
    read, gain, floor, dark, sat = 4.0, 0.2, 20.0, 10.0, 4000.0
    profile = covariance_profile(read_noise=read, shot_gain=gain, noise_floor=floor, dark_level=dark,
                                 saturation_level=sat).model_copy(update={"quantisation_step": 1.0})
    e = np.array([[[3000.0, 1500.0, 900.0],  # every channel usable
                   [3000.0, 1500.0, sat - dark],  # B exactly at saturation (raw = level)
                   [3000.0, 1500.0, floor],  # B exactly at the floor (not above it)
                   [3000.0, 1500.0, floor + 5.0]]])  # B just above it: counts
    raw = e + dark
    usable = np.ones(e.shape, bool)
    usable[0, 1:3, 2] = False
    got = RangeEstimator(profile).calibration_variance(raw, block=1)
    np.testing.assert_allclose(got, reference(profile, e, raw - dark, usable, read**2, gain, 1.0), rtol=1e-6)
    assert abs(got[0, 3] - got[0, 2]) > 1e-3 * got[0, 2]  # the channel above the floor changed the share
    pair = RangeEstimator(profile, pair=("R", "G")).calibration_variance(raw, block=1)
    only_rg = np.zeros(e.shape, bool)
    only_rg[..., :2] = True
    np.testing.assert_allclose(pair, reference(profile, e, raw - dark, only_rg, read**2, gain, 1.0), rtol=1e-6)


def test_a_noise_model_below_one_code_squared_weighs_by_its_own_variance():
    """σ² of 0.01–2 DN²: the weights are E²/σ² with those σ², not with σ² clipped at 1."""
    read, gain = 0.1, 0.001
    profile = covariance_profile(read_noise=read, shot_gain=gain).model_copy(update={"quantisation_step": 0.0})
    e = np.array([[[40.0, 300.0, 1900.0], [25.0, 900.0, 150.0]]])
    got = RangeEstimator(profile).calibration_variance(e, block=1)
    np.testing.assert_allclose(got, reference(profile, e, e, np.ones(e.shape, bool), read**2, gain, 0.0), rtol=1e-6)


def test_a_channel_less_than_one_code_above_dark_still_counts_with_a_floor_of_zero():
    read = 0.05
    profile = covariance_profile(read_noise=read).model_copy(update={"quantisation_step": 0.0})
    e = np.array([[[0.9, 0.7, 0.5]]])
    got = RangeEstimator(profile).calibration_variance(e, block=1)
    np.testing.assert_allclose(got, reference(profile, e, e, np.ones(e.shape, bool), read**2, 0.0, 0.0), rtol=1e-6)
    zero_b = np.array([[[0.9, 0.7, 0.0]]])  # nothing at all in B: not usable, the pair R–G alone
    usable = np.array([[[True, True, False]]])
    got = RangeEstimator(profile).calibration_variance(zero_b, block=1)
    np.testing.assert_allclose(got, reference(profile, zero_b, zero_b, usable, read**2, 0.0, 0.0), rtol=1e-6)


def test_blocks_of_two_pixels_give_the_share_of_each_blocks_mean():
    read, gain = 5.0, 0.3
    profile = covariance_profile(read_noise=read, shot_gain=gain)
    i, j = np.mgrid[0:4, 0:4]
    path = 2.0 + 0.8 * i + 0.5 * j  # varies inside every block: a block's share is not a pixel's
    e = 4e4 * np.exp(-C * path[..., None])
    got = RangeEstimator(profile).calibration_variance(e.astype(np.float32), block=2)
    means = e.reshape(2, 2, 2, 2, 3).mean(axis=(1, 3))  # (2, 2, 3) block means
    share = reference(profile, means, means, np.ones(means.shape, bool), read**2, gain, 1.0)
    assert got.shape == (4, 4)
    # Bilinear interpolation between block centres, clamped at the border: corners are block values.
    np.testing.assert_allclose([got[0, 0], got[0, 3], got[3, 0], got[3, 3]], share.ravel(), rtol=1e-4)
    pixel = reference(profile, e, e, np.ones(e.shape, bool), read**2, gain, 1.0)
    assert abs(pixel[0, 0] - share[0, 0]) > 1e-3 * share[0, 0]


def test_a_frame_narrower_than_a_block_is_one_column_of_blocks():
    read, gain = 5.0, 0.3
    profile = covariance_profile(read_noise=read, shot_gain=gain)
    path = np.repeat(np.linspace(1.5, 7.0, 6)[None], 8, axis=0)  # 8 rows, 6 very different columns
    e = 4e4 * np.exp(-C * path[..., None])
    got = RangeEstimator(profile).calibration_variance(e.astype(np.float32), block=8)
    mean = e.mean(axis=(0, 1))[None, None]
    share = reference(profile, mean, mean, np.ones(mean.shape, bool), read**2, gain, 1.0)
    np.testing.assert_allclose(got, np.full((8, 6), share[0, 0]), rtol=1e-4)


def test_a_channel_without_any_noise_model_counts_one_code_squared():
    """Read noise 0 in R only, no step: R's σ² is 0, taken as 1 DN² (as for ranging itself)."""
    read = np.array([0.0, 2.0, 3.0])
    profile = covariance_profile(read_noise=read).model_copy(update={"quantisation_step": 0.0})
    e = np.array([[[800.0, 1500.0, 900.0], [50.0, 400.0, 700.0]]])
    got = RangeEstimator(profile).calibration_variance(e, block=1)
    read2 = np.where(read > 0, read**2, 1.0)
    np.testing.assert_allclose(got, reference(profile, e, e, np.ones(e.shape, bool), read2, 0.0, 0.0), rtol=1e-6)


@pytest.mark.parametrize("side", ["above", "below", "left", "right"])
def test_pixels_without_a_range_take_the_largest_share_among_their_neighbours(side):
    """block=1, 4×4 pixels ranged only along one edge, with different shares: the others (1 to 3
    pixels away) grow from it one pixel per step, each taking the largest share in its 3×3
    neighbourhood: a pixel r away ends with the largest share within r pixels on the edge."""
    read, gain = 5.0, 0.3
    profile = covariance_profile(read_noise=read, shot_gain=gain)
    along_edge = np.array([5.0, 2.0, 3.0, 4.5])  # not monotonic: the largest share is not always nearest
    path = np.repeat(along_edge[:, None], 4, axis=1) if side in ("left", "right") else np.repeat(along_edge[None], 4, axis=0)
    e = 4e4 * np.exp(-C * path[..., None])
    rows, cols = {"above": (slice(0, 1), slice(None)), "below": (slice(3, 4), slice(None)),
                  "left": (slice(None), slice(0, 1)), "right": (slice(None), slice(3, 4))}[side]
    ranged = np.zeros((4, 4), bool)
    ranged[rows, cols] = True
    frame = np.where(ranged[..., None], e, 0.0)
    got = RangeEstimator(profile).calibration_variance(frame, block=1)
    share = reference(profile, e, e, np.ones(e.shape, bool), read**2, gain, 1.0)
    np.testing.assert_allclose(got[ranged], share[ranged], rtol=1e-6)
    along = share[ranged]
    assert len(set(np.round(along / along.max(), 6))) == 4  # four different shares on the edge
    for i in range(4):
        for j in range(4):
            if ranged[i, j]:
                continue
            reach = np.maximum(np.abs(np.arange(4)[:, None] - i), np.abs(np.arange(4)[None, :] - j))
            within = ranged & (reach == reach[ranged].min())
            assert got[i, j] == pytest.approx(share[within].max(), rel=1e-6), (i, j)


def test_blocks_more_than_three_blocks_from_any_range_get_no_share():
    """block=1, a 7×7 frame ranged along its top row only: rows 1–3 take the largest share within
    their reach on that row (docs/calibration.md), rows 4–6, more than three blocks away, none."""
    read, gain = 5.0, 0.3
    profile = covariance_profile(read_noise=read, shot_gain=gain)
    path = np.repeat(np.array([5.0, 2.0, 3.0, 4.5, 2.5, 3.5, 4.0])[None], 7, axis=0)
    e = 4e4 * np.exp(-C * path[..., None])
    ranged = np.zeros((7, 7), bool)
    ranged[0] = True
    got = RangeEstimator(profile).calibration_variance(np.where(ranged[..., None], e, 0.0), block=1)
    share = reference(profile, e, e, np.ones(e.shape, bool), read**2, gain, 1.0)[0]
    for i in range(1, 4):  # reach i on the top row: columns j − i … j + i
        for j in range(7):
            assert got[i, j] == pytest.approx(share[max(j - i, 0):j + i + 1].max(), rel=1e-6), (i, j)
    assert np.all(got[4:] == 0.0)
