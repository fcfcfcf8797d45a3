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

import cv2
import numpy as np
from numpy.typing import NDArray

from uwcam.config import ProcessingConfig
from uwcam.drivers.base import Frame
from uwcam.drivers.supervisor import SupervisedCamera
from uwcam.runtime.lamp_control import LampCommander
from uwcam.runtime.memory import release_compiler_pages, release_free_memory
from uwcam.calibration.profile import CalibrationProfile, check_intrinsics_fit
from uwcam.ranging.estimator import RangeEstimator, range_frame
from uwcam.runtime.published import Published
from uwcam.runtime.stages.compensation import CompensationStage, UnrelatedExposure
from uwcam.runtime.stages.orientation import OrientationEstimator
from uwcam.runtime.stages.patch_tracker import PatchTracker
from uwcam.runtime.stages.reflectance import ReflectanceCorrector
from uwcam.runtime.stages.temporal import TemporalFuser, frames_summary
from uwcam.runtime.warm_up import warm_up_ranging

QUEUED_FRAME_BUDGET_S = 0.030
"""A frame that waited longer than this (seconds since capture) is skipped when a newer one is
already queued. Younger frames are ranged in order: a hiccup of the loop (a scrape, a snapshot
encoded, the garbage collector) then costs a few milliseconds of latency instead of frames, while
a loop that cannot keep up falls back to the newest frame and its latency stays bounded."""

log = logging.getLogger(__name__)


