"""The calibration's share of each pixel's variance at the edges of its use: with a background
(backscatter) subtracted, next to pixels without a range, on frames narrower than a block, and
for integer frames in which no code carries a signal. Expected values are written out here."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from tests.test_calibration_statistics import covariance_profile
from tests.synthetic import make_profile
from uwcam.optics.validity import Reason
from uwcam.ranging.estimator import RangeEstimator

C = np.array([0.46, 0.11, 0.06])
READ2, GAIN = 25.0, 0.3  # covariance_profile's noise model: read 5 DN, 0.3 DN per electron


def expected_calibration_variance(profile, signal, total, path):
    """deriv² · hᵀ(Σbb − 2d·Σvb + d²·Σvv)h with h the fusion's sensitivity to each channel's ln E
    (weights E²/σ², σ² from the total light), and ∂d_c/∂d_T for a lamp at S on the optical axis
    ray of each pixel (here: the whole frame sees one path along the axis)."""
    w = signal**2 / (READ2 + GAIN * total + 1 / 12)
    cw = (w * C).sum(-1, keepdims=True) / w.sum(-1, keepdims=True)
    h = w * (C - cw) / (w * (C - cw) ** 2).sum(-1, keepdims=True)
    cvv, cvb, cbb = profile.covariance_blocks()
    d = path[..., None, None]
    hv = np.einsum("...k,...kl->...l", h, cbb - d * (cvb + cvb.T) + d**2 * cvv)
    return (hv * h).sum(-1)


def test_with_a_background_the_weights_come_from_the_total_light_and_the_signal_from_the_rest():
    _, profile, _ = covariance_profile(lamp=(0.0, 0.0, 0.0))
    est = RangeEstimator(profile)
    path = np.full((48, 64), 4.0)
    signal = 4e4 * np.exp(-C * path[..., None])
    background = np.broadcast_to([300.0, 2000.0, 3500.0], signal.shape)
    out = est((signal + background).astype(np.float32), background=background.astype(np.float32))
    # Lamp at the camera: d_c = d_T / 2, so ∂d_c/∂d_T = ½ everywhere.
    expected = 0.25 * expected_calibration_variance(profile, signal, signal + background, path)
    np.testing.assert_allclose(out.common_variance, expected, rtol=1e-3)
    without = est(signal.astype(np.float32)).common_variance
    assert np.all(np.abs(without - out.common_variance) > 1e-3 * out.common_variance)


def test_pixels_next_to_a_hole_keep_a_positive_calibration_share():
    _, profile, _ = covariance_profile(lamp=(0.3, 0.0, 0.0))
    path = np.full((64, 96), 3.0)
    frame = 4e4 * np.exp(-C * path[..., None])
    frame[16:40, 24:56] = 0.0  # a dark hole: no range there, no calibration share to interpolate
    out = RangeEstimator(profile)(frame.astype(np.float32))
    valid = out.reasons == Reason.VALID
    assert valid.sum() > 0.7 * valid.size and np.all(out.reasons[20:36, 28:52] == Reason.BELOW_NOISE_FLOOR)
    share = out.common_variance[valid]
    far = out.common_variance[:8, :8].min()
    assert np.all(share >= 0.5 * far), "pixels next to the hole got less than their share (or a negative one)"


@pytest.mark.parametrize("shape", [(5, 6), (30, 4)])
def test_frames_smaller_than_a_block_get_the_share_of_their_mean(shape):
    _, profile, _ = covariance_profile(lamp=(0.0, 0.0, 0.0))
    path = np.full(shape, 4.0)
    signal = 4e4 * np.exp(-C * path[..., None])
    out = RangeEstimator(profile)(signal.astype(np.float32))
    expected = 0.25 * expected_calibration_variance(profile, signal, signal, path)
    np.testing.assert_allclose(out.common_variance, expected, rtol=1e-3)


def test_an_integer_frame_in_which_no_code_carries_signal_is_all_below_the_floor():
    """Every uint8 code lies below a floor of 300 DN: the lookup table has no usable code."""
    profile = make_profile(C, np.zeros(3), read_noise=2.0, shot_gain=0.1, noise_floor=300.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = RangeEstimator(profile)(np.full((4, 5, 3), 200, np.uint8))
    assert np.all(out.reasons == Reason.BELOW_NOISE_FLOOR) and np.all(np.isnan(out.range))


def test_a_frame_lower_than_a_block_is_one_row_of_blocks():
    """Six rows whose path differs a lot: the share of every row is that of the 6×8 block means."""
    _, profile, _ = covariance_profile(lamp=(0.0, 0.0, 0.0))
    h, w = 6, 40
    path = np.repeat(np.linspace(2.0, 7.0, h)[:, None], w, axis=1)
    signal = 4e4 * np.exp(-C * path[..., None])
    out = RangeEstimator(profile)(signal.astype(np.float32))
    means = signal.reshape(1, h, w // 8, 8, 3).mean(axis=(1, 3))  # (1, 5, 3) block means
    weight = means**2 / (READ2 + GAIN * means + 1 / 12)
    y = np.log(means)  # log constants 0
    cw = (weight * C).sum(-1, keepdims=True) / weight.sum(-1, keepdims=True)
    yw = (weight * y).sum(-1, keepdims=True) / weight.sum(-1, keepdims=True)
    block_path = -(weight * (C - cw) * (y - yw)).sum(-1) / (weight * (C - cw) ** 2).sum(-1)
    expected = 0.25 * expected_calibration_variance(profile, means, means, block_path)  # (1, 5)
    np.testing.assert_allclose(out.common_variance, np.repeat(np.repeat(expected, h, 0), 8, 1), rtol=1e-3)


def test_a_lamp_beside_the_camera_without_intrinsics_uses_the_optical_axis():
    """No intrinsics: every block is taken on the axis, where S·u = S_z (here 0): the calibration
    share is that of a lamp at the camera's distance |S| aside, ∂d_c/∂d_T = ½(d² + s²)/d² at d_T = d."""
    from tests.synthetic import make_profile
    from uwcam.calibration.profile import CalibrationCovariance

    a = np.random.default_rng(3).normal(size=(4, 4)) * np.array([3e-4, 3e-4, 2e-3, 2e-3])
    base = make_profile(C, [0.0, 0.0, 0.0], read_noise=5.0, shot_gain=0.3, lamp=(0.3, 0.0, 0.0))
    profile = base.model_copy(update={"covariance": CalibrationCovariance(parameters=["V:G", "V:B", "b:G", "b:B"],
                                                                           matrix=(a @ a.T).tolist())})
    path = np.full((16, 24), 4.0)
    signal = 4e4 * np.exp(-C * path[..., None])
    out = RangeEstimator(profile)(signal.astype(np.float32))
    s2 = 0.3**2
    deriv = 0.5 * (16.0 + s2) / 16.0
    expected = deriv**2 * expected_calibration_variance(profile, signal, signal, path)
    np.testing.assert_allclose(out.common_variance, expected, rtol=1e-3)


