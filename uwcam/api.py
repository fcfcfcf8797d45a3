"""REST and WebSocket API (FastAPI). OpenAPI at /docs.

The API reads the frame loop's published state and never blocks it: the loop calls back
with each published frame, the callback only records "newest" and sets an asyncio event
thread-safely, and every WebSocket client sends the newest frame when it can: a slow client
skips frames instead of building a backlog.

Binary stream messages: a 36-byte little-endian header (struct ``<4sIqqHHB3xf``: magic
b"UWR1", frame number, capture time and send time in ns since the epoch, width, height,
data type (1 = float16 metres, 2 = uint16 millimetres, 0 invalid), scale in metres per
unit), then the range map row-major.
"""

from __future__ import annotations

import asyncio
import hmac
import io
import ipaddress
import json
import logging
import os
import re
import struct
import time
from contextlib import asynccontextmanager
from typing import Annotated, Literal

import cv2
import numpy as np
import tifffile
from fastapi import Depends, FastAPI, HTTPException, Query, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import JSONResponse, PlainTextResponse, Response
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from uwcam import __version__
from uwcam.config import DaemonConfig, PatchConfig, ProcessingConfig
from uwcam.daemon import Daemon
from uwcam.fileio import UserInputError
from uwcam.optics.geometry import pixel_rays
from uwcam.pipeline import Published

HEADER = struct.Struct("<4sIqqHHB3xf")
MAX_PROFILE_BYTES = 1 << 20
NAME = re.compile(r"[A-Za-z0-9._-]{1,64}")
MAGIC = b"UWR1"
FLOAT16_METRES, UINT16_MILLIMETRES = 1, 2


def is_loopback(host: str) -> bool:
    if host in ("localhost", ""):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def required_token(config: DaemonConfig) -> str | None:
    """The bearer token for state-changing endpoints; UserInputError if one is needed and missing."""
    token = config.api.token or os.environ.get("UWCAM_TOKEN")
    if not is_loopback(config.api.host) and not token:
        raise UserInputError(
            f"refusing to listen on {config.api.host} without a token: set api.token in the configuration or UWCAM_TOKEN"
        )
    return token


class LampCommand(BaseModel):
    model_config = ConfigDict(extra="forbid")
    on: bool | None = None
    intensity: Annotated[float, Field(ge=0, le=100)] | None = None
    """Percent."""


class ProcessingPatch(BaseModel):
    """Live-tunable processing settings; omitted keys keep their value."""

    model_config = ConfigDict(extra="forbid")
    pair: tuple[str, str] | None = None
    fuse: bool | None = None
    """true: fuse all channels (clears pair)."""
    smoothing: Literal["none", "mean", "median"] | None = None
    smoothing_stage: Literal["after", "before"] | None = None
    path_length_bounds: tuple[float, float] | None = None
    patch: PatchConfig | None = None
    lamp_off_interval: Annotated[int, Field(ge=0)] | None = None


