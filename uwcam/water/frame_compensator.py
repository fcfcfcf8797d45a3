"""Backscatter compensation in the frame loop, within the frame's time budget.

The model is that of :mod:`uwcam.water.backscatter` (the profile's black-patch measurements and, when
one was taken, a lamp-lit frame of open water). Every frame: range without compensation (or
with the ambient light only), then ``iterations`` times: the backscatter in front of each
pixel's surface at that range → subtracted → range again. A channel whose signal left after the
subtraction is not 3σ of the total light's noise above zero carries only water: reason 3,
"backscatter only", and no range (docs/physics.md §5).

The backscatter varies slowly across the image, so it is evaluated on blocks of
:data:`BLOCK` pixels (each at the median depth of its pixels, open water where none has a
range) and interpolated; the subtraction and transform run in the compiled kernel. A block
where only a few pixels keep a range loses them (:data:`uwcam.water.unresolved.MIN_SUPPORT`: more likely chance than a
surface), and the model's own doubt, the same in neighbouring pixels and in every frame, is kept
in the result's ``common_variance``, which no mean over pixels or frames divides.
"""

from __future__ import annotations

import time

import cv2
import numpy as np
from numpy.typing import NDArray

from uwcam.water.backscatter import BackscatterModel, patch_disagreement
from uwcam.optics.geometry import pixel_rays
from uwcam.optics.validity import Reason
from uwcam.calibration.profile import CalibrationProfile
from uwcam.ranging.result import RangeResult
from uwcam.ranging.smoothing import block_means
from uwcam.ranging.estimator import RangeEstimator
from uwcam.water.unresolved import drop_blocks, drop_unresolved, drop_unsupported
from uwcam.water.water_light import WaterLight

BLOCK = 8
"""Side of the blocks (pixels) the backscatter is evaluated on."""

COARSE = 4
"""The intermediate passes range the frame reduced this many times (COARSE×COARSE means)."""

MODEL_UNCERTAINTY = 0.10
"""Relative standard uncertainty of the backscatter modelled from the calibration's black-patch
measurements alone: it enters each value's variance as (0.10·B)², so a pixel whose own light is
not well above the backscatter's uncertainty has no range (reason 3) instead of a wrong one, and
the variance of the rest says how much the model can be trusted. The model extrapolates the lit
column from the patch at 1–2 m across the view: against the simulator's own backscatter (Jerlov
IB, lamp 0.3 m aside, seabed 1–7 m) its level is 8–26 % high (median per channel) and varies
across the view. At 0.05 the ranges' z-scores had sd 1.6–5.5 with 4–15 % of pixels beyond 3σ
from 3 to 7 m; at 0.10, sd 0.96 and 1.04 at 2 and 3 m, 0.4 at 5 m (where the judge and the
unresolved test leave only pixels the model does not decide), never more than 0.1 % beyond 3σ.
(A fitted bound, measured in the simulator, not a property of the model.) It is a floor: where
the patch measurements themselves stray from the model further
(:func:`uwcam.water.backscatter.patch_disagreement`), that disagreement is the uncertainty."""

MAX_MODEL_UNCERTAINTY = 10.0
"""The largest relative uncertainty the model is given (the estimator's bound): a model whose patch
measurements stray from it further (:func:`uwcam.water.backscatter.patch_disagreement`: a range-gated
camera in Jerlov 3C, eleven times) tells nothing of the water's light at any range either way."""

