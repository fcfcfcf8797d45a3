"""Driver interfaces: what every camera, lamp and rangefinder offers, whatever the hardware.

Drivers know nothing of optics. A camera driver is the thin layer over one SDK or device
(open, configure, start, read one frame); :class:`uwcam.drivers.supervisor.SupervisedCamera`
adds what every camera needs and most tools get wrong: one acquisition thread, a bounded
queue that drops the oldest frame, a no-frame watchdog, retries with backoff, finding the
same device again by serial number and re-applying its settings.
"""

from __future__ import annotations

import enum
import threading
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray


class DriverError(Exception):
    """A device problem; the message says what happened and what to do."""


class ConfigurationError(DriverError):
    """The configuration cannot work (unknown driver, missing producer, absent port, bad format): fatal at start."""


class DeviceLost(DriverError):
    """The device went away (unplugged, powered off, network gone). Recoverable."""


class FrameTimeout(DriverError):
    """No frame arrived in time. Recoverable; repeated, the watchdog declares the device lost."""


class CorruptFrame(DriverError):
    """A frame arrived damaged (incomplete, wrong size). Dropped and counted; the stream goes on."""


class EndOfStream(DriverError):
    """A finite source (a replayed recording played once) has no more frames."""


class HealthState(str, enum.Enum):
    OK = "ok"
    RECOVERING = "recovering"
    LOST = "lost"
    STOPPED = "stopped"


@dataclass(frozen=True)
class Health:
    """Where a device stands, why, and since when (wall clock and monotonic seconds)."""

    state: HealthState
    reason: str
    since: float = field(default_factory=time.time)
    since_monotonic: float = field(default_factory=time.monotonic)

    def as_dict(self) -> dict:
        return {"state": self.state.value, "reason": self.reason, "since": self.since,
                "for_s": round(time.monotonic() - self.since_monotonic, 3)}


class HealthTracker:
    """Thread-safe current health; a new state only when state or reason changes."""

    def __init__(self, initial: Health | None = None) -> None:
        self._lock = threading.Lock()
        self._health = initial or Health(HealthState.STOPPED, "not started")

    def set(self, state: HealthState, reason: str) -> None:
        with self._lock:
            if self._health.state != state or self._health.reason != reason:
                self._health = Health(state, reason)

    @property
    def current(self) -> Health:
        with self._lock:
            return self._health


@dataclass(frozen=True)
class DeviceInfo:
    """One device a driver can open."""

    id: str
    serial_number: str
    model: str = ""
    vendor: str = ""


@dataclass
class Frame:
    """One frame with everything needed to trust it. Timestamps in nanoseconds / seconds."""

    data: NDArray
    """(H, W, C) with C ≥ 2 at the sensor's full bit depth (uint8 or uint16)."""
    sequence: int
    """Frame counter of the device (or of the driver where the device has none)."""
    host_monotonic_ns: int
    """time.monotonic_ns() when the frame was received: ages and latencies."""
    wall_time: float
    """time.time() at receipt, for logs and humans."""
    device_timestamp_ns: int | None = None
    """The camera's own (PTP or free-running) timestamp, where it has one."""
    exposure_us: float | None = None
    """One exposure time (µs) for every channel; see :attr:`channel_exposure_us`."""
    gain_db: float | None = None
    lamp_on: bool | None = None
    channel_names: tuple[str, ...] = ("R", "G", "B")
    bit_depth: int | None = None
    channel_exposure_us: tuple[float, ...] | None = None
    """Exposure time (µs) of each channel, where channels are exposed apart (a 3-chip camera's
    sensors, a multi-device rig, a merged high-dynamic-range frame); None: ``exposure_us`` for all."""
    channel_gain_db: tuple[float, ...] | None = None
    """Analogue gain (dB) of each channel; None: ``gain_db`` for all."""

    @property
    def age_s(self) -> float:
        return (time.monotonic_ns() - self.host_monotonic_ns) / 1e9

    def exposures(self) -> tuple[tuple[float, ...] | None, tuple[float, ...] | None]:
        """(exposure µs, gain dB) per channel, each None where the frame does not say."""
        n = len(self.channel_names) if self.data.ndim < 3 else self.data.shape[-1]

        def per_channel(values: tuple[float, ...] | None, common: float | None) -> tuple[float, ...] | None:
            if values is not None:
                return tuple(float(v) for v in values)
            return None if common is None else (float(common),) * n

        return per_channel(self.channel_exposure_us, self.exposure_us), per_channel(self.channel_gain_db, self.gain_db)

    def light_gathered(self) -> NDArray[np.float64] | None:
        """Per channel, exposure × linear gain (µs): what the signal in counts is proportional to;
        None where the frame does not say its exposure (gain unknown counts as 0 dB)."""
        exposure, gain = self.exposures()
        if exposure is None:
            return None
        return np.asarray(exposure, dtype=np.float64) * 10.0 ** (np.asarray(gain or 0.0, dtype=np.float64) / 20.0)


