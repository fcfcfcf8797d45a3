"""Simulated devices: a camera rendering the simulated world, sharing it with a simulated lamp
and rangefinder so that a whole rig is consistent (lamp off → only ambient light and noise;
the rangefinder measures the scene the camera sees).

The simulated camera is a first-class driver, registered as ``sim``. Devices can be
unplugged, stalled or made to send a damaged frame, to exercise the recovery paths.
"""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass, field, replace
from typing import Annotated, Callable, NamedTuple

import numpy as np
from pydantic import Field
from numpy.typing import NDArray

from uwcam.drivers.base import (CameraDriver, CameraSettings, ConfigurationError, ConfigureReport, CorruptFrame,
                                DeviceInfo, DeviceLost, Frame, FrameTimeout)
from uwcam.drivers.options import DriverOptions as _DriverOptions
from uwcam.drivers.options import Flag as _Flag
from uwcam.drivers.options import Real as _Real
from uwcam.calibration.rig import builtin_rig_path, load_rig
from uwcam.simulation import Ambient, CameraModel, Lamp, SimulatedWorld, water_preset
from uwcam.compute.jit import set_threads
from uwcam.simulation.survey import SurveyWorld
from uwcam.simulation.terrain import SurveyMotion


# The simulated sensor's exposure time at which it has the world's auto-exposure (µs).
NOMINAL_EXPOSURE_US = 10000.0
# Exposure limits of the simulated sensor (µs).
EXPOSURE_RANGE_US = (10.0, 1e6)


class RigState(NamedTuple):
    """What a frame is rendered from, read once: lamp lit, its level 0–1, survey time (s),
    and each channel's exposure time (µs)."""

    lit: bool
    level: float
    t: float
    exposure_us: tuple[float, ...] = (NOMINAL_EXPOSURE_US,) * 3


