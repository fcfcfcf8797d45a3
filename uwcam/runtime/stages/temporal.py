"""Temporal fusion: a running per-pixel mean of the frames over which the scene held still
(docs/physics.md §11).

Each pixel keeps the mean of its raw values (linear DN, all channels) since it last changed, and
the sum of the squares of the frames' weights in it, Σw² (1/K for K equal weights). A new frame
is added to a pixel's mean when every channel of it lies within ``change_sigmas`` standard
deviations of the mean (the noise model's frame-to-frame noise of the difference, which has no
fixed-pattern part: the pixel is the same); otherwise the pixel starts afresh from the new frame,
as it does where the new frame or the mean is saturated. The whole image starts afresh when the
frame's exposure differs from the last one (the values are no longer comparable) or the frame's
size changes. The mean is then ranged as one frame whose noise is the noise model's with the
temporal part times Σw² and the fixed pattern (the same in every frame) whole: exactly what
``uwcam range`` does with several images (:func:`uwcam.ranging.images.fuse_frames`). So a pixel
that held still for N frames has its range's σ from the temporal noise divided by √N, and one
that changed is ranged from the new frame alone: never a blend of two scenes beyond what the
noise hides.

The functions here are pure (arrays in, arrays out); :class:`TemporalFuser` holds the state.
"""

from __future__ import annotations

import collections
import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from uwcam.compute.jit import HAVE_NUMBA, njit, prange, repeat_per_pixel
from uwcam.config import TemporalConfig
from uwcam.ranging.estimator import RangeEstimator
from uwcam.ranging.images import samples_of_mean


def changed_pixels(frame: NDArray, mean: NDArray, weight_squares: NDArray, dark: NDArray, read_variance: NDArray,
                   shot_gain: NDArray, sigmas: float) -> NDArray[np.bool_]:
    """(H, W) True where a new frame's pixel is not the same scene as the running mean's.

    frame, mean: (H, W, N) raw linear values (DN); weight_squares: (H, W) Σw² of the mean; dark,
    read_variance (read noise² + quantisation step²/12, DN²), shot_gain (DN per photo-electron):
    (N,) the noise model. The difference x − x̄ of an unchanged pixel has the variance
    σ_t²(E)·(1 + Σw²), σ_t² the frame-to-frame noise at the mean's signal E = x̄ − dark (the fixed
    pattern is common to both and cancels); a pixel is changed where any channel's difference
    exceeds ``sigmas`` of it."""
    signal = np.maximum(mean - dark, 0.0)
    variance = (read_variance + shot_gain * signal) * (1.0 + weight_squares[..., None])
    difference = frame - mean
    return np.any(difference * difference > (sigmas * sigmas) * variance, axis=-1)


def fuse_step(mean: NDArray[np.float32] | None, count: NDArray[np.uint16] | None, weight_squares: NDArray[np.float32] | None,
              frame: NDArray, restart: NDArray[np.bool_] | bool, max_frames: int
              ) -> tuple[NDArray[np.float32], NDArray[np.uint16], NDArray[np.float32]]:
    """Add a frame (H, W, N) to the running mean: (mean, count, Σw²) after it.

    Where ``restart`` (or everywhere without a previous mean) the pixel becomes the frame itself,
    count 1, Σw² 1. Elsewhere count grows by one up to ``max_frames`` and the new frame weighs
    α = 1/count: the plain mean of the frames so far, then a running average of weight
    1/max_frames. Σw² follows exactly: Σw² ← (1 − α)²·Σw² + α² (1/K for K equal weights, 1/(2M − 1)
    for a long running average of weight 1/M)."""
    x = np.asarray(frame, np.float32)
    if mean is None or count is None or weight_squares is None or mean.shape != x.shape:
        h, w = x.shape[:2]
        return x.copy(), np.ones((h, w), np.uint16), np.ones((h, w), np.float32)
    restart = np.broadcast_to(np.asarray(restart, bool), count.shape)
    count = np.where(restart, 1, np.minimum(count.astype(np.int32) + 1, max_frames)).astype(np.uint16)
    alpha = (1.0 / count).astype(np.float32)
    mean = mean + alpha[..., None] * (x - mean)
    np.copyto(mean, x, where=restart[..., None])  # exactly the frame, not mean + (x − mean) rounded
    keep = 1.0 - alpha
    weight_squares = keep * keep * weight_squares + alpha * alpha
    weight_squares[restart] = 1.0
    return mean, count, weight_squares.astype(np.float32)


def image_shift_px(turn_rate_rad_s: float | None, speed_m_s: float | None, interval_s: float, focal_px: float,
                   range_m: float) -> float | None:
    """How far (pixels) the vehicle's motion over ``interval_s`` seconds moves the image, at most:
    turning at ω rad/s moves every pixel by about f·ω·Δt; moving at v m/s moves a surface at
    range r by up to f·v·Δt/r (sideways; straight ahead the image grows by less). None when
    neither rate is known."""
    if turn_rate_rad_s is None and speed_m_s is None:
        return None
    shift = focal_px * (turn_rate_rad_s or 0.0) * interval_s
    if speed_m_s is not None and range_m > 0:
        shift += focal_px * speed_m_s * interval_s / range_m
    return shift


