"""The daemon: devices from the configuration, the frame loop, and orderly start and stop.

With simulated devices, camera, lamp and rangefinder share one :class:`SimulatedRig`; without
a calibration profile the daemon calibrates in that simulated water at start (grey plate at
1 m and 2 m), as a crew would in a tank, and locates the scene's calibration patch.
"""

from __future__ import annotations

import glob
import logging
import os
import time

import numpy as np

from uwcam.calibration import project_plate_box
from uwcam.config import DaemonConfig, PatchConfig, ReflectanceConfig
from uwcam.drivers import registry
from uwcam.drivers.base import CameraSettings
from uwcam.drivers.sim import SimulatedRig
from uwcam.drivers.supervisor import SupervisedCamera
from uwcam.fileio import UserInputError
from uwcam.outputs.mavlink import MavlinkOutput
from uwcam.pipeline import FramePipeline
from uwcam.profile import CalibrationProfile, load_profile, save_profile
from uwcam.simulation import Lamp, water_preset
from uwcam.simulation.camera import CameraModel
from uwcam.simulation.tank import calibrate_in_simulation
from uwcam.simulation.scene import PATCH_CENTRE_M, PATCH_DISTANCE_M, PATCH_SIZE_M

log = logging.getLogger(__name__)
SIMULATED = {"sim", "sim-ascii", "sim-ping1d"}


def simulated_calibration(rig: SimulatedRig) -> CalibrationProfile:
    """Calibrate in the rig's simulated water: grey plate with black patch at 1 m and 2 m."""
    water = water_preset(rig.water, [675.0, 575.0, 475.0])
    return calibrate_in_simulation(water, Lamp(position=tuple(rig.lamp_offset)), tuple(rig.size),
                                   CameraModel(bits=rig.bits), seed_base=11)