class Broadcaster:
    """Newest published frame, handed from the loop's thread to the event loop without blocking."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self.latest: Published | None = None
        self.changed = asyncio.Event()

    def publish(self, published: Published) -> None:  # called in the processing thread
        self.latest = published
        self.loop.call_soon_threadsafe(self.changed.set)


def range_millimetres(range_m: np.ndarray) -> np.ndarray:
    """Range in metres → little-endian uint16 millimetres, 0 where invalid (1 mm at the least)."""
    return np.where(np.isfinite(range_m), np.clip(np.rint(range_m * 1000.0), 1, 65535), 0).astype("<u2")


def encode_range(published: Published, encoding: str) -> bytes:
    r = published.result.range
    h, w = r.shape
    if encoding == "mm":
        data = range_millimetres(r)
        dtype, scale = UINT16_MILLIMETRES, 0.001
    else:
        data = r.astype("<f2")
        dtype, scale = FLOAT16_METRES, 1.0
    header = HEADER.pack(MAGIC, published.number, int(published.frame.wall_time * 1e9), time.time_ns(), w, h, dtype, scale)
    return header + data.tobytes()


def create_app(config: DaemonConfig, daemon: Daemon | None = None) -> FastAPI:
    token = required_token(config)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        d = daemon or Daemon(config)
        await asyncio.to_thread(d.start)
        app.state.daemon = d
        app.state.broadcaster = Broadcaster(asyncio.get_running_loop())
        d.pipeline.subscribe(app.state.broadcaster.publish)
        try:
            yield
        finally:
            d.pipeline.unsubscribe(app.state.broadcaster.publish)
            await asyncio.to_thread(d.stop)

    app = FastAPI(title="uwcam", version=__version__, lifespan=lifespan,
                  description="Underwater ranging camera: range maps from colour attenuation, live.")

    @app.exception_handler(UserInputError)
    async def _user_error(request: Request, exc: UserInputError):
        return JSONResponse(status_code=400, content={"error": str(exc)})

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception):
        # A clear JSON message, never a stack trace; the trace goes to the daemon's log.
        logging.getLogger("uwcam.api").exception("unexpected error in %s %s", request.method, request.url.path)
        return JSONResponse(status_code=500, content={"error": f"internal error ({type(exc).__name__}); see the daemon log"})

    def get_daemon(request: Request) -> Daemon:
        return request.app.state.daemon

    def authorised(request: Request) -> None:
        if token is None:
            return
        given = request.headers.get("authorization", "")
        if not hmac.compare_digest(given, f"Bearer {token}"):
            raise HTTPException(status_code=401, detail="this endpoint changes state: send 'Authorization: Bearer <token>'")

    def latest(d: Daemon) -> Published:
        published = d.pipeline.latest if d.pipeline else None
        if published is None:
            raise HTTPException(status_code=503, detail="no frame processed yet; see /api/v1/status")
        return published

    @app.get("/api/v1/status")
    def status(d: Daemon = Depends(get_daemon)) -> dict:
        """Health of every device, frame counters, fps, latency, calibration and tracking, rangefinder, lamp."""
        return d.status()

    # Registered before /snapshot/{kind}, which would otherwise match it first.
    @app.get("/api/v1/snapshot/pointcloud", responses={200: {"content": {"application/octet-stream": {}}}})
    def pointcloud(d: Daemon = Depends(get_daemon)) -> Response:
        """The latest range map as a binary PLY point cloud (camera frame, metres; colour from the image)."""
        published = latest(d)
        profile = d.profiles[d.profile_name]
        intr = profile.camera_intrinsics()
        if intr is None:
            raise HTTPException(status_code=409, detail="a point cloud needs camera intrinsics in the calibration profile")
        r = published.result.range
        rays = pixel_rays(intr, *r.shape)
        ok = np.isfinite(r)
        xyz = (r[ok, None] * rays[ok]).astype("<f4")
        img = published.frame.data[ok][:, :3].astype(np.float64)
        peak = float(img.max()) if img.size else 1.0  # a frame may have no valid pixel at all (lamp off)
        rgb = np.clip(img / max(peak, 1.0) * 255.0, 0, 255).astype(np.uint8)
        vertex = np.empty(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
        vertex["x"], vertex["y"], vertex["z"] = xyz.T
        vertex["red"], vertex["green"], vertex["blue"] = rgb.T
        header = ("ply\nformat binary_little_endian 1.0\n"
                  f"comment uwcam frame {published.number}\nelement vertex {len(vertex)}\n"
                  "property float x\nproperty float y\nproperty float z\n"
                  "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n").encode()
        return Response(header + vertex.tobytes(), media_type="application/octet-stream",
                        headers={"X-Frame-Number": str(published.number)})

    @app.get("/api/v1/snapshot/{kind}", responses={200: {"content": {"application/octet-stream": {}, "image/png": {},
                                                                      "image/tiff": {}}}})
    def snapshot(kind: Literal["range", "variance", "reasons", "image"],
                 format: Literal["npy", "tiff", "png16", "png"] = Query("npy"),
                 d: Daemon = Depends(get_daemon)) -> Response:
        """The latest processed frame's range (m), variance (m²), reason codes or colour image.
        png16: range in millimetres as uint16, 0 invalid. png: the colour image (8 or 16 bit)."""
        published = latest(d)
        data = {"range": published.result.range, "variance": published.result.variance,
                "reasons": published.result.reasons, "image": published.frame.data}[kind]
        headers = {"X-Frame-Number": str(published.number), "X-Capture-Time": f"{published.frame.wall_time:.6f}"}
        if format == "npy":
            buf = io.BytesIO()
            np.save(buf, data, allow_pickle=False)
            return Response(buf.getvalue(), media_type="application/octet-stream", headers=headers)
        if format == "tiff":
            buf = io.BytesIO()
            tifffile.imwrite(buf, data)
            return Response(buf.getvalue(), media_type="image/tiff", headers=headers)
        if format == "png16":
            if kind != "range":
                raise HTTPException(status_code=422, detail="png16 is for the range map (millimetres); use npy or tiff")
            mm = range_millimetres(data)
            return Response(cv2.imencode(".png", mm)[1].tobytes(), media_type="image/png", headers=headers)
        if kind != "image":
            raise HTTPException(status_code=422, detail="png is for the colour image; use png16, npy or tiff for maps")
        bgr = cv2.cvtColor(data[:, :, :3], cv2.COLOR_RGB2BGR)
        return Response(cv2.imencode(".png", bgr)[1].tobytes(), media_type="image/png", headers=headers)

    @app.get("/api/v1/config")
    def get_config(d: Daemon = Depends(get_daemon)) -> dict:
        """The live-tunable processing settings."""
        return d.pipeline.processing.model_dump(mode="json")

    @app.patch("/api/v1/config", dependencies=[Depends(authorised)])
    def patch_config(change: ProcessingPatch, d: Daemon = Depends(get_daemon)) -> dict:
        """Change processing settings; validated before they apply, the previous ones kept on error."""
        current = d.pipeline.processing.model_dump()
        update = change.model_dump(exclude_unset=True)
        if update.pop("fuse", None):
            current["pair"] = None
        current.update(update)
        try:
            new = ProcessingConfig.model_validate(current)
        except ValidationError as exc:
            raise HTTPException(status_code=422, detail=exc.errors(include_url=False, include_context=False)) from None
        names = d.pipeline.profile.channel_names
        if new.pair is not None and (len(set(new.pair)) != 2 or any(p not in names for p in new.pair)):
            raise HTTPException(status_code=422, detail=f"pair needs two different channels of {names}")
        try:
            d.pipeline.reconfigure(new)
        except ValueError as exc:  # e.g. a lamp-off interval without a lamp
            raise HTTPException(status_code=422, detail=str(exc)) from None
        return new.model_dump(mode="json")

    @app.post("/api/v1/config/restore", dependencies=[Depends(authorised)])
    def restore_config(d: Daemon = Depends(get_daemon)) -> dict:
        """Go back to the processing settings that were in force before the last change."""
        try:
            return d.pipeline.restore().model_dump(mode="json")
        except ValueError as exc:
            raise HTTPException(status_code=409, detail=str(exc)) from None

    @app.get("/api/v1/calibration/profiles")
    def list_profiles(d: Daemon = Depends(get_daemon)) -> list[dict]:
        """Known calibration profiles; one is active."""
        return [{"name": name, "active": name == d.profile_name, "created": p.provenance.created,
                 "channels": p.channel_names, "method": p.provenance.method} for name, p in d.profiles.items()]

    @app.get("/api/v1/calibration/profiles/{name}")
    def get_profile(name: str, d: Daemon = Depends(get_daemon)) -> dict:
        if name not in d.profiles:
            raise HTTPException(status_code=404, detail=f"no profile '{name}'; known: {', '.join(d.profiles)}")
        return d.profiles[name].model_dump(mode="json")

    @app.put("/api/v1/calibration/profiles/{name}", dependencies=[Depends(authorised)], openapi_extra={
        "requestBody": {"required": True, "content": {
            "application/x-yaml": {"schema": {"type": "string"}},
            "application/json": {"schema": {"type": "object", "description": "a uwcam calibration profile"}}}}})
    async def upload_profile(name: str, request: Request, d: Daemon = Depends(get_daemon)) -> dict:
        """Upload a profile (YAML or JSON body, at most 1 MiB). It is validated in full; a bad one
        is refused with the reason and changes nothing. Uploading does not activate it."""
        import yaml

        from uwcam.profile import profile_from_mapping

        if not NAME.fullmatch(name):
            raise HTTPException(status_code=422, detail="profile names use letters, digits, '.', '_' and '-' (1–64)")
        body = await request.body()
        if len(body) > MAX_PROFILE_BYTES:
            raise HTTPException(status_code=413, detail=f"profile larger than {MAX_PROFILE_BYTES} bytes")
        try:
            data = yaml.safe_load(body.decode("utf-8"))
        except (UnicodeDecodeError, yaml.YAMLError) as exc:
            raise HTTPException(status_code=422, detail=f"profile is not valid YAML or JSON: {exc}") from None
        if not isinstance(data, dict):
            raise HTTPException(status_code=422, detail="profile must be a mapping of keys to values")
        try:
            profile = profile_from_mapping(data, f"profile {name}")
        except UserInputError as exc:
            raise HTTPException(status_code=422, detail=str(exc)) from None
        d.save_profile(name, profile)
        return {"name": name, "active": name == d.profile_name, "channels": profile.channel_names}

    @app.post("/api/v1/calibration/profiles/{name}/activate", dependencies=[Depends(authorised)])
    def activate_profile(name: str, d: Daemon = Depends(get_daemon)) -> dict:
        if name not in d.profiles:
            raise HTTPException(status_code=404, detail=f"no profile '{name}'; known: {', '.join(d.profiles)}")
        try:
            d.activate(name)
        except UserInputError as exc:
            raise HTTPException(status_code=422, detail=str(exc)) from None
        return {"name": name, "active": True}

    @app.get("/api/v1/lamp")
    def get_lamp(d: Daemon = Depends(get_daemon)) -> dict:
        if d.lamp is None:
            raise HTTPException(status_code=404, detail="no lamp configured")
        s = d.lamp.status()
        return {"on": s.on, "intensity": s.percent, "temperature_c": s.temperature_c, "fault": s.fault,
                "health": d.lamp.health.as_dict()}

    @app.put("/api/v1/lamp", dependencies=[Depends(authorised)])
    def put_lamp(command: LampCommand, d: Daemon = Depends(get_daemon)) -> dict:
        if d.lamp is None:
            raise HTTPException(status_code=404, detail="no lamp configured")
        try:
            if command.intensity is not None:
                d.lamp.set_intensity(command.intensity)
            if command.on is True:
                d.lamp.on()
            elif command.on is False:
                d.lamp.off()
        except Exception as exc:
            raise HTTPException(status_code=502, detail=f"lamp did not accept the command: {exc}") from None
        return get_lamp(d)  # reads the lamp's status back, so status() shows it too

    @app.get("/metrics", response_class=PlainTextResponse)
    def metrics(d: Daemon = Depends(get_daemon)) -> str:
        """Prometheus text format."""
        s = d.status()
        lines = [
            "# TYPE uwcam_frames_captured_total counter", f"uwcam_frames_captured_total {s['frames']['captured']}",
            "# TYPE uwcam_frames_processed_total counter", f"uwcam_frames_processed_total {s['frames']['processed']}",
            "# TYPE uwcam_frames_dropped_total counter", f"uwcam_frames_dropped_total {s['frames']['dropped']}",
            "# TYPE uwcam_fps gauge", f"uwcam_fps {s['frames']['fps']}",
        ]
        if s["latency_ms"]:
            lines += ["# TYPE uwcam_latency_ms gauge",
                      f'uwcam_latency_ms{{quantile="0.5"}} {s["latency_ms"]["p50"]}',
                      f'uwcam_latency_ms{{quantile="0.99"}} {s["latency_ms"]["p99"]}']
        camera = s["camera"]["health"]["state"] if s["camera"] else "none"
        lines += ["# TYPE uwcam_camera_ok gauge", f"uwcam_camera_ok {int(camera == 'ok')}"]
        return "\n".join(lines) + "\n"

    @app.websocket("/api/v1/stream")
    async def stream(ws: WebSocket, rate: float = 30.0, encoding: Literal["float16", "mm"] = "float16") -> None:
        """Hello (JSON), then the newest range map per frame (binary) and telemetry (JSON, ~10 Hz)."""
        await ws.accept()
        rate = min(max(rate, 0.1), config.api.stream_rate_hz)
        b: Broadcaster = ws.app.state.broadcaster
        d: Daemon = ws.app.state.daemon
        await ws.send_text(json.dumps({
            "type": "hello", "version": __version__,
            "binary": {"header": "<4sIqqHHB3xf", "fields": ["magic", "frame", "capture_time_ns", "send_time_ns", "width",
                                                          "height", "dtype", "scale"],
                       "magic": MAGIC.decode(), "dtypes": {"1": "float16 metres", "2": "uint16 millimetres, 0 invalid"},
                       "encoding": encoding},
            "telemetry_hz": 10, "rate_hz": rate,
        }))
        last_sent, next_telemetry, period = 0, 0.0, 1.0 / rate
        try:
            while True:
                try:
                    await asyncio.wait_for(b.changed.wait(), timeout=0.1)
                except TimeoutError:
                    pass
                b.changed.clear()
                now = time.monotonic()
                if now >= next_telemetry:
                    next_telemetry = now + 0.1
                    s = d.status()
                    await ws.send_text(json.dumps({"type": "telemetry", "frames": s["frames"], "latency_ms": s["latency_ms"],
                                                   "camera": s["camera"]["health"] if s["camera"] else None,
                                                   "rangefinder": s["rangefinder"]}, default=str))
                published = b.latest
                if published is not None and published.number != last_sent:
                    await ws.send_bytes(encode_range(published, encoding))
                    last_sent = published.number
                    await asyncio.sleep(max(0.0, period - (time.monotonic() - now)))
        except (WebSocketDisconnect, RuntimeError):
            return

    return app
