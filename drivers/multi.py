"""One registered frame from several sensors: 3-chip (prism) and multi-band cameras whose
sensors appear as separate devices or streams, each delivering one component.

Each sensor is any registered camera driver; the frame takes one channel from each, read in
turn and matched in time: a sensor whose frame is older than the newest by more than
``max_skew_ms`` is read again, so channels never mix exposures far apart.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from typing import Annotated

from pydantic import ConfigDict, Field, model_validator

from uwcam.drivers.options import ChannelNames, DriverOptions, Real, Whole
from uwcam.drivers.base import CameraDriver, CameraSettings, ConfigurationError, ConfigureReport, CorruptFrame, DeviceInfo, Frame


class MultiSensorCamera(CameraDriver):
    class Sensor(DriverOptions):
        """One sensor: a camera driver by name, the channel it gives, and that driver's options."""

        model_config = ConfigDict(extra="allow", allow_inf_nan=False)
        driver: str
        channel: Annotated[Whole, Field(ge=0, le=15)] = 0

        @model_validator(mode="after")
        def _driver_options(self) -> "MultiSensorCamera.Sensor":
            from uwcam.drivers import registry

            registry.validate_options("camera", self.driver, dict(self.model_extra or {}))
            return self

    class Options(DriverOptions):
        sensors: Annotated[list["MultiSensorCamera.Sensor"], Field(min_length=2, max_length=16)]
        """One entry per channel."""
        channel_names: ChannelNames | None = None
        max_skew_ms: Annotated[Real, Field(gt=0, le=10000)] = 20.0
        """Frames further apart in time than this are not combined."""

    name = "multi"

    def __init__(self, sensors: list[dict], channel_names: tuple[str, ...] | None = None, max_skew_ms: float = 20.0) -> None:
        from uwcam.drivers import registry

        if len(sensors) < 2:
            raise ConfigurationError("a multi-sensor camera needs two or more sensors, one per channel")
        self.parts: list[tuple[CameraDriver, int]] = []
        for k, spec in enumerate(sensors):
            spec = dict(spec)
            if "driver" not in spec:
                raise ConfigurationError(f"sensor {k} needs a 'driver' (one of {', '.join(registry.known('camera'))})")
            name, channel = spec.pop("driver"), int(spec.pop("channel", 0))
            self.parts.append((registry.create("camera", name, **spec), channel))
        self.channel_names = tuple(channel_names or [f"ch{k}" for k in range(len(self.parts))])
        if len(self.channel_names) != len(self.parts):
            raise ConfigurationError(f"{len(self.parts)} sensors but {len(self.channel_names)} channel names")
        self.max_skew_ns = int(max_skew_ms * 1e6)
        self._sequence = 0
        self._part_channels: list[int | None] = [None] * len(self.parts)

    @property
    def exposure_control(self) -> str:  # type: ignore[override]
        """One exposure per sensor: per channel, where every sensor's exposure can be set."""
        return "per-channel" if all(getattr(d, "exposure_control", "") for d, _ in self.parts) else ""

    def set_exposure(self, exposure_us: tuple[float, ...], gain_db: tuple[float, ...] | None = None) -> None:
        if len(exposure_us) != len(self.parts) or (gain_db is not None and len(gain_db) != len(self.parts)):
            raise ConfigurationError(f"need one exposure (and gain) per sensor, {len(self.parts)}, got {list(exposure_us)}")
        for k, (driver, _) in enumerate(self.parts):
            n = self._part_channels[k]
            if n is None:
                raise ConfigurationError(f"no frame yet from sensor {k}: its exposure is set after the first frame")
            driver.set_exposure((float(exposure_us[k]),) * n, None if gain_db is None else (float(gain_db[k]),) * n)

    @property
    def serial_number(self) -> str | None:  # type: ignore[override]
        serials = [d.serial_number for d, _ in self.parts]
        return None if any(s is None for s in serials) else "+".join(serials)

    @serial_number.setter
    def serial_number(self, value: str | None) -> None:
        if value is not None:
            for (driver, _), serial in zip(self.parts, value.split("+")):
                driver.serial_number = serial

    @classmethod
    def list_devices(cls, **_) -> list[DeviceInfo]:
        return []  # each sensor's own driver lists its devices

    def open(self) -> DeviceInfo:
        infos = [driver.open() for driver, _ in self.parts]
        for (driver, _), info in zip(self.parts, infos):
            if driver.serial_number is None:
                driver.serial_number = info.serial_number
        return DeviceInfo("+".join(i.id for i in infos), "+".join(i.serial_number for i in infos),
                          " + ".join(i.model for i in infos), infos[0].vendor)

    def configure(self, settings: CameraSettings) -> ConfigureReport:
        merged = ConfigureReport()
        for k, (driver, _) in enumerate(self.parts):
            own = settings
            if settings.channel_exposure_us is not None or settings.channel_gain_db is not None:
                # Per channel: sensor k takes channel k's exposure and gain.
                own = replace(settings, channel_exposure_us=None, channel_gain_db=None,
                              exposure_us=settings.exposure_us if settings.channel_exposure_us is None else settings.channel_exposure_us[k],
                              gain_db=settings.gain_db if settings.channel_gain_db is None else settings.channel_gain_db[k])
            report = driver.configure(own)
            merged.applied.update({f"sensor{k}.{key}": value for key, value in report.applied.items()})
            merged.unsupported += [f"sensor{k}.{item}" for item in report.unsupported]
            merged.radiometry_not_disabled += [f"sensor{k}.{item}" for item in report.radiometry_not_disabled]
        return merged

    def start(self) -> None:
        for driver, _ in self.parts:
            driver.start()

    def read(self, timeout_s: float) -> Frame:
        deadline = time.monotonic() + timeout_s
        frames = [driver.read(timeout_s) for driver, _ in self.parts]
        while True:
            newest = max(f.host_monotonic_ns for f in frames)
            stale = [k for k, f in enumerate(frames) if newest - f.host_monotonic_ns > self.max_skew_ns]
            if not stale:
                break
            if time.monotonic() > deadline:
                raise CorruptFrame(f"sensors could not be matched within {self.max_skew_ns / 1e6:g} ms")
            for k in stale:
                frames[k] = self.parts[k][0].read(max(deadline - time.monotonic(), 0.01))
        planes = [f.data[:, :, channel] if f.data.ndim == 3 else f.data for f, (_, channel) in zip(frames, self.parts)]
        if len({p.shape for p in planes}) != 1 or len({p.dtype for p in planes}) != 1:
            raise CorruptFrame(f"sensor images differ in size or type: {[(p.shape, str(p.dtype)) for p in planes]}")
        self._sequence += 1
        first = frames[0]
        self._part_channels = [1 if f.data.ndim == 2 else f.data.shape[-1] for f in frames]
        # Each channel was exposed by its own sensor: its exposure and gain are that sensor's.
        own = [f.exposures() for f in frames]
        exposure = [None if e is None else e[ch] for (e, _), (_, ch) in zip(own, self.parts)]
        gain = [None if g is None else g[ch] for (_, g), (_, ch) in zip(own, self.parts)]
        return Frame(data=np.stack(planes, axis=-1), sequence=self._sequence,
                     host_monotonic_ns=max(f.host_monotonic_ns for f in frames), wall_time=time.time(),
                     device_timestamp_ns=first.device_timestamp_ns, exposure_us=first.exposure_us, gain_db=first.gain_db,
                     channel_names=self.channel_names, bit_depth=first.bit_depth,
                     channel_exposure_us=None if None in exposure else tuple(exposure),
                     channel_gain_db=None if None in gain else tuple(gain))

    def stop(self) -> None:
        for driver, _ in self.parts:
            driver.stop()

    def close(self) -> None:
        for driver, _ in self.parts:
            driver.close()
