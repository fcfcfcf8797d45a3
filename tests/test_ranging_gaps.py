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
