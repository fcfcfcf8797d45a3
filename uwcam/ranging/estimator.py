"""Frame → range map, variance map and reason map, from a calibration profile.

:class:`RangeEstimator` turns a profile into the per-channel quantities of docs/physics.md §5
once (attenuation differences, log constants corrected for the surface's hue, lookup
tables for integer sensors) and then processes frames in one pass (compiled with numba when it
is installed, see :mod:`uwcam.optics.kernels`).
"""

from __future__ import annotations

import math

from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from uwcam.compute.jit import kernel_array
from uwcam.fileio import UserInputError

from uwcam.optics import kernels
from uwcam.optics.noise import signal_variance
from uwcam.optics.validity import ChannelState, Reason, channel_states
from uwcam.calibration.profile import CalibrationProfile
from uwcam.ranging.result import RangeResult
from uwcam.ranging.adaptive import adaptive_windows
from uwcam.ranging.calibration_share import calibration_variance_map
from uwcam.ranging.smoothing import smooth_frame, smooth_range_map

# A channel state the kernel neither uses nor counts (channels outside a chosen pair).
_IGNORED = 4
# With a known background subtracted, a channel needs this many σ of signal to be used.
BACKGROUND_SIGMAS = kernels.BACKGROUND_SIGMAS
_NO_SAMPLES = np.empty((0, 0, 0), np.float32)
"""An empty samples array for the background kernel: every value one pixel's noise."""
# The calibration's share of the variance is smooth across the image: it is computed on blocks
# of this many pixels a side and interpolated (bench/bench_fusion.py prints the error and cost).
CALIBRATION_VARIANCE_BLOCK = 8
DEFAULT_SMOOTHING_TARGET = 0.02
"""Adaptive smoothing's default target: σ no more than 2 % of the range (``processing.smoothing_target``)."""


