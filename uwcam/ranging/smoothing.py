"""Smoothing for ranging: area means, a frame smoothed before the transform (its variance
divided by the window's count), and the range map smoothed after it, weighted by its σ."""

from __future__ import annotations


import cv2
import numpy as np
from numpy.typing import NDArray

from uwcam.compute.jit import HAVE_NUMBA, kernel_array, njit, prange
from uwcam.fileio import UserInputError

from uwcam.ranging.result import RangeResult


def block_means(image: NDArray, size: tuple[int, int]) -> NDArray:
    """``image`` (H, W) or (H, W, N) reduced to ``size`` = (w, h) by area averaging (OpenCV's
    INTER_AREA), the type kept. An integer image whose sides are ``size`` times a power of two is
    halved step by step instead: each step the exact 2×2 mean, rounded (½ DN at most), so a block of
    8 is within 1.5 DN of its exact mean (against ½ DN in one reduction) and 2–3× faster than one
    reduction by 8 (OpenCV's general path): 0.5 against 1.4 ms for a 1080p frame."""
    w, h = size
    height, width = image.shape[:2]
    if np.issubdtype(image.dtype, np.integer) and w > 0 and h > 0 and height % h == 0 and width % w == 0:
        fy, fx = height // h, width // w
        if fy == fx and fy > 2 and fy & (fy - 1) == 0:
            while image.shape[0] > h:
                image = cv2.resize(image, (image.shape[1] // 2, image.shape[0] // 2), interpolation=cv2.INTER_AREA)
            return image
    return cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)


def window_light(frame: NDArray[np.float32], usable: NDArray[np.float32], samples: NDArray | None,
                 background: NDArray | None, size: int) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray | None]:
    """Each value's mean over the ``size``×``size`` window around it (clipped at the border) of the
    values with ``usable`` 1 (unsaturated, not the vehicle), the number of single-pixel noises its
    variance equals, and the background's mean over the same values.

    frame, usable: (H, W, N) float32 (linear DN; 1 or 0); samples: (H, W, N) how many single-pixel
    noises each value of ``frame`` already equals (frames fused over time), None: one. The mean of
    n values with variances σ²/s_k has the variance σ²·Σ(1/s_k)/n², so it equals n²/Σ(1/s_k)
    single-pixel noises (n without fusion). A value that is saturated itself stays as it is (the
    estimator then marks that channel saturated), as does one without a usable value around it."""
    box = dict(ddepth=-1, ksize=(size, size), normalize=False, borderType=cv2.BORDER_CONSTANT)
    shape = frame.shape
    # OpenCV sums float32 windows in float64 (its box filter's sum type), so 289 values of 16 bits stay exact enough.
    count = np.rint(cv2.boxFilter(usable, **box)).reshape(shape)
    total = cv2.boxFilter(frame * usable, **box).reshape(shape)
    keep = (count > 0) & (usable > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(keep, total / count, frame).astype(np.float32)
        if samples is None:
            counts = np.where(keep, count, 1.0).astype(np.float32)
        else:
            s = np.maximum(np.asarray(samples, np.float32), np.float32(1e-6))
            inverse = cv2.boxFilter(np.ascontiguousarray(usable / s), **box).reshape(shape)
            counts = np.where(keep, count * count / inverse, s).astype(np.float32)
        light = None
        if background is not None:
            bg = np.ascontiguousarray(np.broadcast_to(background, shape), dtype=np.float32)
            light = np.where(count > 0, cv2.boxFilter(bg * usable, **box).reshape(shape) / count, bg).astype(np.float32)
    return mean, counts, light


def nanmedian_of_windows(windows: NDArray) -> NDArray[np.float64]:
    """The median over axis 0 of the values that are not NaN, NaN where a window has none.

    np.nanmedian warns on an all-NaN window, and silencing it with ``warnings.catch_warnings``
    swaps the process's warning filters, which is not thread-safe: the frame loop did it beside
    the API's threads, and a filter restored under another thread let an "All-NaN slice" warning
    through, an error in the restore of the settings under a strict filter."""
    empty = np.isnan(windows).all(axis=0)
    if empty.any():
        windows = np.where(empty, 0.0, windows)
    out = np.asarray(np.nanmedian(windows, axis=0), dtype=np.float64)
    out[empty] = np.nan
    return out


def smooth_frame(frame: NDArray, kind: str, saturation_level: float) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """3×3 smoothing of a raw frame (H, W, N) before the transform (docs/physics.md §7).

    Each channel of each pixel becomes the mean ("mean") or median ("median") of the unsaturated
    values of that channel in its 3×3 window (clipped at the image border): a clipped value says
    only "at least this bright" and would bias its neighbours. A pixel whose own value is
    saturated stays saturated (its neighbours do not lend it a value). Returns the smoothed frame
    (float32) and, per value, the number of independent samples its noise is averaged over:
    n for the mean of n values (variance σ²/n); 1 for the median, whose variance is left at a
    single pixel's (a conservative bound: 1.7 to 6 times the true one for 9 to 3 samples).
    """
    if kind not in ("mean", "median"):
        raise UserInputError(f"smoothing must be 'mean' or 'median', got '{kind}'")
    raw = np.asarray(frame)
    saturated = raw >= saturation_level
    values = raw.astype(np.float32)
    usable = (~saturated).astype(np.float32)
    if kind == "mean":  # a saturated value stays as it is, with 1 sample
        smoothed, samples, _ = window_light(values, usable, None, None, 3)
        return smoothed, samples
    smoothed = np.empty_like(values)
    for k in range(raw.shape[-1]):
        smoothed[..., k] = cv2.medianBlur(np.ascontiguousarray(values[..., k]), 3)
    # The border and windows holding a saturated value: the median of the usable values alone.
    box = dict(ddepth=-1, ksize=(3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
    redo = np.rint(cv2.boxFilter(usable, **box)).reshape(raw.shape) < 9
    if redo.any():
        padded = np.pad(np.where(saturated, np.nan, values), ((1, 1), (1, 1), (0, 0)), constant_values=np.nan)
        ii, jj, kk = np.nonzero(redo)
        windows = np.stack([padded[ii + di, jj + dj, kk] for di in range(3) for dj in range(3)])
        smoothed[ii, jj, kk] = nanmedian_of_windows(windows)  # all-NaN windows: kept below
    # A saturated value stays as it was (the estimator then marks that channel saturated); the
    # median's variance is left at a single pixel's.
    return np.where(saturated, values, smoothed).astype(np.float32), np.ones(raw.shape, np.float32)


def _smooth_mean_py(range_m, variance, calibration, with_calibration, out_range, out_variance, out_common):
    """The 3×3 mean of :func:`smooth_range_map` in one pass over (H, W) float32 maps: each valid
    pixel's mean over the n valid pixels of its window (clipped at the border), variance
    Σ(σ_k² − cal_k)/n² + (Σ√cal_k / n)², the common parts (``calibration``, read only where
    ``with_calibration``) taken as fully correlated, and that common part in ``out_common``; NaN
    where the pixel itself has no range. Sums in float64, by columns of three rows first; without
    branches (a choice of value instead), which the compiler turns into vector instructions."""
    h, w = range_m.shape
    nan = np.float32(np.nan)
    count = np.zeros(w + 2)  # the column sums of rows i−1..i+1, one column of zeros either side
    total = np.zeros(w + 2)
    noise = np.zeros(w + 2)
    shared = np.zeros(w + 2)
    for i in range(h):
        for x in range(w + 2):
            count[x] = 0.0
            total[x] = 0.0
            noise[x] = 0.0
            shared[x] = 0.0
        for y in range(max(i - 1, 0), min(i + 2, h)):
            for x in range(w):
                r = range_m[y, x]
                ok = r - r == 0.0  # finite
                common = np.float64(calibration[y, x]) if with_calibration else 0.0
                count[x + 1] += 1.0 if ok else 0.0
                total[x + 1] += r if ok else 0.0
                noise[x + 1] += variance[y, x] - common if ok else 0.0
                shared[x + 1] += np.sqrt(max(common, 0.0)) if ok else 0.0
        for j in range(w):
            r = range_m[i, j]
            ok = r - r == 0.0
            n = count[j] + count[j + 1] + count[j + 2]
            common = (shared[j] + shared[j + 1] + shared[j + 2]) / max(n, 1.0)
            common *= common
            out_range[i, j] = (total[j] + total[j + 1] + total[j + 2]) / n if ok else nan
            out_variance[i, j] = (noise[j] + noise[j + 1] + noise[j + 2]) / (n * n) + common if ok else nan
            out_common[i, j] = common if ok else nan


# Compiled: numpy's box filters and temporaries took 43 ms per 720p map on the 2-core test
# machine, a fifth of the frame loop's time; this pass 8.6 ms on one core, the same values to 1
# float32 ulp. Not parallel: split over rows it was no faster (8.7 ms, quiet machine) and took
# 2–3× as long to compile, which a first start waits for.
_smooth_mean = njit(cache=True, nogil=True)(_smooth_mean_py) if HAVE_NUMBA else None


def smooth_range_map(result: RangeResult, kind: str = "mean") -> RangeResult:
    """3×3 smoothing of a range map over valid neighbours only (docs/physics.md §7).

    kind "mean": average of the n valid pixels in each 3×3 window, with the variance of that
    average for independent neighbours, Σσ_k²/n² (σ²/n when all are equal), plus the
    share neighbours have in common (``common_variance``: calibration, backscatter model), which
    averaging does not reduce: fully correlated, (Σσ_c,k/n)², so a neighbour whose range came from
    other light (other channels, a larger doubt) brings its larger share into the mean; the
    result's ``common_variance`` is that share. "median": their median, variance kept.
    Invalid pixels stay invalid with their reasons, and never leak into valid ones.
    """
    if kind not in ("mean", "median"):
        raise UserInputError(f"smoothing must be 'mean' or 'median', got '{kind}'")
    r = result.range
    valid = np.isfinite(r)
    # The common share (calibration, backscatter model) is the neighbours' too: averaging does not reduce it.
    cal = 0.0 if result.common_variance is None else result.common_variance
    if kind == "mean" and _smooth_mean is not None:
        shape = r.shape
        maps = [kernel_array(a, shape, np.float32) for a in (r, result.variance)]
        with_calibration = result.common_variance is not None
        calibration = kernel_array(result.common_variance, shape, np.float32) if with_calibration else maps[1]
        out_range, out_variance, out_common = (np.empty(shape, np.float32) for _ in range(3))
        _smooth_mean(*maps, calibration, with_calibration, out_range, out_variance, out_common)
        return RangeResult(out_range, out_variance, result.reasons.copy(), out_common if with_calibration else None)
    if kind == "mean":
        # Window sums as box filters (outside the image and at invalid pixels: 0, not counted),
        # in float32 like the maps themselves (sums of nine: within 3 units in the last place):
        # ~10× faster at 720p than over nine shifted float64 copies, so it can be on by default.
        def window_sum(a: NDArray[np.float32]) -> NDArray[np.float32]:
            return cv2.boxFilter(a, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)

        zero = np.float32(0)
        count = window_sum(valid.astype(np.float32))
        with np.errstate(invalid="ignore", divide="ignore"):
            smoothed = window_sum(np.where(valid, r, zero)) / count
        # The noise of independent neighbours averages as Σσ_k²/n²; the common shares, fully
        # correlated, as (Σσ_c,k / n)²: a neighbour ranged from other light (other channels, a
        # model's doubt) brings its own common share into the mean.
        noise = np.where(valid, result.variance.astype(np.float32) - np.float32(cal), zero)
        n = np.maximum(count, np.float32(1))
        common = (window_sum(np.where(valid, np.sqrt(np.maximum(np.float32(cal), zero)), zero)) / n) ** 2
        variance = window_sum(noise) / n**2 + common
    else:
        padded = np.pad(np.where(valid, r.astype(np.float64), np.nan), 1, constant_values=np.nan)
        h, w = r.shape
        windows = np.stack([padded[dy : dy + h, dx : dx + w] for dy in range(3) for dx in range(3)])
        smoothed = nanmedian_of_windows(windows)
        variance = result.variance
    return RangeResult(
        np.where(valid, smoothed, np.nan).astype(np.float32),
        np.where(valid, variance, np.nan).astype(np.float32),
        result.reasons.copy(),
        result.common_variance if result.common_variance is None or kind == "median"
        else np.where(valid, common, np.nan).astype(np.float32),
    )
