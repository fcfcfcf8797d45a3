"""Frame → range map, variance map and reason map, from a calibration profile.

:class:`RangeEstimator` turns a profile into the per-channel quantities of DESIGN.md §5
once (attenuation differences, log constants corrected for the surface's hue, lookup
tables for integer sensors) and then processes frames in one compiled pass.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from uwcam.fileio import UserInputError
from uwcam.optics import kernels
from uwcam.optics.noise import signal_variance
from uwcam.optics.validity import ChannelState, channel_states
from uwcam.profile import CalibrationProfile

# A channel state the kernel neither uses nor counts (channels outside a chosen pair).
_IGNORED = 4
# With a known background subtracted, a channel needs this many σ of signal to be used.
BACKGROUND_SIGMAS = 3.0


@dataclass(frozen=True)
class RangeResult:
    """Outputs for one frame, each (H, W)."""

    range: NDArray[np.float32]
    """Camera range d_c in metres along each pixel's ray; NaN where invalid."""
    variance: NDArray[np.float32]
    """Variance of ``range`` in m²; NaN where invalid."""
    reasons: NDArray[np.uint8]
    """:class:`uwcam.optics.validity.Reason` code per pixel."""


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
    ) -> None:
        """pair: two channel names for single-pair ranging (default: fuse all channels).
        surface_reflectance: (N,) reflectance of the imaged surface, when it differs in hue
        from the calibration target (only ratios matter). backscatter_level: (N,) signal
        (DN, dark-corrected) of open water; pixels not above it carry no surface signal.
        path_length_bounds: (min, max) accepted path length d_T in metres."""
        self.profile = profile
        names = profile.channel_names
        n = len(names)
        self.n_channels = n
        self.dark = profile.array("dark_level")
        self.floor = profile.array("noise_floor")
        self.read_noise = profile.array("read_noise")
        self.shot_gain = profile.array("shot_gain")
        self.backscatter = None if backscatter_level is None else np.asarray(backscatter_level, dtype=np.float64)
        v = profile.array("attenuation_difference")
        b = profile.array("log_constant")
        if surface_reflectance is not None:
            rho_s = np.asarray(surface_reflectance, dtype=np.float64)
            if rho_s.shape != (n,) or np.any(rho_s <= 0):
                raise UserInputError(f"surface reflectance needs {n} positive values ({','.join(names)}), got {list(rho_s)}")
            # U_ij(surface) = U_ij(target)·(ρ_j/ρ_i)(surface)/(ρ_j/ρ_i)(target)  (DESIGN.md §3)
            b = b + np.log(rho_s / rho_s[0]) - np.log(profile.array("target_reflectance") / profile.array("target_reflectance")[0])
        self.log_constant = b
        self.active = np.ones(n, dtype=bool)
        if pair is not None:
            unknown = [p for p in pair if p not in names]
            if unknown or len(set(pair)) != 2:
                raise UserInputError(f"--pair needs two different channel names from {','.join(names)}, got {','.join(pair)}")
            self.active[:] = False
            self.active[[names.index(p) for p in pair]] = True
            if v[self.active][0] == v[self.active][1]:
                raise UserInputError(f"channels {pair[0]} and {pair[1]} have equal attenuation, so the pair carries no range")
        self.bounds = np.array(path_length_bounds, dtype=np.float64)
        self._tables: dict[int, tuple[NDArray, NDArray, float]] = {}
        # Kernel constants: centred attenuations as a tuple (the channel loop unrolls; only
        # differences matter and centring keeps sums well conditioned), one bit per distinct
        # attenuation value, and the geometry.
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
        distinct = sorted(set(self._c))
        self._bits = tuple(1 << distinct.index(x) for x in self._c)

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

    def channel_terms(self, raw: NDArray, background: NDArray | None = None) -> tuple[NDArray, NDArray, NDArray]:
        """y = ln E − b, weight E²/σ² and ChannelState for raw values (any shape (..., N)).

        background: light (DN, dark-corrected, same shape) known not to come from the surface,
        such as modelled backscatter. It is subtracted from E but still counts in the shot
        noise, and a channel whose remaining signal is not 3σ above it is not usable.
        """
        e = np.asarray(raw, dtype=np.float64) - self.dark
        if background is not None:
            e = e - background
        state = channel_states(raw, e, self.floor, self.profile.saturation_level, self.backscatter)
        with np.errstate(divide="ignore", invalid="ignore"):
            total = e if background is None else e + background
            var = signal_variance(total, self.read_noise, self.shot_gain, self.profile.quantisation_step)
            # A profile without any noise model (float data, nothing measured) counts as 1 DN of noise.
            var = np.where(var > 0, var, 1.0)
            if background is not None:
                state[(state == ChannelState.USABLE) & (e <= BACKGROUND_SIGMAS * np.sqrt(var))] = ChannelState.BACKSCATTER_ONLY
        state[..., ~self.active] = _IGNORED
        ok = state == ChannelState.USABLE
        with np.errstate(divide="ignore", invalid="ignore"):
            weight = np.where(ok, e * e / var, 0.0)
            y = np.where(ok, np.log(np.where(ok, e, 1.0)) - self.log_constant, 0.0)
        return y, weight, state.astype(np.uint8)

    def _lookup_tables(self, dtype: np.dtype) -> tuple[NDArray, NDArray]:
        """Per-channel tables over every code of an integer dtype: (N, L, 2) float32 [ln E − offset,
        E²/σ²] and (N, L) uint8 states. They do not depend on the log constants b, which the
        kernel subtracts, so b can follow the surface every frame for free."""
        bits = np.dtype(dtype).itemsize * 8
        if bits not in self._tables:
            codes = np.arange(2**bits, dtype=np.float64)[:, None].repeat(self.n_channels, axis=1)
            y, w, state = self.channel_terms(codes)
            ln_e = np.where(w > 0, y + self.log_constant, 0.0)
            # A common offset of ln E changes nothing; removing it keeps float32 digits for differences.
            offset = float(np.median(ln_e[w > 0])) if np.any(w > 0) else 0.0
            ln_e = np.where(w > 0, ln_e - offset, 0.0)
            table = np.stack([ln_e.T, w.T], axis=-1).astype(np.float32)
            self._tables[bits] = (np.ascontiguousarray(table), np.ascontiguousarray(state.T), offset)
        return self._tables[bits]

    def set_log_constants(self, log_constant: NDArray | list[float]) -> None:
        """Use new log constants b_k (e.g. of the surface, from a rangefinder); cheap: no table rebuild."""
        b = np.asarray(log_constant, dtype=np.float64)
        if b.shape != (self.n_channels,) or not np.all(np.isfinite(b)):
            raise ValueError(f"need {self.n_channels} finite log constants, got {b}")
        self.log_constant = b

    def __call__(self, frame: NDArray, out: RangeResult | None = None, background: NDArray | None = None) -> RangeResult:
        """Range, variance and reasons for one frame (H, W, N); ``out`` reuses output arrays.

        background: (H, W, N) light in DN not from the surface (see :meth:`channel_terms`).
        """
        if frame.ndim != 3 or frame.shape[-1] != self.n_channels:
            got = frame.shape[-1] if frame.ndim == 3 else 1
            raise UserInputError(
                f"the image has {got} channel(s) but the calibration profile has {self.n_channels} "
                f"({','.join(self.profile.channel_names)}); use a profile made with this camera"
            )
        h, w = frame.shape[:2]
        if out is None:
            out = RangeResult(np.empty((h, w), np.float32), np.empty((h, w), np.float32), np.empty((h, w), np.uint8))
        common = (self._bits, self._geo, self.bounds, out.range, out.variance, out.reasons)
        if background is None and frame.dtype in (np.uint8, np.uint16):
            table, states, offset = self._lookup_tables(frame.dtype)
            b = tuple(float(v) for v in self.log_constant - offset)
            kernels.fuse_lookup(frame, table, states, self._c, b, *common)
        elif np.issubdtype(frame.dtype, np.integer) or np.issubdtype(frame.dtype, np.floating):
            y, weight, state = self.channel_terms(frame, background)  # y already has b subtracted
            kernels.fuse_arrays(y, weight, state, self._c, (0.0,) * self.n_channels, *common)
        else:
            raise UserInputError(f"unsupported pixel type {frame.dtype}; give uint8, uint16 or float images")
        return out