def test_wrong_channel_count_and_a_pair_without_contrast_say_what_is_wrong():
    from tests.synthetic import make_profile
    from uwcam.fileio import UserInputError

    profile = make_profile([0.46, 0.11, 0.11], [0.0, 0.0, 0.0])
    with pytest.raises(UserInputError, match=r"the image has 2 channel\(s\) but the calibration profile has 3 \(R,G,B\)"):
        RangeEstimator(profile)(np.ones((4, 4, 2), np.uint16))
    with pytest.raises(UserInputError, match=r"the image has 1 channel\(s\)"):
        RangeEstimator(profile)(np.ones((4, 4), np.uint16))
    with pytest.raises(UserInputError, match="channels G and B have equal attenuation"):
        RangeEstimator(profile, pair=("G", "B"))


def test_a_share_beyond_float32_stays_the_largest_float32_not_its_neighbours(monkeypatch):
    """A block whose ∂d_c/∂d_T is enormous (a path at the lamp's own distance) has an enormous
    calibration share: it must not become inf, which the filling of blocks without a range would
    replace with the neighbours' (small) share."""
    import uwcam.ranging.calibration_share as ranging

    _, profile, _ = covariance_profile(lamp=(0.0, 0.0, 0.0))
    path = np.full((32, 32), 4.0)
    frame = (4e4 * np.exp(-C * path[..., None])).astype(np.float32)
    real = ranging.camera_range_derivative

    def blown_up(*args, **kwargs):
        deriv = np.array(real(*args, **kwargs), dtype=np.float64, copy=True)
        deriv = np.broadcast_to(deriv, args[0].shape).copy()
        deriv[1, 1] = 1e30  # one block: far beyond float32 once squared
        return deriv

    monkeypatch.setattr(ranging, "camera_range_derivative", blown_up)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no overflow warning either
        share = RangeEstimator(profile).calibration_variance(frame, block=8)
    assert share[12, 12] > 1e38  # by block 1, 1 of the 8-pixel blocks (interpolated: near float32's largest)
    assert np.all(np.isfinite(share))


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
@pytest.mark.parametrize("shape,size", [((64, 96, 3), (12, 8)), ((64, 96), (12, 8)), ((60, 90, 3), (11, 7)), ((32, 32, 3), (16, 16))])
def test_block_means_are_the_mean_of_each_block(dtype, shape, size):
    from uwcam.ranging.smoothing import block_means

    rng = np.random.default_rng(5)
    top = 250 if dtype == np.uint8 else 60000
    image = (rng.random(shape) * top).astype(dtype)
    got = block_means(image, size).astype(np.float64)
    assert got.shape[:2] == (size[1], size[0]) and block_means(image, size).dtype == dtype
    h, w = shape[:2]
    if h % size[1] == 0 and w % size[0] == 0:  # blocks of whole pixels: their plain means, written out
        by, bx = h // size[1], w // size[0]
        exact = image.astype(np.float64).reshape(size[1], by, size[0], bx, *shape[2:]).mean(axis=(1, 3))
        # Integers: a rounding (≤ ½ DN) per halving, three halvings for blocks of 8; floats: float32's own.
        tolerance = 0.5 * np.log2(by) if np.issubdtype(dtype, np.integer) else 1e-6 * top
        assert np.abs(got - exact).max() <= tolerance
    else:  # fractional blocks: OpenCV's area average itself
        import cv2

        np.testing.assert_array_equal(block_means(image, size), cv2.resize(image, size, interpolation=cv2.INTER_AREA))
