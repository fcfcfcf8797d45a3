"""V4L2 cameras (USB/UVC, CSI) through OpenCV's CAP_V4L2 backend.

Controls go through OpenCV properties: manual exposure (CAP_PROP_AUTO_EXPOSURE = 1 is
V4L2's "manual mode"), gain, white balance off, gamma and frame size/format. What the device
refuses is reported; the automatic modes are read back to check they are really off. The
device is found again by its USB serial number (sysfs) when it re-enumerates under another
/dev/videoN. ``api: any`` opens files and streams with OpenCV's default backend (tests, replay
of recordings); note that OpenCV delivers 8-bit BGR from most V4L2 formats.
"""

from __future__ import annotations

import glob
import os
import time
from pathlib import Path

import cv2

from typing import Annotated

from pydantic import Field

from uwcam.drivers.options import ChannelNames, DriverOptions
from uwcam.drivers.base import (
    CameraDriver,
    CameraSettings,
    ConfigurationError,
    ConfigureReport,
    DeviceInfo,
    DeviceLost,
    Frame,
    FrameTimeout,
)

APIS = {"v4l2": cv2.CAP_V4L2, "any": cv2.CAP_ANY}
MANUAL_EXPOSURE = 1  # V4L2_EXPOSURE_MANUAL as OpenCV's V4L2 backend passes it through


def usb_serial(device: str) -> str:
    """USB serial number of /dev/videoN from sysfs, or "" when the device has none."""
    node = Path("/sys/class/video4linux") / Path(device).name / "device"
    for parent in (node, *node.resolve().parents[:4]) if node.exists() else ():
        serial = parent / "serial"
        if serial.is_file():
            return serial.read_text().strip()
    return ""