def simulated_patch(rig: SimulatedRig) -> PatchConfig:
    """Where the seabed-patch scene's calibration patch appears, and its path length."""
    intr = rig.world.intrinsics
    x, y, w, h = project_plate_box(PATCH_CENTRE_M, (PATCH_SIZE_M, PATCH_SIZE_M), PATCH_DISTANCE_M, intr)
    inset = max(1, min(w, h) // 5)  # keep clear of the patch's blurred edges
    centre = np.array([*PATCH_CENTRE_M, PATCH_DISTANCE_M])
    path = float(np.linalg.norm(centre) + np.linalg.norm(centre - np.array(rig.lamp_offset)))
    return PatchConfig(region=(x + inset, y + inset, w - 2 * inset, h - 2 * inset), path_length_m=path)


class Daemon:
    def __init__(self, config: DaemonConfig) -> None:
        self.config = config
        self.started = time.time()
        self.rig: SimulatedRig | None = None
        self.camera: SupervisedCamera | None = None
        self.lamp = None
        self.rangefinder = None
        self.pipeline: FramePipeline | None = None
        self.mavlink: MavlinkOutput | None = None
        self.profile_name = ""
        self.profiles: dict[str, CalibrationProfile] = {}
        """Calibration profiles known to the daemon by name; the active one is ``profile_name``."""

    def _options(self, name: str, options: dict) -> dict:
        if name in SIMULATED:
            if self.rig is None:
                sim = dict(self.config.simulation)
                for key in ("size", "lamp_offset", "ambient"):
                    if key in sim:
                        sim[key] = tuple(sim[key])
                self.rig = SimulatedRig(**sim)
            return {"rig": self.rig, **options}
        return dict(options)

    def start(self) -> None:
        cfg = self.config
        try:
            driver = registry.create("camera", cfg.camera.driver, **self._options(cfg.camera.driver, cfg.camera.options))
            if cfg.lamp is not None:
                self.lamp = registry.create("lamp", cfg.lamp.driver, **self._options(cfg.lamp.driver, cfg.lamp.options))
                self.lamp.open()
            if cfg.rangefinder is not None:
                self.rangefinder = registry.create("rangefinder", cfg.rangefinder.driver,
                                                   **self._options(cfg.rangefinder.driver, cfg.rangefinder.options))
            if cfg.calibration is not None:
                profile = load_profile(cfg.calibration)
            elif self.rig is not None:
                log.info("calibrating in the simulated water")
                profile = simulated_calibration(self.rig)
            else:
                raise UserInputError("no calibration profile configured")
            self.profile_name = profile.name
            self._load_profiles_dir()
            self.profiles[profile.name] = profile
            processing = cfg.processing
            if processing.patch is None and self.rig is not None and self.rig.scene == "seabed-patch":
                processing = processing.model_copy(update={"patch": simulated_patch(self.rig)})
            if processing.reflectance is None and self.rig is not None and cfg.rangefinder is not None \
                    and cfg.rangefinder.driver in SIMULATED:
                # The simulated sonar looks along the optical axis: its footprint is the image centre.
                w, h = self.rig.size
                processing = processing.model_copy(update={"reflectance": ReflectanceConfig(
                    footprint=(w // 2 - 4, h // 2 - 4, 9, 9))})
            settings = CameraSettings(**cfg.camera.settings.model_dump())
            self.camera = SupervisedCamera(driver, settings, queue_size=cfg.camera.queue_size, watchdog_s=cfg.camera.watchdog_s)
            if self.lamp is not None:
                self.lamp.on()
                self.lamp.status()  # so status shows the lamp's own word from the start
            self.camera.start()
            if self.rangefinder is not None:
                self.rangefinder.start()
            self.pipeline = FramePipeline(self.camera, profile, processing, self.rangefinder, self.lamp)
            self.pipeline.start()
            if cfg.mavlink is not None:
                self.mavlink = MavlinkOutput(cfg.mavlink, self.pipeline)
                self.mavlink.start()
        except BaseException:
            self.stop()
            raise

    def stop(self) -> None:
        """Stop the outputs and the loop, switch the lamp off, release every device. Safe to call twice."""
        if self.mavlink is not None:
            self.mavlink.stop()
            self.mavlink = None
        if self.pipeline is not None:
            self.pipeline.stop()
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

    def save_profile(self, name: str, profile: CalibrationProfile) -> None:
        """Keep a profile by name; with a profiles folder, also write it there atomically."""
        if self.config.profiles_dir is not None:
            save_profile(profile, os.path.join(self.config.profiles_dir, f"{name}.yaml"))
        self.profiles[name] = profile

    def _created(self) -> str | None:
        profile = self.profiles.get(self.profile_name)
        return None if profile is None else profile.provenance.created

    def activate(self, name: str) -> None:
        profile = self.profiles[name]
        active = self.profiles[self.profile_name]
        if len(profile.channels) != len(active.channels):
            raise UserInputError(f"profile {name} has {len(profile.channels)} channels but the camera delivers "
                                 f"{len(active.channels)}; upload a profile made with this camera")
        self.pipeline.set_profile(profile)
        self.profile_name = name

    def status(self) -> dict:
        camera = self.camera.status() if self.camera else None
        rf = None
        if self.rangefinder is not None:
            reading = self.rangefinder.latest()
            rf = {"health": self.rangefinder.health.as_dict(),
                  "range_m": None if reading is None else reading.range_m,
                  "confidence": None if reading is None else reading.confidence,
                  "age_s": None if reading is None else round(reading.age_s, 3)}
        lamp = None
        if self.lamp is not None:
            last = self.lamp.last_status
            lamp = {"health": self.lamp.health.as_dict(), "on": None if last is None else last.on,
                    "percent": None if last is None else last.percent}
        stats = self.pipeline.stats() if self.pipeline else {}
        cam_stats = camera["stats"] if camera else {}
        return {
            "uptime_s": round(time.time() - self.started, 1),
            "camera": camera,
            "frames": {"captured": cam_stats.get("captured", 0), "processed": stats.get("processed", 0),
                       "dropped": cam_stats.get("dropped", 0) + stats.get("skipped_for_newer", 0),
                       "fps": stats.get("fps", 0.0)},
            "latency_ms": stats.get("latency_ms"),
            "calibration": {"name": self.profile_name, "created": self._created(), "tracking": stats.get("patch"),
                            "reflectance": stats.get("reflectance")},
            "rangefinder": rf,
            "lamp": lamp,
            "mavlink": self.mavlink.status() if self.mavlink is not None else None,
        }
