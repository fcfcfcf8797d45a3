"""The frame loop: newest frame → range, variance, reasons → published state.

Acquisition runs in the camera's own supervisor thread; processing runs here, in one thread
that ranges queued frames in order while they are fresh and skips to the newest when it falls
behind (skipped frames are counted, never the newest; see QUEUED_FRAME_BUDGET_S), tracks the
attenuation difference live from a calibration patch in view
(docs/physics.md §6) and publishes immutable results. Readers (the API) never block the loop:
they read the latest published result or are called back with it.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from uwcam.config import OrientationConfig, PatchConfig, ProcessingConfig, ReflectanceConfig
from uwcam.drivers.base import Frame
from uwcam.drivers.supervisor import SupervisedCamera
from uwcam.lamp_control import LampCommander
from uwcam.memory import release_compiler_pages, release_free_memory
from uwcam.optics.geometry import Intrinsics, path_length_from_camera_range, pixel_rays
from uwcam.optics.orientation import (beam_pattern, block_irradiance, block_means, incidence_from_blocks, normals_from_range,
                                      surface_scale)
from uwcam.optics.reflectance import surface_log_constant
from uwcam.profile import CalibrationProfile, check_intrinsics_fit
from uwcam.ranging import RangeEstimator, RangeResult, range_frame

QUEUED_FRAME_BUDGET_S = 0.030
"""A frame that waited longer than this (seconds since capture) is skipped when a newer one is
already queued. Younger frames are ranged in order: a hiccup of the loop (a scrape, a snapshot
encoded, the garbage collector) then costs a few milliseconds of latency instead of frames, while
a loop that cannot keep up falls back to the newest frame and its latency stays bounded."""

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Published:
    """One processed frame. Arrays are never modified after publication."""

    number: int
    frame: Frame
    result: RangeResult
    publish_monotonic_ns: int
    attenuation_differences: tuple[float, ...]
    log_constants: tuple[float, ...] = ()
    """The log constants b_k this frame was ranged with (the calibration's, or the surface's)."""
    ambient: NDArray[np.float32] | None = None
    """(H, W, C) light not from the lamp (DN, dark-corrected) subtracted from this frame, or None."""
    incidence: NDArray[np.float32] | None = None
    """(H // block, W // block) incidence angle γ in degrees per pixel block (Kirlin), NaN where
    none was found; None when orientation is off or unavailable."""
    incidence_block: int = 0
    """Side of the pixel blocks of ``incidence``."""
    water_source: str | None = None
    """What the open-water light this frame was judged against came from (uwcam.water_light), or None."""
    light_scale: tuple[float, ...] | None = None
    """Per channel, this frame's exposure × gain over that of the backscatter model's light (None: 1)."""
    open_water: NDArray[np.float32] | None = None
    """The open-water frame the backscatter model was made with, when it was (raw DN less ambient)."""

    @property
    def latency_s(self) -> float:
        return (self.publish_monotonic_ns - self.frame.host_monotonic_ns) / 1e9


@dataclass
class PatchTracker:
    """Re-estimates c_k − c_ref every frame from a patch of known path length (docs/physics.md §6):
    ln(E_k/E_ref) = b_k − V_k·d_T^p, so V_k = (b_k − ln(E_k/E_ref)) / d_T^p; smoothed by an EMA,
    with frames rejected when the patch is saturated, too dark or the estimate jumps."""

    config: PatchConfig
    profile: CalibrationProfile
    tracked: NDArray[np.float64] = field(init=False)
    accepted: int = 0
    rejected: int = 0
    last_reason: str = "no frame yet"

    def __post_init__(self) -> None:
        self._detector = None
        self.region = self.config.region
        self.calibrated = self.profile.array("attenuation_difference")
        self.tracked = self.calibrated.copy()
        self.log_constant = self.profile.array("log_constant")
        self.dark = self.profile.array("dark_level")
        self.floor = self.profile.array("noise_floor")
        self.ref = self.profile.reference_index

    def locate(self, data: NDArray) -> tuple[int, int, int, int] | None:
        """The patch region in pixels: fixed, or placed beside the marker found in this frame."""
        if self.config.marker is None:
            return self.config.region
        m = self.config.marker
        if self._detector is None:
            dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, m.dictionary))
            self._detector = cv2.aruco.ArucoDetector(dictionary, cv2.aruco.DetectorParameters())
        # Detect on the brightest channel, stretched to 8 bits.
        channel = data[:, :, int(np.argmax(data.reshape(-1, data.shape[-1])[:: 97].mean(axis=0)))].astype(np.float32)
        top = float(np.percentile(channel[::4, ::4], 99.5)) or 1.0
        grey = np.clip(channel * (255.0 / top), 0, 255).astype(np.uint8)
        corners, ids, _ = self._detector.detectMarkers(grey)
        if ids is None or m.id not in ids.ravel():
            return None
        c = corners[list(ids.ravel()).index(m.id)].reshape(4, 2)
        side = float(np.mean([np.linalg.norm(c[1] - c[0]), np.linalg.norm(c[3] - c[0])]))
        x, y = c[0] + np.array(m.offset) * side
        w, h = np.array(m.size) * side
        x0, y0 = max(int(round(x)), 0), max(int(round(y)), 0)
        return x0, y0, max(int(round(w)), 1), max(int(round(h)), 1)

    def update(self, data: NDArray, background: NDArray | None = None, exposure_shift: NDArray | None = None) -> bool:
        """background: light (DN) not from the lamp, e.g. the ambient frame, subtracted first;
        exposure_shift: ln m_k of the frame's exposure against the calibration's (the estimator's)."""
        region = self.locate(data)
        if region is None:
            self.last_reason = f"marker {self.config.marker.id} not found (occluded, dark or out of view?)"
            self.rejected += 1
            return False
        self.region = region
        x, y, w, h = region
        patch = data[y : y + h, x : x + w]
        if patch.size == 0:
            self.last_reason = "patch region lies outside the image"
            self.rejected += 1
            return False
        if np.any(patch >= self.profile.saturation_level):
            self.last_reason = "patch saturated"
            self.rejected += 1
            return False
        e = patch.reshape(-1, patch.shape[-1]).astype(np.float64).mean(axis=0) - self.dark
        if background is not None:
            e = e - background[y : y + h, x : x + w].reshape(-1, patch.shape[-1]).mean(axis=0)
        if np.any(e <= np.maximum(self.floor, 0.0)) or np.any(e <= 0):
            self.last_reason = "patch below the noise floor (occluded or lamp off?)"
            self.rejected += 1
            return False
        if exposure_shift is not None:
            e = e * np.exp(-np.asarray(exposure_shift))  # as if at the calibration's exposure
        estimate = (self.log_constant - (np.log(e) - np.log(e[self.ref]))) / self.config.path_length_m
        estimate[self.ref] = 0.0
        if self.accepted and np.max(np.abs(estimate - self.tracked)) > self.config.max_step:
            self.last_reason = f"estimate jumped by {np.max(np.abs(estimate - self.tracked)):.3f} 1/m (outlier)"
            self.rejected += 1
            return False
        a = 1.0 if self.accepted == 0 else self.config.smoothing
        self.tracked = (1 - a) * self.tracked + a * estimate
        self.accepted += 1
        self.last_reason = "tracking"
        return True

    def status(self) -> dict:
        names = self.profile.channel_names
        return {
            "attenuation_differences": dict(zip(names, map(float, self.tracked))),
            "drift": dict(zip(names, map(float, self.tracked - self.calibrated))),
            # The calibration's own uncertainty of each difference (1/m; 0: not known): a drift
            # within a few of these is the calibration's noise, beyond them the water has changed.
            "drift_std": dict(zip(names, map(float, self.profile.array("attenuation_difference_std")))),
            "accepted": self.accepted,
            "rejected": self.rejected,
            "state": self.last_reason,
            "region": None if self.region is None else list(self.region),
        }


@dataclass
class ReflectanceCorrector:
    """Surface log constants b_k from rangefinder readings at the beam's footprint (docs/physics.md §8),
    and, when the profile has absolute attenuations, the surface's absolute scale s_k of Kirlin's
    model (§9), the light a surface facing the lamp squarely would return at that range.

    The reading is taken as the camera range along the ray through the footprint's centre. Where
    the surface there is tilted, each footprint pixel looks at it from another range, and an
    absolute scale divides by the cosine of the incidence angle: both come from the surface normal
    at the footprint, estimated from the previous frame's range map (:meth:`observe`).

    A reading is used only if it is fresh relative to the frame's capture time and the
    rangefinder is healthy; otherwise the correction pauses (the last estimate stays in use)
    and :meth:`status` says why.
    """

    config: ReflectanceConfig
    profile: CalibrationProfile
    rangefinder: object
    beam_half_angle_deg: float | None = None
    """The lamp's beam pattern (see :func:`uwcam.optics.orientation.beam_pattern`), for the scale."""
    log_constant: NDArray[np.float64] | None = None
    scale: NDArray[np.float64] | None = None
    """(N,) absolute scale s_k (DN, at the calibration's exposure) of the surface at the footprint, or None."""
    normal: NDArray[np.float64] | None = None
    """(3,) unit surface normal at the footprint (camera frame), from the range map; None: unknown."""
    incidence_deg: float | None = None
    """Incidence angle at the footprint's centre from ``normal``, degrees."""
    used: int = 0
    state: str = "no reading yet"

    def __post_init__(self) -> None:
        attenuation = [c.attenuation for c in self.profile.channels]
        self.attenuation = None if any(a is None for a in attenuation) else np.array(attenuation, np.float64)

    def observe(self, range_map: NDArray) -> None:
        """The surface normal at the footprint from a range map (H, W), metres: the mean of the
        range-map normals (:func:`normals_from_range`) over the footprint; None where it has none."""
        intr = self.profile.camera_intrinsics()
        if intr is None:
            return
        x, y, w, h = self.config.footprint
        margin = 8  # the normals' 7-pixel window, and a pixel to spare
        x0, y0 = max(x - margin, 0), max(y - margin, 0)
        x1, y1 = min(x + w + margin, range_map.shape[1]), min(y + h + margin, range_map.shape[0])
        crop = np.asarray(range_map[y0:y1, x0:x1], dtype=np.float64)
        if crop.shape[0] < 3 or crop.shape[1] < 3:
            self.normal = None
            return
        n = normals_from_range(crop, Intrinsics(intr.fx, intr.fy, intr.cx - x0, intr.cy - y0), window=min(7, 2 * (min(crop.shape) // 2) - 1))
        inside = n[y - y0 : y - y0 + h, x - x0 : x - x0 + w].reshape(-1, 3)
        inside = inside[np.all(np.isfinite(inside), axis=1)]
        if len(inside) < max(4, (w * h) // 4):
            self.normal = None
            return
        mean = inside.astype(np.float64).mean(axis=0)
        self.normal = mean / np.linalg.norm(mean)

    def update(self, frame: Frame, attenuation_differences: NDArray, background: NDArray | None = None,
               exposure_shift: NDArray | None = None) -> NDArray[np.float64] | None:
        """background: light (DN) not from the lamp, e.g. the ambient frame, subtracted first;
        exposure_shift: ln m_k of the frame's exposure against the calibration's (the estimator's)."""
        rf = self.rangefinder
        health = rf.health
        reading = rf.latest()
        if health.state.value != "ok":
            self.state = f"paused: rangefinder {health.state.value} ({health.reason})"
            return self.log_constant
        if reading is None:
            self.state = "paused: no valid reading yet"
            return self.log_constant
        skew = abs(reading.monotonic_ns - frame.host_monotonic_ns) / 1e9
        if skew > self.config.max_age_s:
            self.state = f"paused: reading {skew:.2f} s from the frame (limit {self.config.max_age_s:g} s)"
            return self.log_constant
        x, y, w, h = self.config.footprint
        pixels = frame.data[y : y + h, x : x + w].reshape(-1, frame.data.shape[-1]).astype(np.float64)
        e = pixels - self.profile.array("dark_level")
        if background is not None:
            e = e - background[y : y + h, x : x + w].reshape(-1, frame.data.shape[-1])
        ok = np.all((e > self.profile.array("noise_floor")) & (pixels < self.profile.saturation_level), axis=1)
        if ok.sum() < max(4, pixels.shape[0] // 4):
            self.state = "paused: footprint too dark or saturated"
            return self.log_constant
        intr = self.profile.camera_intrinsics()
        rays = None
        camera_range = np.full(int(ok.sum()), reading.range_m)
        cos = np.ones(int(ok.sum()))
        if intr is not None:  # rays of the footprint only: the principal point shifted into it
            window = Intrinsics(intr.fx, intr.fy, intr.cx - x, intr.cy - y)
            rays = pixel_rays(window, pixels.shape[0] // w, w).reshape(-1, 3)[ok]
            if self.normal is not None:
                # The reading lies on the ray through the footprint's centre; every other footprint
                # pixel meets the tilted surface (the plane of the normal) at its own range.
                centre = pixel_rays(Intrinsics(intr.fx, intr.fy, intr.cx - x - (w - 1) / 2, intr.cy - y - (h - 1) / 2), 1, 1)[0, 0]
                facing = rays @ self.normal
                camera_range = reading.range_m * float(centre @ self.normal) / facing
                cos = np.abs(facing)
                self.incidence_deg = float(np.degrees(np.arccos(min(abs(float(centre @ self.normal)), 1.0))))
        path = path_length_from_camera_range(camera_range, self.profile.lamp_position_m, rays)
        # The light at the calibration's exposure: estimates from frames at any exposure agree.
        light = e[ok] if exposure_shift is None else e[ok] * np.exp(-np.asarray(exposure_shift))
        estimate = surface_log_constant(light, path, attenuation_differences, self.profile.reference_index)
        a = 1.0 if self.log_constant is None else self.config.smoothing
        self.log_constant = estimate if self.log_constant is None else (1 - a) * self.log_constant + a * estimate
        if self.attenuation is not None and rays is not None and self.normal is not None:
            # Only with the surface's normal: an absolute scale divides by cos γ.
            beam = beam_pattern(rays, self.beam_half_angle_deg)
            log_scale = np.log(surface_scale(light, camera_range, self.attenuation, cos, self.profile.lamp_radius_m or 0.0, beam))
            self.scale = np.exp(log_scale if self.scale is None else (1 - a) * np.log(self.scale) + a * log_scale)
        self.used += 1
        self.state = "correcting"
        return self.log_constant

    def status(self) -> dict:
        names = self.profile.channel_names
        target = self.profile.array("log_constant")
        ratio = None if self.log_constant is None else dict(zip(names, map(float, np.exp(self.log_constant - target))))
        return {"state": self.state, "readings_used": self.used, "reflectance_ratio_to_target": ratio,
                "incidence_deg": None if self.incidence_deg is None or self.normal is None else round(self.incidence_deg, 2),
                "scale": None if self.scale is None else dict(zip(names, map(float, self.scale)))}


@dataclass
class OrientationEstimator:
    """Incidence angles per pixel block by Kirlin's Gauss–Newton step (docs/physics.md §9), seeded
    with the fused range, from the profile's absolute attenuations and the absolute scale that the
    reflectance corrector measures at the rangefinder's footprint."""

    config: OrientationConfig
    profile: CalibrationProfile
    state: str = "no frame yet"
    valid_fraction: float | None = None
    ms: collections.deque = field(default_factory=lambda: collections.deque(maxlen=100))

    def __post_init__(self) -> None:
        attenuation = [c.attenuation for c in self.profile.channels]
        self.attenuation = None if any(a is None for a in attenuation) else np.array(attenuation, np.float64)
        self._beam: tuple[tuple[int, int], NDArray] | None = None

    def unavailable(self, corrector: ReflectanceCorrector | None) -> str | None:
        """Why no incidence can be had with this profile and corrector, or None."""
        if self.attenuation is None:
            return (f"unavailable: the calibration profile '{self.profile.name}' has no absolute attenuations "
                    "(calibrate with the lamp's effective radius, docs/calibration.md)")
        if corrector is None:
            return ("unavailable: needs the surface's absolute scale from the rangefinder "
                    "(configure processing.reflectance with its footprint)")
        if self.config.beam_half_angle_deg is not None and self.profile.camera_intrinsics() is None:
            return "unavailable: a beam pattern needs camera intrinsics in the calibration profile"
        if corrector.scale is None:
            return f"waiting for an absolute scale at the rangefinder's footprint ({corrector.state})"
        return None

    def beam(self, shape: tuple[int, int]) -> NDArray:
        """The lamp's relative intensity toward the centre of every block, (bh, bw)."""
        if self._beam is None or self._beam[0] != shape:
            intr = self.profile.camera_intrinsics()
            if intr is None or self.config.beam_half_angle_deg is None:
                values = np.ones(shape)
            else:
                b = self.config.block
                # Block (i, j) is centred on pixel (j·b + (b − 1)/2, i·b + (b − 1)/2).
                centres = Intrinsics(intr.fx / b, intr.fy / b, (intr.cx - (b - 1) / 2) / b, (intr.cy - (b - 1) / 2) / b)
                values = beam_pattern(pixel_rays(centres, *shape), self.config.beam_half_angle_deg)
            self._beam = (shape, values)
        return self._beam[1]

    def estimate(self, data: NDArray, result: RangeResult, corrector: ReflectanceCorrector | None,
                 background: NDArray | None = None, exposure_shift: NDArray | None = None) -> NDArray[np.float32] | None:
        """(H // block, W // block) incidence in degrees for this frame, or None (``state`` says why);
        exposure_shift: ln m_k of the frame's exposure against the calibration's (the estimator's):
        the scale, measured in the calibration's exposure, is taken to the frame's raw counts."""
        why = self.unavailable(corrector)
        if why is not None:
            self.state = why
            return None
        started = time.perf_counter()
        p = self.profile
        b = self.config.block
        if data.shape[0] < b or data.shape[1] < b:
            self.state = f"unavailable: the image is smaller than one block of {b} pixels"
            return None
        irradiance, share, usable = block_irradiance(data, result.range, p.array("dark_level"), p.array("noise_floor"),
                                                     p.saturation_level, b, background)
        maps = [np.asarray(m, np.float32) for m in (result.range, result.variance, result.calibration_variance) if m is not None]
        means = block_means(cv2.merge(maps), usable, b)  # one pass over the three maps
        seed, variance = means[..., 0], means[..., 1]
        common = means[..., 2] if means.shape[-1] > 2 else 0.0
        count = share * (b * b)
        # Variances of the block means: the camera's noise model per pixel over the pixels averaged,
        # and the fused range's own (its calibration part is common to all pixels: not averaged down).
        with np.errstate(invalid="ignore", divide="ignore"):
            pixel_var = (p.array("read_noise") ** 2 + p.array("shot_gain") * irradiance
                         + (p.array("fixed_pattern") * irradiance) ** 2 + p.quantisation_step**2 / 12.0)
            irradiance_var = pixel_var / count[..., None]
            range_var = (variance - common) / count + common
        scale = corrector.scale * self.beam(seed.shape)[..., None]
        if exposure_shift is not None:
            scale = scale * np.exp(np.asarray(exposure_shift, np.float64))
        _, incidence = incidence_from_blocks(irradiance, seed, self.attenuation, scale, p.lamp_radius_m or 0.0,
                                             self.config.iterations, irradiance_variance=irradiance_var,
                                             range_variance=range_var)
        self.ms.append((time.perf_counter() - started) * 1e3)
        found = np.isfinite(incidence)
        self.valid_fraction = float(found.mean())
        self.state = "estimating"
        return incidence.astype(np.float32)

    def status(self) -> dict:
        ms = list(self.ms)
        return {"enabled": True, "state": self.state, "block": self.config.block,
                "ms_per_frame": round(float(np.median(ms)), 2) if ms else None,
                "blocks_with_angle": None if self.valid_fraction is None else round(self.valid_fraction, 4)}


class FramePipeline:
    """Processes frames from a supervised camera in one thread and publishes the results."""

    def __init__(self, camera: SupervisedCamera, profile: CalibrationProfile, processing: ProcessingConfig,
                 rangefinder: object | None = None, lamp: object | None = None) -> None:
        self.camera = camera
        self.profile = profile
        self.rangefinder = rangefinder
        self.lamp = lamp
        # Lamp-off frames for ambient subtraction (processing thread only).
        self._ambient: NDArray[np.float32] | None = None
        self._ambient_frames = 0
        self._lit_since_dark = 0
        self._lamp_off_since_ns = 0
        self._cycle = "lit"
        self._lit_while_dark = 0
        self._ticket = 0
        self._lamp_commander = LampCommander(lamp) if lamp is not None else None
        # Backscatter compensation (processing thread only, apart from the open-water frame): wherever
        # the profile knows the water's light (uwcam.backscatter_loop.compensation_iterations).
        self._compensator = None
        self.open_water: NDArray[np.float32] | None = None
        """A lamp-lit frame (H, W, N) of open water, raw DN less ambient light, or None."""
        self.open_water_info: dict = {}
        self.on_open_water: Callable[[NDArray[np.float32], dict], None] | None = None
        """Called (from the processing thread) when an open-water frame has been taken."""
        self._open_water_request: dict | None = None
        self._open_water_thread: threading.Thread | None = None
        self._open_water_capture: str | None = None
        """How the last open-water request ended (None: none made)."""
        self._compensation_ms: collections.deque[float] = collections.deque(maxlen=100)
        self._frame_shape: tuple[int, ...] | None = None
        """(H, W, N) of the last frame taken, for building the compensator before it is needed."""
        self._frame_integer: bool | None = None
        """Whether the last frame taken held integer DN (None: no frame yet), to check profiles against."""
        self._lock = threading.Lock()  # guards configuration swaps and the published result
        self._apply(processing, profile)
        self.previous_processing: ProcessingConfig | None = None
        self._latest: Published | None = None
        self._subscribers: list[Callable[[Published], None]] = []
        self._unranged_subscribers: list[Callable[[Frame, str], None]] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.processed = 0
        self.skipped = 0
        self._latencies: collections.deque[float] = collections.deque(maxlen=600)
        self._times: collections.deque[float] = collections.deque(maxlen=4096)  # publish times, s
        self._started_s: float | None = None

    def _build(self, processing: ProcessingConfig, profile: CalibrationProfile) -> tuple:
        """Everything that ranges with ``processing`` and ``profile``; raises ValueError (changing
        nothing) if they do not fit together or with the devices."""
        if processing.reflectance is not None and self.rangefinder is None:
            raise ValueError("reflectance correction needs a rangefinder in the configuration")
        if processing.lamp_off_interval and self.lamp is None:
            raise ValueError("lamp_off_interval needs a lamp in the configuration")
        if processing.backscatter is not None and profile.backscatter is None:
            raise ValueError(f"backscatter compensation needs backscatter measurements in the calibration profile "
                             f"'{profile.name}' (calibrate with a rig that has a black patch, e.g. grey-plate)")
        if processing.pair is not None and any(p not in profile.channel_names for p in processing.pair):
            raise ValueError(f"pair {list(processing.pair)} is not two of the profile's channels {profile.channel_names}")
        control = getattr(self.camera, "exposure_control", "")
        if processing.exposure is not None and control not in ("per-channel", "common"):
            raise ValueError("exposure control needs a camera whose exposure can be set while streaming "
                             f"(driver '{getattr(getattr(self.camera, 'driver', None), 'name', '?')}' cannot)")
        if self._frame_shape is not None:
            check_intrinsics_fit(profile.intrinsics, self._frame_shape[1], self._frame_shape[0])
        # A response curve gives each code its own width (uwcam.response): its step 0 is right.
        if self._frame_integer and profile.quantisation_step == 0 and profile.response is None:
            raise ValueError(f"profile '{profile.name}' has quantisation_step 0 (float data) but the camera delivers "
                             "integer values; calibrate with this camera")
        estimator = RangeEstimator(profile, pair=processing.pair, path_length_bounds=processing.path_length_bounds)
        tracker = PatchTracker(processing.patch, profile) if processing.patch else None
        beam = processing.orientation.beam_half_angle_deg if processing.orientation else None
        corrector = ReflectanceCorrector(processing.reflectance, profile, self.rangefinder, beam) if processing.reflectance else None
        orientation = OrientationEstimator(processing.orientation, profile) if processing.orientation else None
        return estimator, tracker, corrector, orientation

    def _apply(self, processing: ProcessingConfig, profile: CalibrationProfile | None = None) -> None:
        profile = profile or self.profile
        estimator, tracker, corrector, orientation = self._build(processing, profile)
        exposure = None
        if processing.exposure is not None:
            from uwcam.exposure import ExposureController

            exposure = ExposureController(processing.exposure, tuple(profile.channel_names), self.camera.exposure_control)
        from uwcam.hdr import HdrMerger

        hdr = HdrMerger(profile.saturation_level) if exposure is not None and exposure.bracketing else None
        # Compile or load the kernels and build lookup tables here, in the caller's thread (start-up
        # or an API request), not on the loop's first frame, which would stall it for seconds.
        estimator.warm_up(background=bool(processing.lamp_off_interval))
        # So is the backscatter compensator (0.3-0.6 s at 720p: 10-17 frames of a 30 fps loop)
        # once frames have come; before that, the loop builds it on the first frame.
        water, compensator = self.open_water, None
        if self._iterations(processing, profile) is not None and self._frame_shape is not None:
            compensator = self._make_compensator(processing, profile, self._frame_shape, water)
        with self._lock:  # one swap: a frame sees the old set or the new set, never a mix
            self.profile = profile
            self.processing = processing
            self.estimator = estimator
            self.tracker = tracker
            self.corrector = corrector
            self.orientation = orientation
            self.exposure = exposure
            self._hdr = hdr
            # An open-water frame taken meanwhile makes the one built here stale: the loop builds anew.
            self._compensator = compensator if self.open_water is water else None

    def check(self, processing: ProcessingConfig | None = None, profile: CalibrationProfile | None = None) -> None:
        """ValueError if these settings or this profile would not work; changes nothing."""
        self._build(processing or self.processing, profile or self.profile)

    def reconfigure(self, processing: ProcessingConfig) -> None:
        """Apply new processing settings from the next frame on (validated by the caller); the
        settings they replace are kept for :meth:`restore`."""
        previous = self.processing
        self._apply(processing)
        self.previous_processing = previous

    def restore(self) -> ProcessingConfig:
        """Go back to the settings before the last change."""
        if self.previous_processing is None:
            raise ValueError("no earlier settings to restore")
        self.reconfigure(self.previous_processing)
        return self.processing

    def set_profile(self, profile: CalibrationProfile) -> None:
        """Range with another calibration from the next frame on; ValueError, changing nothing,
        if it does not fit the processing settings."""
        self._apply(self.processing, profile)

    def set_open_water(self, frame: NDArray | None, info: dict | None = None) -> None:
        """Use this open-water frame (H, W, N; raw DN less ambient light) for backscatter from the
        next frame on; None forgets it (the profile's black-patch measurements are used alone).
        The compensator for it is built here, in the caller's thread (0.3-0.6 s at 720p), while
        the loop goes on with the one it has."""
        water = None if frame is None else np.asarray(frame, np.float32)
        processing, profile, shape = self.processing, self.profile, self._frame_shape
        compensator = None
        if self._iterations(processing, profile) is not None and shape is not None:
            try:
                compensator = self._make_compensator(processing, profile, shape, water)
            except Exception:  # the frame is kept all the same; the loop tries again, and says why
                log.exception("could not build backscatter compensation for the open-water frame")
        with self._lock:
            self.open_water = water
            self.open_water_info = dict(info or {})
            # Settings or profile changed meanwhile: the loop builds one for what it has now.
            current = self.processing is processing and self.profile is profile
            self._compensator = compensator if current else None

    def request_open_water(self, frames: int = 4, timeout_s: float = 10.0) -> threading.Event:
        """Average the next ``frames`` lamp-lit frames into the open-water frame; the event is set
        when it is in use. Frames later than ``timeout_s`` from now are not taken (the request
        lapses, and :meth:`backscatter_status` says so). The view must show only water meanwhile."""
        done = threading.Event()
        with self._lock:
            self._open_water_request = {"frames": int(frames), "sum": None, "count": 0, "done": done,
                                        "deadline": time.monotonic() + timeout_s, "timeout_s": timeout_s}
            self._open_water_capture = "capturing"
        return done

    def _pending_open_water(self) -> dict | None:
        """The open-water request still pending, dropping one past its deadline."""
        with self._lock:
            request = self._open_water_request
            if request is not None and time.monotonic() > request["deadline"]:
                self._open_water_request = None
                self._open_water_capture = (f"lapsed: {request['count']} of {request['frames']} lamp-lit frames came "
                                            f"within {request['timeout_s']:g} s (is the camera streaming and the lamp on?)")
                return None
            return request

    def _take_open_water(self, frame: Frame, ambient: NDArray | None, source: str) -> None:
        """Accumulate ``frame`` for a pending open-water request."""
        request = self._pending_open_water()
        if request is None:
            return
        light = frame.data.astype(np.float32) if ambient is None else frame.data.astype(np.float32) - ambient
        gathered = frame.light_gathered()
        if gathered is not None:
            if request.get("exposure") is None:
                request["exposure"] = gathered
            elif not np.array_equal(gathered, request["exposure"]):  # the exposure moved: to the first frame's
                dark = self.profile.array("dark_level").astype(np.float32)
                light = dark + (light - dark) * (request["exposure"] / gathered).astype(np.float32)
        request["sum"] = light if request["sum"] is None else request["sum"] + light
        request["count"] += 1
        total, count = request["sum"], request["count"]
        if count < request["frames"]:
            return
        info = {"source": source, "frames": count, "wall_time": frame.wall_time, "monotonic": time.monotonic(),
                "shape": list(frame.data.shape)}
        if request.get("exposure") is not None:
            info["exposure"] = [float(v) for v in request["exposure"]]  # per channel, exposure × gain (µs)
        with self._lock:
            self._open_water_request = None  # no more frames taken; still "capturing" until in use
        # Put in use by a thread of its own: building its compensator would stall the loop.
        self._open_water_thread = threading.Thread(target=self._use_open_water, args=(total / count, info, request),
                                                   name="open-water", daemon=True)
        self._open_water_thread.start()

    def _use_open_water(self, mean: NDArray, info: dict, request: dict) -> None:
        try:
            self.set_open_water(mean, info)
        except Exception as exc:  # e.g. the profile changed to one the frame does not fit
            log.exception("the open-water frame could not be put in use")
            with self._lock:
                self._open_water_capture = f"failed: {exc}"
            return
        with self._lock:
            self._open_water_capture = "done"
        request["done"].set()
        if self.on_open_water is not None:
            self.on_open_water(mean, info)

    @staticmethod
    def _iterations(processing: ProcessingConfig, profile: CalibrationProfile) -> int | None:
        """Passes of backscatter compensation: as configured, else wherever the profile knows the
        water's light (:func:`uwcam.backscatter_loop.compensation_iterations`); None: none."""
        from uwcam.backscatter_loop import compensation_iterations

        return compensation_iterations(None if processing.backscatter is None else processing.backscatter.iterations, profile)

    @classmethod
    def _make_compensator(cls, processing: ProcessingConfig, profile: CalibrationProfile, frame_shape: tuple[int, ...],
                          open_water: NDArray | None):
        """A backscatter compensator for frames of ``frame_shape`` (H, W, N), with the open-water
        frame if it is of that shape."""
        from uwcam.backscatter_loop import BackscatterCompensator

        water = open_water if open_water is not None and open_water.shape == tuple(frame_shape) else None
        return BackscatterCompensator(profile, tuple(frame_shape[:2]), cls._iterations(processing, profile), water,
                                      pair=processing.pair, path_length_bounds=processing.path_length_bounds)

    def _compensation(self, frame: Frame, processing: ProcessingConfig, profile: CalibrationProfile,
                      estimator: RangeEstimator, ambient: NDArray | None) -> tuple:
        """(the transform of range_frame that subtracts backscatter or None, the open-water light
        each pixel is judged against or None, the frame's light over the model's per channel or None)."""
        from uwcam.backscatter_loop import compensation, light_scale

        exposure = self.open_water_info.get("exposure")
        if self._iterations(processing, profile) is None:
            return None, None, None
        comp = self._compensator
        if comp is None or comp.shape != frame.data.shape[:2]:
            comp = self._make_compensator(processing, profile, frame.data.shape, self.open_water)
            self._compensator = comp
        # The modelled backscatter is in the counts of the light it came from: scaled to this frame's exposure.
        scale = light_scale(profile, estimator, frame.light_gathered(), comp.open_water, exposure)
        return compensation(comp, estimator, ambient, scale, self._compensation_ms), comp.water, scale

    def _light_before_footprint(self, frame: Frame, corrector, transform, ambient: NDArray | None,
                                scale: NDArray | None) -> NDArray | None:
        """The light (DN) in the rangefinder's footprint that is not the surface's: the ambient
        light and, where backscatter is subtracted before ranging, the water's own light in front
        of a surface at the reading's range. The corrector's log constants must describe the
        surface's light alone, as the ranges they enter are made from it: fitted to light with the
        water's in it, they absorbed the backscatter that compensation then subtracts again
        (Jerlov IB, seabed at 2 m: +3.4 % in the middle of the view)."""
        comp = self._compensator
        reading = corrector.rangefinder.latest()
        if transform is None or comp is None or reading is None or not np.isfinite(reading.range_m):
            return ambient
        x, y, w, h = corrector.config.footprint
        # The reading's range over the footprint's blocks, open water (no surface) elsewhere.
        at = np.full(frame.data.shape[:2], np.nan, np.float32)
        at[y : y + h, x : x + w] = reading.range_m
        water = comp.level(at, scale=1.0 if scale is None else np.asarray(scale, np.float32))
        return water if ambient is None else water + ambient

    def backscatter_status(self) -> dict:
        """Whether backscatter is compensated, with what, and its cost per frame."""
        iterations = self._iterations(self.processing, self.profile)
        info = dict(self.open_water_info)
        if "monotonic" in info:
            info["age_s"] = round(time.monotonic() - info.pop("monotonic"), 1)
        ms = list(self._compensation_ms)
        # Compensated wherever the profile knows the water's light, asked for or not (a range with
        # that light left in reads short): "configured" says whether the settings asked for it.
        return {"enabled": iterations is not None, "iterations": iterations,
                "configured": self.processing.backscatter is not None,
                "open_water": info or None,
                "model": None if iterations is None else ("open-water frame and black-patch measurements" if self.open_water is not None
                                                       else "black-patch measurements of the calibration"),
                "ms_per_frame": round(float(np.median(ms)), 2) if ms else None,
                "capture": "capturing" if self._pending_open_water() is not None else self._open_water_capture}

    def subscribe(self, callback: Callable[[Published], None]) -> None:
        """``callback(published)`` from the processing thread; it must not block."""
        self._subscribers.append(callback)

    def unsubscribe(self, callback: Callable[[Published], None]) -> None:
        if callback in self._subscribers:
            self._subscribers.remove(callback)

    def subscribe_unranged(self, callback: Callable[[Frame, str], None]) -> None:
        """``callback(frame, why)`` from the processing thread for every frame taken from the camera
        that gets no range: "skipped for newer" or "lamp off". With :meth:`subscribe`, a recorder
        sees every frame the camera delivered (lamp-off frames carry the ambient light). Must not block."""
        self._unranged_subscribers.append(callback)

    def unsubscribe_unranged(self, callback: Callable[[Frame, str], None]) -> None:
        if callback in self._unranged_subscribers:
            self._unranged_subscribers.remove(callback)

    def _unranged(self, frame: Frame, why: str) -> None:
        for callback in list(self._unranged_subscribers):
            callback(frame, why)

    @property
    def latest(self) -> Published | None:
        with self._lock:
            return self._latest

    def start(self) -> None:
        self._started_s = time.monotonic()
        if self._lamp_commander is not None:
            self._lamp_commander.start()
        self._thread = threading.Thread(target=self._run, name="frame-pipeline", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10.0)
        if self._open_water_thread is not None:
            self._open_water_thread.join(timeout=10.0)
        if self._lamp_commander is not None:
            self._lamp_commander.stop()

    def _run(self) -> None:
        next_release = next_compiler_release = time.monotonic()
        while not self._stop.is_set():
            if time.monotonic() >= next_release:
                release_free_memory()  # ~0.1 ms: keeps resident memory at what frames in flight need
                next_release = time.monotonic() + 1.0
            if self.processed and time.monotonic() >= next_compiler_release:
                # Kernels are loaded once a frame is ranged; later ones (settings changed, another
                # output started) are caught by the next round. ~0.1 ms when nothing came back.
                release_compiler_pages()
                next_compiler_release = time.monotonic() + 30.0
            frame = self.camera.get(timeout_s=0.25)
            if frame is None:
                continue
            while time.monotonic_ns() - frame.host_monotonic_ns > QUEUED_FRAME_BUDGET_S * 1e9:
                newer = self.camera.get(timeout_s=0.0)
                if newer is None:
                    break
                self.skipped += 1  # too old to be worth its latency, and a newer one waits
                self._unranged(frame, "skipped for newer")
                frame = newer
            try:
                self._process(frame)
            except Exception:  # one bad frame must not stop the loop
                log.exception("processing frame %s failed", frame.sequence)

    def _dark_frame_due(self, frame: Frame, interval: int) -> bool:
        """Run the lamp-off cycle; True if ``frame`` is not to be ranged (taken as the ambient frame,
        or still dark for a moment while the lamp comes back on).

        Lamp commands only ever *request* a change from the lamp commander: a lamp that does not
        answer delays the cycle, never the loop. Every other frame is ranged and published, lit
        or not, so the stream and status show what the camera sees (a lamp stuck off gives frames
        whose pixels are marked too dark, not silence)."""
        commander = self._lamp_commander
        if self._cycle == "lit":
            if frame.lamp_on is not False:
                self._lit_since_dark += 1
            if self._lit_since_dark >= interval:
                self._ticket = commander.request(False)
                self._cycle = "switching off"
            return False
        if self._cycle == "switching off":
            if commander.done(self._ticket):
                self._lamp_off_since_ns = commander.acknowledged_ns
            elif frame.lamp_on is not False:
                return False  # still lit: range it
            self._cycle, self._lit_while_dark = "dark", 0
        if self._cycle == "dark":
            dark = frame.lamp_on is False if frame.lamp_on is not None else frame.host_monotonic_ns > self._lamp_off_since_ns
            if not dark:
                self._lit_while_dark += 1
                if self._lit_while_dark > max(interval, 5):
                    # Acknowledged, yet still lit: the command was lost or the reply was another's
                    # (a lamp reconnected mid-command). Ask again rather than wait for ever.
                    log.warning("lamp acknowledged 'off' but frames are still lit; switching it off again")
                    self._ticket = commander.request(False)
                    self._cycle = "switching off"
                return False  # captured before the lamp went off: an ordinary frame
            # Daylight varies smoothly across the image and slowly in time: a 5×5 box and an
            # average over dark frames keep the subtraction from adding a frame's worth of noise.
            level = cv2.blur(frame.data.astype(np.float32), (5, 5)) - self.profile.array("dark_level").astype(np.float32)
            level = level.clip(0)
            if self._ambient is None:
                # Estimates so far included daylight: start tracking afresh on corrected light,
                # or the outlier test would hold on to the biased values.
                self._ambient = level
                with self._lock:
                    if self.tracker is not None:
                        self.tracker.accepted = 0
                    if self.corrector is not None:
                        self.corrector.log_constant = None
                        self.corrector.scale = None
            else:
                self._ambient = 0.5 * (self._ambient + level)
            self._ambient_frames += 1
            self._ticket = commander.request(True)
            self._cycle = "switching on"
            return True
        # switching on
        if commander.done(self._ticket):
            self._cycle, self._lit_since_dark = "lit", 0
            return False
        # A frame or two still dark while the lamp comes on would flash an empty range map; a lamp
        # that does not come back is another matter: publish what there is.
        return frame.lamp_on is False and not commander.failing

    def _process(self, frame: Frame) -> None:
        self._frame_shape = frame.data.shape
        self._frame_integer = bool(np.issubdtype(frame.data.dtype, np.integer))
        if frame.lamp_on is None and self.lamp is not None:
            # The camera cannot know: record the lamp's last reported state with the frame.
            last = getattr(self.lamp, "last_status", None)
            frame.lamp_on = None if last is None else bool(last.on)
        with self._lock:
            estimator, tracker, processing, corrector = self.estimator, self.tracker, self.processing, self.corrector
            profile, orientation, exposure, hdr = self.profile, self.orientation, self.exposure, self._hdr
        taken = frame.exposures()[0]
        coded = None
        if estimator.response is not None and np.issubdtype(frame.data.dtype, np.integer):
            # A gamma camera: every step below (patch tracking, open water, backscatter, exposure
            # control, ranging) works on linear light (the profile's noise model is in linear DN);
            # the camera's own codes are what is shown and recorded.
            coded, frame = frame, dataclasses.replace(frame, data=estimator.response.linearise(frame.data))
        if hdr is not None:  # one exposure for all channels, bracketed: merged per channel with the frame before
            frame = hdr(frame)
        # The frame's own exposure per channel: the estimator ranges it exactly whatever it was.
        estimator.set_exposure(*frame.exposures())
        if not processing.lamp_off_interval and self._cycle != "lit":
            # The cycle was switched off halfway (lamp possibly off): end it with the lamp on.
            self._lamp_commander.request(True)
            self._cycle, self._lit_since_dark = "lit", 0
        if processing.lamp_off_interval and self._dark_frame_due(frame, processing.lamp_off_interval):
            self._unranged(frame, "lamp off")
            return
        ambient = self._ambient if processing.lamp_off_interval else None
        if tracker is not None and tracker.update(frame.data, ambient, estimator.exposure_shift):
            estimator.set_attenuation_differences(tracker.tracked)
        attenuation = tracker.tracked if tracker is not None else profile.array("attenuation_difference")
        # (The transform reads the estimator's log constants when it runs, after the corrector's.)
        transform, water, scale = self._compensation(frame, processing, profile, estimator, ambient)
        if corrector is not None:
            background = self._light_before_footprint(frame, corrector, transform, ambient, scale)
            b = corrector.update(frame, attenuation, background, estimator.exposure_shift)
            if b is not None and np.max(np.abs(b - estimator.log_constant)) > processing.reflectance.tolerance:
                estimator.set_log_constants(b)
        if frame.lamp_on is not False:
            self._take_open_water(frame, ambient, "taken on request")
        result = range_frame(estimator, frame.data, processing.smoothing, processing.smoothing_stage, ambient,
                             processing.vehicle_mask, transform, water, scale)
        if exposure is not None:
            wanted = exposure.update(frame.data, frame.exposures()[0], frame.lamp_on, profile.array("dark_level"),
                                     estimator.floor, profile.saturation_level, taken)
            if wanted is not None:
                self.camera.set_exposure(wanted)
        incidence = None
        if frame.lamp_on is not False:
            if corrector is not None:
                corrector.observe(result.range)  # the normal at the footprint, for the next reading
            if orientation is not None:
                # The surface's light alone, as the corrector's scale it is compared with: less the
                # water's own light in front of each surface where that is subtracted before ranging.
                light = ambient
                if transform is not None and self._compensator is not None:
                    light = self._compensator.level(result.range, scale=1.0 if scale is None else np.asarray(scale, np.float32))
                    light = light if ambient is None else light + ambient
                incidence = orientation.estimate(frame.data, result, corrector, light, estimator.exposure_shift)
        now = time.monotonic_ns()
        published = Published(self.processed + 1, frame if coded is None else coded, result, now, tuple(float(v) for v in attenuation),
                               tuple(float(v) for v in estimator.log_constant), ambient, incidence,
                               orientation.config.block if orientation is not None else 0,
                               None if water is None else water.source,
                               None if scale is None else tuple(float(v) for v in np.asarray(scale).ravel()),
                               self.open_water if water is not None and water.source == "open-water frame" else None)
        with self._lock:
            self._latest = published
        self.processed += 1
        self._latencies.append(published.latency_s)
        self._times.append(now / 1e9)  # monotonic seconds
        for callback in list(self._subscribers):
            callback(published)

    FPS_WINDOW_S = 2.0
    """fps is the number of frames published in this many seconds before now, per second."""

    def stats(self) -> dict:
        lat = np.array(self._latencies)
        times = list(self._times)
        now = time.monotonic()
        # Counted up to *now*: no frames lately is 0 fps, not the rate of the last frames that came.
        window = min(self.FPS_WINDOW_S, now - self._started_s) if self._started_s is not None else 0.0
        recent = sum(1 for t in times if now - t <= window)
        fps = recent / window if window > 0 else 0.0
        return {
            "processed": self.processed,
            "skipped_for_newer": self.skipped,
            "fps": round(fps, 2),
            "since_last_processed_s": None if not times else round(now - times[-1], 3),
            "lamp_commands": None if self._lamp_commander is None else self._lamp_commander.status(),
            "latency_ms": None if lat.size == 0 else {"p50": round(float(np.percentile(lat, 50)) * 1e3, 2),
                                                      "p99": round(float(np.percentile(lat, 99)) * 1e3, 2)},
            "patch": None if self.tracker is None else self.tracker.status(),
            "reflectance": None if self.corrector is None else self.corrector.status(),
            "ambient_frames": self._ambient_frames,
            "backscatter": self.backscatter_status(),
            "orientation": {"enabled": False} if self.orientation is None else self.orientation.status(),
            "exposure": self.exposure_status(),
        }

    def exposure_status(self) -> dict:
        """The exposure controller's state, or where exposure control stands without it."""
        exposure = self.exposure
        if exposure is not None:
            return exposure.status()
        control = getattr(self.camera, "exposure_control", "")
        return {"enabled": False, "control": control or None,
                "state": "off" if control else "the camera's exposure cannot be set while streaming"}
