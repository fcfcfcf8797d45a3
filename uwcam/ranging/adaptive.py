"""Spatial windows that adapt to the signal (``processing.smoothing: adaptive``, docs/physics.md §7).

A pixel whose range is already known to ``target`` (σ no more than that fraction of the range)
keeps it, bit for bit. Any other pixel, a range with a larger σ or none because its light is too
weak (reasons 1, 3, 4 and 5), is ranged again from the mean light of a square window around it: the
smallest of :data:`LADDER` whose range reaches the target, else the largest one accepted. The
window's light is averaged per channel over its unsaturated values (each pixel's read, shot and
fixed-pattern noise are its own, so the mean of n values has the variance σ²/n) and goes through
the same transform and the same judgement against the water's light as a single pixel: the σ
reported is that of the window actually used, and a pixel too dark on its own gets a range where
its window's light is clearly above the water's.

Light is averaged, not ranges. The log of a noisy signal reads low by σ²/2E², which n pixels'
√n smaller noise would leave standing as several σ; weights 1/σ² follow each pixel's own noise
(a pixel that caught more light reads nearer and weighs more); and the valid pixels of a dark
area are those whose noise happened to lift them over the threshold, so their ranges' mean reads
short. The mean light of all the pixels has none of these biases.

A window must not cross a range discontinuity: two surfaces' light mixed reads a range between
them (nearer the brighter), with a small σ. Growing stops, and the pixel keeps the last window
accepted (or its own range), at the first window
- whose mean light differs from the pixel's own, in a channel ranged with, by more than
  :data:`LIGHT_SIGMAS` standard deviations of that difference (a brighter surface in the window), or
- whose range differs from that of the last window accepted, or the pixel's first range, by more
  than :data:`RANGE_SIGMAS` standard deviations of the difference of the two nested means
  (Var(small) − Var(large)): the intersection of confidence intervals rule of adaptive scale
  selection (Katkovnik), which catches a step whose light does not differ by much.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import cv2
import numpy as np
from numpy.typing import NDArray

from uwcam.optics.noise import signal_variance
from uwcam.optics.validity import Reason
from uwcam.ranging.result import RangeResult
from uwcam.ranging.smoothing import window_light

if TYPE_CHECKING:  # the estimator imports this module
    from uwcam.ranging.estimator import RangeEstimator

LADDER: tuple[int, ...] = (3, 5, 9, 17)
"""Window sides (pixels) tried in turn after the pixel alone: each holds about 3 times the pixels
of the one before (σ falls by about √3 a step), up to 289."""
LIGHT_SIGMAS = 4.0
"""A window whose mean light is this many σ from the pixel's own in any channel is given up: by
chance about once in 5000 tries with three channels."""
RANGE_SIGMAS = 3.0
"""A window whose range is this many σ (of the difference) from a smaller window's is given up."""
RESCUED = (Reason.BELOW_NOISE_FLOOR, Reason.BACKSCATTER_ONLY, Reason.TOO_FEW_CHANNELS, Reason.PATH_OUT_OF_BOUNDS)
"""Reasons a window may lift: too little light (or a path that noise put out of bounds). A saturated
pixel or the vehicle stays as it is."""

Ranger = Callable[[NDArray, NDArray, "NDArray | None"], RangeResult]
"""(frame, samples, background) → the range of that frame, judged against the water's light and
masked as a single frame is (:func:`uwcam.ranging.estimator.range_frame`)."""


def _noise_variance(estimator: RangeEstimator, frame: NDArray, samples: NDArray | None) -> NDArray[np.float32]:
    """(H, W, N) noise variance (DN²) of values that are means of ``samples`` pixels (None: one),
    in float32 (a test statistic's scale, not a result: in float64 it was half the cost of the
    windows at 720p)."""
    f32 = np.float32
    var = signal_variance(np.asarray(frame, f32) - estimator.dark.astype(f32), estimator.read_noise,
                          estimator.shot_gain, estimator.profile.quantisation_step, estimator.fixed_pattern, f32)
    var = np.where(var > 0, var, f32(1))  # a profile without a noise model counts 1 DN, as the estimator does
    return var if samples is None else var / np.maximum(np.asarray(samples, f32), f32(1e-6))