OPEN_WATER_UNCERTAINTY = 0.004
"""Relative standard uncertainty of the backscatter modelled with an open-water frame where the
frame measured all of it: the open water's own level, smoothed (:data:`uwcam.water.backscatter.OPEN_WATER_SMOOTHING`).
The model takes from the frame the light of the whole lit column and from the physics only the
share of it beyond the surface (:data:`OPEN_WATER_TAIL_UNCERTAINTY`). Against the simulator's own
backscatter (16 open-water frames, 320×240, Jerlov II, III and 3C, the lamp on the axis and 0.3
and 0.6 m aside, a seabed at 1–7 m), the smooth part of the level's error (15-pixel means) lies
within −0.5 to +0.35 % (5th–95th percentile per channel) wherever that share is under 1 %, the
lamp on the axis reading it low by 0.2–0.5 % in every channel. At 0.3 % the red light of a seabed
at 3 m in Jerlov III (the lamp on the axis: the water's red light 20–30 times the seabed's) read
short enough for 1.3 % of its pixels to fall beyond 3σ; at 0.4 %, 0.6 %.

Until this version one doubt of 2 % stood for the whole model, and each pixel's fixed pattern
was counted on the whole light, backscatter included, though the open-water frames take most of
it out (:meth:`uwcam.water.backscatter.ResponseEstimate.residual_fixed_pattern`). In the water study's Jerlov II at
7 m (lamp 0.3 m aside, 16 frames) σ came out 32 % of the range where the ranges' rms error was
3.5 % (z-scores' sd 0.08): a pilot was told ±2 m of what was known to ±0.25 m."""

OPEN_WATER_TAIL_UNCERTAINTY = 0.4
"""Relative standard uncertainty of the modelled share of the open water's light that lies beyond
the surface (what the open-water frame saw and the scene's water column does not hold): the
physics of the column with the attenuation and beam fitted to the frame. Near the camera in murky
water that share is large and the model least sure: Jerlov 3C at 1 m with the lamp 0.6 m aside,
the share is 11–19 % of the open water's light per channel and the level 2–6 % high (0.2–0.35 of
the share); Jerlov II and III at 1 m, 0.03–0.13 of it."""


DEFAULT_ITERATIONS = 2
"""Passes of compensation where the settings do not ask for it but the water's light is known
(the profile has black-patch measurements): see :func:`compensation_iterations`."""


def compensation_iterations(configured: int | None, profile: CalibrationProfile) -> int | None:
    """How many passes of backscatter compensation frames ranged with ``profile`` get: ``configured``
    (the settings' ``backscatter.iterations``, None where they do not ask for it), else, where the
    profile has black-patch measurements, :data:`DEFAULT_ITERATIONS`; None where nothing tells the
    water's light.

    A range made with the water's own light left in it reads short, and the shortfall is a bias
    shared by the whole view, not noise: −5 % at 2 m in Jerlov IB with the lamp 0.3 m aside (the
    simulator, against the same frame without backscatter: +0.3 %), −60 % at 5 m. Counted in σ as the
    bound it is (the range with all of the open water's light subtracted), σ grew to cover it (6–9 %
    of the range at 2 m) and no longer described the spread of the ranges; left out, σ was 2 % and
    the range 2.5σ off in every pixel. Where the water's light is known, the only honest range is
    the one with the backscatter in front of the surface subtracted, with the model's uncertainty
    in σ: that is what compensation does (z-scores at 2 m: sd 1.07, mean 0.03)."""
    if configured is not None:
        return configured
    return DEFAULT_ITERATIONS if profile.backscatter is not None else None


MAX_PASSES = 6
"""Most passes of range → backscatter → subtract per frame where ``iterations`` is 2 or more: the
configured number at least, more (up to this) while the depths the backscatter was subtracted for
still move (see :data:`SETTLED`). ``iterations`` 1 is one pass, as before. With the open-water
model's 2 % doubt the near start climbs to a far seabed in smaller steps (more of its light is
judged the surface's at each): Jerlov II at 7 m, lamp 0.3 m aside, kept 58 % of its pixels with 4
passes (the rest unsettled), 95 % with 6 or 8 alike."""

