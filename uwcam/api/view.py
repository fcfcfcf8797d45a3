"""WS /api/v1/view: what the operator page draws — range, σ, reasons and the colour image.

One binary message per frame, encoded once per frame however many pages watch (in a worker
thread, never on the event loop or in the frame loop):

    b"UWV1" | u32 header length | header (JSON, padded to 8 bytes) | sections

The header's ``sections`` give each section's byte offset (from the start of the message),
length and layout:

* ``range``: uint16 little-endian, row-major, ``width × height`` of the range map sampled every
  ``step`` pixels. Values below ``invalid_base`` (65500) are the camera range in millimetres
  along the pixel's ray; ``invalid_base + r`` marks an invalid pixel with reason code r.
* ``sigma``: float16, the range's standard deviation in millimetres, at half the range
  section's resolution (σ varies slowly); NaN where invalid.
* ``colour``: a JPEG of the colour image, display-stretched from the sensor's full bit depth
  (per-channel percentiles, smoothed over frames, gamma 1/2.2) at half the image resolution.

Resolution: ``step`` fixes it; or ``width`` (pixels) says how wide the page draws the range map,
and each frame is sent at the coarsest step whose map is still that wide (full resolution for a
720p image costs 1.8 MB a frame; a pane half a screen wide shows no more than every other pixel).
The page sends ``{"width": N}`` when its layout changes.

Flow control: a page acknowledges each frame it has painted (``{"ack": N}``); the daemon keeps at
most ``window`` frames unacknowledged per page and otherwise skips to the newest, so a slow page
or link shows fresh frames at a lower rate and never a backlog.
"""

from __future__ import annotations

import asyncio
import json
import logging
import struct
import threading
import time
from dataclasses import dataclass, field

import cv2
import numpy as np
from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from numpy.typing import NDArray

from uwcam import __version__
from uwcam.api.common import Broadcaster
from uwcam.runtime.daemon import Daemon
from uwcam.optics.validity import Reason
from uwcam.runtime.published import Published

router = APIRouter(prefix="/api/v1", tags=["stream"])
MAGIC = b"UWV1"
INVALID_BASE = 65500
WINDOW = 2
"""Frames a page may have in flight (sent, not yet painted)."""
MAX_WIDTH = 16384
"""The widest drawing a page may ask for, pixels."""