def adaptive_windows(single: RangeResult, frame: NDArray, ranged: Ranger, estimator: RangeEstimator, target: float,
                     samples: NDArray | None = None, background: NDArray | None = None,
                     ladder: tuple[int, ...] = LADDER) -> RangeResult:
    """``single`` (the frame's own ranging) with each pixel above ``target`` (σ/range, e.g. 0.02)
    or without a range for too little light ranged from the smallest window of ``ladder`` that
    reaches the target (see the module's docstring); the others are returned unchanged.

    frame: (H, W, N) the frame ``single`` was ranged from; ranged: ranges a frame of window means
    as ``single`` was (:data:`Ranger`); estimator: the :class:`~uwcam.ranging.estimator.RangeEstimator`
    (its noise model, saturation level and channels); samples, background: those ``single`` was
    ranged with (frames fused over time; light not from the lamp)."""
    if not (np.isfinite(target) and target > 0):
        raise ValueError(f"the smoothing target must be a positive fraction of the range, got {target}")
    r1, v1, reasons1 = single.range, single.variance, single.reasons
    have = np.isfinite(r1)
    with np.errstate(invalid="ignore"):
        settled = have & (v1.astype(np.float64) <= (target * r1.astype(np.float64)) ** 2)
    active = ~settled & (have | np.isin(reasons1, [int(r) for r in RESCUED]))
    if not active.any():
        return single
    data = np.asarray(frame)
    if estimator.response is not None and np.issubdtype(data.dtype, np.integer):
        data = estimator.response.linearise(data)  # average light, not codes of a tone curve
    data = data.astype(np.float32)
    saturation = estimator.profile.saturation_level
    usable = ((data < saturation) & np.isfinite(data) & (reasons1 != Reason.VEHICLE)[..., None]).astype(np.float32)
    n = data.shape[-1]
    # The light test looks at the channels ranged with, where the pixel's own value is usable; it
    # runs on the pixels still growing only (gathered as rows of N values).
    judged = ((usable > 0) & estimator.active).reshape(-1, n)
    flat_data = data.reshape(-1, n)
    flat_samples = None if samples is None else np.broadcast_to(samples, data.shape).reshape(-1, n)
    best_r = np.where(have, r1, np.nan).astype(np.float64)
    best_v = np.where(have, v1, np.nan).astype(np.float64)
    first_r, first_v = best_r.copy(), best_v.copy()
    chosen = np.zeros(r1.shape, bool)
    # The common share of each pixel's variance (calibration, backscatter model), of the light its range came from.
    cal = None if single.common_variance is None else np.array(single.common_variance, np.float32)
    for size in ladder:
        if not active.any():
            break
        mean, counts, light = window_light(data, usable, samples, background, size)
        result = ranged(mean, counts, light)
        r, v = result.range.astype(np.float64), result.variance.astype(np.float64)
        rows = np.flatnonzero(active)
        own, window = flat_data[rows], mean.reshape(-1, n)[rows]
        with np.errstate(invalid="ignore", divide="ignore"):
            z2 = (own - window) ** 2 / (_noise_variance(estimator, own, None if flat_samples is None else flat_samples[rows])
                                        + _noise_variance(estimator, window, counts.reshape(-1, n)[rows]))
            alike = np.zeros(r1.shape, bool)
            alike.flat[rows] = np.max(np.where(judged[rows], z2, np.float32(0)), axis=-1) <= LIGHT_SIGMAS**2
            known = np.isfinite(best_r)

            def consistent(ref_r: NDArray, ref_v: NDArray) -> NDArray[np.bool_]:
                # Nested means: the difference has the variance of the smaller less that of the larger.
                spread = ref_v - v
                return ~np.isfinite(ref_r) | ((spread > 0) & ((r - ref_r) ** 2 <= RANGE_SIGMAS**2 * spread))

            take = active & np.isfinite(r) & alike & consistent(best_r, best_v) & consistent(first_r, first_v)
            reached = take & (v <= (target * r) ** 2)
        first = take & ~np.isfinite(first_r)
        first_r[first], first_v[first] = r[first], v[first]
        best_r[take], best_v[take] = r[take], v[take]
        if cal is not None and result.common_variance is not None:
            cal[take] = result.common_variance[take]
        chosen |= take
        # Growing stops at the target, and at the first window given up once a range is had (or
        # whose light is unlike the pixel's own): a larger one would cross the same edge.
        active &= ~(reached | (~take & (known | ~alike)))
    if not chosen.any():
        return single
    return RangeResult(
        np.where(chosen, best_r, r1).astype(np.float32),
        np.where(chosen, best_v, v1).astype(np.float32),
        np.where(chosen, np.uint8(Reason.VALID), reasons1).astype(np.uint8),
        cal,
    )