class RangeEstimator:
    """Computes range maps for frames shaped (H, W, N) with N the profile's channel count."""

    def __init__(
        self,
        profile: CalibrationProfile,
        *,
        pair: tuple[str, str] | None = None,
        surface_reflectance: NDArray | list[float] | None = None,
        backscatter_level: NDArray | list[float] | None = None,
        path_length_bounds: tuple[float, float] = (0.0, np.inf),
        calibration_variance: bool = True,
        background_uncertainty: float = 0.0,
        background_fixed_pattern: NDArray | list[float] | None = None,
    ) -> None:
        """pair: two channel names for single-pair ranging (default: fuse all channels).
        surface_reflectance: (N,) reflectance of the imaged surface, when it differs in hue
        from the calibration target (only ratios matter). backscatter_level: (N,) signal
        (DN, dark-corrected) of open water; pixels not above it carry no surface signal.
        path_length_bounds: (min, max) accepted path length d_T in metres.
        calibration_variance: add the calibration's own uncertainty (the profile's covariance of
        attenuation differences and log constants) to every pixel's variance.
        background_uncertainty: relative standard uncertainty of a background passed to
        :meth:`__call__` (a modelled backscatter is known to a few per cent; a measured lamp-off
        frame's noise is already in the shot noise: 0); it adds (u·B)² to each value's variance,
        so that where the surface's light is small next to the background the pixel has no range
        (reason 3) rather than a wrong one.
        background_fixed_pattern: (N,) relative rms of the sensor's fixed pattern that a background
        passed to :meth:`__call__` still carries (a model that knows each pixel's response takes
        most of it out: :meth:`uwcam.water.backscatter.ResponseEstimate.residual_fixed_pattern`);
        None: all of it (the profile's ``fixed_pattern``), the background being smooth. With r
        this and f the profile's, a value's variance counts r²·(E + B)² + (f² − r²)·E² of fixed
        pattern instead of f²·(E + B)² (E the surface's light, B the background)."""
        self.profile = profile
        names = profile.channel_names
        n = len(names)
        self.n_channels = n
        self.dark = profile.array("dark_level")
        self.floor = profile.array("noise_floor")
        self.read_noise = profile.array("read_noise")
        self.shot_gain = profile.array("shot_gain")
        self.fixed_pattern = profile.array("fixed_pattern")
        self.response = profile.response_curve()
        """A gamma camera's response curve: integer frames are codes, linearised before anything else."""
        self.covariance = profile.covariance_blocks()
        self._cv = kernels.pair_noise(self.covariance[0])
        """The kernels' significance test of a pixel's attenuation spread (kernels.ATTENUATION_SIGMAS)."""
        self.with_calibration_variance = bool(calibration_variance) and any(np.any(m != 0) for m in self.covariance)
        self._low_res_rays: dict[tuple[int, int, int, int], NDArray | None] = {}
        self.backscatter = None if backscatter_level is None else np.asarray(backscatter_level, dtype=np.float64)
        if not (np.isfinite(background_uncertainty) and 0.0 <= background_uncertainty <= 10.0):
            raise ValueError(f"background_uncertainty must be a relative uncertainty from 0 to 10, got {background_uncertainty}")
        self.background_uncertainty = float(background_uncertainty)
        if background_fixed_pattern is None:
            self.background_fixed_pattern = self.fixed_pattern
        else:
            r = np.asarray(background_fixed_pattern, dtype=np.float64)
            if r.shape != (n,) or not np.all(np.isfinite(r)) or np.any(r < 0) or np.any(r > 1):
                raise ValueError(f"background_fixed_pattern needs {n} relative rms values from 0 to 1, got {r}")
            self.background_fixed_pattern = r
        v = profile.array("attenuation_difference")
        b = profile.array("log_constant")
        if surface_reflectance is not None:
            rho_s = np.asarray(surface_reflectance, dtype=np.float64)
            if rho_s.shape != (n,) or np.any(rho_s <= 0):
                raise UserInputError(f"surface reflectance needs {n} positive values ({','.join(names)}), got {list(rho_s)}")
            # U_ij(surface) = U_ij(target)·(ρ_j/ρ_i)(surface)/(ρ_j/ρ_i)(target)  (docs/physics.md §3)
            b = b + np.log(rho_s / rho_s[0]) - np.log(profile.array("target_reflectance") / profile.array("target_reflectance")[0])
        self.log_constant = b
        self.exposure_shift = np.zeros(n)
        """ln m_k: each channel's exposure × gain relative to the calibration's (see :meth:`set_exposure`)."""
        self._gain_ratio = np.ones(n)
        self.active = np.ones(n, dtype=bool)
        if pair is not None:
            unknown = [p for p in pair if p not in names]
            if unknown or len(set(pair)) != 2:
                raise UserInputError(f"--pair needs two different channel names from {','.join(names)}, got {','.join(pair)}")
            self.active[:] = False
            self.active[[names.index(p) for p in pair]] = True
            if v[self.active][0] == v[self.active][1]:
                raise UserInputError(f"channels {pair[0]} and {pair[1]} have equal attenuation, so the pair carries no range")
            i, j = (names.index(p) for p in pair)
            doubt = float(self._cv[i, j])  # (3σ)² of the pair's difference (kernels.ATTENUATION_SIGMAS)
            if (v[i] - v[j]) ** 2 <= doubt:
                raise UserInputError(
                    f"channels {pair[0]} and {pair[1]} differ in attenuation by {v[i] - v[j]:+.4f} ± "
                    f"{math.sqrt(doubt) / kernels.ATTENUATION_SIGMAS:.4f} 1/m in this calibration, not clearly "
                    f"({kernels.ATTENUATION_SIGMAS:g}σ): every pixel would have no range (reason 4; 2 or 3 where "
                    "one of them is clipped or lost in the water's light, docs/physics.md §5); choose a pair "
                    "that attenuates more differently, or leave out --pair to fuse all channels")
        if n > kernels.MAX_CHANNELS:
            raise UserInputError(f"the profile has {n} channels; at most {kernels.MAX_CHANNELS} are supported")
        self.bounds = np.array(path_length_bounds, dtype=np.float64)
        self._tables: dict[int, tuple[NDArray, float]] = {}
        # Kernel constants: centred attenuations as a tuple (the channel loop unrolls; only
        # differences matter) and the geometry.
        self.set_attenuation_differences(v)
        self._geo = self._geometry()

    def set_attenuation_differences(self, differences: NDArray | list[float]) -> None:
        """Use new attenuation differences c_k − c_ref (1/m), e.g. tracked live from a patch.
        Lookup tables do not depend on them, so this is cheap enough for every frame."""
        v = np.asarray(differences, dtype=np.float64)
        if v.shape != (self.n_channels,) or not np.all(np.isfinite(v)):
            raise ValueError(f"need {self.n_channels} finite attenuation differences, got {v}")
        self.attenuation = v - v.mean()
        self._c = tuple(float(x) for x in self.attenuation)

    # Geometry parameters for the kernel: [mode, Sx, Sy, Sz, |S|, 1/fx, 1/fy, cx, cy].
    def _geometry(self) -> NDArray[np.float64]:
        s = np.array(self.profile.lamp_position_m, dtype=np.float64)
        intr = self.profile.camera_intrinsics()
        if not np.any(s):
            mode = kernels.EQUIDISTANT
        elif intr is None:
            mode = kernels.LAMP_ON_AXIS_RAY
        else:
            mode = kernels.LAMP_PIXEL_RAYS
        f = (1.0 / intr.fx, 1.0 / intr.fy, intr.cx, intr.cy) if intr else (1.0, 1.0, 0.0, 0.0)
        return np.array([mode, *s, np.linalg.norm(s), *f], dtype=np.float64)

    @property
    def effective_log_constant(self) -> NDArray[np.float64]:
        """b_k + ln m_k: the log constants for raw values at the present exposure and gain."""
        return self.log_constant + self.exposure_shift

    def set_exposure(self, exposure_us: Sequence[float] | None, gain_db: Sequence[float] | None = None) -> None:
        """Range frames whose channels were exposed ``exposure_us`` (µs, (N,)) with analogue gain
        ``gain_db`` (dB, (N,)); None: as in the calibration.

        Channel k then holds m_k = (t_k/t_k,cal)·10^((g_k − g_k,cal)/20) times the signal it had
        at calibration, so ln E_k is shifted by ln m_k: the estimator subtracts b_k + ln m_k, which
        is exact. Validity and noise stay in the sensor's own counts: the floor and saturation
        apply to the raw values, and the variance is that of the raw counts (E²/σ² is the same
        for E and E/m). The noise floor stays in counts as measured: a longer exposure lifts a
        weak channel above it (light that is backscatter, not surface, is the compensation's to
        remove: reason 3). Gain scales the noise in counts (read and shot noise, and the floor,
        are amplified with the signal), so a gain change rebuilds the lookup tables; an exposure
        change costs nothing. Where the profile did not record its exposure, only ratios between
        channels count (a common factor does not move the range)."""
        n = self.n_channels
        cal_t, cal_g = self.profile.calibration_exposure()
        values = []
        for name, v in (("exposure_us", exposure_us), ("gain_db", gain_db)):
            v = None if v is None else np.asarray(v, dtype=np.float64)
            if v is not None and (v.shape != (n,) or not np.all(np.isfinite(v))):
                raise ValueError(f"need {n} finite values of {name}, got {v}")
            values.append(v)
        t, g = values
        if t is not None and np.any(t <= 0):
            raise ValueError(f"exposure times must be positive, got {t}")
        shift = np.zeros(n)
        if t is not None:  # without the calibration's exposure, only ratios between channels: the mean is removed
            shift += np.log(t / cal_t) if cal_t is not None else np.log(t) - np.mean(np.log(t))
        ratio = np.ones(n)
        if g is not None:
            ln10 = np.log(10.0) / 20.0
            if cal_g is not None:
                ratio = 10.0 ** ((g - cal_g) / 20.0)
                shift += np.log(ratio)
            else:  # the noise model was measured at an unknown gain: ratios between channels only, noise unscaled
                shift += (g - np.mean(g)) * ln10
        self.exposure_shift = shift
        if not np.array_equal(ratio, self._gain_ratio):
            self._gain_ratio = ratio
            self.floor = self.profile.array("noise_floor") * ratio
            self.read_noise = self.profile.array("read_noise") * ratio
            self.shot_gain = self.profile.array("shot_gain") * ratio
            self._tables = {}

    def channel_terms(self, raw: NDArray, background: NDArray | None = None,
                      samples: NDArray | None = None,
                      background_variance: NDArray | None = None) -> tuple[NDArray, NDArray, NDArray]:
        """y = ln E − b, weight E²/σ² and ChannelState for raw values (any shape (..., N)).

        background: light (DN, dark-corrected, same shape) known not to come from the surface,
        such as modelled backscatter. It is subtracted from E but still counts in the shot
        noise, and a channel whose remaining signal is not 3σ above it is not usable.
        samples: when ``raw`` is the mean of this many pixels (same shape), each with the noise
        of the noise model, independent: its variance is σ²/samples.
        background_variance: (same shape) DN², the background's own uncertainty beyond the
        relative ``background_uncertainty`` (a model's doubt that varies across the view), added
        to each value's variance; only with ``background``.
        """
        e = np.asarray(raw, dtype=np.float64) - self.dark
        if background is not None:
            e = e - background
        state = channel_states(raw, e, self.floor, self.profile.saturation_level, self.backscatter)
        with np.errstate(divide="ignore", invalid="ignore"):
            total = e if background is None else e + background
            if background is None:
                var = signal_variance(total, self.read_noise, self.shot_gain, self.profile.quantisation_step,
                                      self.fixed_pattern)
            else:
                var = self.background_signal_variance(total, e)
            if self.response is not None:
                # A linearised code is known only to its width in linear DN (width²/12): the least
                # variance it can have, whatever the noise model measured (see uwcam.imaging.response).
                var = np.maximum(var, self.response.quantisation_variance(total + self.dark))
            # A profile without any noise model (float data, nothing measured) counts as 1 DN of noise.
            var = np.where(var > 0, var, 1.0)
            if samples is not None:
                var = var / np.maximum(samples, 1)
            if background is not None and self.background_uncertainty > 0:
                var = var + (self.background_uncertainty * background) ** 2
            if background is not None and background_variance is not None:
                var = var + background_variance
            if background is not None:
                state[(state == ChannelState.USABLE) & (e <= BACKGROUND_SIGMAS * np.sqrt(var))] = ChannelState.BACKSCATTER_ONLY
        state[..., ~self.active] = _IGNORED
        ok = state == ChannelState.USABLE
        with np.errstate(divide="ignore", invalid="ignore"):
            weight = np.where(ok, e * e / var, 0.0)
            y = np.where(ok, np.log(np.where(ok, e, 1.0)) - self.effective_log_constant, 0.0)
        return y, weight, state.astype(np.uint8)

    def background_signal_variance(self, total: NDArray, surface: NDArray) -> NDArray[np.float64]:
        """σ² (DN²) of the surface's light ``surface`` = E left once a background B is subtracted
        from ``total`` = E + B (dark-corrected DN, (..., N)): the noise model's of the total light,
        with the fixed pattern counted as the background leaves it (``background_fixed_pattern``
        r, f the profile's): r²·(E + B)² + (f² − r²)·E², E clipped at 0."""
        r = self.background_fixed_pattern
        var = signal_variance(total, self.read_noise, self.shot_gain, self.profile.quantisation_step, r)
        if np.array_equal(r, self.fixed_pattern):
            return var
        return var + (self.fixed_pattern**2 - r**2) * np.maximum(surface, 0.0) ** 2

    def _noise_terms(self) -> NDArray[np.float64]:
        """(N, 10) per channel: dark, read², shot gain, fixed pattern, q²/12, floor, b, active, relative
        background uncertainty, the fixed pattern a background leaves (``background_fixed_pattern``),
        for the compiled background kernel (b follows :meth:`set_log_constants`)."""
        q = float(np.asarray(self.profile.quantisation_step, dtype=np.float64))
        return np.stack([self.dark, self.read_noise**2, self.shot_gain, self.fixed_pattern,
                         np.full(self.n_channels, q**2 / 12.0), self.floor, self.effective_log_constant,
                         self.active.astype(np.float64), np.full(self.n_channels, self.background_uncertainty),
                         self.background_fixed_pattern], axis=1).astype(np.float64)

    @property
    def _open_water_levels(self) -> NDArray[np.float64]:
        return np.full(self.n_channels, -np.inf) if self.backscatter is None else self.backscatter.astype(np.float64)

    def _lookup_tables(self, dtype: np.dtype) -> tuple[NDArray[np.uint64], float]:
        """Per-channel table over every code of an integer dtype: (N, L) pairs [ln E − offset, E²/σ²]
        (see :func:`uwcam.optics.kernels.pack_pairs`) and the offset. They do not depend on the log
        constants b, which the kernel subtracts, so b can follow the surface every frame for free."""
        bits = np.dtype(dtype).itemsize * 8
        if bits not in self._tables:
            codes = np.arange(2**bits, dtype=np.float64)[:, None].repeat(self.n_channels, axis=1)
            if self.response is not None:  # the table over codes holds their linear values' terms
                if self.response.bits != bits:
                    raise UserInputError(f"the profile's response curve is for {self.response.bits}-bit codes; "
                                         f"this frame has {bits}-bit pixels: use a profile made with this camera mode")
                codes = self.response.table.T.copy()
            y, w, state = self.channel_terms(codes)
            ln_e = np.where(w > 0, y + self.effective_log_constant, 0.0)
            # A common offset of ln E changes nothing; removing it keeps float32 digits for differences.
            offset = float(np.median(ln_e[w > 0])) if np.any(w > 0) else 0.0
            pairs = kernels.pack_pairs(ln_e - offset, w, state, ChannelState.SATURATED, ChannelState.BACKSCATTER_ONLY)
            self._tables[bits] = (np.ascontiguousarray(pairs.T), offset)
        return self._tables[bits]

    def set_log_constants(self, log_constant: NDArray | list[float]) -> None:
        """Use new log constants b_k (e.g. of the surface, from a rangefinder); cheap: no table rebuild."""
        b = np.asarray(log_constant, dtype=np.float64)
        if b.shape != (self.n_channels,) or not np.all(np.isfinite(b)):
            raise ValueError(f"need {self.n_channels} finite log constants, got {b}")
        self.log_constant = b

    def warm_up(self, dtypes: tuple[type, ...] = (np.uint8, np.uint16), background: bool = True,
                strided: bool = True) -> None:
        """Compile the kernels (or load them from numba's on-disk cache) and build the lookup tables
        for frames of these pixel types, and for frames with a background when ``background``, so
        that the first real frame is as fast as the rest. Call it before the frame loop starts.
        strided: also for strided views (e.g. BGR reordered), which numba compiles apart; a caller
        that knows its frames are contiguous saves those compilations (seconds each, cold)."""
        zeros = np.zeros((2, 8, self.n_channels), np.float32)
        if self.response is not None:  # codes of the curve's depth, and the linearised (float) frames
            dtypes = tuple(d for d in dtypes if np.dtype(d).itemsize * 8 == self.response.bits) + (np.float32,)
        for dtype in dtypes:
            frame = np.zeros((2, 8, self.n_channels), dtype)
            layouts = (frame, frame[:, :, ::-1]) if strided else (frame,)
            for data in layouts:
                self(data)
                if background:  # the background kernel is compiled for each pixel type and layout
                    self(data, background=zeros)
        if background:
            self(zeros, background=zeros)

    def __call__(self, frame: NDArray, out: RangeResult | None = None, background: NDArray | None = None,
                 samples: NDArray | None = None, background_variance: NDArray | None = None) -> RangeResult:
        """Range, variance and reasons for one frame (H, W, N); ``out`` reuses output arrays.

        background: (H, W, N) light in DN not from the surface (see :meth:`channel_terms`).
        samples: (H, W, N) how many pixels each value of ``frame`` is the mean of (see
        :func:`smooth_frame`); None: one.
        background_variance: (H, W, N) DN², the background's own uncertainty (see :meth:`channel_terms`).
        """
        if background_variance is not None and background is None:
            raise ValueError("background_variance is the uncertainty of a background: pass the background too")
        if frame.ndim != 3 or frame.shape[-1] != self.n_channels:
            got = frame.shape[-1] if frame.ndim == 3 else 1
            raise UserInputError(
                f"the image has {got} channel(s) but the calibration profile has {self.n_channels} "
                f"({','.join(self.profile.channel_names)}); use a profile made with this camera"
            )
        h, w = frame.shape[:2]
        if out is None:
            out = RangeResult(np.empty((h, w), np.float32), np.empty((h, w), np.float32), np.empty((h, w), np.uint8))
        common = (self._cv, self._geo, self.bounds, out.range, out.variance, out.reasons)
        if self.response is not None and np.issubdtype(frame.dtype, np.integer) and (
                background is not None or samples is not None):
            frame = self.response.linearise(frame)  # codes → linear DN; the tables path does it per code
        if background is None and samples is None and frame.dtype in (np.uint8, np.uint16):
            table, offset = self._lookup_tables(frame.dtype)
            b = tuple(float(v) for v in self.effective_log_constant - offset)
            kernels.fuse_lookup(frame, table, self._c, b, *common)
        elif background is not None and kernels.fuse_background is not None and (
                self.response is None) and (
                np.issubdtype(frame.dtype, np.integer) or np.issubdtype(frame.dtype, np.floating)):
            # Compiled: the per-channel terms of channel_terms, computed row by row in the kernel.
            bg = kernel_array(background, frame.shape, np.float32)
            # The kernel reads rows as contiguous runs of values (a strided view, e.g. channels
            # reordered, is copied once here).
            # Values that are means (frames fused over time) have their noise divided in the kernel.
            counts = _NO_SAMPLES if samples is None else kernel_array(samples, frame.shape, np.float32)
            doubt = _NO_SAMPLES if background_variance is None else kernel_array(background_variance, frame.shape,
                                                                                    np.float32)
            kernels.fuse_background(np.ascontiguousarray(frame), bg, doubt, counts, self._noise_terms(),
                                    self._open_water_levels, float(self.profile.saturation_level), self._c, *common)
        elif np.issubdtype(frame.dtype, np.integer) or np.issubdtype(frame.dtype, np.floating):
            y, weight, state = self.channel_terms(frame, background, samples, background_variance)  # b subtracted
            pairs = kernels.pack_pairs(y, weight, state, ChannelState.SATURATED, ChannelState.BACKSCATTER_ONLY)
            kernels.fuse_arrays(pairs, self._c, (0.0,) * self.n_channels, *common)
        else:
            raise UserInputError(f"unsupported pixel type {frame.dtype}; give uint8, uint16 or float images")
        if self.with_calibration_variance:
            cal = self.calibration_variance(frame, background)
            np.add(out.variance, cal, out=out.variance)  # NaN (invalid) stays NaN
            out = RangeResult(out.range, out.variance, out.reasons, cal)
        return out

    def calibration_variance(self, frame: NDArray, background: NDArray | None = None,
                             block: int = CALIBRATION_VARIANCE_BLOCK) -> NDArray[np.float32]:
        """(H, W) variance of camera range (m²) due to the calibration's uncertainty, for ``frame``
        (H, W, N): :func:`uwcam.ranging.calibration_share.calibration_variance_map`."""
        return calibration_variance_map(self, frame, background, block)