def smooth_range_map(result: RangeResult, kind: str = "mean") -> RangeResult:
    """3×3 smoothing of a range map over valid neighbours only (DESIGN.md §7).

    kind "mean": average of the n valid pixels in each 3×3 window, with the variance of that
    average for independent neighbours, Σσ_k²/n² (σ²/n when all are equal); "median": their
    median, variance kept.
    Invalid pixels stay invalid with their reasons, and never leak into valid ones.
    """
    if kind not in ("mean", "median"):
        raise UserInputError(f"smoothing must be 'mean' or 'median', got '{kind}'")
    r = result.range.astype(np.float64)
    valid = np.isfinite(r)
    padded = np.pad(np.where(valid, r, np.nan), 1, constant_values=np.nan)
    h, w = r.shape
    windows = np.stack([padded[dy : dy + h, dx : dx + w] for dy in range(3) for dx in range(3)])
    count = np.isfinite(windows).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        if kind == "mean":
            smoothed = np.nansum(windows, axis=0) / count
            v = np.pad(np.where(valid, result.variance.astype(np.float64), 0.0), 1)
            variance = sum(v[dy : dy + h, dx : dx + w] for dy in range(3) for dx in range(3)) / np.maximum(count, 1) ** 2
        else:
            import warnings

            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN windows
                smoothed = np.nanmedian(windows, axis=0)
            variance = result.variance
    return RangeResult(
        np.where(valid, smoothed, np.nan).astype(np.float32),
        np.where(valid, variance, np.nan).astype(np.float32),
        result.reasons.copy(),
    )