@njit(parallel=True, cache=True, nogil=True, error_model="numpy")
def _fuse_compiled(frame, mean, count, weight_squares, dark, read_variance, shot_gain, fixed_squared, saturation, sigmas_squared,
                   max_frames, samples):  # pragma: no cover - compiled; its numpy twin is changed_pixels + fuse_step + samples_of_mean
    """One pass of :func:`changed_pixels`, the saturation test, :func:`fuse_step` and
    :func:`uwcam.ranging.images.samples_of_mean` per row, in float32, updating mean, count and
    weight_squares in place and filling samples (H, W, N); returns how many pixels started afresh.
    Each row is taken as W·N contiguous values with each channel's constants repeated along it:
    the per-value passes have no branch and vectorise; only the per-pixel pass joins channels."""
    h, w, n = mean.shape
    m = w * n
    one, zero = np.float32(1.0), np.float32(0.0)
    frame_rows, mean_rows, sample_rows = frame.reshape(h, m), mean.reshape(h, m), samples.reshape(h, m)
    t = np.empty((4, m), np.float32)
    repeat_per_pixel(dark, t[0])
    repeat_per_pixel(read_variance, t[1])
    repeat_per_pixel(shot_gain, t[2])
    repeat_per_pixel(fixed_squared, t[3])
    restarted = np.zeros(h, np.int64)
    for i in prange(h):
        xs, ms, out = frame_rows[i], mean_rows[i], sample_rows[i]
        spread = np.empty(m, np.float32)  # 1 + Σw² of each value's pixel
        for j in range(w):
            for k in range(n):
                spread[j * n + k] = one + weight_squares[i, j]
        far = np.empty(m, np.int32)  # 1 where a value is not the same scene as the mean
        for x in range(m):  # per value: the change test
            v = np.float32(xs[x])
            u = ms[x]
            e = max(u - t[0, x], zero)
            d = v - u
            far[x] = np.int32((v >= saturation) | (u >= saturation)
                              | (d * d > sigmas_squared * ((t[1, x] + t[2, x] * e) * spread[x])))
        alpha_row = np.empty(m, np.float32)
        s_row = np.empty(m, np.float32)
        fresh = np.empty(m, np.int32)
        for j in range(w):  # per pixel: a change in any channel restarts it
            changed = 0
            for k in range(n):
                changed |= far[j * n + k]
            c = 1 if changed else min(np.int64(count[i, j]) + 1, max_frames)
            restarted[i] += changed
            alpha = one / np.float32(c)
            keep = one - alpha
            s = one if changed else keep * keep * weight_squares[i, j] + alpha * alpha
            count[i, j] = c
            weight_squares[i, j] = s
            for k in range(n):
                alpha_row[j * n + k] = alpha
                s_row[j * n + k] = s
                fresh[j * n + k] = changed
        for x in range(m):  # per value: the mean and its samples
            v = np.float32(xs[x])
            u = v if fresh[x] else ms[x] + alpha_row[x] * (v - ms[x])
            ms[x] = u
            e = max(u - t[0, x], zero)
            temporal = t[1, x] + t[2, x] * e
            fixed = t[3, x] * e * e
            fused = temporal * s_row[x] + fixed
            out[x] = (temporal + fixed) / fused if fused > zero else one / s_row[x]
    return restarted.sum()


