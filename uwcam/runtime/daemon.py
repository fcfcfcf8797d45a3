"""The daemon: devices from the configuration, the frame loop, and orderly start and stop.

With simulated devices, camera, lamp and rangefinder share one :class:`SimulatedRig`; without
a calibration profile the daemon calibrates in that simulated water at start (grey plate at
1 m and 2 m), as a crew would in a tank, and locates the scene's calibration patch.
"""

from __future__ import annotations

import glob
import json
import logging
import os
import threading
import time
from typing import TYPE_CHECKING

import numpy as np

from uwcam.config import DaemonConfig, ProcessingConfig, ReflectanceConfig
from uwcam.drivers import registry
from uwcam.drivers.base import CameraSettings, ConfigurationError, DriverError
from uwcam.drivers.supervisor import SupervisedCamera
from uwcam.fileio import UserInputError, atomic_write
from uwcam.outputs.mavlink import MavlinkOutput
from uwcam.runtime.background_warm_up import BackgroundWarmUp
from uwcam.runtime.pipeline import FramePipeline
from uwcam.calibration.profile import CalibrationProfile, load_profile, save_profile
from uwcam.runtime.simulated_rig import PATCH_SCENES, simulated_calibration, simulated_patch, simulated_vehicle_mask
from uwcam.runtime.state import SavedState, load_state, remove_stale_temporaries, save_state

# The simulation (renderer, water models) is imported only where a simulated device is
# configured, so that a real rig does not carry it in memory.
if TYPE_CHECKING:
    from uwcam.drivers.sim import SimulatedRig

log = logging.getLogger(__name__)
SIMULATED = {"sim", "sim-ascii", "sim-ping1d"}


def check_devices(config: DaemonConfig) -> dict[str, dict]:
    """Validate what a configuration asks of the drivers, touching no device: each driver exists
    in the registry and its options fit the driver's ``Options``. Returns the validated options by kind; UserInputError
    (one line: which driver, which key, what is wrong) otherwise."""
    validated = {}
    for kind, device in (("camera", config.camera), ("lamp", config.lamp), ("rangefinder", config.rangefinder)):
        if device is None:
            continue
        try:
            validated[kind] = registry.validate_options(kind, device.driver, device.options)
        except ConfigurationError as exc:
            raise UserInputError(str(exc)) from None
    # The simulation section's keys, numbers and water preset are checked where the configuration
    # is validated (uwcam.simulation.options).
    return validated


