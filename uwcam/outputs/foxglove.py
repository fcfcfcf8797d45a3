"""Live view in Foxglove: a Foxglove WebSocket server (``foxglove-sdk``) on its own port carrying
the recorder's topics (:mod:`uwcam.recording.format`) plus an 8-bit colour preview and a point cloud.

A user opens Foxglove, connects to ``ws://HOST:PORT`` and sees colour, depth and points; no uwcam
code on their side. An output of the frame loop: the loop's callback only replaces the newest
frame in a one-slot holder; a thread of its own encodes and sends at most ``rate_hz`` frames a
second, so a slow client or a busy encoder never slows the loop (skipped frames are counted).
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable

import numpy as np

from uwcam.recording import format as rec
from uwcam.config import FoxgloveConfig
from uwcam.fileio import UserInputError
from uwcam.outputs.foxglove_gateway import FoxgloveGateway
from uwcam.optics.geometry import pixel_rays
from uwcam.recording.records import to_depth
from uwcam.runtime.pipeline import FramePipeline
from uwcam.runtime.published import Published
from uwcam.outputs.subscriber import ThreadedOutput

log = logging.getLogger(__name__)
PREVIEW = "/uwcam/image/preview"
POINTS = "/uwcam/points"


def preview_rgb8(data: np.ndarray) -> np.ndarray:
    """First three channels stretched to 8 bits by the frame's 99.9th percentile (for display only)."""
    rgb = data[:, :, :3].astype(np.float32)
    top = float(np.percentile(rgb[::4, ::4], 99.9)) or 1.0
    return np.clip(rgb * (255.0 / top), 0, 255).astype(np.uint8)


def point_cloud(range_m: np.ndarray, rays: np.ndarray, rgb: np.ndarray, stride: int) -> tuple[bytes, int]:
    """Packed points (x, y, z float32 metres in the camera frame; red, green, blue uint8; one pad
    byte) of every ``stride``-th valid pixel; returns (data, point count)."""
    r = range_m[::stride, ::stride]
    ok = np.isfinite(r)
    xyz = (r[ok, None] * rays[::stride, ::stride][ok]).astype("<f4")
    points = np.zeros(len(xyz), dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3), ("pad", "u1")])
    points["xyz"] = xyz
    points["rgb"] = rgb[::stride, ::stride][ok]
    return points.tobytes(), len(points)