@dataclass
class TemporalFuser:
    """The running mean of the frames over which each pixel held still, for the frame loop."""

    config: TemporalConfig
    mean: NDArray[np.float32] | None = None
    """(H, W, N) running mean of the raw linear values (DN), or None before the first frame."""
    count: NDArray[np.uint16] | None = None
    """(H, W) frames each pixel's mean is built from since it last started afresh (up to max_frames)."""
    weight_squares: NDArray[np.float32] | None = None
    """(H, W) Σw² of each pixel's mean."""
    restarted: str = "no frame yet"
    """Why the whole image last started afresh."""
    changed_fraction: float | None = None
    """Share of the pixels that started afresh on the last frame."""
    _exposures: tuple | None = None
    shift_px: float | None = None
    """The image shift the vehicle's reported motion made over the last frame interval (None: no report)."""
    _last_ns: int | None = None
    ms: collections.deque = field(default_factory=lambda: collections.deque(maxlen=100))

    def reset(self, why: str) -> None:
        """Forget the running mean: the next frame starts every pixel afresh."""
        self.mean = self.count = self.weight_squares = None
        self.restarted = why

    def judge_motion(self, capture_ns: int, turn_rate_rad_s: float | None, speed_m_s: float | None, focal_px: float,
                     range_m: float) -> None:
        """Start every pixel afresh when the vehicle's reported motion since the last frame (captured
        at ``capture_ns``, monotonic ns) moved the image by more than ``config.motion_pixels``."""
        last, self._last_ns = self._last_ns, capture_ns
        if last is None or self.config.motion_pixels is None:
            self.shift_px = None
            return
        self.shift_px = image_shift_px(turn_rate_rad_s, speed_m_s, max(capture_ns - last, 0) / 1e9, focal_px, range_m)
        if self.shift_px is not None and self.shift_px > self.config.motion_pixels and self.mean is not None:
            self.reset(f"the vehicle moved ({self.shift_px:.1f} pixels in a frame)")

    def update(self, data: NDArray, exposures: tuple, estimator: RangeEstimator) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Add a frame's raw linear values (H, W, N) taken at ``exposures`` (the frame's exposure times
        and gains); returns (the running mean to range, samples per value for the estimator, see
        :func:`uwcam.ranging.images.samples_of_mean`)."""
        started = time.perf_counter()
        key = tuple(None if v is None else tuple(np.ravel(v).tolist()) for v in exposures)
        if self.mean is not None and self.mean.shape != data.shape:
            self.reset("the frame size changed")
        elif self.mean is not None and key != self._exposures:
            self.reset("the exposure changed")
        self._exposures = key
        if self.mean is None:
            restart: NDArray[np.bool_] | bool = True
            self.changed_fraction = 1.0
            if self.restarted == "no frame yet":
                self.restarted = "started with the first frame"
        elif HAVE_NUMBA:
            return self._update_compiled(np.ascontiguousarray(data), estimator, started)
        else:
            x = np.asarray(data, np.float32)
            q = float(np.asarray(estimator.profile.quantisation_step, np.float64))
            read_variance = (estimator.read_noise ** 2 + q * q / 12.0).astype(np.float32)
            restart = changed_pixels(x, self.mean, self.weight_squares, estimator.dark.astype(np.float32), read_variance,
                                     estimator.shot_gain.astype(np.float32), float(self.config.change_sigmas))
            # Saturated values say only "at least this much": a mean of them is no measurement.
            level = estimator.profile.saturation_level
            restart |= np.any(x >= level, axis=-1) | np.any(self.mean >= level, axis=-1)
            self.changed_fraction = float(np.count_nonzero(restart)) / restart.size
        self.mean, self.count, self.weight_squares = fuse_step(self.mean, self.count, self.weight_squares, data, restart,
                                                               self.config.max_frames)
        samples = samples_of_mean(estimator, self.mean - estimator.dark.astype(np.float32), self.weight_squares[..., None])
        self.ms.append((time.perf_counter() - started) * 1e3)
        return self.mean, samples

    def _update_compiled(self, data: NDArray, estimator: RangeEstimator, started: float) -> tuple[NDArray, NDArray]:
        q = float(np.asarray(estimator.profile.quantisation_step, np.float64))
        f32 = lambda v: np.ascontiguousarray(v, np.float32)  # noqa: E731
        samples = np.empty(data.shape, np.float32)
        restarted = _fuse_compiled(data, self.mean, self.count, self.weight_squares, f32(estimator.dark),
                                   f32(estimator.read_noise ** 2 + q * q / 12.0), f32(estimator.shot_gain),
                                   f32(estimator.fixed_pattern ** 2), np.float32(estimator.profile.saturation_level),
                                   np.float32(self.config.change_sigmas ** 2), self.config.max_frames, samples)
        self.changed_fraction = float(restarted) / self.count.size
        self.ms.append((time.perf_counter() - started) * 1e3)
        return self.mean, samples

    def frames(self, valid: NDArray[np.bool_]) -> NDArray[np.uint16]:
        """(H, W) frames each pixel's range is built from: its count where it has a range, else 0."""
        assert self.count is not None
        return np.where(valid, self.count, 0).astype(np.uint16)

    def status(self) -> dict:
        ms = list(self.ms)
        return {"enabled": True, "max_frames": self.config.max_frames, "change_sigmas": self.config.change_sigmas,
                "changed_fraction": None if self.changed_fraction is None else round(self.changed_fraction, 4),
                "restarted": self.restarted, "ms_per_frame": round(float(np.median(ms)), 2) if ms else None,
                "motion_pixels": self.config.motion_pixels,
                "vehicle_shift_px": None if self.shift_px is None else round(self.shift_px, 2)}


def frames_summary(frames: NDArray[np.uint16] | None) -> dict:
    """Median and 10th percentile of the frames per pixel with a range (None where none has one)."""
    if frames is None:
        return {"median_frames": None, "p10_frames": None, "pixels_with_range": None}
    counts = np.bincount(frames.ravel())
    counts[0] = 0  # no range
    total = int(counts.sum())
    if total == 0:
        return {"median_frames": None, "p10_frames": None, "pixels_with_range": 0}
    cumulative = np.cumsum(counts)
    return {"median_frames": int(np.searchsorted(cumulative, 0.5 * total)),
            "p10_frames": int(np.searchsorted(cumulative, 0.1 * total)), "pixels_with_range": total}
