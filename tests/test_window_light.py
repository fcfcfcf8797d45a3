"""window_light (uwcam.ranging.smoothing): each value's window mean over usable values, how many
single-pixel noises that mean equals, and the background's mean over the same values, against
sums written out pixel by pixel (issue #27: its sample counts and background were untested)."""

import numpy as np
import pytest

from uwcam.ranging.smoothing import window_light


def expected(frame, usable, samples, background, size):
    h, w, n = frame.shape
    r = size // 2
    mean = frame.astype(np.float64).copy()
    counts = np.ones(frame.shape) if samples is None else samples.astype(np.float64).copy()
    light = None if background is None else np.broadcast_to(background, frame.shape).astype(np.float64).copy()
    bg = None if background is None else np.broadcast_to(background, frame.shape)
    for i in range(h):
        for j in range(w):
            for k in range(n):
                window = [(a, b) for a in range(max(0, i - r), min(h, i + r + 1))
                          for b in range(max(0, j - r), min(w, j + r + 1)) if usable[a, b, k] > 0]
                if window and bg is not None:
                    light[i, j, k] = sum(float(bg[a, b, k]) for a, b in window) / len(window)
                if not window or usable[i, j, k] == 0:
                    continue  # a saturated value, or one with nothing usable around it, stays
                mean[i, j, k] = sum(float(frame[a, b, k]) for a, b in window) / len(window)
                if samples is None:
                    counts[i, j, k] = len(window)
                else:  # the mean of n values of variances σ²/s: σ²·Σ(1/s)/n², i.e. n²/Σ(1/s) noises
                    counts[i, j, k] = len(window) ** 2 / sum(1.0 / float(samples[a, b, k]) for a, b in window)
    return mean, counts, light


@pytest.mark.parametrize("size", [3, 5])
def test_means_sample_counts_and_background_over_usable_neighbours(size):
    rng = np.random.default_rng(7)
    h, w, n = 9, 11, 3
    frame = rng.uniform(10.0, 4000.0, (h, w, n)).astype(np.float32)
    usable = (rng.uniform(size=(h, w, n)) > 0.2).astype(np.float32)
    usable[0:size, 0:size, 1] = 0.0  # a corner with nothing usable in channel 1
    samples = rng.integers(1, 9, (h, w, n)).astype(np.float32)  # frames fused over time, per value
    background = rng.uniform(0.0, 300.0, (h, w, n)).astype(np.float32)
    mean, counts, light = window_light(frame, usable, samples, background, size)
    want_mean, want_counts, want_light = expected(frame, usable, samples, background, size)
    np.testing.assert_allclose(mean, want_mean, rtol=2e-6)
    np.testing.assert_allclose(counts, want_counts, rtol=2e-6)
    np.testing.assert_allclose(light, want_light, rtol=2e-6, atol=1e-4)
    assert counts[0, 0, 1] == samples[0, 0, 1] and light[0, 0, 1] == background[0, 0, 1]


def test_single_frames_count_their_window_and_a_common_background_broadcasts():
    rng = np.random.default_rng(8)
    frame = rng.uniform(0.0, 255.0, (6, 7, 3)).astype(np.float32)
    usable = (rng.uniform(size=frame.shape) > 0.3).astype(np.float32)
    background = np.array([5.0, 7.0, 11.0], np.float32)  # (N,): one level per channel
    mean, counts, light = window_light(frame, usable, None, background, 3)
    want_mean, want_counts, want_light = expected(frame, usable, None, background, 3)
    np.testing.assert_allclose(mean, want_mean, rtol=2e-6)
    np.testing.assert_array_equal(counts, want_counts)
    np.testing.assert_allclose(light, want_light, rtol=2e-6)
    assert window_light(frame, usable, None, None, 3)[2] is None