@dataclass
class SimulatedRig:
    """One simulated world seen by camera, lamp and rangefinder alike.

    scene ``survey``: a vehicle surveying a varied seabed (:mod:`uwcam.simulation.survey`),
    moving with the rig's clock; other scenes are static, at ``distance``."""

    scene: str = "seabed"
    distance: float = 2.0
    size: tuple[int, int] = (640, 480)
    water: str = "jerlov-II"
    lamp_offset: tuple[float, float, float] = (0.3, 0.0, 0.0)
    bits: int = 16
    seed: int = 0
    material: str | None = None
    """One material for every surface (e.g. "grey", the calibration plate's hue); None: each its own."""
    ambient: tuple[float, ...] | None = None
    """Daylight from above per channel (relative to the lamp), present whether the lamp is on or not."""
    lamp_on: bool = True
    lamp_intensity: float = 1.0
    """0–1, set by the simulated lamp."""
    speed: float = 0.4
    """Survey: the vehicle's speed over ground, m/s."""
    altitude: tuple[float, float] = (1.5, 4.0)
    """Survey: lowest and highest altitude above the smooth seabed, m."""
    altitude_period: float = 120.0
    """Survey: seconds from lowest to highest and back."""
    clock: Callable[[], float] = field(default=time.monotonic, repr=False)
    """Survey time source (s); the survey starts when the world is built."""
    plate_rig: str | None = None
    """Built-in rig (e.g. "charuco-plate") drawn by the "plate" scene; None: the grey plate."""
    drift: tuple[float, ...] | None = None
    """Static scenes: how much the water's attenuation (c and G alike, 1/m per channel) changes, as a
    tide, a plume or a temperature front would: c(t) = c + drift·(1 − cos(2πt/drift_period))/2, t the
    rig's time since the world was built; None: the water never changes."""
    drift_period: float = 300.0
    """Seconds of one drift cycle (from the calibration's water to c + drift and back)."""
    exposure_us: tuple[float, ...] = (NOMINAL_EXPOSURE_US,) * 3
    """Exposure time of each channel's sensor (µs), as a 3-chip camera sets them apart;
    NOMINAL_EXPOSURE_US is the world's auto-exposure, electrons scale with the time."""
    _exposure: float | None = field(default=None, repr=False)
    _world: SimulatedWorld | SurveyWorld | None = field(default=None, repr=False)
    _drifted: tuple | None = field(default=None, repr=False)
    _t0: float = field(default=0.0, repr=False)
    _cache: dict = field(default_factory=dict, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    _place_lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    """One move of the scene at a time (rendering the new view happens outside ``_lock``)."""
    placing_to: float | None = field(default=None, repr=False)
    """Where a move announced to the operator (the tank's rail) takes the scene (m); None when it is still."""
    _lamp_lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    """Guards lamp_on and lamp_intensity together, so a frame sees one consistent lamp state."""

    def _build(self, distance: float, exposure: float | None) -> SimulatedWorld | SurveyWorld:
        wl = (675.0, 575.0, 475.0)
        common = dict(water=water_preset(self.water, list(wl)), lamp=Lamp(position=tuple(self.lamp_offset)),
                      camera=CameraModel(bits=self.bits), seed=self.seed, material=self.material,
                      ambient=None if self.ambient is None else Ambient(tuple(self.ambient)))
        if self.scene == "survey":
            motion = SurveyMotion(speed=self.speed, altitude=tuple(self.altitude), altitude_period=self.altitude_period)
            return SurveyWorld(size=tuple(self.size), motion=motion, **common)
        return SimulatedWorld(scene=self.scene, distance=distance, size=tuple(self.size), **common,
                              rig=None if self.plate_rig is None else load_rig(builtin_rig_path(self.plate_rig)),
                              fixed_exposure=exposure)

    @property
    def world(self) -> SimulatedWorld | SurveyWorld:
        with self._lock:
            if self._world is None:
                self._world = self._build(self.distance, self._exposure)
                self._t0 = self.clock()
            return self._world

    def place(self, distance: float) -> None:
        """Move the scene (e.g. the plate on a tank's rail) to ``distance`` m, keeping the exposure, as a
        crew would; every frame rendered after the return shows it.

        Once the world exists, the new view is rendered (seconds at 640×360) before it replaces
        the old one: frames keep coming from the old view meanwhile, so the camera never stalls
        while the plate moves. One move at a time."""
        if self.scene == "survey":
            raise ValueError("the survey moves by itself; only a static scene can be placed")
        with self._place_lock:
            with self._lock:
                old = self._world
            if old is None:  # nothing rendered yet: the first world exposes itself at ``distance``
                with self._lock:
                    self.distance, self._cache = float(distance), {}
                return
            new = self._build(float(distance), old.exposure)
            new.components(True)  # the slow part: rendering the view
            new.components(False)
            with self._lock:
                self._exposure, self.distance, self._world, self._cache = old.exposure, float(distance), new, {}

    def show(self, scene: str) -> None:
        """Point the camera at another scene (e.g. "open-water": nothing in range), keeping the
        exposure, as turning a real vehicle does; the next frame shows it."""
        with self._lock:
            self._exposure = None if self._world is None else self._world.exposure
            self.scene = scene
            self._world = None
            self._cache = {}

    @property
    def moving(self) -> bool:
        return self.scene == "survey"

    def now(self) -> float:
        """Survey time (s) since the world was built."""
        _ = self.world
        return self.clock() - self._t0

    def snapshot(self) -> RigState:
        """The lamp state and the survey time, read once, atomically: a frame is rendered from
        this and labelled with it, so a lamp switched mid-frame cannot relabel a lit frame."""
        t = self.now()
        with self._lamp_lock:
            on = self.lamp_on and self.lamp_intensity > 0
            return RigState(on, round(self.lamp_intensity, 2) if on else 0.0, t, tuple(self.exposure_us))

    def set_exposure(self, exposure_us: tuple[float, ...]) -> None:
        """Each channel's exposure time (µs), within EXPOSURE_RANGE_US; from the next frame on."""
        values = tuple(float(v) for v in exposure_us)
        low, high = EXPOSURE_RANGE_US
        if len(values) != len(self.exposure_us) or not all(low <= v <= high for v in values):
            raise ConfigurationError(f"the simulated camera needs {len(self.exposure_us)} exposure times from "
                                     f"{low:g} to {high:g} µs, got {list(values)}")
        with self._lamp_lock:
            self.exposure_us = values

    def render(self, state: RigState, index: int) -> NDArray:
        """Frame number ``index`` (the noise counter) of the rig in ``state``, (H, W, 3)."""
        world = self.world
        scale = np.asarray(state.exposure_us, np.float64) / NOMINAL_EXPOSURE_US
        if isinstance(world, SurveyWorld):
            return world.frame(state.t, index, state.level, exposure_scale=None if np.all(scale == 1) else scale)
        mean, std = self.expected((state.lit, state.level), state.exposure_us, self._drift_step(state.t))
        return world.camera.digitise(mean, std, world.seed, index)

    DRIFT_STEP_S = 0.25
    """The drifting water is rendered anew every this many seconds of rig time."""

    def _drift_step(self, t: float) -> int:
        return 0 if self.drift is None else int(t // self.DRIFT_STEP_S)

    def water_change(self, t: float) -> NDArray[np.float64]:
        """(N,) the change of the water's attenuation (1/m) at rig time ``t`` (s), as rendered."""
        if self.drift is None:
            return np.zeros(3)
        t = self._drift_step(t) * self.DRIFT_STEP_S
        return np.asarray(self.drift, np.float64) * (1.0 - np.cos(2.0 * np.pi * t / self.drift_period)) / 2.0

    def _world_at(self, step: int) -> SimulatedWorld:
        """The static world with its water drifted to ``step`` (see :attr:`drift`), exposure held."""
        world = self.world
        if step == 0:
            return world
        drifted = self._drifted
        if drifted is None or drifted[0] != (id(world), step):
            delta = self.water_change(step * self.DRIFT_STEP_S)
            water = world.water.with_overrides(attenuation=world.water.attenuation + delta,
                                               scatter_attenuation=world.water.scatter_attenuation + delta)
            drifted = ((id(world), step), replace(world, water=water, fixed_exposure=world.exposure))
            self._drifted = drifted
        return drifted[1]

    def set_lamp(self, on: bool | None = None, intensity: float | None = None) -> None:
        """Change the lamp (the simulated lamp device calls this); both values change together."""
        with self._lamp_lock:
            if on is not None:
                self.lamp_on = bool(on)
            if intensity is not None:
                self.lamp_intensity = float(intensity)

    def expected(self, state: tuple[bool, float] | None = None, exposure_us: tuple[float, ...] | None = None,
                 drift_step: int = 0) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Static scenes: mean and σ (DN) for a lamp state (lit, level; default: the present one)
        and each channel's exposure time (µs; default: the present ones); lamp light scales with
        its level, electrons with the exposure time."""
        if state is None:
            state = self.snapshot()[:2]
        if exposure_us is None:
            exposure_us = tuple(self.exposure_us)
        on, level = state
        key = (on, level, tuple(exposure_us), drift_step)
        cache = self._cache  # place() swaps in a new dict: a world being replaced cannot write into it
        if key not in cache:
            w = self._world_at(drift_step)
            if on:
                lit = w.components(True)
                ambient = w.components(False).total
                radiance = ambient + level * (lit.total - ambient)
            else:
                radiance = w.components(False).total
            if len(cache) > 16:  # an exposure controller walks through many exposures
                cache.clear()
            scale = np.asarray(exposure_us, np.float64) / NOMINAL_EXPOSURE_US
            cache[key] = w.camera.expected(radiance, w.exposure * scale)
        return cache[key]

    def true_range(self) -> float:
        """Camera range (m) at the image centre, where the rangefinder points: for the survey,
        along the optical axis to the seabed under the vehicle now."""
        world = self.world
        if isinstance(world, SurveyWorld):
            return world.axis_range(self.now())
        truth = world.camera_range
        h, w = truth.shape
        return float(truth[h // 2, w // 2])


def _lowest_priority() -> None:
    """The calling thread at the lowest CPU priority (nice 19; Linux gives each thread its own).

    Rendering a simulated 720p frame costs most of a core: at the loop's priority, the simulated
    sensor took half of a 2-core machine from the frame loop and the page it stands in for
    hardware for. At the lowest, the loop and the server have the CPU first and the simulated
    camera delivers what is left (fewer frames, each counted as captured, when the host is short),
    as a real sensor's frames cost the host nothing to make."""
    tid = threading.get_native_id()
    try:
        if os.getpriority(os.PRIO_PROCESS, tid) < 19:
            os.setpriority(os.PRIO_PROCESS, tid, 19)
    except OSError:  # not Linux-like, or not allowed: the frames come all the same
        pass


class SimulatedCamera(CameraDriver):
    """Frames of a :class:`SimulatedRig` at ``fps``, paced on the monotonic clock."""

    class Options(_DriverOptions):
        """What ``camera.options`` may hold for ``driver: sim`` (the rig itself is set under
        ``simulation:``): checked alike by ``uwcam config check`` and ``uwcam run``."""

        fps: Annotated[_Real, Field(gt=0, le=1000)] = 10.0
        """Frames per second."""
        serial_number: Annotated[str, Field(min_length=1, max_length=64)] | None = "SIM-0001"
        one_exposure: _Flag = False

    name = "sim"
    exposure_control = "per-channel"
    # Fault injection, per serial number: shared so a test can unplug "the" device.
    _unplugged: set[str] = set()
    _stalled: set[str] = set()
    _corrupt_next: set[str] = set()

    def __init__(self, rig: SimulatedRig | None = None, fps: float = 10.0, serial_number: str | None = "SIM-0001",
                 one_exposure: bool = False, **rig_options) -> None:
        """one_exposure: behave as a camera with one exposure for all channels (a Bayer sensor)
        rather than a 3-chip camera exposing each channel apart."""
        if not fps > 0:
            raise ConfigurationError(f"sim camera fps must be positive, got {fps}")
        self.exposure_control = "common" if one_exposure else "per-channel"
        self.rig = rig or SimulatedRig(**rig_options)
        self.fps = float(fps)
        self.serial_number = serial_number
        self._open = False
        self._streaming = False
        self._sequence = 0
        self._next_due = 0.0
        self._closed = threading.Event()  # wakes a pacing wait when the camera closes

    # Fault injection (tests and demonstrations) ---------------------------------------
    @classmethod
    def unplug(cls, serial: str) -> None:
        cls._unplugged.add(serial)

    @classmethod
    def plug(cls, serial: str) -> None:
        cls._unplugged.discard(serial)

    @classmethod
    def stall(cls, serial: str, stalled: bool = True) -> None:
        (cls._stalled.add if stalled else cls._stalled.discard)(serial)

    @classmethod
    def corrupt_next(cls, serial: str) -> None:
        cls._corrupt_next.add(serial)

    # CameraDriver ---------------------------------------------------------------------
    @classmethod
    def list_devices(cls, serial_numbers: tuple[str, ...] = ("SIM-0001",), **_) -> list[DeviceInfo]:
        return [DeviceInfo(f"sim:{s}", s, "simulated 3-chip RGB", "uwcam") for s in serial_numbers if s not in cls._unplugged]

    def _check_present(self) -> None:
        if self.serial_number in self._unplugged:
            raise DeviceLost(f"simulated camera {self.serial_number} is unplugged")

    def open(self) -> DeviceInfo:
        self._check_present()
        # Build the scene (and compile the survey's kernels) now, not on the first frame.
        self.rig.render(self.rig.snapshot(), 0)
        self._open = True
        self._closed.clear()
        return DeviceInfo(f"sim:{self.serial_number}", self.serial_number or "", "simulated 3-chip RGB", "uwcam")

    def configure(self, settings: CameraSettings) -> ConfigureReport:
        report = ConfigureReport()
        if settings.frame_rate:
            self.fps = float(settings.frame_rate)
            report.applied["frame_rate"] = self.fps
        exposure = settings.channel_exposure_us or (
            None if settings.exposure_us is None else (settings.exposure_us,) * len(self.rig.exposure_us))
        if exposure is not None:
            self.set_exposure(tuple(exposure))
            report.applied["exposure_us"] = list(self.rig.exposure_us)
        for name in ("gain_db", "channel_gain_db", "pixel_format", "region", "black_level"):
            if getattr(settings, name) is not None:
                report.unsupported.append(name)  # the simulated sensor has fixed gain and format
        return report

    def set_exposure(self, exposure_us: tuple[float, ...], gain_db: tuple[float, ...] | None = None) -> None:
        if gain_db is not None and any(g != 0 for g in gain_db):
            raise ConfigurationError("the simulated camera has a fixed gain (0 dB)")
        if self.exposure_control == "common" and len(set(exposure_us)) > 1:
            raise ConfigurationError(f"this simulated camera has one exposure for all channels, got {list(exposure_us)}")
        self.rig.set_exposure(exposure_us)

    def start(self) -> None:
        self._check_present()
        self._streaming = True
        self._next_due = time.monotonic()

    def read(self, timeout_s: float) -> Frame:
        if not self._streaming:
            raise DeviceLost("simulated camera is not streaming")
        self._check_present()
        wait = self._next_due - time.monotonic()
        if self.serial_number in self._stalled or wait > timeout_s:
            self._closed.wait(timeout_s)
            self._check_present()
            raise FrameTimeout(f"no frame within {timeout_s:g} s")
        if wait > 0:
            self._closed.wait(wait)
        self._check_present()
        self._next_due = max(self._next_due + 1.0 / self.fps, time.monotonic() - 1.0 / self.fps)
        self._sequence += 1
        if self.serial_number in self._corrupt_next:
            self._corrupt_next.discard(self.serial_number)
            raise CorruptFrame("simulated damaged frame")
        # One numba thread (a per-thread setting): the simulated sensor stands in for hardware
        # that costs the host nothing, and must not compete with the frame loop for cores.
        set_threads(1)
        _lowest_priority()
        # The lamp state (and survey time) is read once: the frame is rendered from it and labelled with it.
        state = self.rig.snapshot()
        data = self.rig.render(state, self._sequence)
        world = self.rig.world
        return Frame(
            data=data, sequence=self._sequence, host_monotonic_ns=time.monotonic_ns(), wall_time=time.time(),
            device_timestamp_ns=None, exposure_us=state.exposure_us[0] if len(set(state.exposure_us)) == 1 else None,
            gain_db=0.0, lamp_on=state.lit, channel_names=("R", "G", "B"),
            bit_depth=world.camera.bits, channel_exposure_us=state.exposure_us, channel_gain_db=(0.0,) * len(state.exposure_us),
        )

    def stop(self) -> None:
        self._streaming = False

    def close(self) -> None:
        self._streaming = False
        self._open = False
        self._closed.set()