class FoxgloveOutput(ThreadedOutput):
    """The Foxglove WebSocket server and its sender thread."""

    def __init__(self, pipeline: FramePipeline, config: FoxgloveConfig,
                 status: Callable[[], dict] | None = None, rangefinder: object | None = None) -> None:
        super().__init__(pipeline, "foxglove-output")
        self.config = config
        self._status_fn = status
        self.rangefinder = rangefinder
        self._next_status = 0.0
        self._newest: Published | None = None
        self.server = None
        self.gateway: FoxgloveGateway | None = None
        self.sent = 0
        self.skipped = 0
        self.error: str | None = None

    def start(self) -> None:
        import foxglove
        from foxglove import channels

        # A context of our own: nothing else logged through the SDK's global context leaks in.
        self._ctx = foxglove.Context()
        # The SDK's server on loopback only; the gateway on the configured address answers both
        # subprotocol names (foxglove.sdk.v1, and foxglove.websocket.v1 for Lichtblick and older
        # Foxglove) and passes the connection through.
        try:
            self.server = foxglove.start_server(name="uwcam", host="127.0.0.1", port=0, context=self._ctx)
        except Exception as exc:  # the SDK reports a failure to bind as a RuntimeError
            raise UserInputError(f"cannot start the Foxglove server on loopback ({exc})") from None
        self.gateway = FoxgloveGateway(self.config.host, self.config.port, self.server.port)
        try:
            self.gateway.start()
        except OSError as exc:
            self.gateway.stop()
            self.gateway = None
            self.server.stop()
            self.server = None
            raise UserInputError(f"cannot start the Foxglove server on {self.config.host}:{self.config.port} ({exc}); "
                                 "choose another foxglove.port or host") from None
        ctx = self._ctx
        self._ch = {
            rec.IMAGE: channels.RawImageChannel(rec.IMAGE, context=ctx),
            PREVIEW: channels.RawImageChannel(PREVIEW, context=ctx),
            rec.DEPTH: channels.RawImageChannel(rec.DEPTH, context=ctx),
            rec.VARIANCE: channels.RawImageChannel(rec.VARIANCE, context=ctx),
            rec.REASONS: channels.RawImageChannel(rec.REASONS, context=ctx),
            rec.CALIBRATION: channels.CameraCalibrationChannel(rec.CALIBRATION, context=ctx),
            POINTS: channels.PointCloudChannel(POINTS, context=ctx),
            rec.STATUS: foxglove.Channel(rec.STATUS, context=ctx),
            rec.RANGEFINDER: foxglove.Channel(rec.RANGEFINDER, context=ctx),
        }
        self._start_thread()
        log.info("Foxglove WebSocket server on ws://%s:%d", self.config.host, self.port)

    @property
    def port(self) -> int:
        return self.gateway.port if self.gateway is not None and self.gateway.port else self.config.port

    def _on_published(self, published: Published) -> None:  # loop thread: hand off only
        with self._lock:
            if self._newest is not None:
                self.skipped += 1
            self._newest = published
            self._ready.notify()

    def close(self) -> None:
        self._stop_thread()
        if self.gateway is not None:
            self.gateway.stop()
            self.gateway = None
        if self.server is not None:
            self.server.stop()
            self.server = None

    def status(self) -> dict:
        with self._lock:
            state = {"url": f"ws://{self.config.host}:{self.port}", "frames_sent": self.sent,
                     "frames_skipped": self.skipped, "error": self.error}
        gateway = self.gateway
        return {**state, **(gateway.status() if gateway is not None else {"clients": 0, "connections_by_protocol": {}})}

    def _run(self) -> None:
        period = 1.0 / self.config.rate_hz
        profile, uz, rays = None, None, None
        while True:
            with self._lock:
                while self._newest is None and not self._stop:
                    self._ready.wait()
                if self._stop:
                    return
                p, self._newest = self._newest, None
            began = time.monotonic()
            try:
                if self.pipeline.profile is not profile:
                    profile = self.pipeline.profile
                    h, w = p.frame.data.shape[:2]
                    uz = rec.depth_factor(profile, h, w)
                    intr = profile.camera_intrinsics()
                    rays = pixel_rays(intr, h, w) if intr is not None else None
                self._send(p, profile, uz, rays)
                with self._lock:
                    self.sent += 1
                    self.error = None
            except Exception as exc:  # keep serving; say what went wrong
                log.exception("Foxglove output failed on frame %s", p.number)
                with self._lock:
                    self.error = f"{type(exc).__name__}: {exc}"
            with self._lock:  # rate limit, waking early only to stop
                if not self._stop:
                    self._ready.wait_for(lambda: self._stop, timeout=max(0.0, period - (time.monotonic() - began)))

    def _send(self, p: Published, profile, uz, rays) -> None:
        import foxglove.messages as m

        t = int(p.frame.wall_time * 1e9)
        h, w = p.frame.data.shape[:2]
        ch = self._ch
        rgb = preview_rgb8(p.frame.data)
        ch[rec.CALIBRATION].log(rec.calibration_message(profile, w, h, t), log_time=t)
        ch[rec.IMAGE].log(rec.raw_image_message(p.frame.data, t), log_time=t)
        ch[PREVIEW].log(rec.raw_image_message(rgb, t, "rgb8"), log_time=t)
        depth, variance = to_depth(p.result.range, p.result.variance, uz)
        ch[rec.DEPTH].log(rec.raw_image_message(depth, t, "32FC1"), log_time=t)
        ch[rec.VARIANCE].log(rec.raw_image_message(variance, t, "32FC1"), log_time=t)
        ch[rec.REASONS].log(rec.raw_image_message(p.result.reasons, t, "mono8"), log_time=t)
        reading = self.rangefinder.latest() if self.rangefinder is not None else None
        if reading is not None:
            ch[rec.RANGEFINDER].log({"range_m": reading.range_m, "confidence": reading.confidence,
                                     "wall_time": reading.wall_time}, log_time=int(reading.wall_time * 1e9))
        if self._status_fn is not None and time.monotonic() >= self._next_status:
            self._next_status = time.monotonic() + 1.0
            ch[rec.STATUS].log(json.loads(json.dumps(self._status_fn(), default=str)), log_time=time.time_ns())
        if rays is not None:
            data, _n = point_cloud(p.result.range, rays, rgb, self.config.point_stride)
            f32, u8 = m.PackedElementFieldNumericType.Float32, m.PackedElementFieldNumericType.Uint8
            fields = [m.PackedElementField(name=n, offset=o, type=ty) for n, o, ty in
                      (("x", 0, f32), ("y", 4, f32), ("z", 8, f32), ("red", 12, u8), ("green", 13, u8), ("blue", 14, u8))]
            ch[POINTS].log(m.PointCloud(timestamp=rec.timestamp(t), frame_id=rec.FRAME_ID, point_stride=16,
                                        fields=fields, data=data), log_time=t)

