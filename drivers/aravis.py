"""GigE Vision and USB3 Vision cameras through Aravis (PyGObject).

``fake: true`` enables Aravis's built-in Fake interface (camera ``Fake_1``), which needs no
hardware. Settings go through Aravis's camera API and GenICam features; automatic exposure,
gain and white balance are switched off where present, and what the camera lacks is
reported. Buffers are copied once, at hand-off, and returned to the stream at once.
"""

from __future__ import annotations

import contextlib
import time

import numpy as np

from typing import Annotated

from pydantic import Field

from uwcam.drivers.options import ChannelNames, DriverOptions, Flag, Whole
from uwcam.drivers.base import (CameraDriver, CameraSettings, ConfigurationError, ConfigureReport, CorruptFrame,
                                DeviceInfo, DeviceLost, Frame, FrameTimeout)
from uwcam.drivers.pixels import decode, refuse_monochrome

# Aravis's older names for PFNC formats.
ALIASES = {"RGB8Packed": "RGB8", "BGR8Packed": "BGR8", "RGB10Packed": "RGB10", "RGB12Packed": "RGB12"}


def _aravis():
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis
    except (ImportError, ValueError) as exc:
        raise ConfigurationError(
            f"Aravis is not available ({exc}); install the aravis gir bindings (Debian: gir1.2-aravis-0.8) and "
            "'aravis-python' with 'PyGObject<3.51'"
        ) from None
    return Aravis