def range_frame(estimator: RangeEstimator, frame: NDArray, smoothing: str = "none", stage: str = "after",
                background: NDArray | None = None, vehicle_mask: Sequence[tuple[int, int, int, int]] = (),
                transform: Callable[[NDArray, NDArray | None], RangeResult] | None = None,
                water=None, water_scale: NDArray | None = None, samples: NDArray | None = None,
                smoothing_target: float = DEFAULT_SMOOTHING_TARGET) -> RangeResult:
    """Range one frame as the daemon's processing settings say: 3×3 smoothing of the image
    (stage "before", :func:`smooth_frame`), the transform (``estimator``, or ``transform(frame,
    samples)`` such as backscatter compensation; ``background``: light not from the lamp, e.g.
    ambient, subtracted by the plain transform and judged against by ``water``), the water's own
    light judged (``water``, a :class:`uwcam.water.water_light.WaterLight`: pixels not clearly above it
    lose their range, reason 3; ``water_scale``: (N,) the frame's exposure × gain over that of the
    water light's), the vehicle mask (:func:`mask_vehicle`), then 3×3 smoothing of the range map
    (stage "after", :func:`smooth_range_map`: the masked vehicle lends no range to its neighbours).
    ``uwcam range``, the frame loop and ``uwcam reprocess`` all range through here. samples: (H, W, N)
    how many single-pixel noises each value's variance equals (frames fused over time,
    :func:`uwcam.ranging.images.fuse_frames`); None: one. smoothing "adaptive" (stage ignored): each
    pixel whose σ is above ``smoothing_target`` × its range, or that has no range for too little
    light, is ranged again from the mean light of the smallest window that reaches the target
    (:func:`uwcam.ranging.adaptive.adaptive_windows`), through these same steps."""
    if smoothing in ("mean", "median") and stage == "before":
        if estimator.response is not None and np.issubdtype(frame.dtype, np.integer):
            frame = estimator.response.linearise(frame)  # average light, not codes of a tone curve
        frame, smoothed = smooth_frame(frame, smoothing, estimator.profile.saturation_level)
        samples = smoothed if samples is None else samples * smoothed

    def ranged(data: NDArray, counts: NDArray | None, light: NDArray | None) -> RangeResult:
        if transform is not None:
            result = transform(data, counts)
        else:
            result = estimator(data, background=light, samples=counts)
        if water is not None:
            water.judge(result, data, estimator, water_scale, light, counts)
        if vehicle_mask:
            mask_vehicle(result, vehicle_mask)
        return result

    result = ranged(frame, samples, background)
    if smoothing == "adaptive":
        result = adaptive_windows(result, frame, ranged, estimator, smoothing_target, samples, background)
    elif smoothing != "none" and stage == "after":
        result = smooth_range_map(result, smoothing)
    return result


def mask_vehicle(result: RangeResult, boxes: Sequence[tuple[int, int, int, int]]) -> RangeResult:
    """Mark pixels where the vehicle itself is in view (x, y, width, height boxes, clipped to the
    image) as having no range, reason VEHICLE, in place; returns ``result``. Done before smoothing
    and publication, so the vehicle's parts never feed a neighbour's range or an obstacle figure."""
    h, w = result.range.shape
    for x, y, bw, bh in boxes:
        rows, cols = slice(min(y, h), min(y + bh, h)), slice(min(x, w), min(x + bw, w))
        result.range[rows, cols] = np.nan
        result.variance[rows, cols] = np.nan
        result.reasons[rows, cols] = Reason.VEHICLE
    return result
