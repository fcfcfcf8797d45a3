"""V4L2 cameras (USB/UVC, CSI): natively through linuxpy's ioctls, OpenCV's CAP_V4L2 as the fallback.

The native path (:mod:`uwcam.drivers.v4l2_native`) enumerates the device's formats and controls,
sets exposure in the control's real unit (``V4L2_CID_EXPOSURE_ABSOLUTE`` counts 100 µs), gain,
a fixed white-balance temperature, UVC gamma 100 and manual exposure, reads every value back and
labels frames with what the device reports; whatever the device refuses or clamps is reported
with what it offers. Frames keep the format's depth (16-bit Bayer where offered).

OpenCV's backend is used where the native path cannot run (``backend: opencv``, linuxpy missing,
or a device that answers no V4L2 ioctl) and for files and streams (``api: any``: tests, replay of
recordings); it delivers 8-bit BGR, and its exposure property is converted from and to 100 µs
units too. The device is found again by its USB serial number (sysfs) when it re-enumerates
under another /dev/videoN.
"""

from __future__ import annotations

import glob
import logging
import os
import time
from pathlib import Path

import cv2

from typing import Annotated, Literal

from pydantic import Field

from uwcam.drivers.options import ChannelNames, DriverOptions, Real
from uwcam.drivers.base import (CameraDriver, CameraSettings, ConfigurationError, ConfigureReport, DeviceInfo,
                                DeviceLost, Frame, FrameTimeout)

