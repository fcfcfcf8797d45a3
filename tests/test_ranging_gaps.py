"""Rules of uwcam/ranging/estimator.py that only particular inputs show, each against a reference written
here: block means of integer frames (exact 2×2 means rounded half up, one halving at a time, for
blocks of a power of two pixels; one area average otherwise), and the exposure correction where
the channels were calibrated at different exposures, or where the profile records no exposure
(docs/calibration.md, docs/exposure.md, the docstrings of ``block_means`` and ``set_exposure``)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.test_exposure import DARK, profile_with, scene
from uwcam.ranging.smoothing import block_means
from uwcam.ranging.estimator import RangeEstimator


def halvings(image: np.ndarray, times: int) -> np.ndarray:
    """The exact 2×2 mean rounded half up (⌊(sum + 2)/4⌋), ``times`` times, in int64."""
    a = image.astype(np.int64)
    for _ in range(times):
        a = (a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2] + a[1::2, 1::2] + 2) // 4
    return a


def exact_block_means(image: np.ndarray, by: int, bx: int) -> np.ndarray:
    h, w = image.shape[0] // by, image.shape[1] // bx
    return image.astype(np.float64).reshape(h, by, w, bx, *image.shape[2:]).mean(axis=(1, 3))


def area_average(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Area-weighted mean over each output pixel's footprint (fractional source pixels weigh by
    the part they cover), float64."""

    def weights(n_in: int, n_out: int) -> np.ndarray:
        scale = n_in / n_out
        m = np.zeros((n_out, n_in))
        for i in range(n_out):
            lo, hi = i * scale, (i + 1) * scale
            for j in range(int(np.floor(lo)), min(int(np.ceil(hi)), n_in)):
                m[i, j] = min(hi, j + 1) - max(lo, j)
        return m / scale

    wy, wx = weights(image.shape[0], size[1]), weights(image.shape[1], size[0])
    return np.einsum("ij,jk...,lk->il...", wy, image.astype(np.float64), wx)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("shape,size", [
    ((64, 96, 3), (12, 8)),   # blocks of 8, as for the calibration's share
    ((32, 48), (12, 8)),      # blocks of 4, as for backscatter compensation's coarse frame
    ((128, 64, 3), (4, 8)),   # blocks of 16
    ((8, 96, 3), (12, 1)),    # one block high
    ((96, 8, 3), (1, 12)),    # one block wide
])
def test_integer_blocks_of_a_power_of_two_are_halved_with_rounding_half_up(dtype, shape, size):
    rng = np.random.default_rng(11)
    top = 256 if dtype == np.uint8 else 65536
    image = rng.integers(0, top, shape).astype(dtype)
    factor = shape[0] // size[1]
    expected = halvings(image, int(np.log2(factor)))
    # The halvings' roundings add up: somewhere they are more than ½ DN from the exact mean, where
    # one reduction would be within it (so this test tells the two apart).
    assert np.abs(expected - exact_block_means(image, factor, factor)).max() > 0.5
    got = block_means(image, size)
    assert got.dtype == dtype and got.shape == expected.shape
    np.testing.assert_array_equal(got.astype(np.int64), expected)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("shape,size", [
    ((24, 36, 3), (12, 8)),   # blocks of 3
    ((48, 72), (12, 8)),      # blocks of 6
    ((56, 84, 3), (12, 8)),   # blocks of 7
    ((64, 48, 3), (12, 8)),   # 8 high, 4 wide
    ((32, 96), (12, 8)),      # 4 high, 8 wide
])
def test_other_integer_blocks_are_one_area_average_within_half_a_count(dtype, shape, size):
    rng = np.random.default_rng(12)
    top = 256 if dtype == np.uint8 else 65536
    image = rng.integers(0, top, shape).astype(dtype)
    got = block_means(image, size)
    assert got.dtype == dtype and got.shape[:2] == (size[1], size[0]) and got.shape == block_means(image, size).shape
    exact = exact_block_means(image, shape[0] // size[1], shape[1] // size[0])
    assert got.shape == exact.shape
    assert np.abs(got - exact).max() <= 0.5 + 1e-9


@pytest.mark.parametrize("shape,size", [((67, 96, 3), (12, 8)), ((64, 101), (12, 8))])
def test_integer_frames_of_fractional_blocks_are_one_area_average(shape, size):
    """One side a whole number of blocks of 8, the other not: the area average over fractional
    pixels, rounded once."""
    image = np.random.default_rng(13).integers(0, 60000, shape).astype(np.uint16)
    got = block_means(image, size)
    assert got.dtype == np.uint16 and got.shape[:2] == (size[1], size[0])
    assert np.abs(got - area_average(image, size)).max() <= 0.5 + 0.01  # OpenCV weighs in float32


def test_channels_calibrated_at_different_exposures_are_corrected_by_their_own_ratio():
    """Calibrated at 500, 1000 and 4000 µs, now all at 1000 µs: channel k holds t/t_k,cal times
    its calibrated signal (2, 1, ¼), and ranges as at calibration."""
    cal = np.array([500.0, 1000.0, 4000.0])
    profile = profile_with(tuple(cal))
    light, truth = scene(3.0)
    t = np.full(3, 1000.0)
    est = RangeEstimator(profile)
    est.set_exposure(t)
    np.testing.assert_allclose(est.exposure_shift, np.log(t / cal), rtol=0, atol=1e-12)
    out = est(light * (t / cal) + DARK)
    valid = np.isfinite(truth)
    assert valid.sum() > 100
    np.testing.assert_allclose(out.range[valid], truth[valid], rtol=1e-5)


def test_without_a_recorded_exposure_channels_are_taken_relative_to_their_geometric_mean():
    """No calibration exposure or gain in the profile: ln m_k = ln t_k − mean ln t, and a gain
    adds (g_k − mean g)·ln 10/20 (docs/exposure.md)."""
    t = np.array([4000.0, 1000.0, 250.0])
    est = RangeEstimator(profile_with(None))
    est.set_exposure(t)
    np.testing.assert_allclose(est.exposure_shift, np.log(t) - np.log(t).mean(), rtol=0, atol=1e-12)
    g = np.array([6.0, 0.0, 12.0])
    est.set_exposure(t, g)
    np.testing.assert_allclose(est.exposure_shift, np.log(t) - np.log(t).mean() + (g - g.mean()) * np.log(10.0) / 20.0,
                               rtol=0, atol=1e-12)
    # The exposure recorded, the gain not: the gain alone is taken relative to its mean.
    est = RangeEstimator(profile_with((1000.0,) * 3))
    est.set_exposure((1000.0,) * 3, g)
    np.testing.assert_allclose(est.exposure_shift, (g - g.mean()) * np.log(10.0) / 20.0, rtol=0, atol=1e-12)


def test_adaptive_smoothing_aims_at_two_percent_of_the_range_unless_told():
    """docs/physics.md: ``processing.smoothing_target`` 0.02 by default, σ no more than 2 % of the range.
    A plate whose plain σ lies about 2 % of its range (1.8–2.2 % across it): with the default,
    exactly the pixels a 0.02 target re-ranges are, some but not all of them."""
    from uwcam.config import ProcessingConfig
    from uwcam.ranging.estimator import range_frame

    assert ProcessingConfig().smoothing_target == 0.02
    light, _ = scene()
    frame = (light * 0.2 + DARK).astype(np.float32)
    est = RangeEstimator(profile_with(read_noise=3.0, shot_gain=0.5))
    plain = est(frame)
    relative = np.sqrt(plain.variance) / plain.range
    assert np.nanmin(relative) < 0.02 < np.nanmax(relative)
    default = range_frame(est, frame, smoothing="adaptive")
    told = range_frame(est, frame, smoothing="adaptive", smoothing_target=0.02)
    np.testing.assert_array_equal(default.range, told.range)
    np.testing.assert_array_equal(default.variance, told.variance)
    changed = default.variance != plain.variance
    assert 0 < changed.sum() < changed.size
    np.testing.assert_array_equal(changed, relative > 0.02)


def test_frames_fused_over_time_and_then_smoothed_count_both():
    """A 3×3 mean (smoothing before the transform) of values that are each a mean of 4 frames is a
    mean of 36 pixels' noise: inside the image, a quarter of the variance the 3×3 mean of single
    frames has (a plate, read and shot noise, no calibration share)."""
    from uwcam.ranging.estimator import range_frame

    light, _ = scene()
    frame = (light + DARK).astype(np.float32)
    est = RangeEstimator(profile_with(read_noise=3.0, shot_gain=0.5))
    single = range_frame(est, frame, smoothing="mean", stage="before")
    fused = range_frame(est, frame, smoothing="mean", stage="before", samples=np.full(frame.shape, 4.0, np.float32))
    inside = (slice(1, -1), slice(1, -1))
    np.testing.assert_allclose(fused.variance[inside], single.variance[inside] / 4.0, rtol=1e-5)
    np.testing.assert_array_equal(fused.range, single.range)


def test_a_gamma_cameras_least_variance_is_the_width_of_the_code_the_light_came_from():
    """uwcam.imaging.response: a linearised value is known only to its code's width (half the
    distance between its neighbours' linear values), variance width²/12, the least it can have.
    The code is that of the raw value, dark level included: an 8-bit sRGB camera with a dark level
    of 40 linear DN and no other noise, codes 120 to 250, against the widths worked out here from
    the IEC 61966-2-1 curve (a code read 80 DN lower, the dark level taken off twice, is 21–93 % narrower)."""
    from tests.synthetic import make_profile

    def linear(code):  # IEC 61966-2-1, 8-bit codes to linear DN (0 … 255)
        v = np.asarray(code, np.float64) / 255.0
        return 255.0 * np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)

    base = make_profile([0.5, 0.2, 0.1], [0.0, 0.0, 0.0], dark_level=40.0, saturation_level=255.0,
                        quantisation_step=0.01)
    from uwcam.calibration.profile import ResponseRecord

    profile = base.model_copy(update={"response": ResponseRecord(kind="srgb", bits=8, method="srgb standard")})
    est = RangeEstimator(profile)
    codes = np.arange(120, 251)
    raw = np.repeat(linear(codes)[:, None], 3, axis=1)
    _, weight, _ = est.channel_terms(raw)
    light = raw - 40.0
    variance = light * light / weight
    width = (linear(codes + 1) - linear(codes - 1)) / 2.0
    np.testing.assert_allclose(variance, np.repeat(width[:, None] ** 2 / 12.0, 3, axis=1), rtol=1e-6)


