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
from typing import Annotated, Literal

import cv2
import numpy as np
from fastapi import APIRouter, Query, WebSocket, WebSocketDisconnect

from uwcam import __version__
from uwcam.api.backpressure import SCOPE_KEY, Pace, unsent_bytes
from uwcam.api.common import Broadcaster
from uwcam.api.snapshots import range_millimetres
from uwcam.runtime.daemon import Daemon
from uwcam.runtime.published import Published

router = APIRouter(prefix="/api/v1", tags=["stream"])
HEADER = struct.Struct("<4sIqqHHB3xf")
MAGIC = b"UWR1"
FLOAT16_METRES, UINT16_MILLIMETRES = 1, 2


# The newest encoded range map per encoding, shared by every client: each frame is converted once,
# however many clients stream it. Read and written only on the event loop's thread.
_encoded: dict[str, tuple[tuple[int, int], memoryview]] = {}


def _encoded_map(published: Published, encoding: str) -> memoryview:
    key = (published.number, published.publish_monotonic_ns)
    hit = _encoded.get(encoding)
    if hit is not None and hit[0] == key:
        return hit[1]
    r = published.result.range
    if encoding == "mm":
        data = range_millimetres(r)
    else:
        # OpenCV's conversion (F16C instructions) is ~10× numpy's astype and gives the same bits;
        # adding −0.0 leaves every value, −0.0 and NaN included, as it is.
        data = cv2.add(r, -0.0, dtype=cv2.CV_16F).astype("<f2", copy=False)
    body = memoryview(np.ascontiguousarray(data)).cast("B")
    _encoded[encoding] = (key, body)
    return body


def encode_range(published: Published, encoding: str) -> bytes:
    """Header (send time now) and the newest range map, encoded once per frame for all clients."""
    h, w = published.result.range.shape
    dtype, scale = (UINT16_MILLIMETRES, 0.001) if encoding == "mm" else (FLOAT16_METRES, 1.0)
    header = HEADER.pack(MAGIC, published.number, int(published.frame.wall_time * 1e9), time.time_ns(), w, h, dtype, scale)
    return b"".join((header, _encoded_map(published, encoding)))


WINDOW = 1
"""Range maps a client that acknowledges may have unacknowledged (sent, not yet taken)."""


@router.websocket("/stream")
async def stream(ws: WebSocket, rate: Annotated[float, Query(gt=0, allow_inf_nan=False)] = 30.0,
                 encoding: Literal["float16", "mm"] = "float16", ack: bool = False) -> None:
    """Hello (JSON), then the newest range map per frame (binary) and telemetry (JSON, ~10 Hz).

    A client only ever gets the newest frame: while the previous message is still on its way
    (being sent, or not yet taken by the client from the network), newer frames are skipped,
    never queued; and the rate is lowered to what the client takes, so that its own buffers
    hold no backlog either (:mod:`uwcam.api.backpressure`). With ``ack=true`` the client asks for each
    map: ``{"ack": 0}`` for the first, ``{"ack": N}`` after the map of frame N when it wants the
    next; it is sent at most one map it has not acknowledged, so whatever its pace the map it
    gets was the newest when it asked (its own buffers can hold no backlog). ``rate``: frames per
    second, above 0 and finite (at most ``api.stream_rate_hz`` is sent); a bad query (NaN, 0, an
    unknown ``encoding``) is refused before the connection is accepted, as FastAPI refuses it (HTTP 403).
    """
    await ws.accept()
    # Clients connected now, for /metrics; changed only on the event loop, so no lock.
    ws.app.state.stream_clients = getattr(ws.app.state, "stream_clients", 0) + 1
    try:
        await _serve(ws, rate, encoding, ack)
    finally:
        ws.app.state.stream_clients -= 1


class _Flow:
    """What a client has acknowledged: once it acknowledges at all, at most ``WINDOW`` maps unacknowledged."""

    def __init__(self, acking: bool) -> None:
        self.acking = acking
        # Acknowledging from the start: the first map waits for {"ack": 0}, so that none is
        # sent before the client asks (it would wait in the client's buffers meanwhile).
        self.unacked: set[int] = {0} if acking else set()

    def may_send_map(self) -> bool:
        return not self.acking or len(self.unacked) < WINDOW

    def ack(self, number: int) -> None:
        self.acking = True
        self.unacked.difference_update({k for k in self.unacked if k <= number})


