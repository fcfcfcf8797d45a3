"""WS /api/v1/stream: the newest range map per frame (binary) and telemetry (JSON).

Binary stream messages: a 36-byte little-endian header (struct ``<4sIqqHHB3xf``: magic
b"UWR1", frame number, capture time and send time in ns since the epoch, width, height,
data type (1 = float16 metres, 2 = uint16 millimetres, 0 invalid), scale in metres per
unit), then the range map row-major.
"""

from __future__ import annotations

import asyncio
import json
import struct
import time
from typing import Literal

from fastapi import APIRouter, WebSocket, WebSocketDisconnect

from uwcam import __version__
from uwcam.api.common import Broadcaster
from uwcam.api.snapshots import range_millimetres
from uwcam.daemon import Daemon
from uwcam.pipeline import Published

router = APIRouter(prefix="/api/v1", tags=["stream"])
HEADER = struct.Struct("<4sIqqHHB3xf")
MAGIC = b"UWR1"
FLOAT16_METRES, UINT16_MILLIMETRES = 1, 2


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


@router.websocket("/stream")
async def stream(ws: WebSocket, rate: float = 30.0, encoding: Literal["float16", "mm"] = "float16") -> None:
    """Hello (JSON), then the newest range map per frame (binary) and telemetry (JSON, ~10 Hz)."""
    await ws.accept()
    # Clients connected now, for /metrics; changed only on the event loop, so no lock.
    ws.app.state.stream_clients = getattr(ws.app.state, "stream_clients", 0) + 1
    try:
        await _serve(ws, rate, encoding)
    finally:
        ws.app.state.stream_clients -= 1


async def _serve(ws: WebSocket, rate: float, encoding: str) -> None:
    rate = min(max(rate, 0.1), ws.app.state.config.api.stream_rate_hz)
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
