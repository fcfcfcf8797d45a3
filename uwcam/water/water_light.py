"""The water's own light: a pixel whose light is not clearly above it has no range (reason 3).

Lamp light scattered back by the water reaches the camera whether or not there is a surface in
front of it. Where a pixel's light is no more than that, its colour is the water's, and the
transform turns it into a range that is wrong yet looks sure (an open-water frame reads a few
tens of centimetres everywhere). So every ranging path (:func:`uwcam.ranging.estimator.range_frame`, used by
``uwcam range``, the frame loop and ``uwcam reprocess``) judges each pixel against the light of
open water in front of *that* pixel: the open-water level W(p) of the backscatter model
(:meth:`uwcam.water.backscatter.BackscatterModel.open_water_level`), from an open-water frame when
there is one, else from the calibration's black-patch measurements. A channel counts as carrying
the surface's light only where

    E − W > 3 · √(σ²(E) + (u·W)²)

with E the dark-corrected value (ambient light subtracted), σ²(E) the noise model's variance of
the total light and u the model's relative uncertainty; a pixel needs two such channels (of
those ranged with) to keep its range. A per-pixel level follows the lamp's backscatter pattern,
which one level per channel cannot (it is brighter where beam and view overlap). Wherever the
water's light is known it is also subtracted before ranging (the frame loop's compensation,
:func:`uwcam.water.frame_compensator.compensation_iterations`): a range with it left in reads short by a
bias the whole view shares, which no σ describing the ranges' spread can cover.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from uwcam.compute.jit import HAVE_NUMBA, kernel_array, njit, prange, repeat_per_pixel
from uwcam.optics.validity import Reason

SIGMAS = 3.0
"""How many standard deviations above the water's light a channel must be (as the compensation's
test of what is left once backscatter is subtracted: :data:`uwcam.ranging.estimator.BACKGROUND_SIGMAS`)."""

def _judge_py(frame, limit, active, saturation, range_m, variance, reasons, reason):
    """Over rows (H, W·N) of frame and limit and (H, W) outputs: a pixel with a range (or a path out
    of bounds, reason 5) whose values exceed their limits (and stay below saturation) in fewer than
    two active channels loses it.
    Each row: the counts in one branch-free pass (it vectorises), then the few pixels that lose."""
    h, w = range_m.shape
    n = active.shape[0]
    on = np.zeros(n, np.int32)
    for k in range(n):
        on[k] = 1 if active[k] else 0
    sat = np.float32(saturation)
    for i in prange(h):
        count = np.zeros(w, np.int32)
        row, lim = frame[i], limit[i]
        for k in range(n):
            if on[k] == 0:
                continue
            for j in range(w):
                v = np.float32(row[j * n + k])
                count[j] += np.int32((v > lim[j * n + k]) & (v < sat))
        for j in range(w):
            if count[j] < 2 and (reasons[i, j] == 0 or reasons[i, j] == 5):
                range_m[i, j] = np.nan
                variance[i, j] = np.nan
                reasons[i, j] = reason


_judge = njit(parallel=True, cache=True, nogil=True)(_judge_py) if HAVE_NUMBA else None


@njit(parallel=True, cache=True, nogil=True, error_model="numpy")
def _threshold_compiled(level, scale, ambient, samples, a, g, f2, dark, k2, u2, out):  # pragma: no cover - compiled
    """:meth:`WaterLight.threshold`'s quadratic per value, for values that are means (``samples``
    (H, W, N), float32; ``ambient`` (H, W, N) float32 or an empty array): the same float64
    arithmetic in one pass instead of a dozen numpy temporaries (a fused frame's threshold changes
    every frame, so it cannot be cached as a single frame's is). Rows are taken as W·N contiguous
    values with each channel's constants repeated along them, a loop without branches that vectorises."""
    h, w, n = out.shape
    m = w * n
    has_ambient = ambient.size > 0
    level_rows, count_rows, out_rows = level.reshape(h, m), samples.reshape(h, m), out.reshape(h, m)
    ambient_rows = ambient.reshape(h, m) if has_ambient else np.zeros((1, m), np.float32)
    step = 1 if has_ambient else 0  # row i of the ambient light, or its one row of zeros
    t = np.empty((5, m))
    repeat_per_pixel(scale, t[0])
    repeat_per_pixel(a, t[1])
    repeat_per_pixel(g, t[2])
    repeat_per_pixel(f2, t[3])
    repeat_per_pixel(dark, t[4])
    for i in prange(h):
        lv, cn, o = level_rows[i], count_rows[i], out_rows[i]
        am = ambient_rows[i * step]
        for x in range(m):
            light = np.float64(lv[x]) * t[0, x]
            base = light + np.float64(am[x])
            count = max(np.float64(cn[x]), 1.0)
            qa = 1.0 - k2 * t[3, x] / count
            qb = -(2.0 * base + k2 * t[2, x] / count)
            qc = base * base - k2 * (t[1, x] / count + u2 * light * light)
            root = (-qb + math.sqrt(max(qb * qb - 4.0 * qa * qc, 0.0))) / (2.0 * qa)
            o[x] = np.float32((root if qa > 0 else np.inf) + t[4, x])


@dataclass
class WaterLight:
    """Open-water light per pixel and channel, and its relative uncertainty."""

    level: NDArray[np.float32]
    """(H, W, N) DN, dark-corrected, at the exposure of the light the model came from."""
    uncertainty: float
    """Relative standard uncertainty of ``level``."""
    source: str
    """Where the level comes from, for status and records."""
    frames: int = 1
    """How many open-water frames the level was made from (1 where it comes from the calibration)."""
    _cache: dict = field(default_factory=dict, repr=False)

    def threshold(self, estimator, scale: NDArray | None = None, ambient: NDArray | None = None,
                  samples: NDArray | None = None) -> NDArray[np.float32]:
        """(H, W, N) raw value (DN, dark included) a channel must exceed to be clearly above the
        water's light, for frames ranged by ``estimator`` (its noise model at the present gain).

        scale: (N,) the frame's exposure × gain over that of the level's light (None: 1);
        ambient: (H, W, N) light not from the lamp (DN), in the frame on top of the water's;
        samples: values are means of this many pixels (their noise variance is divided by it).

        The smallest E with (E − W)² = k²·(σ²(E_total) + u²W²), σ²(x) = a + g·x + f²·x², solved
        in closed form (the larger root of a quadratic in the total light y = E + ambient)."""
        plain = ambient is None and samples is None
        if samples is not None and HAVE_NUMBA:
            return self._threshold_of_means(estimator, scale, ambient, samples)
        key = (None if scale is None else tuple(np.asarray(scale, np.float64)), tuple(estimator.read_noise),
               tuple(estimator.shot_gain), tuple(estimator.fixed_pattern))
        if plain and key in self._cache:
            return self._cache[key]
        w = self.level.astype(np.float64)
        if scale is not None:
            w = w * np.asarray(scale, np.float64)
        base = w if ambient is None else w + np.asarray(ambient, np.float64)
        q = float(np.asarray(estimator.profile.quantisation_step, np.float64))
        a = estimator.read_noise**2 + q * q / 12.0
        g = estimator.shot_gain * np.ones_like(a)
        f2 = estimator.fixed_pattern**2 * np.ones_like(a)
        a, g, f2 = (np.broadcast_to(t, base.shape) for t in (a, g, f2))
        if samples is not None:
            n = np.maximum(np.asarray(samples, np.float64), 1.0)
            a, g, f2 = a / n, g / n, f2 / n
        k2 = SIGMAS**2
        u2 = self.uncertainty**2
        qa = 1.0 - k2 * f2
        qb = -(2.0 * base + k2 * g)
        qc = base * base - k2 * (a + u2 * w * w)
        with np.errstate(invalid="ignore", divide="ignore"):
            root = (-qb + np.sqrt(np.maximum(qb * qb - 4.0 * qa * qc, 0.0))) / (2.0 * qa)
        # A fixed pattern of a third or more of the signal: no light is ever clearly above the water's.
        y = np.where(qa > 0, root, np.inf)
        out = (y + estimator.dark).astype(np.float32)  # y is the total light above dark at the threshold
        if plain:
            self._cache[key] = out
        return out

    def _threshold_of_means(self, estimator, scale: NDArray | None, ambient: NDArray | None,
                            samples: NDArray) -> NDArray[np.float32]:
        """:meth:`threshold` for values that are means, compiled (:func:`_threshold_compiled`)."""
        n = self.level.shape[-1]
        q = float(np.asarray(estimator.profile.quantisation_step, np.float64))
        per = lambda v: kernel_array(v, (n,), np.float64)  # noqa: E731
        full = lambda v: kernel_array(v, self.level.shape, np.float32)  # noqa: E731
        out = np.empty(self.level.shape, np.float32)
        _threshold_compiled(full(self.level), per(1.0 if scale is None else scale),
                            np.empty((0, 0, 0), np.float32) if ambient is None else full(ambient), full(samples),
                            per(estimator.read_noise**2 + q * q / 12.0), per(estimator.shot_gain),
                            per(estimator.fixed_pattern**2), per(estimator.dark), SIGMAS**2, self.uncertainty**2, out)
        return out

    def judge(self, result, frame: NDArray, estimator, scale: NDArray | None = None,
              ambient: NDArray | None = None, samples: NDArray | None = None) -> None:
        """In place: pixels of ``result`` with a range whose light, in fewer than two of the
        channels ranged with, is clearly above the water's (see :meth:`threshold`) lose it:
        NaN range and variance, reason 3 ("backscatter only"). So do those whose path came out of
        bounds (reason 5) on such light: the water's light, once subtracted, leaves a ratio of
        noise, whose path says nothing; that the light is the water's is the reason."""
        if frame.shape[:2] != self.level.shape[:2]:
            raise ValueError(f"the water's light is known for {self.level.shape[1]}×{self.level.shape[0]} frames, "
                             f"not {frame.shape[1]}×{frame.shape[0]}")
        response = getattr(estimator, "response", None)
        if response is not None and np.issubdtype(np.asarray(frame).dtype, np.integer):
            frame = response.linearise(frame)  # a gamma camera's codes: judged as linear light
        limit = self.threshold(estimator, scale, ambient, samples)
        active = estimator.active
        saturation = estimator.profile.saturation_level
        arrays = (result.range, result.variance, result.reasons)
        if _judge is not None and all(a.flags.c_contiguous for a in arrays):
            h, w = result.range.shape
            rows = np.ascontiguousarray(frame).reshape(h, -1)
            _judge(rows, np.ascontiguousarray(limit, np.float32).reshape(h, -1), active, float(saturation),
                   *arrays, np.uint8(Reason.BACKSCATTER_ONLY))
            return
        above = (np.asarray(frame) > limit) & (np.asarray(frame) < saturation)
        count = above[..., active].sum(axis=-1)
        lost = (count < 2) & ((result.reasons == Reason.VALID) | (result.reasons == Reason.PATH_OUT_OF_BOUNDS))
        if lost.any():
            result.range[lost] = np.nan
            result.variance[lost] = np.nan
            result.reasons[lost] = Reason.BACKSCATTER_ONLY
