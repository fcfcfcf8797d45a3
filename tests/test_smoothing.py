"""3×3 smoothing of range maps: values, variances and invalid pixels against a naive reference.

The reference below is a plain double loop over windows, written apart from
``uwcam.ranging.smoothing.smooth_range_map``: the mean of the valid neighbours, and the variance of that
mean for independent neighbours, Var(Σ r_k / n) = Σ σ_k² / n² (σ² / n when all are equal), plus
the neighbours' common shares, fully correlated: (Σ σ_c,k / n)².
"""

from __future__ import annotations

import numpy as np
import pytest

from uwcam.fileio import UserInputError
from uwcam.optics.validity import Reason
from uwcam.ranging.result import RangeResult
from uwcam.ranging.smoothing import smooth_frame, smooth_range_map


def naive(range_map: np.ndarray, variance: np.ndarray, kind: str) -> tuple[np.ndarray, np.ndarray]:
    h, w = range_map.shape
    out_r = np.full((h, w), np.nan)
    out_v = np.full((h, w), np.nan)
    for i in range(h):
        for j in range(w):
            if not np.isfinite(range_map[i, j]):
                continue  # an invalid pixel stays invalid
            values, variances = [], []
            for di in (-1, 0, 1):
                for dj in (-1, 0, 1):
                    y, x = i + di, j + dj
                    if 0 <= y < h and 0 <= x < w and np.isfinite(range_map[y, x]):
                        values.append(float(range_map[y, x]))
                        variances.append(float(variance[y, x]))
            n = len(values)
            if kind == "mean":
                out_r[i, j] = sum(values) / n
                out_v[i, j] = sum(variances) / n**2
            else:
                out_r[i, j] = sorted(values)[n // 2] if n % 2 else 0.5 * (sorted(values)[n // 2 - 1] + sorted(values)[n // 2])
                out_v[i, j] = variance[i, j]
    return out_r, out_v


def naive_common(range_map: np.ndarray, common: np.ndarray) -> np.ndarray:
    """The common share of the 3×3 mean: the neighbours' common errors fully correlated, so their
    standard deviations (not variances) average, (Σ σ_c,k / n)²."""
    h, w = range_map.shape
    out = np.full((h, w), np.nan)
    for i in range(h):
        for j in range(w):
            if not np.isfinite(range_map[i, j]):
                continue
            sds = [np.sqrt(float(common[y, x])) for y in range(max(i - 1, 0), min(i + 2, h))
                   for x in range(max(j - 1, 0), min(j + 2, w)) if np.isfinite(range_map[y, x])]
            out[i, j] = (sum(sds) / len(sds)) ** 2
    return out


def result(range_map, variance, reasons=None) -> RangeResult:
    r = np.asarray(range_map, np.float32)
    if reasons is None:
        reasons = np.where(np.isfinite(r), Reason.VALID, Reason.BELOW_NOISE_FLOOR).astype(np.uint8)
    return RangeResult(r, np.where(np.isfinite(r), np.asarray(variance, np.float32), np.nan).astype(np.float32), reasons)


@pytest.fixture(params=["compiled", "numpy"])
def mean_path(request, monkeypatch):
    """The 3×3 mean through the compiled pass and through its numpy twin (platforms without numba)."""
    from uwcam.ranging import smoothing

    if request.param == "numpy":
        monkeypatch.setattr(smoothing, "_smooth_mean", None)
    elif smoothing._smooth_mean is None:
        pytest.skip("numba is not installed: only the numpy path exists")
    return request.param


def test_the_compiled_mean_stays_inside_its_arrays():
    """The compiled pass, compiled again here with numba's bounds checks on, reads and writes
    nothing outside its arrays (without the checks an index one past the end reads whatever
    memory follows, which no value test can be sure to see), and gives the naive reference."""
    numba = pytest.importorskip("numba")
    from uwcam.ranging import smoothing

    checked = numba.njit(boundscheck=True)(smoothing._smooth_mean_py)
    rng = np.random.default_rng(5)
    for shape in ((1, 1), (1, 6), (7, 1), (9, 13)):
        r = rng.uniform(1.0, 4.0, shape)
        r[rng.random(shape) < 0.3] = np.nan
        var = rng.uniform(1e-4, 4e-2, shape)
        cal = rng.uniform(0.0, 1e-3, shape)
        maps = [np.ascontiguousarray(a, np.float32) for a in (r, var + cal, cal)]
        for with_calibration in (True, False):
            out_r, out_v, out_c = (np.empty(shape, np.float32) for _ in range(3))
            checked(*maps, with_calibration, out_r, out_v, out_c)
            ref_r, ref_v = naive(maps[0], np.where(np.isfinite(r), var if with_calibration else var + cal, np.nan).astype(np.float32), "mean")
            if with_calibration:
                ref_v = ref_v + naive_common(maps[0], maps[2])
                np.testing.assert_allclose(out_c, naive_common(maps[0], maps[2]), rtol=1e-5, equal_nan=True)
            np.testing.assert_allclose(out_r, ref_r, rtol=1e-6, equal_nan=True)
            np.testing.assert_allclose(out_v, ref_v, rtol=1e-5, equal_nan=True)


def test_mean_of_a_constant_variance_map_divides_the_variance_by_the_window_count(mean_path):
    r = np.full((5, 6), 2.0)
    out = smooth_range_map(result(r, np.full((5, 6), 0.09)), "mean")
    np.testing.assert_allclose(out.range, 2.0)
    # 9 neighbours inside, 6 on an edge, 4 in a corner.
    assert out.variance[2, 2] == pytest.approx(0.01, rel=1e-6)
    assert out.variance[0, 2] == pytest.approx(0.09 / 6, rel=1e-6)
    assert out.variance[0, 0] == pytest.approx(0.09 / 4, rel=1e-6)


def test_mean_matches_the_naive_reference_with_unequal_variances_and_holes(mean_path):
    rng = np.random.default_rng(7)
    r = rng.uniform(1.0, 4.0, (9, 11))
    var = rng.uniform(1e-4, 4e-2, (9, 11))
    r[rng.random((9, 11)) < 0.25] = np.nan
    r[4, :] = np.nan  # a whole invalid row
    r[0:3, 0:3] = np.nan
    r[1, 1] = 3.0  # a valid pixel ringed by invalid ones: nothing to average with
    out = smooth_range_map(result(r, var), "mean")
    ref_r, ref_v = naive(r.astype(np.float32), np.where(np.isfinite(r), var, np.nan).astype(np.float32), "mean")
    np.testing.assert_allclose(out.range, ref_r, rtol=1e-6, equal_nan=True)
    np.testing.assert_allclose(out.variance, ref_v, rtol=1e-5, equal_nan=True)
    assert out.range[1, 1] == 3.0 and out.variance[1, 1] == pytest.approx(var[1, 1], rel=1e-6)


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "numpy"])
def test_mean_with_a_calibration_share_matches_the_naive_reference_in_both_paths(compiled, monkeypatch):
    """The compiled pass and its numpy twin (platforms without numba) give the naive reference's
    values; the calibration's share of each variance is common to neighbours: it is not divided."""
    from uwcam.ranging import smoothing

    if not compiled:
        monkeypatch.setattr(smoothing, "_smooth_mean", None)
    elif smoothing._smooth_mean is None:
        pytest.skip("numba is not installed: only the numpy path exists")
    rng = np.random.default_rng(11)
    shape = (13, 17)
    r = rng.uniform(1.0, 6.0, shape)
    noise = rng.uniform(1e-4, 4e-2, shape)
    cal = rng.uniform(0.0, 1e-2, shape)
    r[rng.random(shape) < 0.3] = np.nan
    r[:, 0] = np.nan  # a whole invalid border column
    r[12, 16] = 2.5  # a corner pixel
    valid = np.isfinite(r)
    base = result(r, noise + cal)
    out = smooth_range_map(RangeResult(base.range, base.variance, base.reasons,
                                       np.where(valid, cal, np.nan).astype(np.float32)), "mean")
    ref_r, ref_noise = naive(r.astype(np.float32), np.where(valid, noise, np.nan).astype(np.float32), "mean")
    np.testing.assert_allclose(out.range, ref_r, rtol=1e-6, equal_nan=True)
    common = naive_common(r, cal)
    np.testing.assert_allclose(out.variance, ref_noise + common, rtol=1e-5, equal_nan=True)
    np.testing.assert_allclose(out.common_variance, common, rtol=1e-5, equal_nan=True)
    assert out.range.dtype == np.float32 and out.variance.dtype == np.float32


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "numpy"])
def test_a_neighbour_ranged_from_other_light_brings_its_common_doubt_into_the_mean(compiled, monkeypatch):
    """Murky water, seen in the water study (Jerlov III, gated, 7 m): a pixel ranged with red, 7.1 m
    ± 0.47 m, beside one whose red was lost, ranged from green and blue alone (channels that
    attenuate alike: 31 m ± 43 m, nearly all of it the calibration's). Their mean was 15 m with the
    first pixel's ± 0.47 m, 17σ from the truth. Checked against sampling: each pixel's error is
    its own noise plus its light's common error (shared by the pixels ranged from the same light,
    and here fully correlated between the two kinds, the case the mean's variance must cover)."""
    from uwcam.ranging import smoothing

    if not compiled:
        monkeypatch.setattr(smoothing, "_smooth_mean", None)
    elif smoothing._smooth_mean is None:
        pytest.skip("numba is not installed: only the numpy path exists")
    truth = 7.0
    own = np.array([[0.05, 0.05, 0.05], [0.05, 0.05, 0.05], [3.0, 3.0, 3.0]])  # σ of each pixel's own noise, m
    shared = np.array([[0.47, 0.47, 0.47], [0.47, 0.47, 0.47], [43.0, 43.0, 43.0]])  # σ of its common error, m
    rng = np.random.default_rng(3)
    trials = 4000
    common_draw = rng.standard_normal(trials)
    means = []
    for t in range(trials):
        r = truth + rng.standard_normal((3, 3)) * own + common_draw[t] * shared
        means.append(np.mean(r))
    sampled = np.var(means)
    out = smooth_range_map(RangeResult(np.full((3, 3), truth, np.float32), (own**2 + shared**2).astype(np.float32),
                                       np.zeros((3, 3), np.uint8), (shared**2).astype(np.float32)), "mean")
    assert out.variance[1, 1] == pytest.approx(sampled, rel=0.1)
    assert out.common_variance[1, 1] == pytest.approx(np.mean(shared) ** 2, rel=1e-5)
    # The old share, the centre's own 0.47², was 2000 times too small.
    assert out.variance[1, 1] > 100 * 0.47**2


