"""Frames from a video stream (RTSP, UDP/RTP, HTTP MJPEG) through OpenCV's FFmpeg backend.

On BlueOS the USB camera belongs to mavlink-camera-manager, which streams it (RTSP/H.264 or
UDP); this driver takes that stream instead of the device, so uwcam runs beside it (see
docs/blueos.md). Frames are the decoder's 8-bit RGB: the camera's tone curve is still in them,
and a compressed stream adds its own errors, so range such a camera with a profile that carries
its response curve (``uwcam calibrate --response srgb``, or a curve from ``uwcam response``),
which linearises every frame before anything else.

A stream says nothing of exposure or gain: ``exposure_us`` (and ``gain_db``) label the frames
with what the camera was set to, where that is known. A stream that stops (server restarted,
link down) is reported lost; the supervisor reopens it with backoff.
"""

from __future__ import annotations

import os
import threading
import time
from typing import Annotated, Literal

import cv2
from pydantic import Field

from uwcam.drivers.base import (CameraDriver, CameraSettings, ConfigurationError, ConfigureReport, DeviceInfo,
                                DeviceLost, Frame, FrameTimeout)
from uwcam.drivers.options import ChannelNames, DriverOptions, Real

SCHEMES = ("rtsp://", "rtsps://", "udp://", "rtp://", "http://", "https://", "tcp://")
# OpenCV reads FFmpeg's options from this variable when a capture opens (process-wide, so the
# lock keeps two streams opening at once from seeing each other's).
_FFMPEG_OPTIONS = "OPENCV_FFMPEG_CAPTURE_OPTIONS"
_OPEN_LOCK = threading.Lock()


def backend_available(name: str) -> bool:
    """Whether this OpenCV build has a video I/O backend (FFMPEG, GSTREAMER)."""
    return any(cv2.videoio_registry.getBackendName(b) == name for b in cv2.videoio_registry.getStreamBackends())


class StreamCamera(CameraDriver):
    class Options(DriverOptions):
        url: Annotated[str, Field(min_length=8)]
        """rtsp://HOST:PORT/PATH, udp://@:PORT (RTP needs rtp:// or an SDP file), http://…/mjpeg."""
        transport: Literal["tcp", "udp"] = "tcp"
        """RTSP transport: tcp survives a lossy tether; udp has less latency."""
        open_timeout_s: Annotated[Real, Field(gt=0, le=120)] = 10.0
        exposure_us: Annotated[Real, Field(gt=0, le=10_000_000)] | None = None
        """Exposure the camera streams at (µs), to label frames with; None: unknown."""
        gain_db: Annotated[Real, Field(ge=-20, le=60)] | None = None
        channel_names: ChannelNames = ["R", "G", "B"]

    name = "stream"

    def __init__(self, url: str, transport: str = "tcp", open_timeout_s: float = 10.0,
                 exposure_us: float | None = None, gain_db: float | None = None,
                 channel_names: tuple[str, ...] = ("R", "G", "B")) -> None:
        if not url.startswith(SCHEMES):
            raise ConfigurationError(f"stream url '{url}' must start with one of {', '.join(SCHEMES)}")
        if transport not in ("tcp", "udp"):
            raise ConfigurationError(f"unknown RTSP transport '{transport}'; known: tcp, udp")
        if not backend_available("FFMPEG"):
            raise ConfigurationError("this OpenCV has no FFmpeg backend: install opencv-python-headless from PyPI")
        self.url = url
        self.transport = transport
        self.open_timeout_s = float(open_timeout_s)
        self.exposure_us = exposure_us
        self.gain_db = gain_db
        self.channel_names = tuple(channel_names)
        self.serial_number = url
        self._cap: cv2.VideoCapture | None = None
        self._sequence = 0

    @classmethod
    def list_devices(cls, **options) -> list[DeviceInfo]:
        url = options.get("url")
        return [DeviceInfo(url, url, "video stream")] if url else []

    def open(self) -> DeviceInfo:
        self.close()
        timeout_ms = self.open_timeout_s * 1000.0
        params = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, timeout_ms, cv2.CAP_PROP_READ_TIMEOUT_MSEC, timeout_ms]
        with _OPEN_LOCK:
            before = os.environ.get(_FFMPEG_OPTIONS)
            if self.url.startswith(("rtsp://", "rtsps://")):
                os.environ[_FFMPEG_OPTIONS] = f"rtsp_transport;{self.transport}"
            try:
                cap = cv2.VideoCapture(self.url, cv2.CAP_FFMPEG, [int(v) for v in params])
            finally:
                if before is None:
                    os.environ.pop(_FFMPEG_OPTIONS, None)
                else:
                    os.environ[_FFMPEG_OPTIONS] = before
        if not cap.isOpened():
            cap.release()
            raise DeviceLost(f"cannot open the stream {self.url} (server down, wrong path or port, or no route)")
        self._cap = cap
        codec = int(cap.get(cv2.CAP_PROP_FOURCC))
        name = "".join(chr((codec >> (8 * i)) & 0xFF) for i in range(4)).strip("\0 ") or "?"
        return DeviceInfo(self.url, self.url, f"{name} stream {int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))}×"
                                               f"{int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))}")

    def configure(self, settings: CameraSettings) -> ConfigureReport:
        report = ConfigureReport()
        # A stream is what its sender makes it: nothing here can be set, only labelled.
        for name in ("exposure_us", "gain_db", "pixel_format", "region", "black_level", "frame_rate"):
            if getattr(settings, name) is not None:
                report.unsupported.append(name)
                report.details[name] = "set it on the camera that feeds the stream (mavlink-camera-manager, v4l2-ctl)"
        if self.exposure_us is not None:
            report.applied["exposure_us"] = self.exposure_us
        else:
            report.radiometry_not_disabled.append("exposure unknown (set the stream's exposure_us option)")
        return report

    def start(self) -> None:
        if self._cap is None:
            raise DeviceLost("stream is not open")

    def read(self, timeout_s: float) -> Frame:
        cap = self._cap
        if cap is None:
            raise DeviceLost("stream is not open")
        ok, bgr = cap.read()
        received = time.monotonic_ns()
        if not ok or bgr is None:
            # FFmpeg gives up on a stalled or closed stream after its read timeout: reopen it.
            raise DeviceLost(f"the stream {self.url} stopped (server restarted or link down)")
        if bgr.ndim != 3 or bgr.shape[-1] < 3:
            raise FrameTimeout(f"the stream {self.url} delivered a frame without colour")
        self._sequence += 1
        return Frame(data=cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), sequence=self._sequence, host_monotonic_ns=received,
                     wall_time=time.time(), exposure_us=self.exposure_us, gain_db=self.gain_db,
                     channel_names=self.channel_names[:3], bit_depth=8)

    def stop(self) -> None:
        pass

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None