SETTLED = 0.02
"""A block of the backscatter's grid has settled when the pass that subtracted the backscatter in
front of its depth found a depth within this share of it. In murky water a pass that ranged a pixel
short left most of the water's light in, which ranged it short again: Jerlov III at 5 m with the
lamp 0.3 m aside, two passes left 160 of 49 000 pixels reading 2 m for 5 m, 143 of them beyond 3σ;
passes until the depths settle find none of them resolvable. A block that has not settled after
:data:`MAX_PASSES` passes has no range (reason 3). Where backscatter matters, this costs a third
pass on the frame reduced 4×4 (settled is known only once a pass has used the depth before).

A depth can settle and still be wrong: 40–60 % short, its own backscatter subtracted, the rest of
the water's red light read as the seabed's, as self-consistent as the true depth. Passes started
from the far side (the open water's light subtracted first) do not reach it, so they run too, and
a block whose two starts settle apart has no range (reason 3): in the water study (Jerlov III, one
frame) that left 0 of the 11 to 25 wrong pixels a cell had."""


class BackscatterCompensator:
    """Subtracts modelled backscatter from frames of one size, for one profile."""

    def __init__(self, profile: CalibrationProfile, shape: tuple[int, int], iterations: int = 2,
                 open_water: NDArray | None = None, frame_dtypes: tuple[type, ...] = (np.uint8, np.uint16),
                 strided: bool = True, open_water_frames: int = 1, **estimator_options) -> None:
        """shape: (H, W) of the frames; open_water: a lamp-lit frame (H, W, N) of open water, raw, or
        several (K, H, W, N), which also give each pixel's own response (:func:`uwcam.water.backscatter.pixel_response`);
        open_water_frames: how many frames the one open-water frame is the mean of (the daemon's
        capture), which with 2 or more gives the response too.
        frame_dtypes, strided: the pixel types and layouts of the frames it will see, whose kernels
        it readies (:meth:`uwcam.ranging.estimator.RangeEstimator.warm_up`).
        Raises UserInputError if the profile has no backscatter measurements."""
        self.model = BackscatterModel.from_profile(profile, open_water, shape, open_water_frames)
        self.iterations = iterations
        self.shape = shape
        self.open_water = open_water is not None
        h, w = shape
        gh, gw = max(h // BLOCK, 1), max(w // BLOCK, 1)
        self._grid = (gh, gw)
        # Block centres in full-resolution pixel coordinates, and the cosine of their ray's angle
        # to the axis (the model's depth is along the optical axis).
        rows = ((np.arange(gh) + 0.5) * (h / gh) - 0.5)[:, None] * np.ones((1, gw))
        cols = np.ones((gh, 1)) * ((np.arange(gw) + 0.5) * (w / gw) - 0.5)[None, :]
        self._rows, self._cols = rows, cols
        intr = profile.camera_intrinsics()
        self._axis_cos = np.ones((h, w), np.float32) if intr is None else pixel_rays(intr, h, w)[..., 2].astype(np.float32)
        pattern = self.model.pattern
        if pattern.shape[0] > 1:  # from an open-water frame: sampled at the block centres
            ri = np.clip(np.rint(rows).astype(int), 0, h - 1)
            ci = np.clip(np.rint(cols).astype(int), 0, w - 1)
            pattern = pattern[ri, ci]
        self._pattern = pattern
        self._corners = self.model.corners(rows, cols) if self.model.grid_step else None
        # Each pixel's own response (several open-water frames), at full and at the coarse resolution.
        response = self.model.response
        self._response = None if response is None else response.astype(np.float32)
        self._footprint_depths: tuple[tuple[int, int, int, int], NDArray] | None = None
        """(region, its blocks' depths for a range of 1 m): the rangefinder's footprint, one at a time."""
        self._coarse_size = coarse = (max(w // COARSE, 1), max(h // COARSE, 1))  # (w, h)
        self._response_coarse = None if response is None else cv2.resize(
            self._response, coarse, interpolation=cv2.INTER_AREA).reshape(coarse[1], coarse[0], -1)
        # Once backscatter is subtracted, the floor that stays is the black patch's own noise
        # (3σ), not backscatter + 3σ.
        sigma = profile.backscatter.noise_sigma if profile.backscatter else {}
        channels = [c.model_copy(update={"noise_floor": 3.0 * sigma.get(c.name, 0.0)}) for c in profile.channels]
        compensated = profile.model_copy(update={"channels": channels})
        # Without an open-water frame the model extrapolates the patch measurements: where they
        # disagree with it beyond their noise, its uncertainty is at least that disagreement.
        self.patch_disagreement = 0.0 if self.open_water else patch_disagreement(self.model, profile)
        self.uncertainty = (OPEN_WATER_UNCERTAINTY if self.open_water
                            else min(max(MODEL_UNCERTAINTY, self.patch_disagreement), MAX_MODEL_UNCERTAINTY))
        options = {"background_uncertainty": self.uncertainty, **estimator_options}
        # Open-water frames that told each pixel's response take its fixed pattern out of the
        # background they model: what is left of it is counted, not the whole.
        estimate = self.model.response_estimate
        if estimate is not None:
            options["background_fixed_pattern"] = estimate.residual_fixed_pattern(profile.array("fixed_pattern"))
        # The open water's light at the block centres (scale 1): the modelled share beyond a
        # surface is this less the level in front of it (:data:`OPEN_WATER_TAIL_UNCERTAINTY`).
        self._open_grid = self._grid_levels(np.full(self._grid, np.nan), 1.0) if self.open_water else None
        spread = self.model.spread_doubt
        self._spread_doubt = None if self.open_water or spread is None else spread[
            np.clip(np.rint(rows).astype(int), 0, h - 1), np.clip(np.rint(cols).astype(int), 0, w - 1)][..., None].astype(np.float32)
        self._tail_uncertainty = np.maximum(OPEN_WATER_TAIL_UNCERTAINTY, 0.0 if self.model.tail_uncertainty is None
                                            else self.model.tail_uncertainty).astype(np.float32)  # column_fit_agrees
        self.estimator = RangeEstimator(compensated, **options)
        # The intermediate iterations' estimator: frames reduced COARSE times (COARSE×COARSE means),
        # whose pixel rays are those of the full frame's COARSE×COARSE block centres.
        coarse_profile = compensated
        if intr is not None:
            reduced = intr.reduced(COARSE, COARSE)
            coarse_profile = compensated.model_copy(update={"intrinsics": {
                "fx": reduced.fx, "fy": reduced.fy, "cx": reduced.cx, "cy": reduced.cy}})
        self._coarse = RangeEstimator(coarse_profile, calibration_variance=False, **options)
        # The same without the model's uncertainty: the difference is the model's share of the variance.
        self._coarse_exact = RangeEstimator(coarse_profile, calibration_variance=False,
                                            **{**options, "background_uncertainty": 0.0})
        self._axis_cos_coarse = cv2.resize(self._axis_cos, coarse, interpolation=cv2.INTER_AREA)
        # Compiled (or loaded from the cache) now, not mid-frame: the full frames' kernels for their
        # pixel types, the coarse estimator's for float means with a background.
        self.estimator.warm_up(dtypes=frame_dtypes, strided=strided)
        self._coarse.warm_up(dtypes=())
        frames = 1 if open_water is None else open_water.shape[0] if np.ndim(open_water) == 4 else open_water_frames
        self.water = WaterLight(self.model.open_water_level(shape).astype(np.float32), self.uncertainty,
                                "open-water frame" if self.open_water else "black-patch measurements", frames=frames)
        """The open-water light of the same model, that each pixel must be clearly above."""

    def level(self, range_m: NDArray, coarse: bool = False, scale: NDArray | float = 1.0) -> NDArray[np.float32]:
        """Backscatter (DN, dark-corrected) in front of surfaces at camera range ``range_m`` metres
        (NaN: no surface, open water), a map of the frame's size or of the coarse size (:data:`COARSE`
        times smaller) → (H, W, N) float32 at the frame's size (or the coarse size when ``coarse``),
        times ``scale`` (scalar or (N,))."""
        return self._level_at(self._block_depth(range_m), coarse, scale)

    def footprint_level(self, range_m: float, region: tuple[int, int, int, int],
                        scale: NDArray | float = 1.0) -> NDArray[np.float32]:
        """:meth:`level` over ``region`` only ((x, y, width, height) pixels, clipped to the frame) for
        a surface at camera range ``range_m`` metres there and open water elsewhere: (h, w, N)
        float32, the values ``level`` gives at those pixels (the reflectance corrector's footprint,
        which needs no more than that: the whole frame's cost 12 % of the loop at 720p)."""
        x, y, w, h = region
        rows = np.arange(min(y, self.shape[0]), min(y + h, self.shape[0]))
        cols = np.arange(min(x, self.shape[1]), min(x + w, self.shape[1]))
        if self._footprint_depths is None or self._footprint_depths[0] != region:
            # The blocks' depths are proportional to the range (each block's mean of range · cosine
            # over its pixels in the region): computed once per region for a range of 1 m.
            unit = np.full(self.shape, np.nan, np.float32)
            unit[rows[:, None], cols[None, :]] = 1.0
            self._footprint_depths = (region, self._block_depth(unit))
        n = self._pattern.shape[-1]
        if rows.size == 0 or cols.size == 0:
            return np.zeros((rows.size, cols.size, n), np.float32)
        # Only the grid's blocks whose centres the footprint's pixels interpolate between.
        taps_y, taps_x = _taps(rows, self.shape[0], self._grid[0]), _taps(cols, self.shape[1], self._grid[1])
        window = (slice(taps_y[0][0], taps_y[1][-1] + 1), slice(taps_x[0][0], taps_x[1][-1] + 1))
        small = self._grid_levels(self._footprint_depths[1][window] * np.float32(range_m), scale, window)
        out = _bilinear(small, _shifted(taps_y, window[0].start), _shifted(taps_x, window[1].start))
        if self._response is not None:
            out *= self._response[rows[:, None], cols[None, :]]
        return out

    def _resolved_depth(self, coarse: RangeResult) -> NDArray:
        """:meth:`_block_depth` of a coarse pass's ranges, less those too uncertain for their length
        (:func:`uwcam.water.unresolved.drop_unresolved`, in place): a range from channels that attenuate
        alike (green and blue in Jerlov III, once red is lost) is anything, and a pass that took it
        for a depth led the passes from the far side to the near side's wrong depth."""
        drop_unresolved(coarse)
        return self._block_depth(coarse.range)

    def _block_depth(self, range_m: NDArray) -> NDArray:
        """(gh, gw) mean depth (m, along the axis) of each block's pixels that have a range, NaN
        where none do (open water), from camera ranges of the frame's size or the coarse size."""
        gh, gw = self._grid
        r = np.asarray(range_m, np.float32)
        cos = self._axis_cos if r.shape == self.shape else self._axis_cos_coarse
        valid = np.isfinite(r)
        depth_sum = cv2.resize(np.where(valid, r * cos, 0.0).astype(np.float32), (gw, gh), interpolation=cv2.INTER_AREA)
        count = cv2.resize(valid.astype(np.float32), (gw, gh), interpolation=cv2.INTER_AREA)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(count > 0.05, depth_sum / count, np.nan)

    def _level_at(self, block_depth: NDArray, coarse: bool = False, scale: NDArray | float = 1.0) -> NDArray[np.float32]:
        """:meth:`level` for surfaces at these block depths ((gh, gw) m, NaN: open water)."""
        return self._level_and_doubt(block_depth, coarse, scale, with_doubt=False)[0]

    def _level_and_doubt(self, block_depth: NDArray, coarse: bool = False, scale: NDArray | float = 1.0,
                         with_doubt: bool = True) -> tuple[NDArray[np.float32], NDArray[np.float32] | None]:
        """:meth:`_level_at`, and the variance (DN², same shape) of the share of it the physics
        modelled beyond each block's depth (:data:`OPEN_WATER_TAIL_UNCERTAINTY`; None without an
        open-water frame, whose model's doubt is all relative: :attr:`uncertainty`, or when not
        ``with_doubt``: the level alone costs no full-frame resize more)."""
        h, w = self.shape
        small = self._grid_levels(block_depth, scale)
        size = self._coarse_size if coarse else (w, h)
        out = cv2.resize(small, size, interpolation=cv2.INTER_LINEAR).reshape(size[1], size[0], -1)
        doubt = None
        if with_doubt and (self._open_grid is not None or self._spread_doubt is not None):
            if self._open_grid is not None:
                spread = np.maximum(self._open_grid * np.asarray(scale, np.float32) - small, np.float32(0.0))
                spread *= self._tail_uncertainty
            else:  # the black patch's level carried across the view (BackscatterModel.spread_doubt)
                spread = small * self._spread_doubt
            doubt = cv2.resize(spread * spread, size, interpolation=cv2.INTER_LINEAR).reshape(size[1], size[0], -1)
        response = self._response_coarse if coarse else self._response
        if response is not None:
            out *= response
            if doubt is not None:
                doubt *= response * response
        return out, doubt

    def _grid_levels(self, block_depth: NDArray, scale: NDArray | float,
                     window: tuple[slice, slice] = (slice(None), slice(None))) -> NDArray[np.float32]:
        """(gh, gw, N) backscatter at the block centres for surfaces at these block depths; or at
        the blocks of ``window`` (rows, columns of the grid) only, ``block_depth`` being theirs."""
        corners = None if self._corners is None else tuple(c[(slice(None), *window)] for c in self._corners)
        fraction = self.model.fraction(block_depth, self._rows[window], self._cols[window], corners)
        pattern = self._pattern[window] if self._pattern.shape[0] > 1 else self._pattern
        return (pattern * fraction * scale).astype(np.float32)

    def range(self, frame: NDArray, attenuation_differences: NDArray, log_constants: NDArray,
              ambient: NDArray | None = None, samples: NDArray | None = None,
              background_scale: NDArray | None = None) -> RangeResult:
        """Range ``frame`` with backscatter subtracted, with these attenuation differences and log
        constants (the loop's); samples: as for :class:`RangeEstimator` (a frame smoothed before
        the transform); background_scale: (N,) the frame's exposure × gain over that of the light
        the model came from (the open-water frame's, or the calibration's), per channel; None: 1.

        All passes but the last only find the depths the backscatter is evaluated at: they run on
        the frame reduced :data:`COARSE` times (4×4 means: a block of the backscatter's grid is
        2×2 of these pixels; half-resolution passes gave the same ranges, to 0.1 %, for 25 % more
        CPU per frame), the first with the ambient light alone, without the calibration's share of
        the variance; the last at full resolution. Then a block with too few ranged pixels loses
        them (:data:`uwcam.water.unresolved.MIN_SUPPORT`), and the model's share of each variance is found, on the
        reduced frame again, and kept as common (:meth:`_with_model_share`)."""
        h, w = self.shape
        for est in (self.estimator, self._coarse, self._coarse_exact):
            est.set_attenuation_differences(attenuation_differences)
            est.set_log_constants(log_constants)
        small = block_means(np.asarray(frame), self._coarse_size)
        small_ambient = None if ambient is None else cv2.resize(ambient, self._coarse_size, interpolation=cv2.INTER_AREA)
        # The first pass subtracts the ambient light alone; without any, it is plain ranging (the
        # lookup-table kernel for integer frames: the same terms as with a zero background).
        result = self._coarse(small, background=small_ambient)
        scale = 1.0 if background_scale is None else np.asarray(background_scale, np.float32)
        # One pass is one, as configured; more than one go on while the depths move.
        most = max(MAX_PASSES, self.iterations) if self.iterations > 1 else 1
        depth, settled = self._settle(small, small_ambient, scale, self._resolved_depth(result), most)
        if self.iterations > 1:
            # The same passes from the far side: the open water's light subtracted first. Where the
            # two settle on different depths, both explain the frame and nothing tells them apart.
            far, far_settled = self._settle(small, small_ambient, scale, np.full_like(depth, np.nan), most)
            settled &= far_settled & _same_depth(far, depth)
        background, doubt = self._level_and_doubt(depth, scale=scale)
        if ambient is not None:
            background += ambient
        result = self.estimator(frame, background=background, samples=samples, background_variance=doubt)
        drop_unresolved(result)
        self._name_the_water(result, frame, ambient)
        if self.iterations > 1:
            self._drop_unsettled(result, settled)
        drop_unsupported(result, self._grid)
        return self._with_model_share(result, small, small_ambient, samples, depth, scale)

    def _with_model_share(self, result: RangeResult, small: NDArray, small_ambient: NDArray | None,
                          samples: NDArray | None, depth: NDArray, scale: NDArray | float) -> RangeResult:
        """``result`` with the backscatter model's share of each pixel's variance added to its
        ``common_variance``: the model's error is the same in every frame and in neighbouring
        pixels (one smooth level per block), so neither a mean over frames nor a 3×3 mean of the
        range map reduces it. Without it, a 3×3 mean divided it by nine: in Jerlov II at 5 m (lamp
        0.3 m aside) it is three quarters of a pixel's variance, and the mean's σ came out 2.7
        times too small. Found on the frame reduced :data:`COARSE` times, with and without the
        model's uncertainty, and interpolated (within 9 % of the full-resolution difference there,
        tests/test_backscatter_common_variance.py); where that frame has no range to tell, all of
        the pixel's variance counts as common (a mean then reduces none of it)."""
        background, doubt = self._level_and_doubt(depth, coarse=True, scale=scale)
        if small_ambient is not None:
            background += small_ambient
        h, w = self.shape
        small_samples = None if samples is None else cv2.resize(
            np.ascontiguousarray(np.broadcast_to(np.asarray(samples, np.float32), (h, w, small.shape[-1]))),
            self._coarse_size, interpolation=cv2.INTER_AREA).reshape(small.shape)
        doubted = self._coarse(small, background=background, samples=small_samples, background_variance=doubt).variance
        exact = self._coarse_exact(small, background=background, samples=small_samples).variance
        coarse_share = np.maximum((doubted - exact).astype(np.float32), np.float32(0.0))
        unranged = np.isnan(coarse_share)
        if unranged.any() and not unranged.all():
            # A reduced pixel without a range takes its neighbours' largest share, so one such pixel
            # does not make the whole variance of every full-resolution pixel around it common.
            grown = cv2.dilate(np.where(unranged, np.float32(0.0), coarse_share), np.ones((3, 3), np.uint8))
            coarse_share = np.where(unranged & (grown > 0), grown, coarse_share)
        share = cv2.resize(coarse_share, (w, h), interpolation=cv2.INTER_LINEAR)
        common = result.common_variance
        own = result.variance if common is None else result.variance - common
        # In place over whole frames (a third of the time of np.where and np.clip at 720p).
        model = np.minimum(share, own)  # NaN where either is: no range, or no share to tell
        np.maximum(model, np.float32(0.0), out=model)
        untold = np.isnan(share)
        np.copyto(model, own, where=untold)
        if common is not None:
            model += common
        return RangeResult(result.range, result.variance, result.reasons, model)

    def _settle(self, small: NDArray, small_ambient: NDArray | None, scale: NDArray | float, depth: NDArray,
                most: int) -> tuple[NDArray, NDArray[np.bool_]]:
        """Coarse passes from the block depths ``depth`` ((gh, gw) m along the axis, NaN: open water),
        each subtracting the backscatter in front of the depths the last found, at least
        ``self.iterations`` − 1 and fewer than ``most``, until every block has settled: → the depths
        and whether each block settled (:data:`SETTLED`)."""
        settled = np.zeros(depth.shape, bool)
        for passes in range(1, most):
            if passes >= self.iterations and settled.all():
                break
            background, doubt = self._level_and_doubt(depth, coarse=True, scale=scale)
            if small_ambient is not None:
                background += small_ambient
            found = self._resolved_depth(self._coarse(small, background=background, background_variance=doubt))
            # Settled: the depth found is the one whose backscatter was subtracted (or both open water).
            settled = _same_depth(found, depth)
            depth = found
        return depth, settled

    def _drop_unsettled(self, result: RangeResult, settled: NDArray[np.bool_]) -> None:
        """In place: the pixels of the blocks whose depth has not settled (``settled``, (gh, gw),
        see :data:`SETTLED`) have no range (reason 3): a range found with the backscatter of another
        depth is no measurement."""
        drop_blocks(result, ~settled)

    def _name_the_water(self, result: RangeResult, frame: NDArray, ambient: NDArray | None) -> None:
        """In place: a pixel too dark once the water's light is subtracted, whose light before was
        above the noise floor in a channel ranged with, has reason 3 ("backscatter only"), not 1:
        the light there is, is the water's (a view of open water, once the passes have found no
        surface in front of it)."""
        dim = result.reasons == Reason.BELOW_NOISE_FLOOR
        if not dim.any():
            return
        active = self.estimator.active
        light = np.asarray(frame)[dim][:, active].astype(np.float32) - self.estimator.dark[active].astype(np.float32)
        if ambient is not None:
            light -= np.asarray(ambient, np.float32)[dim][:, active]
        lit = np.any(light > self.estimator.floor[active].astype(np.float32), axis=-1)
        rows, cols = np.nonzero(dim)
        result.reasons[rows[lit], cols[lit]] = Reason.BACKSCATTER_ONLY


def _same_depth(found: NDArray, depth: NDArray) -> NDArray[np.bool_]:
    """Blocks where ``found`` is within :data:`SETTLED` of ``depth`` (m), or both are open water (NaN)."""
    with np.errstate(invalid="ignore"):
        return (np.isnan(found) & np.isnan(depth)) | (np.abs(found - depth) <= SETTLED * depth)


def _taps(dst: NDArray, n_dst: int, n_src: int) -> tuple[NDArray, NDArray, NDArray]:
    """For destination pixels ``dst`` of a side of ``n_dst`` enlarged from ``n_src`` as OpenCV's
    bilinear resize (INTER_LINEAR) does (pixel centres aligned, edges held): the two source
    pixels each lies between and the weight of the second (float32)."""
    at = (dst + 0.5) * (n_src / n_dst) - 0.5
    first = np.floor(at).astype(int)
    frac = (at - first).astype(np.float32)
    frac[first < 0] = 0.0
    first = np.clip(first, 0, n_src - 1)
    frac[first >= n_src - 1] = 0.0
    return first, np.minimum(first + 1, n_src - 1), frac


def _shifted(taps: tuple[NDArray, NDArray, NDArray], offset: int) -> tuple[NDArray, NDArray, NDArray]:
    """:func:`_taps` counted from source pixel ``offset``."""
    return taps[0] - offset, taps[1] - offset, taps[2]


def _bilinear(small: NDArray[np.float32], taps_y: tuple, taps_x: tuple) -> NDArray[np.float32]:
    """``small`` (gh, gw, N) at the destination pixels of these :func:`_taps` (rows × columns, N)."""
    y0, y1, fy = taps_y
    x0, x1, fx = taps_x
    fy, fx = fy[:, None, None], fx[None, :, None]
    top = small[y0][:, x0] * (1 - fx) + small[y0][:, x1] * fx
    bottom = small[y1][:, x0] * (1 - fx) + small[y1][:, x1] * fx
    return (top * (1 - fy) + bottom * fy).astype(np.float32)


def compensation(comp: BackscatterCompensator, estimator: RangeEstimator, ambient: NDArray | None = None,
                 scale: NDArray | None = None, timings: list | None = None):
    """The transform of :func:`uwcam.ranging.estimator.range_frame` that ranges with ``comp``: the estimator's
    attenuation differences (centred: only differences matter) and log constants (those of the
    exposure: effective), ``ambient`` light subtracted too, the model scaled by ``scale``.
    timings: a list (or deque) that each call's time (ms) is appended to."""

    def transform(data: NDArray, samples: NDArray | None) -> RangeResult:
        started = time.perf_counter()
        result = comp.range(data, estimator.attenuation, estimator.effective_log_constant, ambient, samples, scale)
        if timings is not None:
            timings.append((time.perf_counter() - started) * 1e3)
        return result

    return transform