def test_median_matches_the_naive_reference_and_keeps_the_variance():
    rng = np.random.default_rng(8)
    r = rng.uniform(1.0, 4.0, (8, 7))
    var = rng.uniform(1e-4, 4e-2, (8, 7))
    r[rng.random((8, 7)) < 0.3] = np.nan
    out = smooth_range_map(result(r, var), "median")
    ref_r, ref_v = naive(r.astype(np.float32), np.where(np.isfinite(r), var, np.nan).astype(np.float32), "median")
    np.testing.assert_allclose(out.range, ref_r, rtol=1e-6, equal_nan=True)
    np.testing.assert_allclose(out.variance, ref_v, rtol=1e-6, equal_nan=True)


@pytest.mark.parametrize("kind", ["mean", "median"])
def test_invalid_pixels_stay_invalid_with_their_reasons(kind):
    r = np.full((5, 5), 2.0)
    reasons = np.zeros((5, 5), np.uint8)
    r[2, 2] = np.nan
    reasons[2, 2] = Reason.SATURATED
    r[0, 4] = np.nan
    reasons[0, 4] = Reason.PATH_OUT_OF_BOUNDS
    r[3, 1] = 1e6  # a wild but valid value: it may move its neighbours, never fill holes
    before = result(r, np.full((5, 5), 0.01), reasons)
    out = smooth_range_map(before, kind)
    assert np.isnan(out.range[2, 2]) and np.isnan(out.variance[2, 2])
    assert np.isnan(out.range[0, 4]) and np.isnan(out.variance[0, 4])
    np.testing.assert_array_equal(out.reasons, reasons)
    assert np.isfinite(out.range).sum() == 23 and np.isfinite(out.variance).sum() == 23
    assert out.reasons is not before.reasons  # the published reasons are not shared with the input
    # The input is left as it was.
    assert np.isnan(before.range[2, 2]) and before.range[3, 1] == np.float32(1e6)