class FramePipeline(CompensationStage):
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
        # the profile knows the water's light (uwcam.water.frame_compensator.compensation_iterations).
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
        self._exposure_refusal: str | None = None  # why frames are not ranged: see CompensationStage._compensation
        self._frame_shape: tuple[int, ...] | None = None
        """(H, W, N) of the last frame taken, for building the compensator before it is needed."""
        self._frame_kind: tuple[np.dtype, bool, bool] | None = None
        """(pixel type, read-only, C-contiguous) of the last frame taken (None: no frame yet): the
        kernels a settings change compiles for, and whether frames hold integer DN, to check
        profiles against."""
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
        self.motion: Callable[[], tuple[float | None, float | None]] | None = None
        """The vehicle's (angular speed rad/s, speed m/s) as the autopilot reports them (MAVLink), for
        temporal fusion to start afresh when the vehicle moves; None: not known."""

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
        # A response curve gives each code its own width (uwcam.imaging.response): its step 0 is right.
        integer = self._frame_kind is not None and np.issubdtype(self._frame_kind[0], np.integer)
        if integer and profile.quantisation_step == 0 and profile.response is None:
            raise ValueError(f"profile '{profile.name}' has quantisation_step 0 (float data) but the camera delivers "
                             "integer values; calibrate with this camera")
        estimator = RangeEstimator(profile, pair=processing.pair, path_length_bounds=processing.path_length_bounds)
        tracker = PatchTracker(processing.patch, profile) if processing.patch else None
        beam = processing.orientation.beam_half_angle_deg if processing.orientation else None
        corrector = ReflectanceCorrector(processing.reflectance, profile, self.rangefinder, beam) if processing.reflectance else None
        orientation = OrientationEstimator(processing.orientation, profile) if processing.orientation else None
        # A new fuser starts every pixel afresh: frames ranged with other settings or another profile
        # are not averaged with the next ones (the settings may change what a frame's values mean).
        temporal = TemporalFuser(processing.temporal) if processing.temporal else None
        return estimator, tracker, corrector, orientation, temporal

    def _apply(self, processing: ProcessingConfig, profile: CalibrationProfile | None = None) -> None:
        profile = profile or self.profile
        estimator, tracker, corrector, orientation, temporal = self._build(processing, profile)
        exposure = None
        if processing.exposure is not None:
            from uwcam.runtime.stages.exposure import ExposureController

            exposure = ExposureController(processing.exposure, tuple(profile.channel_names), self.camera.exposure_control)
        from uwcam.runtime.stages.hdr import HdrMerger

        hdr = HdrMerger(profile.saturation_level) if exposure is not None and exposure.bracketing else None
        # Compile or load the kernels the paths these settings take (smoothing, fusion, water light)
        # need for the frames the camera gives, and build lookup tables, here, in the caller's thread
        # (an API request), not in the loop, which would stall for seconds. Before the first frame
        # its kind is not known: the loop readies them for it then (_ready_for), and only for it (on
        # a cold cache every other kind costs seconds more of the first start).
        if self._frame_kind is not None:
            self._ready(estimator, processing, self._frame_kind)
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
            self.temporal = temporal
            self.exposure = exposure
            self._hdr = hdr
            # An open-water frame taken meanwhile makes the one built here stale: the loop builds anew.
            self._compensator = compensator if self.open_water is water else None

    def _ready(self, estimator: RangeEstimator, processing: ProcessingConfig, kind: tuple[np.dtype, bool, bool]) -> None:
        """Compile or load the kernels ``estimator`` needs to range frames of ``kind`` (pixel type,
        read-only, C-contiguous) with ``processing``."""
        dtype, read_only, contiguous = kind
        estimator.warm_up(dtypes=(dtype.type,), background=bool(processing.lamp_off_interval), strided=not contiguous)
        warm_up_ranging(estimator, processing, dtypes=(dtype.type,), read_only=(read_only,))

    def _ready_for(self, frame: Frame) -> None:
        """Before ranging a frame of a kind not met before (the first frame, or a camera that
        changed its pixel type): ready the kernels for it, in the loop, once."""
        kind = (frame.data.dtype, not frame.data.flags.writeable, bool(frame.data.flags.c_contiguous))
        if kind == self._frame_kind:
            return
        started = time.monotonic()
        with self._lock:
            estimator, processing = self.estimator, self.processing
        self._ready(estimator, processing, kind)
        self._frame_kind = kind
        log.info("readied the kernels for %s%s frames in %.1f s", kind[0], " read-only" if kind[1] else "",
                 time.monotonic() - started)

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
        self._ready_for(frame)
        if frame.lamp_on is None and self.lamp is not None:
            # The camera cannot know: record the lamp's last reported state with the frame.
            last = getattr(self.lamp, "last_status", None)
            frame.lamp_on = None if last is None else bool(last.on)
        with self._lock:
            estimator, tracker, processing, corrector = self.estimator, self.tracker, self.processing, self.corrector
            profile, orientation, exposure, hdr = self.profile, self.orientation, self.exposure, self._hdr
            temporal = self.temporal
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
        try:
            transform, water, scale = self._compensation(frame, processing, profile, estimator, ambient)
        except UnrelatedExposure:  # an open-water frame asked for is what relates it: still taken
            if frame.lamp_on is not False:
                self._take_open_water(frame, ambient, "taken on request")
            self._unranged(frame, "exposure unknown to the backscatter model")
            return
        if corrector is not None:
            background = self._light_before_footprint(frame, corrector, transform, ambient, scale)
            b = corrector.update(frame, attenuation, background, estimator.exposure_shift)
            if b is not None and np.max(np.abs(b - estimator.log_constant)) > processing.reflectance.tolerance:
                estimator.set_log_constants(b)
        if frame.lamp_on is not False:
            self._take_open_water(frame, ambient, "taken on request")
        data, samples = frame.data, None
        if temporal is not None:  # the running mean of the frames over which each pixel held still
            self._judge_motion(temporal, frame, profile)
            data, samples = temporal.update(frame.data, frame.exposures(), estimator)
        result = range_frame(estimator, data, processing.smoothing, processing.smoothing_stage, ambient,
                             processing.vehicle_mask, transform, water, scale, samples, processing.smoothing_target)
        frames = None if temporal is None else temporal.frames(np.isfinite(result.range))
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
                               self.open_water if water is not None and water.source == "open-water frame" else None,
                               frames, 1 if water is None else water.frames)
        with self._lock:
            self._latest = published
        self.processed += 1
        self._latencies.append(published.latency_s)
        self._times.append(now / 1e9)  # monotonic seconds
        for callback in list(self._subscribers):
            callback(published)

    def _judge_motion(self, temporal: TemporalFuser, frame: Frame, profile: CalibrationProfile) -> None:
        """Hand temporal fusion the vehicle's reported motion, the focal length and the median range."""
        turn, speed = self.motion() if self.motion is not None else (None, None)
        intrinsics = profile.camera_intrinsics()
        # Without intrinsics a focal length of the image width (a 53° field of view) stands in.
        focal = intrinsics.fx if intrinsics is not None else float(frame.data.shape[1])
        latest = self.latest
        range_m = 1.0  # no range yet: a near surface, so that motion counts for much
        if latest is not None and speed is not None:
            sample = latest.result.range[::8, ::8]  # the median of every 64th pixel is plenty here
            sample = sample[np.isfinite(sample)]
            range_m = float(np.median(sample)) if sample.size else range_m
        temporal.judge_motion(frame.host_monotonic_ns, turn, speed, focal, range_m)

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
            "temporal": self.temporal_status(),
            "exposure": self.exposure_status(),
        }

    def temporal_status(self) -> dict:
        """Temporal fusion's state, with the frames per pixel of the latest published range."""
        temporal = self.temporal
        latest = self.latest
        if temporal is None:
            return {"enabled": False}
        frames = latest.frames if latest is not None else None
        return {**temporal.status(), **frames_summary(frames)}

    def exposure_status(self) -> dict:
        """The exposure controller's state, or where exposure control stands without it."""
        exposure = self.exposure
        if exposure is not None:
            return exposure.status()
        control = getattr(self.camera, "exposure_control", "")
        return {"enabled": False, "control": control or None,
                "state": "off" if control else "the camera's exposure cannot be set while streaming"}