@dataclass(frozen=True)
class CameraSettings:
    """Settings a camera is opened with and re-applied after every reconnection."""

    exposure_us: float | None = None
    gain_db: float | None = None
    pixel_format: str | None = None
    region: tuple[int, int, int, int] | None = None  # x, y, width, height
    black_level: float | None = None
    frame_rate: float | None = None
    channel_exposure_us: tuple[float, ...] | None = None
    """Exposure (µs) per channel, for cameras that expose channels apart (overrides exposure_us)."""
    channel_gain_db: tuple[float, ...] | None = None
    """Gain (dB) per channel (overrides gain_db)."""


@dataclass
class ConfigureReport:
    """What configure() did: applied settings, what the device lacks, and radiometry it could not fix.

    ``radiometry_not_disabled`` lists automatic features (auto exposure, gain, white balance,
    gamma, LUT) that are on and could not be turned off: they break intensity ratios.
    """

    applied: dict[str, object] = field(default_factory=dict)
    unsupported: list[str] = field(default_factory=list)
    radiometry_not_disabled: list[str] = field(default_factory=list)
    details: dict[str, str] = field(default_factory=dict)
    """Per setting named above, what the device did instead and what it offers (one line each)."""


class CameraDriver(ABC):
    """One camera device behind one SDK. Not thread-safe: the supervisor owns it."""

    #: Registry name, e.g. "genicam".
    name: str = ""
    #: The device to open; set after the first open so a reconnection finds the same one.
    serial_number: str | None = None

    @classmethod
    @abstractmethod
    def list_devices(cls, **options) -> list[DeviceInfo]:
        """Devices this driver can see now."""

    @abstractmethod
    def open(self) -> DeviceInfo:
        """Open the configured device; DeviceLost if absent, ConfigurationError if it can never work."""

    @abstractmethod
    def configure(self, settings: CameraSettings) -> ConfigureReport:
        """Apply settings and turn off everything that breaks radiometry."""

    @abstractmethod
    def start(self) -> None: ...

    @abstractmethod
    def read(self, timeout_s: float) -> Frame:
        """Block for the next frame: FrameTimeout, DeviceLost or CorruptFrame on failure."""

    @abstractmethod
    def stop(self) -> None: ...

    @abstractmethod
    def close(self) -> None:
        """Release the device; safe to call twice and after a failure."""

    #: How exposure can be set while streaming: "per-channel" (each channel its own, e.g. a
    #: 3-chip camera's sensors), "common" (one for all channels) or "" (not at all).
    exposure_control: str = ""

    def set_exposure(self, exposure_us: tuple[float, ...], gain_db: tuple[float, ...] | None = None) -> None:
        """Change exposure (µs) and gain (dB) per channel while streaming, from the next frame on.
        With ``exposure_control`` "common", all values must be equal. The supervisor calls this
        between reads (drivers are not thread-safe)."""
        raise ConfigurationError(f"camera driver '{self.name}' cannot change exposure while streaming")


def to_channels(data: NDArray, channels: int) -> NDArray:
    """View (H, W) or (H, W, C) as (H, W, C) keeping the first ``channels`` (drops alpha) without copying."""
    if data.ndim == 2:
        return data[:, :, None]
    return data[:, :, :channels]


def require_colour(data: NDArray, what: str) -> None:
    if data.ndim != 3 or data.shape[-1] < 2:
        raise ConfigurationError(
            f"{what} delivers one channel per pixel (monochrome); ranging needs two or more colour channels: "
            "choose a colour pixel format or a 3-chip/multi-band camera"
        )


def as_frame_array(data: NDArray) -> NDArray:
    """Frames are uint8 or uint16 at full depth."""
    if data.dtype not in (np.uint8, np.uint16):
        raise CorruptFrame(f"unexpected pixel type {data.dtype}")
    return data