def srgb_plate() -> tuple:
    """An 8-bit sRGB camera's frame of the plate (codes from the IEC 61966-2-1 curve written out,
    dark level 5 linear DN) and its profile with the curve."""
    from uwcam.calibration.profile import ResponseRecord
    from tests.synthetic import make_profile
    from tests.test_exposure import B, C

    light, truth = scene()
    linear = light * (200.0 / light.max()) + 5.0
    v = linear / 255.0
    codes = np.rint(255.0 * np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)).astype(np.uint8)
    # Little noise, so that the codes' widths (up to 2.3 linear DN: variance 0.44) set the variance.
    profile = make_profile(C, B, dark_level=5.0, saturation_level=255.0, read_noise=0.1, shot_gain=0.001,
                           quantisation_step=0.01)
    return codes, profile.model_copy(update={"response": ResponseRecord(kind="srgb", bits=8, method="srgb standard")}), truth


def test_a_gamma_cameras_codes_are_linearised_on_every_path():
    """Ranged alone (the lookup tables, per code), with a background of no light, or as means of
    one frame, a gamma camera's codes are its linear light, known to their widths: the three agree
    in range and variance, and range the plate (a code's rounding, up to half a code, moves a range
    by a few per cent at most)."""
    codes, profile, truth = srgb_plate()
    est = RangeEstimator(profile)
    alone = est(codes)
    zero = np.zeros(codes.shape, np.float32)
    with_background = est(codes, background=zero)
    as_means = est(codes, samples=np.ones(codes.shape, np.float32))
    valid = np.isfinite(truth)
    assert np.isfinite(alone.range[valid]).all()
    for other in (with_background, as_means):
        np.testing.assert_allclose(other.range, alone.range, rtol=1e-4)
        np.testing.assert_allclose(other.variance, alone.variance, rtol=1e-4)
    assert np.nanmax(np.abs(alone.range[valid] / truth[valid] - 1.0)) < 0.05


def test_a_gamma_cameras_frames_of_another_bit_depth_are_refused():
    from uwcam.fileio import UserInputError

    codes, profile, _ = srgb_plate()
    est = RangeEstimator(profile)
    est(codes)  # its own 8 bits: ranged
    with pytest.raises(UserInputError, match="8-bit codes; this frame has 16-bit pixels"):
        est(codes.astype(np.uint16))