def test_a_hole_next_to_a_pixel_does_not_count_in_its_mean(mean_path):
    r = np.array([[1.0, np.nan, 3.0]])
    var = np.array([[0.04, 9.0, 0.16]])
    out = smooth_range_map(result(r, var), "mean")
    assert out.range[0, 0] == pytest.approx(1.0) and out.range[0, 2] == pytest.approx(3.0)
    assert out.variance[0, 0] == pytest.approx(0.04) and np.isnan(out.range[0, 1])


def test_two_pixels_average_and_their_variance_is_the_variance_of_the_mean(mean_path):
    r = np.array([[1.0, 3.0]])
    var = np.array([[0.04, 0.16]])
    out = smooth_range_map(result(r, var), "mean")
    np.testing.assert_allclose(out.range, [[2.0, 2.0]])
    np.testing.assert_allclose(out.variance, [[(0.04 + 0.16) / 4] * 2], rtol=1e-6)


def test_outputs_are_float32_and_unknown_kinds_are_refused():
    out = smooth_range_map(result(np.ones((3, 3)), np.ones((3, 3))), "mean")
    assert out.range.dtype == np.float32 and out.variance.dtype == np.float32 and out.reasons.dtype == np.uint8
    with pytest.raises(UserInputError, match="smoothing must be 'mean' or 'median', got 'gaussian'"):
        smooth_range_map(result(np.ones((3, 3)), np.ones((3, 3))), "gaussian")