class V4L2Camera(CameraDriver):
    class Options(DriverOptions):
        device: str = "/dev/video0"
        serial_number: str | None = None
        api: str = "v4l2"
        """OpenCV capture back-end."""
        fourcc: Annotated[str, Field(min_length=4, max_length=4)] | None = None
        """Pixel format to ask for, e.g. YUYV."""
        channel_names: ChannelNames = ["R", "G", "B"]

    name = "v4l2"

    def __init__(self, device: str = "/dev/video0", serial_number: str | None = None, api: str = "v4l2",
                 fourcc: str | None = None, channel_names: tuple[str, ...] = ("R", "G", "B")) -> None:
        if api not in APIS:
            raise ConfigurationError(f"unknown OpenCV api '{api}'; known: {', '.join(APIS)}")
        self.device = device
        self.serial_number = serial_number
        self.api = api
        self.fourcc = fourcc
        self.channel_names = tuple(channel_names)
        self._cap: cv2.VideoCapture | None = None
        self._sequence = 0
        self._exposure: float | None = None
        self._gain: float | None = None

    @classmethod
    def list_devices(cls, **_) -> list[DeviceInfo]:
        return [DeviceInfo(d, usb_serial(d) or d, "V4L2 device") for d in sorted(glob.glob("/dev/video*"))]

    def _path(self) -> str:
        if self.serial_number and self.api == "v4l2":
            for info in self.list_devices():
                if info.serial_number == self.serial_number:
                    return info.id
            raise DeviceLost(f"no V4L2 device with serial number {self.serial_number}")
        return self.device

    def open(self) -> DeviceInfo:
        self.close()
        path = self._path()
        if self.api == "v4l2" and not os.path.exists(path):
            raise DeviceLost(f"{path} does not exist (camera unplugged?)")
        cap = cv2.VideoCapture(path, APIS[self.api])
        if not cap.isOpened():
            cap.release()
            raise DeviceLost(f"OpenCV cannot open {path} with the {self.api} backend")
        self._cap = cap
        serial = (usb_serial(path) if self.api == "v4l2" else "") or self.serial_number or path
        return DeviceInfo(path, serial, cap.getBackendName())

    def _set(self, prop: int, value: float) -> bool:
        return bool(self._cap.set(prop, value))

    def configure(self, settings: CameraSettings) -> ConfigureReport:
        report = ConfigureReport()
        if self.fourcc or settings.pixel_format:
            code = (self.fourcc or settings.pixel_format or "")[:4]
            if not self._set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*code.ljust(4))):
                report.unsupported.append(f"pixel_format {code}")
        if settings.region is not None:
            x, y, w, h = settings.region
            if x or y:
                report.unsupported.append("region offset (V4L2 through OpenCV sets only the frame size)")
            for prop, value, name in ((cv2.CAP_PROP_FRAME_WIDTH, w, "width"), (cv2.CAP_PROP_FRAME_HEIGHT, h, "height")):
                if not self._set(prop, value):
                    report.unsupported.append(name)
        # Radiometry: manual exposure, fixed white balance, linear response.
        if not self._set(cv2.CAP_PROP_AUTO_EXPOSURE, MANUAL_EXPOSURE) or self._cap.get(cv2.CAP_PROP_AUTO_EXPOSURE) not in (
                MANUAL_EXPOSURE, 0.25):  # some builds report the DirectShow-style 0.25 for manual
            report.radiometry_not_disabled.append("auto exposure")
        if not self._set(cv2.CAP_PROP_AUTO_WB, 0) or self._cap.get(cv2.CAP_PROP_AUTO_WB) not in (0, -1):
            report.radiometry_not_disabled.append("auto white balance")
        if not self._set(cv2.CAP_PROP_GAMMA, 100):  # UVC gamma 100 = 1.0
            report.radiometry_not_disabled.append("gamma")
        for prop, value, name in ((cv2.CAP_PROP_EXPOSURE, settings.exposure_us, "exposure_us"),
                                  (cv2.CAP_PROP_GAIN, settings.gain_db, "gain_db"),
                                  (cv2.CAP_PROP_FPS, settings.frame_rate, "frame_rate")):
            if value is None:
                continue
            if self._set(prop, value):
                report.applied[name] = self._cap.get(prop)
            else:
                report.unsupported.append(name)
        if settings.black_level is not None:
            report.unsupported.append("black_level")
        # Device units (V4L2 exposure is in 100 µs steps on most UVC cameras); None if not set.
        self._exposure = report.applied.get("exposure_us")  # type: ignore[assignment]
        self._gain = report.applied.get("gain_db")  # type: ignore[assignment]
        return report

    def start(self) -> None:
        if self._cap is None:
            raise DeviceLost("camera is not open")

    def read(self, timeout_s: float) -> Frame:
        cap = self._cap
        if cap is None:
            raise DeviceLost("camera is not open")
        if hasattr(cv2, "CAP_PROP_READ_TIMEOUT_MSEC"):  # honoured by the V4L2 backend of OpenCV ≥ 4.6
            cap.set(cv2.CAP_PROP_READ_TIMEOUT_MSEC, max(1.0, timeout_s * 1000.0))
        ok, bgr = cap.read()
        received = time.monotonic_ns()
        if not ok:
            if self.api == "v4l2" and not os.path.exists(self.device if not self.serial_number else self._path()):
                raise DeviceLost(f"{self.device} disappeared")
            if self.api == "any":
                raise DeviceLost(f"{self.device} has no more frames")
            raise FrameTimeout(f"no frame from {self.device} within {timeout_s:g} s")
        if bgr.ndim != 3 or bgr.shape[-1] < 3:
            from uwcam.drivers.pixels import refuse_monochrome

            refuse_monochrome("Mono8")
        self._sequence += 1
        data = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        return Frame(data=data, sequence=self._sequence, host_monotonic_ns=received, wall_time=time.time(),
                     exposure_us=self._exposure, gain_db=self._gain,
                     channel_names=self.channel_names[:3], bit_depth=8 * data.dtype.itemsize)

    def stop(self) -> None:
        pass

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None