class Daemon:
    def __init__(self, config: DaemonConfig) -> None:
        self.config = config
        self.started = time.time()
        self.rig: SimulatedRig | None = None
        self.camera: SupervisedCamera | None = None
        self.lamp = None
        self.rangefinder = None
        self.pipeline: FramePipeline | None = None
        self.recorder = None
        self.foxglove = None
        self.zenoh = None
        self.alerts = None
        self.mavlink: MavlinkOutput | None = None
        self.profile_name = ""
        self.profiles: dict[str, CalibrationProfile] = {}
        """Calibration profiles known to the daemon by name; the active one is ``profile_name``."""
        self.warm_up_in_background = False
        """Start :class:`uwcam.runtime.background_warm_up.BackgroundWarmUp` (``uwcam run`` does)."""
        self.background_warm_up = BackgroundWarmUp()
        self._profiles_lock = threading.RLock()  # one profile change at a time, validated then applied
        # The open-water frame's file: each capture and each removal is a new generation, and a
        # write lands only if no later capture or removal came meanwhile (a slow write finishing
        # after DELETE must not bring the frame back at the next start).
        self._open_water_file_lock = threading.Lock()
        self._open_water_generation = 0
        self._state_lock = threading.Lock()  # one state file write at a time

    @property
    def state_dir(self) -> str | None:
        """Where state that survives a restart is kept (None: nowhere)."""
        return self.config.state_dir or self.config.profiles_dir

    def _options(self, name: str, options: dict) -> dict:
        if name in SIMULATED:
            if self.rig is None:
                from uwcam.drivers.sim import SimulatedRig

                sim = dict(self.config.simulation)
                for key in ("size", "lamp_offset", "ambient"):
                    if key in sim:
                        sim[key] = tuple(sim[key])
                try:
                    self.rig = SimulatedRig(**sim)
                except (TypeError, ValueError) as exc:
                    raise UserInputError(f"simulation: {exc}") from None
            return {"rig": self.rig, **options}
        return dict(options)

    def _start_background_warm_up(self) -> CalibrationProfile | None:
        """Before the devices open, where the profile is at hand without them (a file, or the one
        that ships for the simulated rig): the child then compiles beside the start's own compiling
        (the simulator's), on the other core; otherwise once the profile is known. Returns the profile
        it read, if any (the start uses a configured file's, not a second read)."""
        cfg = self.config
        try:
            if cfg.calibration is not None:
                profile = load_profile(cfg.calibration)
            elif cfg.camera.driver in SIMULATED:
                from uwcam.runtime.simulated_rig import shipped_calibration_path

                path = shipped_calibration_path(self._options(cfg.camera.driver, {})["rig"])
                if not os.path.exists(path):
                    return None
                profile = load_profile(path)
            else:
                return None
        except UserInputError:
            return None  # the start says what is wrong, below
        self.background_warm_up.start(profile, cfg.processing)
        return profile

    def start(self) -> None:
        cfg = self.config
        for folder in {cfg.profiles_dir, self.state_dir} - {None}:
            if os.path.isdir(folder):
                remove_stale_temporaries(folder)
        saved = load_state(self.state_dir) if self.state_dir else None
        options = check_devices(cfg)
        if cfg.zenoh is not None:  # before any device opens: a missing library is a set-up error
            from uwcam.outputs.zenoh_publisher import require_zenoh

            require_zenoh()
        try:
            configured = self._start_background_warm_up() if self.warm_up_in_background else None
            driver = registry.create("camera", cfg.camera.driver, **self._options(cfg.camera.driver, options["camera"]))
            if cfg.lamp is not None:
                lamp = registry.create("lamp", cfg.lamp.driver, **self._options(cfg.lamp.driver, options["lamp"]))
                try:
                    lamp.open()
                except BaseException:  # never opened: nothing to switch off, only to release
                    lamp.close()
                    raise
                self.lamp = lamp
            if cfg.rangefinder is not None:
                self.rangefinder = registry.create("rangefinder", cfg.rangefinder.driver,
                                                   **self._options(cfg.rangefinder.driver, options["rangefinder"]))
            if cfg.calibration is not None:
                profile = configured if configured is not None else load_profile(cfg.calibration)
            elif self.rig is not None:
                profile = simulated_calibration(self.rig)
            else:
                raise UserInputError("no calibration profile configured")
            self.profile_name = profile.name
            if self.warm_up_in_background and self.background_warm_up.state == "not started":
                self.background_warm_up.start(profile, cfg.processing)
            self._load_profiles_dir()
            self.profiles[profile.name] = profile
            if saved is not None and saved.profile in self.profiles and saved.profile != profile.name:
                restored = self.profiles[saved.profile]
                if len(restored.channels) == len(profile.channels):
                    log.info("restoring the active calibration profile %s", saved.profile)
                    profile, self.profile_name = restored, saved.profile
                else:
                    log.warning("saved active profile %s does not fit this camera; using %s", saved.profile, profile.name)
            processing = cfg.processing
            if processing.patch is None and self.rig is not None and self.rig.scene in PATCH_SCENES:
                processing = processing.model_copy(update={"patch": simulated_patch(self.rig)})
                if not processing.vehicle_mask:
                    processing = processing.model_copy(update={"vehicle_mask": simulated_vehicle_mask(self.rig)})
            if processing.reflectance is None and self.rig is not None and cfg.rangefinder is not None \
                    and cfg.rangefinder.driver in SIMULATED and self.rig.scene != "plate":
                # (Not in the tank: the plate is the calibration's own material, and a profile made
                # there must range it unaided, or the tank could not tell a bad profile.)
                # The simulated sonar looks along the optical axis: its footprint is the image centre.
                w, h = self.rig.size
                processing = processing.model_copy(update={"reflectance": ReflectanceConfig(
                    footprint=(w // 2 - 4, h // 2 - 4, 9, 9))})
            settings = CameraSettings(**cfg.camera.settings.model_dump())
            self.camera = SupervisedCamera(driver, settings, queue_size=cfg.camera.queue_size, watchdog_s=cfg.camera.watchdog_s)
            # Built before the camera starts: the pipeline readies its kernels now, not on the first frames.
            self.pipeline = self._restored_pipeline(profile, processing, saved)
            self._restore_open_water()
            self.pipeline.on_open_water = self._keep_open_water
            if self.lamp is not None:
                self._start_lamp(saved)
            self.camera.start()
            if self.rangefinder is not None:
                self.rangefinder.start()
            self._start_outputs()
            self.pipeline.start()
            if cfg.mavlink is not None:
                self.mavlink = MavlinkOutput(cfg.mavlink, self.pipeline)
                self.pipeline.motion = self.mavlink.motion  # the vehicle's motion, for temporal fusion
                self.mavlink.start()
            self._start_alerts()
        except BaseException:
            self.stop()
            raise

    def _start_lamp(self, saved: SavedState | None) -> None:
        """Lamp on at the saved intensity; a lamp that does not answer is reported, not fatal:
        ranging works from whatever light there is, and the loop retries the lamp."""
        try:
            if saved is not None and saved.lamp_percent is not None:
                self.lamp.set_intensity(saved.lamp_percent)
            self.lamp.on()
            self.lamp.status()  # so status shows the lamp's own word from the start
        except DriverError as exc:
            if isinstance(exc, ConfigurationError):
                raise
            log.error("lamp does not answer at start: %s; its health in /api/v1/status says when it does", exc)

    def _restored_pipeline(self, profile: CalibrationProfile, processing: ProcessingConfig,
                           saved: SavedState | None) -> FramePipeline:
        if saved is not None and saved.processing is not None:
            try:
                restored = ProcessingConfig.model_validate(saved.processing)
                pipeline = FramePipeline(self.camera, profile, restored, self.rangefinder, self.lamp)
                log.info("restored the processing settings saved before the last stop")
                return pipeline
            except ValueError as exc:  # includes pydantic's ValidationError
                log.warning("saved processing settings no longer apply (%s); using the configuration's",
                            str(exc).splitlines()[0])
        try:
            return FramePipeline(self.camera, profile, processing, self.rangefinder, self.lamp)
        except ValueError as exc:  # settings that do not fit the profile (a pair of unknown channels)
            raise UserInputError(f"processing: {exc}") from None

    OPEN_WATER_FILE = "open-water.npz"
    """Beside the state file: the open-water frame backscatter compensation uses, with its origin."""

    def _restore_open_water(self) -> None:
        if self.state_dir is None:
            return
        path = os.path.join(self.state_dir, self.OPEN_WATER_FILE)
        if not os.path.exists(path):
            return
        try:
            with np.load(path, allow_pickle=False) as saved:
                frame, info = saved["frame"], json.loads(str(saved["info"]))
            if frame.ndim != 3 or frame.shape[-1] != len(self.pipeline.profile.channels) or not np.all(np.isfinite(frame)):
                raise ValueError(f"a {frame.shape} frame does not fit the {len(self.pipeline.profile.channels)}-channel profile")
        except (OSError, ValueError, KeyError) as exc:
            log.warning("ignoring the saved open-water frame %s: %s", path, exc)
            return
        info.pop("monotonic", None)
        self.pipeline.set_open_water(frame, {**info, "restored_from": path})
        log.info("restored the open-water frame taken %s", info.get("source", "earlier"))

    def _keep_open_water(self, frame: np.ndarray, info: dict) -> None:
        """Called by the frame loop when it has taken an open-water frame: written atomically in
        a thread of its own (megabytes; the loop must not wait for the disk)."""
        if self.state_dir is None:
            return
        path = os.path.join(self.state_dir, self.OPEN_WATER_FILE)
        kept = {k: v for k, v in info.items() if k != "monotonic"}
        with self._open_water_file_lock:
            self._open_water_generation += 1
            generation = self._open_water_generation

        def write() -> None:
            # Held through the write: a removal waits for it, then removes what it wrote.
            with self._open_water_file_lock:
                if generation != self._open_water_generation:
                    return  # a later capture or a removal came first: this frame is no longer the one in use
                try:
                    with atomic_write(path) as f:
                        np.savez(f, frame=frame, info=np.array(json.dumps(kept)))
                except OSError as exc:
                    log.error("could not keep the open-water frame in %s: %s", path, exc)

        threading.Thread(target=write, name="open-water-writer", daemon=True).start()

    def forget_open_water(self) -> None:
        """Stop using the open-water frame and remove its file (after a write in progress, so it
        cannot come back at the next start). Blocks for that write: call it off the event loop."""
        self.pipeline.set_open_water(None)
        if self.state_dir is not None:
            with self._open_water_file_lock:
                self._open_water_generation += 1
                try:
                    os.unlink(os.path.join(self.state_dir, self.OPEN_WATER_FILE))
                except FileNotFoundError:
                    pass

    def save_state(self) -> None:
        """Persist live settings, the active profile and the lamp's intensity (if there is a state
        folder). A failure to write is logged: the change itself has been made."""
        if self.state_dir is None or self.pipeline is None:
            return
        last = getattr(self.lamp, "last_status", None) if self.lamp is not None else None
        state = SavedState(processing=self.pipeline.processing.model_dump(mode="json"), profile=self.profile_name,
                           lamp_percent=None if last is None else int(last.percent))
        try:
            with self._state_lock:
                save_state(self.state_dir, state)
        except OSError as exc:
            log.error("could not save state in %s: %s", self.state_dir, exc)

    def _start_outputs(self) -> None:
        """The recorder (idle until asked, or recording from the start), the Foxglove server and
        the Zenoh publisher."""
        from uwcam.recording.recorder import Recorder

        self.recorder = Recorder(self.pipeline, self.config.recording, status=self.status, rangefinder=self.rangefinder,
                                 mounting=self.config.mounting)
        if self.config.recording.start_file:
            self.recorder.start(self.config.recording.start_file)
        if self.config.foxglove.enabled:
            from uwcam.outputs.foxglove import FoxgloveOutput

            self.foxglove = FoxgloveOutput(self.pipeline, self.config.foxglove, status=self.status,
                                           rangefinder=self.rangefinder)
            self.foxglove.start()
        if self.config.zenoh is not None:
            from uwcam.outputs.zenoh_publisher import ZenohOutput

            self.zenoh = ZenohOutput(self.pipeline, self.config.zenoh, status=self.status)
            self.zenoh.start()

    def _start_alerts(self) -> None:
        """The alert monitor, last: every output its events go to is running by then."""
        if self.config.alerts.enabled:
            from uwcam.outputs.alert_monitor import AlertMonitor

            self.alerts = AlertMonitor(self.pipeline, self.config.alerts, status=self.status, sinks=[self._send_alert])
            self.alerts.start()

    def _send_alert(self, event, active) -> None:
        """An alert raised or cleared, to Zenoh ``alerts`` and MAVLink STATUSTEXT where configured.
        In the alert monitor's thread; both only queue it for their own threads."""
        if self.zenoh is not None:
            self.zenoh.offer_alerts(event, active)
        if self.mavlink is not None:
            self.mavlink.offer_statustext(event.severity if event.state == "raised" else "info", f"uwcam: {event.message}")

    def stop(self) -> None:
        """Stop the outputs and the loop, switch the lamp off, release every device. Safe to call twice."""
        self.background_warm_up.stop()
        if self.alerts is not None:
            self.alerts.close()  # first: its events go to the outputs stopped below
            self.alerts = None
        if self.mavlink is not None:
            self.mavlink.stop()
            self.mavlink = None
        if self.pipeline is not None:
            self.pipeline.stop()
        for output in (self.recorder, self.foxglove, self.zenoh):
            if output is not None:
                output.close()  # after the loop: everything it published is written
        if self.camera is not None:
            self.camera.stop()
        if self.rangefinder is not None:
            self.rangefinder.stop()
            self.rangefinder = None
        if self.lamp is not None:
            try:
                self.lamp.off()
            except Exception as exc:  # report, but finish shutting down
                log.error("could not switch the lamp off: %s", exc)
            self.lamp.close()
            self.lamp = None

    def _load_profiles_dir(self) -> None:
        folder = self.config.profiles_dir
        if folder is None:
            return
        os.makedirs(folder, exist_ok=True)
        for path in sorted(glob.glob(os.path.join(folder, "*.yaml"))):
            try:
                self.profiles[os.path.splitext(os.path.basename(path))[0]] = load_profile(path)
            except UserInputError as exc:  # one bad file must not stop the vehicle's camera
                log.warning("skipping calibration profile: %s", exc)

    def check_profile(self, name: str, profile: CalibrationProfile) -> None:
        """UserInputError unless ``profile`` can range this camera's frames with the live settings."""
        active = self.profiles[self.profile_name]
        if len(profile.channels) != len(active.channels):
            raise UserInputError(f"profile {name} has {len(profile.channels)} channels but the camera delivers "
                                 f"{len(active.channels)}; upload a profile made with this camera")
        if self.pipeline is not None:
            try:
                self.pipeline.check(profile=profile)
            except ValueError as exc:
                raise UserInputError(f"profile {name} does not fit the processing settings: {exc}") from None

    def save_profile(self, name: str, profile: CalibrationProfile) -> None:
        """Keep a profile by name; with a profiles folder, also write it there atomically. Replacing
        the active profile is checked like activating it and takes effect at once; nothing changes
        if it is refused."""
        with self._profiles_lock:
            active = name == self.profile_name
            if active:
                self.check_profile(name, profile)
            if self.config.profiles_dir is not None:
                save_profile(profile, os.path.join(self.config.profiles_dir, f"{name}.yaml"))
            if active:
                self.pipeline.set_profile(profile)
            self.profiles[name] = profile

    def _created(self) -> str | None:
        profile = self.profiles.get(self.profile_name)
        return None if profile is None else profile.provenance.created

    def activate(self, name: str) -> None:
        """Range with profile ``name`` from the next frame on; validated in full first, so a
        refusal (UserInputError) changes nothing."""
        with self._profiles_lock:
            profile = self.profiles[name]
            self.check_profile(name, profile)
            try:
                self.pipeline.set_profile(profile)
            except ValueError as exc:
                raise UserInputError(f"profile {name} does not fit the processing settings: {exc}") from None
            self.profile_name = name
        self.save_state()

    def status(self) -> dict:
        camera = self.camera.status() if self.camera else None
        # Each device read once: stop() clears them while outputs may still ask for status.
        rangefinder, lamp_driver = self.rangefinder, self.lamp
        rf = None
        if rangefinder is not None:
            reading = rangefinder.latest()
            rf = {"health": rangefinder.health.as_dict(),
                  "range_m": None if reading is None else reading.range_m,
                  "confidence": None if reading is None else reading.confidence,
                  "age_s": None if reading is None else round(reading.age_s, 3)}
        lamp = None
        stats = self.pipeline.stats() if self.pipeline else {}
        stats_lamp = stats.get("lamp_commands")
        if lamp_driver is not None:
            last = lamp_driver.last_status
            lamp = {"health": lamp_driver.health.as_dict(), "on": None if last is None else last.on,
                    "percent": None if last is None else last.percent, "commands": stats_lamp}
        cam_stats = camera["stats"] if camera else {}
        return {
            "uptime_s": round(time.time() - self.started, 1),
            "camera": camera,
            "frames": {"captured": cam_stats.get("captured", 0), "processed": stats.get("processed", 0),
                       "dropped": cam_stats.get("dropped", 0) + stats.get("skipped_for_newer", 0),
                       "fps": stats.get("fps", 0.0), "since_last_processed_s": stats.get("since_last_processed_s")},
            "latency_ms": stats.get("latency_ms"),
            "calibration": {"name": self.profile_name, "created": self._created(), "tracking": stats.get("patch"),
                            "reflectance": stats.get("reflectance")},
            "backscatter": stats.get("backscatter"),
            "orientation": stats.get("orientation"),
            "temporal": stats.get("temporal"),
            "exposure": stats.get("exposure"),
            "rangefinder": rf,
            "lamp": lamp,
            "recording": self.recorder.status() if self.recorder else None,
            "foxglove": self.foxglove.status() if self.foxglove else None,
            "zenoh": self.zenoh.status() if self.zenoh is not None else None,
            "alerts": self.alerts.status() if self.alerts is not None else None,
            "mavlink": self.mavlink.status() if self.mavlink is not None else None,
        }