# ---------------------------------------------------------------- smoothing the image before the transform

def naive_frame(raw: np.ndarray, kind: str, saturation: float) -> tuple[np.ndarray, np.ndarray]:
    """Per channel: mean or median of the window's unsaturated values; a saturated value kept."""
    h, w, n = raw.shape
    out = np.zeros((h, w, n))
    samples = np.ones((h, w, n))
    for i in range(h):
        for j in range(w):
            for k in range(n):
                if raw[i, j, k] >= saturation:
                    out[i, j, k] = raw[i, j, k]
                    continue
                values = [float(raw[y, x, k]) for y in range(max(i - 1, 0), min(i + 2, h))
                          for x in range(max(j - 1, 0), min(j + 2, w)) if raw[y, x, k] < saturation]
                if kind == "mean":
                    out[i, j, k] = sum(values) / len(values)
                    samples[i, j, k] = len(values)
                else:
                    s = sorted(values)
                    m = len(s)
                    out[i, j, k] = s[m // 2] if m % 2 else 0.5 * (s[m // 2 - 1] + s[m // 2])
    return out, samples


@pytest.mark.parametrize("kind", ["mean", "median"])
def test_image_smoothing_leaves_saturated_values_out_and_keeps_them_saturated(kind):
    from uwcam.ranging.smoothing import smooth_frame

    rng = np.random.default_rng(3)
    raw = rng.integers(100, 4000, (7, 9, 3)).astype(np.uint16)
    raw[rng.random(raw.shape) < 0.15] = 4095  # clipped
    raw[0, 0, :] = 4095
    smoothed, samples = smooth_frame(raw, kind, 4095)
    ref, ref_samples = naive_frame(raw, kind, 4095)
    np.testing.assert_allclose(smoothed, ref, rtol=1e-6)
    np.testing.assert_array_equal(samples, ref_samples)
    assert np.all(smoothed[raw >= 4095] >= 4095)


def test_mean_of_the_image_divides_the_noise_variance_by_the_samples_and_the_error_agrees():
    """A flat plate 2 m away in a camera with read and shot noise (the noise drawn here, from
    the stated model): averaging 3×3 pixels before the transform must cut the reported variance
    ninefold inside the image, and the reported σ must match the scatter of the ranges."""
    from tests.synthetic import RGB_ATTENUATION, make_profile
    from uwcam.ranging.estimator import RangeEstimator, range_frame

    read, gain = 4.0, 0.5  # DN rms, DN per electron: σ² = read² + gain·E (+ 1/12 quantisation)
    b = np.log([0.6, 1.0, 0.9])
    profile = make_profile(RGB_ATTENUATION, b, read_noise=read, shot_gain=gain, saturation_level=65535.0)
    est = RangeEstimator(profile, calibration_variance=False)
    d_t = 4.0  # lamp at the camera: path 2 × 2 m
    mean_e = 3000.0 * np.exp(b - RGB_ATTENUATION * d_t) / np.exp(b - RGB_ATTENUATION * d_t).max()
    rng = np.random.default_rng(11)
    shape = (120, 160, 3)
    noisy = mean_e + rng.normal(size=shape) * np.sqrt(read**2 + gain * mean_e)
    frame = np.clip(np.rint(noisy), 0, 65535).astype(np.uint16)
    single = range_frame(est, frame)
    mean = range_frame(est, frame, "mean", "before")
    inner = (slice(1, -1), slice(1, -1))
    ratio = np.median(mean.variance[inner]) / np.median(single.variance[inner])
    assert ratio == pytest.approx(1 / 9, rel=0.03)
    # Neighbouring smoothed values share pixels, so judge the scatter on every third pixel.
    sub = mean.range[1:-1:3, 1:-1:3]
    predicted = np.sqrt(np.median(mean.variance[1:-1:3, 1:-1:3]))
    assert np.std(sub) == pytest.approx(predicted, rel=0.1)
    assert abs(np.median(sub) - 2.0) < 3 * predicted / np.sqrt(sub.size) + 1e-3


def test_a_saturated_pixel_is_not_given_a_range_by_smoothing_before_the_transform():
    from tests.synthetic import RGB_ATTENUATION, make_profile
    from uwcam.ranging.estimator import RangeEstimator, range_frame

    profile = make_profile(RGB_ATTENUATION, np.log([0.6, 1.0, 0.9]), read_noise=2.0, shot_gain=0.2,
                           saturation_level=4095.0)
    # Values consistent with one range (so that fusion weights cannot move it): path 4 m.
    e = np.exp(np.log([0.6, 1.0, 0.9]) - RGB_ATTENUATION * 4.0)
    frame = np.full((5, 5, 3), 3000.0 * e / e.max()).astype(np.float32)
    frame[2, 2, 1] = 4095  # one channel clipped: with two usable channels left, fusion goes on
    frame[0, 0, :] = 4095  # every channel clipped
    out = range_frame(RangeEstimator(profile, calibration_variance=False), frame, "mean", "before")
    assert out.reasons[0, 0] == Reason.SATURATED and np.isnan(out.range[0, 0])
    # Its neighbours average only unclipped values: the same range as the untouched pixels.
    assert out.range[1, 1] == pytest.approx(out.range[4, 4], rel=1e-5)


def test_the_median_keeps_each_pixels_variance_and_common_share():
    """The median is one pixel's value: its variance, and the common share within it, stay the pixel's own."""
    rng = np.random.default_rng(2)
    r = rng.uniform(1.0, 4.0, (5, 6)).astype(np.float32)
    common = rng.uniform(0.0, 1e-3, (5, 6)).astype(np.float32)
    variance = (common + rng.uniform(1e-4, 1e-2, (5, 6))).astype(np.float32)
    out = smooth_range_map(RangeResult(r, variance, np.zeros((5, 6), np.uint8), common), "median")
    np.testing.assert_array_equal(out.variance, variance)
    np.testing.assert_array_equal(out.common_variance, common)


def test_a_common_share_rounded_below_zero_is_no_share(mean_path):
    """A common share found as a difference of variances can come out a rounding below zero; the
    mean takes it as 0 (its square root would be NaN and take the pixel's variance with it)."""
    r = np.full((3, 4), 2.0, np.float32)
    common = np.full((3, 4), -1e-9, np.float32)
    variance = np.full((3, 4), 0.09, np.float32)
    out = smooth_range_map(RangeResult(r, variance, np.zeros((3, 4), np.uint8), common), "mean")
    assert np.all(np.isfinite(out.variance)) and np.all(out.common_variance == 0.0)
    assert out.variance[1, 1] == pytest.approx(0.09 / 9, rel=1e-5)



def test_medians_over_windows_without_values_neither_warn_nor_touch_the_warning_filters(monkeypatch):
    """The frame loop smooths beside the API's threads: swapping the process's warning filters
    (warnings.catch_warnings, to silence nanmedian's all-NaN warning) is not thread-safe and let the
    warning through another thread's restore. Both medians (of the range map, and of the frame
    before the transform around saturated values) must neither warn (the suite's filter makes a
    warning an error) nor touch the filters."""
    import warnings

    def refuse(*args, **kwargs):
        raise AssertionError("warning filters swapped in the frame loop")

    r = np.full((6, 7), np.nan, np.float32)
    r[2, 3] = 2.0
    result = RangeResult(r, np.where(np.isfinite(r), 0.01, np.nan).astype(np.float32),
                         np.where(np.isfinite(r), 0, 1).astype(np.uint8))
    raw = np.full((6, 7, 3), 100.0, np.float32)
    raw[0:3, 0:3] = 4000.0  # saturated: their windows are taken again, the corner's with no usable value
    monkeypatch.setattr(warnings, "catch_warnings", refuse)
    smoothed = smooth_range_map(result, "median")
    frame, _ = smooth_frame(raw, "median", 4000.0)
    assert smoothed.range[2, 3] == 2.0 and np.isnan(smoothed.range[0, 0])
    assert np.all(frame[0:3, 0:3] == 4000.0) and frame[5, 6, 0] == 100.0