class AravisCamera(CameraDriver):
    class Options(DriverOptions):
        device_id: str | None = None
        """Aravis device id (e.g. "Fake-1" or a GigE camera's id); None: the first found."""
        serial_number: str | None = None
        """Open the camera with this serial number (and find it again after a reconnection)."""
        fake: Flag = False
        """Enable Aravis's Fake interface (testing without a camera)."""
        buffers: Annotated[Whole, Field(ge=1, le=64)] = 4
        channel_names: ChannelNames = ["R", "G", "B"]

    name = "aravis"

    def __init__(self, device_id: str | None = None, serial_number: str | None = None, fake: bool = False,
                 buffers: int = 4, channel_names: tuple[str, ...] = ("R", "G", "B")) -> None:
        self.Aravis = _aravis()
        if fake:
            self.Aravis.enable_interface("Fake")
        self.device_id = device_id
        self.serial_number = serial_number
        self.buffers = buffers
        self.channel_names = tuple(channel_names)
        self._camera = None
        self._stream = None
        self._format = ""
        self._exposure_us: float | None = None
        self._gain_db: float | None = None

    @classmethod
    def list_devices(cls, fake: bool = False, **_) -> list[DeviceInfo]:
        Aravis = _aravis()
        if fake:
            Aravis.enable_interface("Fake")
        Aravis.update_device_list()
        return [DeviceInfo(Aravis.get_device_id(i), Aravis.get_device_serial_nbr(i) or Aravis.get_device_id(i),
                           Aravis.get_device_model(i) or "", Aravis.get_device_vendor(i) or "")
                for i in range(Aravis.get_n_devices())]

    def open(self) -> DeviceInfo:
        self.close()
        devices = self.list_devices()
        chosen = [d for d in devices
                  if (self.serial_number is None or d.serial_number == self.serial_number)
                  and (self.device_id is None or d.id == self.device_id)]
        if not chosen:
            seen = ", ".join(f"{d.id} ({d.serial_number})" for d in devices) or "none"
            raise DeviceLost(f"no Aravis camera matching serial {self.serial_number} / id {self.device_id} (present: {seen})")
        info = chosen[0]
        try:
            self._camera = self.Aravis.Camera.new(info.id)
        except Exception as exc:  # GLib.Error
            raise DeviceLost(f"cannot open {info.id}: {exc}") from None
        return info

    def _feature(self, name: str) -> bool:
        return bool(self._camera.get_device().is_feature_available(name))

    def configure(self, settings: CameraSettings) -> ConfigureReport:
        cam, Aravis = self._camera, self.Aravis
        report = ConfigureReport()
        try:
            if cam.is_exposure_auto_available():
                cam.set_exposure_time_auto(Aravis.Auto.OFF)
            if cam.is_gain_auto_available():
                cam.set_gain_auto(Aravis.Auto.OFF)
        except Exception:
            report.radiometry_not_disabled.append("auto exposure/gain")
        dev = cam.get_device()
        for feature, value in (("BalanceWhiteAuto", "Off"), ("GammaEnable", False)):
            if self._feature(feature):
                try:
                    (dev.set_string_feature_value if isinstance(value, str) else dev.set_boolean_feature_value)(feature, value)
                except Exception:
                    report.radiometry_not_disabled.append(feature)
        offered = list(cam.dup_available_pixel_formats_as_strings())
        if settings.pixel_format:
            if settings.pixel_format not in offered:
                raise ConfigurationError(f"camera does not offer pixel format {settings.pixel_format}; it offers {', '.join(offered)}")
            refuse_monochrome(settings.pixel_format)
            cam.set_pixel_format_from_string(settings.pixel_format)
            report.applied["PixelFormat"] = settings.pixel_format
        self._format = ALIASES.get(cam.get_pixel_format_as_string(), cam.get_pixel_format_as_string())
        refuse_monochrome(self._format)
        actions = (
            ("exposure_us", settings.exposure_us, cam.is_exposure_time_available, cam.set_exposure_time, cam.get_exposure_time),
            ("gain_db", settings.gain_db, cam.is_gain_available, cam.set_gain, cam.get_gain),
            ("frame_rate", settings.frame_rate, cam.is_frame_rate_available, cam.set_frame_rate, cam.get_frame_rate),
        )
        for name, value, available, setter, getter in actions:
            if value is None:
                continue
            try:
                if not available():
                    raise RuntimeError("not available")
                setter(value)
                report.applied[name] = getter()
            except Exception as exc:
                report.unsupported.append(f"{name} ({exc})")
        if settings.region is not None:
            try:
                cam.set_region(*settings.region)
                report.applied["region"] = tuple(cam.get_region())
            except Exception as exc:
                report.unsupported.append(f"region ({exc})")
        self._exposure_us = cam.get_exposure_time() if cam.is_exposure_time_available() else None
        self._gain_db = cam.get_gain() if cam.is_gain_available() else None
        if settings.black_level is not None:
            if self._feature("BlackLevel"):
                dev.set_float_feature_value("BlackLevel", settings.black_level)
                report.applied["black_level"] = settings.black_level
            else:
                report.unsupported.append("black_level")
        return report

    def start(self) -> None:
        try:
            self._stream = self._camera.create_stream(None, None)
            payload = self._camera.get_payload()
            for _ in range(self.buffers):
                self._stream.push_buffer(self.Aravis.Buffer.new_allocate(payload))
            self._camera.start_acquisition()
        except Exception as exc:
            raise DeviceLost(f"cannot start acquisition: {exc}") from None

    def read(self, timeout_s: float) -> Frame:
        buf = self._stream.timeout_pop_buffer(int(timeout_s * 1e6))
        if buf is None:
            raise FrameTimeout(f"no frame within {timeout_s:g} s")
        received = time.monotonic_ns()
        try:
            if buf.get_status() != self.Aravis.BufferStatus.SUCCESS:
                raise CorruptFrame(f"buffer status {buf.get_status().value_nick}")
            width, height = buf.get_image_width(), buf.get_image_height()
            raw = np.frombuffer(buf.get_data(), dtype=np.uint8)
            data, bits = decode(self._format, raw, width, height)
            data = np.ascontiguousarray(data).copy()  # the buffer goes straight back to the stream
            stamp, sequence = buf.get_timestamp(), buf.get_frame_id()
        finally:
            self._stream.push_buffer(buf)
        return Frame(data=data, sequence=int(sequence), host_monotonic_ns=received, wall_time=time.time(),
                     device_timestamp_ns=int(stamp) or None, exposure_us=self._exposure_us, gain_db=self._gain_db,
                     channel_names=self.channel_names[: data.shape[-1]], bit_depth=bits)

    def stop(self) -> None:
        if self._camera is not None:
            with contextlib.suppress(Exception):  # a camera that went away stops as best it can
                self._camera.stop_acquisition()

    def close(self) -> None:
        self.stop()
        self._stream = None
        self._camera = None