async def _read_acks(ws: WebSocket, flow: _Flow, changed: asyncio.Event) -> None:
    """Takes the client's messages: acknowledgements count, anything else is ignored."""
    while True:
        message = await ws.receive()
        if message["type"] == "websocket.disconnect":
            return
        try:
            number = int(json.loads(message.get("text") or "")["ack"])
        except (ValueError, KeyError, TypeError, OverflowError):
            continue  # a client's noise (binary, malformed) must not end its stream
        flow.ack(number)
        changed.set()  # a slot opened: look for the newest frame now


async def _serve(ws: WebSocket, rate: float, encoding: str, ack: bool) -> None:
    rate = min(max(rate, 0.1), ws.app.state.config.api.stream_rate_hz)
    b: Broadcaster = ws.app.state.broadcaster
    d: Daemon = ws.app.state.daemon
    connection = ws.scope.get(SCOPE_KEY)
    await ws.send_text(json.dumps({
        "type": "hello", "version": __version__,
        "binary": {"header": "<4sIqqHHB3xf", "fields": ["magic", "frame", "capture_time_ns", "send_time_ns", "width",
                                                      "height", "dtype", "scale"],
                   "magic": MAGIC.decode(), "dtypes": {"1": "float16 metres", "2": "uint16 millimetres, 0 invalid"},
                   "encoding": encoding},
        "telemetry_hz": 10, "rate_hz": rate,
        "ack": {"enabled": ack, "window": WINDOW, "message": '{"ack": <frame>}',
                "meaning": "with ?ack=true, send {\"ack\": 0} for the first range map and {\"ack\": N} "
                           "after frame N's when you want the next: at most one unacknowledged map is sent"},
    }))

    async def send_frame(published: Published) -> None:
        data = await asyncio.to_thread(encode_range, published, encoding)  # a 1080p map: off the loop
        # Sending may outlast the frame's turn as the newest: the frame (a 1080p one, raw and
        # results, is 31 MB) is not kept alive for it, only the encoded map.
        del published
        await ws.send_bytes(data)

    def telemetry() -> str:
        s = d.status()
        return json.dumps({"type": "telemetry", "frames": s["frames"], "latency_ms": s["latency_ms"],
                           "camera": s["camera"]["health"] if s["camera"] else None,
                           "rangefinder": s["rangefinder"]}, default=str)

    flow, changed = _Flow(ack), b.listen()
    reader = asyncio.ensure_future(_read_acks(ws, flow, changed))
    last_sent, next_telemetry, next_frame = 0, 0.0, 0.0
    pace, sent_at = Pace(rate, time.monotonic()), None  # sent_at: when the message in flight was sent (monotonic s)
    in_flight: asyncio.Task | None = None
    try:
        while not reader.done():
            try:
                await asyncio.wait_for(changed.wait(), timeout=0.02 if in_flight or connection else 0.1)
            except TimeoutError:
                pass
            changed.clear()
            if in_flight is not None:
                if not in_flight.done():
                    continue  # still sending: whatever is newer waits for the next turn
                in_flight.result()  # a closed connection ends the stream here
                in_flight = None
            if unsent_bytes(connection):
                continue  # the client has not taken the last message yet
            now = time.monotonic()
            if sent_at is not None:
                pace.taken(now - sent_at, now)
                sent_at = None
            if now >= next_telemetry and flow.may_send_map():  # acking: telemetry at the client's pace too
                next_telemetry = now + max(0.1, pace.period_s)
                in_flight, sent_at = asyncio.create_task(ws.send_text(telemetry())), now
                continue
            if b.latest is not None and b.latest.number != last_sent and now >= next_frame and flow.may_send_map():
                newest = b.latest  # read once: the loop's thread replaces it at any time
                last_sent, next_frame, sent_at = newest.number, now + pace.period_s, now
                pace.sent_map()
                if flow.acking:
                    flow.unacked.add(newest.number)
                in_flight = asyncio.create_task(send_frame(newest))
                del newest  # held by the task alone, and only until it is encoded
    except (WebSocketDisconnect, RuntimeError, OSError):
        return
    finally:
        b.forget(changed)
        for task in (in_flight, reader):
            if task is not None and not task.done():
                task.cancel()
        try:
            await reader
        except (asyncio.CancelledError, WebSocketDisconnect, RuntimeError, OSError):
            pass