def step_for_width(width: int, image_width: int) -> int:
    """The coarsest step (4, 2 or 1) whose range map (``ceil(image_width / step)`` wide) is still at
    least ``width`` pixels wide."""
    for step in (4, 2):
        if -(-image_width // step) >= width:
            return step
    return 1


def range_plane(range_m: NDArray[np.float32], reasons: NDArray[np.uint8], step: int) -> NDArray[np.uint16]:
    """Millimetres where valid, ``INVALID_BASE + reason`` where not; every ``step``-th pixel."""
    r = range_m[::step, ::step]
    mm = np.rint(r * 1000.0)
    np.clip(mm, 1.0, INVALID_BASE - 1.0, out=mm, where=np.isfinite(mm))
    out = np.where(np.isfinite(mm), mm, 0.0).astype("<u2")
    invalid = ~np.isfinite(r)
    out[invalid] = INVALID_BASE + np.maximum(reasons[::step, ::step][invalid], 1).astype(np.uint16)
    return out


def sigma_plane(variance_m2: NDArray[np.float32], step: int) -> NDArray[np.float16]:
    """σ in millimetres at every ``step``-th pixel, float16 (NaN where invalid)."""
    v = variance_m2[::step, ::step]
    with np.errstate(over="ignore"):  # σ over 65.5 m is float16's infinity, as meant: no warning per frame
        return (np.sqrt(v, dtype=np.float32) * 1000.0).astype("<f2")


@dataclass
class Stretch:
    """Display stretch of the colour image, smoothed over frames so that it does not flicker."""

    low: NDArray[np.float32] | None = None
    high: NDArray[np.float32] | None = None
    smoothing: float = 0.2
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def __call__(self, image: NDArray) -> NDArray[np.uint8]:
        """(H, W, C) at any bit depth → (H/2, W/2, 3) uint8 BGR for JPEG."""
        h, w = image.shape[:2]
        rgb = np.ascontiguousarray(image[:, :, :3]) if image.shape[2] >= 3 else np.repeat(image[:, :, :1], 3, axis=2)
        small = cv2.resize(rgb, (max(w // 2, 1), max(h // 2, 1)), interpolation=cv2.INTER_AREA)
        sample = small[::4, ::4].reshape(-1, 3).astype(np.float32)
        low = np.percentile(sample, 1.0, axis=0).astype(np.float32)
        high = np.percentile(sample, 99.7, axis=0).astype(np.float32)
        with self._lock:  # two resolutions may be encoded at once
            if self.low is None:
                self.low, self.high = low, high
            else:
                self.low = self.low + self.smoothing * (low - self.low)
                self.high = self.high + self.smoothing * (high - self.high)
            low, high = self.low, self.high
        span = np.maximum(high - low, 1.0)
        if small.dtype in (np.uint8, np.uint16):
            # Integer codes: the curve is computed once per code value and looked up per pixel
            # (a third of the CPU of computing it per pixel at 720p, the same bytes out).
            codes = np.arange(np.iinfo(small.dtype).max + 1, dtype=np.float32)
            out = np.empty(small.shape, np.uint8)
            for c in range(3):
                out[..., 2 - c] = np.take(display_curve(codes, low[c], span[c]), small[..., c])  # RGB → BGR
            return out
        return cv2.cvtColor(display_curve(small.astype(np.float32), low, span), cv2.COLOR_RGB2BGR)


def display_curve(values: NDArray[np.float32], low: NDArray[np.float32] | float,
                  span: NDArray[np.float32] | float) -> NDArray[np.uint8]:
    """Linear sensor values → display codes: ``low`` … ``low + span`` onto 0 … 255 with a gamma of
    1/2.2, roughly as sRGB does (linear values look dark on a display)."""
    x = (values - low) * (1.0 / span)
    np.clip(x, 0.0, 1.0, out=x)
    cv2.pow(x, 1.0 / 2.2, x)
    x *= 255.0
    return x.astype(np.uint8)


def colour_section(published: Published, stretch: Stretch) -> bytes:
    """The colour image as JPEG, display-stretched, at half resolution."""
    return cv2.imencode(".jpg", stretch(published.frame.data), [cv2.IMWRITE_JPEG_QUALITY, 80])[1].tobytes()


def encode_view(published: Published, step: int, colour: bytes | None) -> bytes:
    """One view message; ``colour`` (JPEG) is left out when None."""
    result = published.result
    rng = range_plane(result.range, result.reasons, step)
    sig = sigma_plane(result.variance, step * 2)
    h, w = result.range.shape
    header = {
        "frame": published.number, "capture_time_ns": int(published.frame.wall_time * 1e9),
        "encoded_time_ns": time.time_ns(), "image_width": w, "image_height": h,
        "lamp_on": published.frame.lamp_on, "latency_ms": round(published.latency_s * 1000.0, 2),
        "attenuation_differences": list(published.attenuation_differences),
    }
    pieces = [
        (rng.tobytes(), {"name": "range", "dtype": "uint16", "unit": "mm", "step": step, "width": rng.shape[1],
                         "height": rng.shape[0], "invalid_base": INVALID_BASE}),
        (sig.tobytes(), {"name": "sigma", "dtype": "float16", "unit": "mm", "step": step * 2, "width": sig.shape[1],
                         "height": sig.shape[0]}),
    ]
    if colour is not None:
        pieces.append((colour, {"name": "colour", "mime": "image/jpeg", "width": w // 2, "height": h // 2}))
    sections = [{**meta, "length": len(data)} for data, meta in pieces]
    header["sections"] = sections
    # Offsets depend on the header's own length, which depends on the offsets' digits: settle it
    # in two passes. Each section starts 8-byte aligned, so typed arrays can view it in place.
    for _ in range(2):
        offset = 8 + len(json.dumps(header, separators=(",", ":")).encode())
        for section in sections:
            offset += (-offset) % 8
            section["offset"] = offset
            offset += section["length"]
    text = json.dumps(header, separators=(",", ":")).encode()
    parts, position = [MAGIC, struct.pack("<I", len(text)), text], 8 + len(text)
    for (data, _), section in zip(pieces, sections):
        parts.append(b"\0" * (section["offset"] - position))
        parts.append(data)
        position = section["offset"] + len(data)
    return b"".join(parts)


@dataclass
class ViewEncoder:
    """Encodes each published frame on demand in worker threads: the colour JPEG once per frame,
    the range and σ planes once per resolution step, however many pages watch."""

    stretch: Stretch = field(default_factory=Stretch)
    _tasks: dict[tuple, asyncio.Future] = field(default_factory=dict)

    def _once(self, key: tuple, number: int, func, *args) -> asyncio.Future:
        task = self._tasks.get(key)
        if task is None:
            task = asyncio.ensure_future(asyncio.to_thread(func, *args))
            self._tasks[key] = task
            for old in [k for k in self._tasks if k[1] < number - 2]:
                del self._tasks[old]
        return task

    async def get(self, published: Published, step: int, colour: bool = True) -> bytes:
        n = published.number
        jpeg = await asyncio.shield(self._once(("colour", n), n, colour_section, published, self.stretch)) if colour else None
        return await asyncio.shield(self._once(("view", n, step, colour), n, encode_view, published, step, jpeg))


def hello(d: Daemon, step: int) -> dict:
    profile = d.pipeline.profile
    intr = profile.camera_intrinsics()
    return {
        "type": "hello", "version": __version__, "magic": MAGIC.decode(), "step": step, "window": WINDOW,
        "channels": profile.channel_names,
        "intrinsics": None if intr is None else {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy},
        "reasons": {str(k): v for k, v in Reason.describe().items()}, "invalid_base": INVALID_BASE,
        "path_length_bounds": list(d.pipeline.processing.path_length_bounds),
    }


@router.websocket("/view")
async def view(ws: WebSocket, step: int = 1, colour: bool = True, width: int | None = None) -> None:
    """The operator page's stream: hello (JSON), then one binary message per frame (see module doc);
    the page answers ``{"ack": frame}`` once it has painted a frame. ``step``: 1, 2 or 4 (resolution),
    or ``width``: the pixels the page draws the range map across, which picks the step per frame
    (``{"width": N}`` from the page changes it); ``colour=false`` leaves the colour image out (the
    Cockpit widget needs range only)."""
    await ws.accept()
    if step not in (1, 2, 4):
        await ws.close(code=1008, reason="step must be 1, 2 or 4")
        return
    if width is not None and not 1 <= width <= MAX_WIDTH:
        await ws.close(code=1008, reason=f"width must be 1 to {MAX_WIDTH} pixels")
        return
    drawn = {"width": width}
    b: Broadcaster = ws.app.state.broadcaster
    encoder: ViewEncoder = ws.app.state.view_encoder
    d: Daemon = ws.app.state.daemon
    await ws.send_text(json.dumps(hello(d, step if width is None else None)))  # with width: per frame
    last_sent = 0
    unacked: set[int] = set()
    changed = b.listen()

    async def read_acks() -> None:
        while True:
            message = await ws.receive()
            if message["type"] == "websocket.disconnect":
                return
            try:
                answer = json.loads(message.get("text") or "")
                if "width" in answer:
                    w = answer["width"]
                    if isinstance(w, int) and not isinstance(w, bool) and 1 <= w <= MAX_WIDTH:
                        drawn["width"] = w
                    continue
                n = int(answer["ack"])
            except (ValueError, KeyError, TypeError, OverflowError):
                continue  # a page's noise (binary, malformed) must not end its stream
            unacked.difference_update({k for k in unacked if k <= n})
            changed.set()  # a slot opened: look for the newest frame now

    reader = asyncio.ensure_future(read_acks())
    try:
        while not reader.done():
            published = b.latest
            if published is None or published.number == last_sent or len(unacked) >= WINDOW:
                waiter = asyncio.ensure_future(changed.wait())
                await asyncio.wait({waiter, reader}, timeout=0.5, return_when=asyncio.FIRST_COMPLETED)
                waiter.cancel()
                changed.clear()
                continue
            frame_step = step if drawn["width"] is None else step_for_width(drawn["width"], published.result.range.shape[1])
            payload = await encoder.get(published, frame_step, colour)
            await ws.send_bytes(payload)
            last_sent = published.number
            unacked.add(published.number)
    except (WebSocketDisconnect, RuntimeError):
        pass
    finally:
        b.forget(changed)
        reader.cancel()
        try:
            await reader
        except (asyncio.CancelledError, WebSocketDisconnect, RuntimeError):
            pass
        except Exception:  # the stream is over; its reader's trouble is only worth a debug line
            logging.getLogger("uwcam.api").debug("view stream reader ended", exc_info=True)
