"""Replay: a folder of frames (.npy, .tif, .png), a video file or a uwcam MCAP recording, looped
or played once, at the recorded rate (video, MCAP), a given one, or as fast as possible (MCAP).
For bench work, demos and regression runs on dives: a recorded dive drives the whole daemon."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import cv2
import numpy as np

from typing import Annotated

from pydantic import Field

from uwcam.drivers.options import ChannelNames, DriverOptions, Flag, Real
from uwcam.drivers.base import (CameraDriver, CameraSettings, ConfigurationError, ConfigureReport, CorruptFrame,
                                DeviceInfo, DeviceLost, EndOfStream, Frame, FrameTimeout)
from uwcam.fileio import UserInputError
from uwcam.imaging.imageio import IMAGE_SUFFIXES, read_frame

VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov")


class ReplayCamera(CameraDriver):
    class Options(DriverOptions):
        source: str
        """A recording: a folder of frames or a file of them."""
        fps: Annotated[Real, Field(gt=0, le=10000)] | None = None
        """Frames per second; None: the recorded rate of a video or MCAP recording, else 10."""
        loop: Flag = True
        channel_names: ChannelNames = ["R", "G", "B"]
        fast: Flag = False
        """MCAP recordings only: deliver frames as fast as they are read (no pacing)."""

    name = "replay"

    def __init__(self, source: str, fps: float | None = None, loop: bool = True,
                 channel_names: tuple[str, ...] = ("R", "G", "B"), fast: bool = False) -> None:
        """fps: frames per second (default: the recorded rate of a video or MCAP recording, else 10).
        fast: MCAP recordings only, deliver frames as fast as they are read (no pacing)."""
        self.source = Path(source)
        self.loop = loop
        self.fast = bool(fast)
        self.channel_names = tuple(channel_names)
        self.serial_number = f"replay:{self.source.name}"
        self._mcap = self.source.suffix.lower() == ".mcap"
        self._frames = None
        self._first_log_ns: int | None = None
        if self._mcap:
            if not self.source.is_file():
                raise ConfigurationError(f"replay recording {self.source} does not exist")
            self.files = []
            self.fps = float(fps) if fps else float("inf")  # inf: the recorded timing
        elif self.source.is_dir():
            self.files = sorted(p for p in self.source.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            if not self.files:
                raise ConfigurationError(f"replay folder {self.source} holds no {', '.join(IMAGE_SUFFIXES)} frames")
            self.fps = float(fps or 10.0)
        elif self.source.is_file() and self.source.suffix.lower() in VIDEO_SUFFIXES:
            self.files = []
            probe = cv2.VideoCapture(str(self.source))
            recorded = probe.get(cv2.CAP_PROP_FPS) if probe.isOpened() else 0.0
            probe.release()
            if not recorded and not fps:
                raise ConfigurationError(f"cannot read a frame rate from {self.source}; give fps")
            self.fps = float(fps or recorded)
        else:
            raise ConfigurationError(f"replay source {self.source} is neither a folder of frames nor a video "
                                     f"({', '.join(VIDEO_SUFFIXES)}) nor an MCAP recording (.mcap)")
        if not self.fps > 0:
            raise ConfigurationError(f"replay fps must be positive, got {self.fps}")
        self._video = None
        self._pending = None
        self._started = 0.0
        self._index = 0
        self._sequence = 0
        self._next_due = 0.0
        self._closed = threading.Event()

    @classmethod
    def list_devices(cls, source: str = "", **_) -> list[DeviceInfo]:
        return [DeviceInfo(f"replay:{source}", f"replay:{Path(source).name}", "replay")] if Path(source).exists() else []

    def open(self) -> DeviceInfo:
        if not self.source.exists():
            raise DeviceLost(f"replay source {self.source} has gone")
        if self._mcap:
            self._frames = self._mcap_frames()
        elif not self.files:
            self._video = cv2.VideoCapture(str(self.source))
            if not self._video.isOpened():
                raise DeviceLost(f"OpenCV cannot open the video {self.source}")
        self._closed.clear()
        return DeviceInfo(f"replay:{self.source}", self.serial_number, "replay")

    def configure(self, settings: CameraSettings) -> ConfigureReport:
        report = ConfigureReport()
        if settings.frame_rate:
            self.fps = float(settings.frame_rate)
            report.applied["frame_rate"] = self.fps
        report.unsupported += [n for n in ("exposure_us", "gain_db", "pixel_format", "region", "black_level")
                               if getattr(settings, n) is not None]
        return report

    def start(self) -> None:
        self._next_due = time.monotonic()
        self._started = self._next_due

    def _mcap_frames(self):
        """Recorded frames one by one, the file reopened at the end when looping."""
        from uwcam.recording import format as recording

        while True:
            count = 0
            try:
                with open(self.source, "rb") as fh:
                    for frame in recording.iter_recorded_frames(recording.open_reader(fh)):
                        count += 1
                        yield frame
            except OSError as exc:
                raise DeviceLost(f"cannot read {self.source}: {exc}") from None
            except Exception as exc:  # the mcap reader's errors for a damaged file have several types
                raise EndOfStream(f"replay of {self.source} stopped at a damaged record ({exc})") from None
            if count == 0:
                raise EndOfStream(f"{self.source} holds no raw frames ({recording.IMAGE})")
            if not self.loop:
                raise EndOfStream(f"replay of {self.source} finished ({count} frames)")
            self._first_log_ns = None
            self._started = time.monotonic()

    def _read_mcap(self, timeout_s: float) -> Frame:
        if self._pending is None:
            self._pending = next(self._frames)
        rf = self._pending
        if self._first_log_ns is None:
            self._first_log_ns, self._started = rf.log_time_ns, time.monotonic()
        if not self.fast:
            due = (self._started + (rf.log_time_ns - self._first_log_ns) / 1e9 if self.fps == float("inf")
                   else self._next_due)
            wait = due - time.monotonic()
            if wait > timeout_s:
                self._closed.wait(timeout_s)
                raise FrameTimeout(f"next replayed frame is due in {wait:.2f} s")
            if wait > 0:
                self._closed.wait(wait)
            if self.fps != float("inf"):
                self._next_due += 1.0 / self.fps
        self._pending = None
        m = rf.metadata
        first = (lambda v: None if not v else float(v[0]))
        each = (lambda v: None if not v else tuple(float(x) for x in v))  # recorded per channel
        return Frame(data=rf.data, sequence=int(m["sequence"]), host_monotonic_ns=time.monotonic_ns(),
                     wall_time=time.time(), device_timestamp_ns=m.get("device_timestamp_ns"),
                     exposure_us=first(m.get("exposure_us")), gain_db=first(m.get("gain_db")), lamp_on=m.get("lamp_on"),
                     channel_names=tuple(m.get("channel_names") or self.channel_names[: rf.data.shape[-1]]),
                     bit_depth=m.get("bit_depth"), channel_exposure_us=each(m.get("exposure_us")),
                     channel_gain_db=each(m.get("gain_db")))

    def _next_image(self) -> np.ndarray:
        if self.files:
            if self._index >= len(self.files):
                if not self.loop:
                    raise EndOfStream(f"replay of {self.source} finished ({len(self.files)} frames)")
                self._index = 0
            path = self.files[self._index]
            self._index += 1
            try:
                return read_frame(path)
            except UserInputError as exc:
                raise CorruptFrame(str(exc)) from None
        ok, bgr = self._video.read()
        if not ok:
            if not self.loop:
                raise EndOfStream(f"replay of {self.source} finished")
            self._video.set(cv2.CAP_PROP_POS_FRAMES, 0)
            ok, bgr = self._video.read()
            if not ok:
                raise DeviceLost(f"cannot read frames from {self.source}")
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def read(self, timeout_s: float) -> Frame:
        if self._mcap:
            return self._read_mcap(timeout_s)
        wait = self._next_due - time.monotonic()
        if wait > timeout_s:
            self._closed.wait(timeout_s)
            raise FrameTimeout(f"next replayed frame is due in {wait:.2f} s")
        if wait > 0:
            self._closed.wait(wait)
        self._next_due += 1.0 / self.fps
        data = self._next_image()
        self._sequence += 1
        return Frame(data=data, sequence=self._sequence, host_monotonic_ns=time.monotonic_ns(), wall_time=time.time(),
                     channel_names=self.channel_names[: data.shape[-1]],
                     bit_depth=16 if data.dtype == np.uint16 else 8)

    def stop(self) -> None:
        pass

    def close(self) -> None:
        self._closed.set()
        if self._frames is not None:
            self._frames.close()
            self._frames = None
            self._pending = None
            self._first_log_ns = None
        if self._video is not None:
            self._video.release()
            self._video = None