log = logging.getLogger(__name__)
APIS = {"v4l2": cv2.CAP_V4L2, "any": cv2.CAP_ANY}
MANUAL_EXPOSURE = 1  # V4L2_EXPOSURE_MANUAL as OpenCV's V4L2 backend passes it through
EXPOSURE_UNIT_US = 100.0  # OpenCV's CAP_PROP_EXPOSURE on V4L2 is V4L2_CID_EXPOSURE_ABSOLUTE: 100 µs units


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
        """OpenCV capture back-end of the fallback path: v4l2, or any (files and streams)."""
        backend: Literal["auto", "native", "opencv"] = "auto"
        """auto: native V4L2 ioctls (linuxpy) where the device answers them, else OpenCV."""
        fourcc: Annotated[str, Field(min_length=4, max_length=4)] | None = None
        """Pixel format to ask for, e.g. YUYV, MJPG, BYR2 (16-bit Bayer); default: the deepest offered."""
        white_balance_k: Annotated[Real, Field(ge=1000, le=15000)] | None = None
        """White-balance temperature to fix (kelvin); default: the device's default value."""
        gain_db_per_step: Annotated[Real, Field(gt=0, le=10)] | None = None
        """dB per step of the device's gain control (UVC gain has no unit); needed for gain_db ≠ 0."""
        channel_names: ChannelNames = ["R", "G", "B"]

    name = "v4l2"

    def __init__(self, device: str = "/dev/video0", serial_number: str | None = None, api: str = "v4l2",
                 fourcc: str | None = None, channel_names: tuple[str, ...] = ("R", "G", "B"),
                 backend: str = "auto", white_balance_k: float | None = None,
                 gain_db_per_step: float | None = None) -> None:
        self.device = device
        self.serial_number = serial_number
        if api not in APIS:
            raise ConfigurationError(f"unknown OpenCV api '{api}'; known: {', '.join(APIS)}")
        self.api = api
        if backend not in ("auto", "native", "opencv"):
            raise ConfigurationError(f"unknown V4L2 backend '{backend}'; known: auto, native, opencv")
        if backend == "native" and api != "v4l2":
            raise ConfigurationError("backend 'native' drives V4L2 devices only; use api: v4l2 (or backend: opencv)")
        self.backend = backend
        self.fourcc = fourcc
        self.white_balance_k = white_balance_k
        self.gain_db_per_step = gain_db_per_step
        self.channel_names = tuple(channel_names)
        self._cap: cv2.VideoCapture | None = None
        self._native = None  # uwcam.drivers.v4l2_native.NativeDevice when the native path runs
        self._format: tuple[str, int, int, int, int] | None = None
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

    @property
    def native(self) -> bool:
        """True while the device is driven through native ioctls (not OpenCV)."""
        return self._native is not None

    def open(self) -> DeviceInfo:
        self.close()
        path = self._path()
        if self.api == "v4l2" and not os.path.exists(path):
            raise DeviceLost(f"{path} does not exist (camera unplugged?)")
        if self.api == "v4l2" and self.backend != "opencv":
            info = self._open_native(path)
            if info is not None:
                return info
        cap = cv2.VideoCapture(path, APIS[self.api])
        if not cap.isOpened():
            cap.release()
            raise DeviceLost(f"OpenCV cannot open {path} with the {self.api} backend")
        self._cap = cap
        serial = (usb_serial(path) if self.api == "v4l2" else "") or self.serial_number or path
        return DeviceInfo(path, serial, cap.getBackendName())

    def _open_native(self, path: str) -> DeviceInfo | None:
        """Open through linuxpy; None (fall back to OpenCV) where that cannot work and backend is auto."""
        try:
            from uwcam.drivers.v4l2_native import NativeDevice
        except ImportError as exc:
            if self.backend == "native":
                raise ConfigurationError(f"backend 'native' needs linuxpy ({exc}); install it or use backend: opencv") from None
            log.warning("linuxpy is not installed: V4L2 through OpenCV's property guesses (install linuxpy)")
            return None
        try:
            self._native = NativeDevice(path)
        except ConfigurationError as exc:
            if self.backend == "native" or "permission" in str(exc) or "cannot capture" in str(exc):
                raise
            log.warning("%s; falling back to OpenCV", exc)
            return None
        serial = usb_serial(path) or self.serial_number or path
        return DeviceInfo(path, serial, f"{self._native.card} ({self._native.driver}, native V4L2)")

    def _set(self, prop: int, value: float) -> bool:
        return bool(self._cap.set(prop, value))

    def configure(self, settings: CameraSettings) -> ConfigureReport:
        if self._native is not None:
            from uwcam.drivers.v4l2_setup import configure_native

            outcome = configure_native(self._native, settings, fourcc=self.fourcc,
                                       white_balance_k=self.white_balance_k, gain_db_per_step=self.gain_db_per_step)
            self._format, self._exposure, self._gain = outcome.format, outcome.exposure_us, outcome.gain_db
            return outcome.report
        return self._configure_opencv(settings)

    def _configure_opencv(self, settings: CameraSettings) -> ConfigureReport:
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
        if settings.exposure_us is not None:
            # OpenCV hands CAP_PROP_EXPOSURE to V4L2_CID_EXPOSURE_ABSOLUTE unchanged: 100 µs units.
            if self._set(cv2.CAP_PROP_EXPOSURE, max(1.0, round(settings.exposure_us / EXPOSURE_UNIT_US))):
                report.applied["exposure_us"] = self._cap.get(cv2.CAP_PROP_EXPOSURE) * EXPOSURE_UNIT_US
            else:
                report.unsupported.append("exposure_us")
        if settings.gain_db is not None:
            # Gain in the device's own steps: only 0 (the minimum) has a known meaning in dB.
            if settings.gain_db == 0 and self._set(cv2.CAP_PROP_GAIN, 0):
                report.applied["gain_db"] = 0.0
            else:
                report.unsupported.append("gain_db")
                if settings.gain_db:
                    report.details["gain_db"] = ("OpenCV's V4L2 gain has no unit; use backend: native with "
                                                 "gain_db_per_step, or gain_db: 0")
        if settings.frame_rate is not None:
            if self._set(cv2.CAP_PROP_FPS, settings.frame_rate):
                report.applied["frame_rate"] = self._cap.get(cv2.CAP_PROP_FPS)
            else:
                report.unsupported.append("frame_rate")
        if settings.black_level is not None:
            report.unsupported.append("black_level")
        self._exposure = report.applied.get("exposure_us")  # type: ignore[assignment]
        self._gain = report.applied.get("gain_db")  # type: ignore[assignment]
        return report

    def start(self) -> None:
        if self._native is not None:
            self._native.start()
            return
        if self._cap is None:
            raise DeviceLost("camera is not open")

    def read(self, timeout_s: float) -> Frame:
        if self._native is not None:
            return self._read_native(timeout_s)
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

    def _read_native(self, timeout_s: float) -> Frame:
        from uwcam.drivers.v4l2_native import bit_depth, decode

        data, sequence, stamp_ns = self._native.read(timeout_s)
        received = time.monotonic_ns()
        fourcc, width, height, stride, _ = self._format or self._native.get_format()
        image = decode(fourcc, data, width, height, stride)
        return Frame(data=image, sequence=sequence, host_monotonic_ns=received, wall_time=time.time(),
                     device_timestamp_ns=stamp_ns or None, exposure_us=self._exposure, gain_db=self._gain,
                     channel_names=self.channel_names[:3], bit_depth=bit_depth(fourcc))

    def stop(self) -> None:
        if self._native is not None:
            self._native.stop()

    def close(self) -> None:
        # Each handle is dropped before it is closed, so a close that raises is not retried on a
        # handle already half closed.
        native, self._native = self._native, None
        if native is not None:
            native.close()
        cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()

    @property
    def exposure_control(self) -> str:  # type: ignore[override]
        """"common" while the native path drives a camera with an exposure-time control."""
        from uwcam.drivers.v4l2_native import CID_EXPOSURE_ABSOLUTE

        return "common" if self._native is not None and CID_EXPOSURE_ABSOLUTE in self._native.controls() else ""

    def set_exposure(self, exposure_us: tuple[float, ...], gain_db: tuple[float, ...] | None = None) -> None:
        """Change the exposure (µs, one value for all channels) while streaming; frames are labelled
        with the value the device reports back."""
        if not self.exposure_control:
            return super().set_exposure(exposure_us, gain_db)
        from uwcam.drivers.v4l2_native import CID_EXPOSURE_ABSOLUTE, exposure_from_device, exposure_to_device

        if len(set(exposure_us)) != 1 or (gain_db is not None and len(set(gain_db)) != 1):
            raise ConfigurationError("a V4L2 camera has one exposure and gain for all channels")
        if gain_db is not None and gain_db[0] != (self._gain or 0.0):
            raise ConfigurationError("changing a UVC camera's gain while streaming is not supported; change exposure")
        got = self._native.set(CID_EXPOSURE_ABSOLUTE, exposure_to_device(exposure_us[0]))
        self._exposure = exposure_from_device(got)
