"""Remote monitoring on Zenoh: status, range summaries, small previews and device health published
under a key prefix (``uwcam/<vehicle>``), within a bandwidth budget, for a topside computer on a
thin link (docs/api.md, "Zenoh").

An output of the frame loop: the loop's callback only appends the published frame to a short
queue that keeps the newest (the oldest is dropped and counted); this output's own thread turns
every queued frame into a range summary, and at most ``preview_rate_hz`` times a second the newest
into a preview, sized and paced so that everything published stays within ``budget_kbit_s``.
Queryables answer ``get`` with the latest value of each key, so a late subscriber sees the state
at once. Read-only: nothing subscribes to commands, so nothing can be changed over Zenoh.
"""

from __future__ import annotations

import json
import logging
import math
import socket
import time
from collections import deque
from collections.abc import Callable

import cv2
import numpy as np

from uwcam.config import ZenohConfig
from uwcam.extras import require_extra
from uwcam.fileio import UserInputError
from uwcam.outputs.foxglove import preview_rgb8
from uwcam.outputs.mavlink_measure import region_statistic
from uwcam.runtime.pipeline import FramePipeline
from uwcam.runtime.published import Published
from uwcam.outputs.subscriber import ThreadedOutput

log = logging.getLogger(__name__)

STATUS, SUMMARY, PREVIEW_RANGE, PREVIEW_COLOUR, HEALTH, ALERTS = (
    "status", "range/summary", "range/preview/range", "range/preview/colour", "health", "alerts")
JSON, PNG, JPEG = "application/json", "image/png", "image/jpeg"
"""Zenoh encodings (MIME types) of the payloads."""
DEVICES = ("camera", "lamp", "rangefinder")
"""Devices of /api/v1/status whose health goes to ``health/<device>``."""
STATUS_PERIOD_S = 1.0
QUEUE_FRAMES = 8
ALERTS_QUEUE = 64
"""Alert documents waiting for the thread at most (events are rare; this only bounds a stuck thread)."""
"""Published frames waiting for their summary; beyond this the oldest is dropped and counted."""
SUMMARY_WIDTH = 320
"""Summaries are computed on the range map subsampled to at most this many pixels across: the
figures barely change, and a 4K frame's summary stays cheap at the full frame rate."""
MINIMUM_BLOCK = 8
"""The minimum range is the smallest median over square tiles of this many (subsampled) pixels."""
MIN_PREVIEW_WIDTH = 16
BUDGET_SHARE = 0.9
"""Previews plan for this share of what the budget leaves them: the rest absorbs the variation
of the other keys' rates."""
SLOWEST_SHARE = 0.25
"""Previews first slow down, to this share of ``preview_rate_hz``, and only then shrink: a
preview every few seconds says more than a thumbnail too small to read."""
BUCKET_S = 2.0
"""The budget's bucket holds at most this many seconds of the budget (the largest burst)."""
RATE_WINDOW_S = 5.0
"""Bytes per second per key are measured over this last stretch of time."""


def require_zenoh():
    """The zenoh module; UserInputError naming the extra to install when it is missing."""
    return require_extra("zenoh")


def open_session(mode: str, listen: list[str], connect: list[str], scouting: bool, hint: str):
    """A Zenoh session in ``mode`` (peer or client) on these endpoints; UserInputError ending with
    ``hint`` (what to check) when Zenoh refuses it."""
    zenoh = require_zenoh()
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(scouting))
    try:
        return zenoh.open(conf)
    except Exception as exc:  # zenoh raises its own ZError for a taken port or an unreachable router
        raise UserInputError(f"cannot open the Zenoh session ({exc}); {hint}") from None


def close_session(session, *declared) -> None:
    """Undeclare what was declared on ``session`` (subscribers, queryables), then close it; parts
    that are None (never opened) are passed over."""
    for entity in declared:
        if entity is not None:
            entity.undeclare()
    if session is not None:
        session.close()


def default_key_prefix() -> str:
    """uwcam/<host name>, the host name reduced to the characters a key allows."""
    host = "".join(c if c.isalnum() or c in "_-" else "_" for c in socket.gethostname()) or "vehicle"
    return f"uwcam/{host}"


def _figure(value: float | None, digits: int = 4) -> float | None:
    return None if value is None or not math.isfinite(value) else round(float(value), digits)


def range_summary(published: Published) -> dict:
    """What one processed frame says, in a few figures. Ranges are camera range along the ray (m);
    ``centre_m`` is the median of the valid pixels in the central fifth of the image (width and
    height), ``minimum_m`` the smallest median over small tiles (no single noisy pixel sets it),
    each with its σ (square root of the median per-pixel variance, m); ``valid_fraction`` is the
    share of the whole image with a valid range; ``time`` the capture time (Unix seconds)."""
    r, v = published.result.range, published.result.variance
    step = max(1, -(-r.shape[1] // SUMMARY_WIDTH))
    r, v = r[::step, ::step], v[::step, ::step]
    h, w = r.shape
    ch, cw = max(h // 5, 1), max(w // 5, 1)
    y0, x0 = (h - ch) // 2, (w - cw) // 2
    centre, centre_var, _ = region_statistic(r[y0:y0 + ch, x0:x0 + cw], v[y0:y0 + ch, x0:x0 + cw], "median", 1)
    minimum, minimum_var, valid = region_statistic(r, v, "minimum", MINIMUM_BLOCK)
    return {
        "frame": published.number,
        "time": round(published.frame.wall_time, 6),
        "centre_m": _figure(centre),
        "centre_sigma_m": _figure(None if centre_var is None else math.sqrt(centre_var)),
        "minimum_m": _figure(minimum),
        "minimum_sigma_m": _figure(None if minimum_var is None else math.sqrt(minimum_var)),
        "valid_fraction": round(valid, 4),
    }


def area_mean(values: np.ndarray, width: int, height: int) -> np.ndarray:
    """(h, w) float values with NaN where invalid → (height, width) means of the valid values each
    output pixel covers; NaN where fewer than half of them are valid. The mean of n pixels has 1/√n
    of their noise, and noise is what makes a range map compress badly."""
    ok = np.isfinite(values)
    total = cv2.resize(np.where(ok, values, 0).astype(np.float32), (width, height), interpolation=cv2.INTER_AREA)
    share = cv2.resize(ok.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(share >= 0.5, total / share, np.nan)


def preview_images(published: Published, width: int, quality: int) -> tuple[bytes, bytes]:
    """(range, colour) previews ``width`` pixels across at most: the range as a 16-bit PNG in
    millimetres rounded to whole centimetres (0 where invalid) and the colour image as a
    display-stretched JPEG."""
    from uwcam.api.snapshots import range_millimetres

    r = published.result.range
    h, w = r.shape
    width = min(width, w)
    height = max(1, round(h * width / w))
    small = area_mean(r, width, height)
    # Whole centimetres: the millimetres of a single pixel are noise, and noise does not compress.
    rng = cv2.imencode(".png", range_millimetres(np.round(small, 2)))[1].tobytes()
    rgb = cv2.resize(preview_rgb8(published.frame.data), (width, height), interpolation=cv2.INTER_AREA)
    colour = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])[1].tobytes()
    return rng, colour


def alerts_document(event, active: list) -> bytes:
    """The ``alerts`` payload: the event (None in the first one) and every alert active after it."""
    return json.dumps({"event": None if event is None else event.as_dict(),
                       "active": [a.as_dict() for a in active]}).encode()


class ByteRates:
    """Bytes published per key over the last ``window_s`` seconds (not thread-safe: one owner)."""

    def __init__(self, window_s: float = RATE_WINDOW_S) -> None:
        self.window_s = window_s
        self._sent: deque[tuple[float, str, int]] = deque()
        self._started = time.monotonic()

    def add(self, key: str, nbytes: int, now: float) -> None:
        self._sent.append((now, key, nbytes))

    def rates(self, now: float) -> dict[str, float]:
        """Bytes per second per key over the window (or since the start, if shorter)."""
        while self._sent and self._sent[0][0] < now - self.window_s:
            self._sent.popleft()
        span = max(min(self.window_s, now - self._started), 1.0)
        out: dict[str, float] = {}
        for _t, key, n in self._sent:
            out[key] = out.get(key, 0.0) + n
        return {k: v / span for k, v in out.items()}


class ByteBucket:
    """A token bucket of bytes: fills at ``rate`` bytes/s up to ``capacity``; everything published
    is spent from it, the mandatory keys even into debt (down to −capacity), and a preview is sent
    only when the bucket holds what it costs. Over any stretch of time the bytes
    published therefore stay within rate × time + capacity, however the other keys vary, as long
    as the mandatory ones alone fit."""

    def __init__(self, rate: float, capacity: float) -> None:
        self.rate, self.capacity = rate, capacity
        self.level = 0.0  # empty at start: no burst on joining
        self._t: float | None = None

    def refill(self, now: float) -> None:
        if self._t is not None:
            self.level = min(self.capacity, self.level + max(now - self._t, 0.0) * self.rate)
        self._t = now if self._t is None else max(self._t, now)

    def spend(self, nbytes: int, now: float) -> None:
        self.refill(now)
        self.level = max(-self.capacity, self.level - nbytes)


def next_preview_width(width: int, sent_bytes: int, target_bytes: float, largest: int) -> int:
    """The preview width that should make a preview of about ``target_bytes``: compressed images
    grow roughly with their area, so the width scales with the square root of the ratio, by at most
    a factor 2 down and 1.25 up a step, within [MIN_PREVIEW_WIDTH, largest]."""
    if sent_bytes <= 0 or target_bytes <= 0:
        return MIN_PREVIEW_WIDTH if target_bytes <= 0 else width
    factor = min(max(math.sqrt(target_bytes / sent_bytes), 0.5), 1.25)
    if 0.8 < factor < 1.0 or (factor >= 1.0 and sent_bytes > 0.6 * target_bytes):
        factor = 1.0  # close enough: keep the size steady rather than hunt around it
    return int(min(max(round(width * factor), MIN_PREVIEW_WIDTH), largest))


class ZenohOutput(ThreadedOutput):
    """The Zenoh session, its queryable and the publishing thread."""

    def __init__(self, pipeline: FramePipeline, config: ZenohConfig, status: Callable[[], dict] | None = None) -> None:
        super().__init__(pipeline, "zenoh-output")
        self.config = config
        self.prefix = config.key_prefix or default_key_prefix()
        self._status_fn = status
        self._queue: deque[Published] = deque(maxlen=QUEUE_FRAMES)
        # Alert documents waiting for the thread: every event is sent (they are rare and small),
        # the first one saying that none is active, so that a late ``get`` always has an answer.
        self._alerts: deque[bytes] = deque([alerts_document(None, [])], maxlen=ALERTS_QUEUE)
        self._latest: dict[str, tuple[bytes, str]] = {}  # full key → (payload, encoding)
        self._session = None
        self._queryable = None
        self._rates = ByteRates()
        budget = config.budget_kbit_s * 1000.0 / 8.0
        self._bucket = ByteBucket(BUDGET_SHARE * budget, BUCKET_S * budget)
        self._rates_now: dict[str, float] = {}
        self.preview_width = config.preview_width
        self.preview_interval_s = 1.0 / config.preview_rate_hz
        self.summaries = 0
        self.previews = 0
        self.dropped = 0
        self.queries = 0
        self.error: str | None = None

    def start(self) -> None:
        self._zenoh = require_zenoh()
        self._session = open_session(self.config.mode, self.config.listen, self.config.connect, self.config.scouting,
                                     "check zenoh.listen and zenoh.connect")
        self._queryable = self._session.declare_queryable(f"{self.prefix}/**", self._on_query, complete=True)
        self._start_thread()
        log.info("publishing on Zenoh under %s/ (%s mode)", self.prefix, self.config.mode)

    def _on_published(self, published: Published) -> None:  # loop thread: hand off only
        with self._lock:
            if len(self._queue) == self._queue.maxlen:
                self.dropped += 1
            self._queue.append(published)
            self._ready.notify()

    def offer_alerts(self, event, active: list) -> None:
        """An alert raised or cleared (:class:`uwcam.runtime.alerts.AlertEvent`) and those active after
        it: queued for this output's thread to publish on ``alerts``."""
        with self._lock:
            self._alerts.append(alerts_document(event, active))
            self._ready.notify()

    def _on_query(self, query) -> None:
        """Zenoh's thread: reply with the latest value of every key the query's key expression
        matches. No logging here: this thread is not Python's."""
        asked = query.key_expr
        with self._lock:
            latest = list(self._latest.items())
            self.queries += 1
        for key, (payload, encoding) in latest:
            try:
                if asked.intersects(self._zenoh.KeyExpr(key)):
                    query.reply(key, payload, encoding=encoding)
            except Exception as exc:  # a subscriber that went away must not break the others
                with self._lock:
                    self.error = f"query: {type(exc).__name__}: {exc}"
        query.drop()

    def close(self) -> None:
        self._stop_thread()
        close_session(self._session, self._queryable)
        self._session = self._queryable = None

    def status(self) -> dict:
        with self._lock:
            rates = dict(self._rates_now)
            total = sum(rates.values())
            return {"key_prefix": self.prefix, "mode": self.config.mode, "page_url": self.config.page_url,
                    "summaries": self.summaries,
                    "previews": self.previews, "frames_dropped": self.dropped, "queries": self.queries,
                    "preview_width": self.preview_width, "preview_interval_s": round(self.preview_interval_s, 3),
                    "bytes_per_s": {k: round(v, 1) for k, v in sorted(rates.items())},
                    "budget_kbit_s": self.config.budget_kbit_s,
                    "over_budget": total * 8 / 1000 > self.config.budget_kbit_s, "error": self.error}

    def _put(self, key: str, payload: bytes, encoding: str, now: float) -> None:
        full = f"{self.prefix}/{key}"
        self._session.put(full, payload, encoding=encoding)
        self._rates.add(key.split("/")[0] if key.startswith(HEALTH) else key, len(payload), now)
        self._bucket.spend(len(payload), now)
        with self._lock:
            self._latest[full] = (payload, encoding)

    def _run(self) -> None:
        next_status, next_preview = 0.0, 0.0
        newest: Published | None = None
        while True:
            with self._lock:
                deadline = min(next_status, next_preview if newest is not None else math.inf)
                self._ready.wait_for(lambda: self._stop or self._queue or self._alerts,
                                     timeout=max(0.0, deadline - time.monotonic()))
                if self._stop:
                    return
                frames = list(self._queue)
                self._queue.clear()
                alerts = list(self._alerts)
                self._alerts.clear()
            try:
                for doc in alerts:
                    self._put(ALERTS, doc, JSON, time.monotonic())
                for p in frames:
                    self._put(SUMMARY, json.dumps(range_summary(p)).encode(), JSON, time.monotonic())
                    with self._lock:
                        self.summaries += 1
                if frames:
                    newest = frames[-1]
                now = time.monotonic()
                if now >= next_status:
                    next_status = now + STATUS_PERIOD_S
                    self._publish_status(now)
                if newest is not None and now >= next_preview:
                    next_preview = now + self._publish_preview(newest, now)
                    newest = None  # the next preview waits for a new frame
                with self._lock:
                    self._rates_now = self._rates.rates(time.monotonic())
                    self.error = None
            except Exception as exc:  # keep publishing; say what went wrong
                log.exception("Zenoh output failed")
                with self._lock:
                    self.error = f"{type(exc).__name__}: {exc}"
                next_status = max(next_status, time.monotonic() + STATUS_PERIOD_S)

    def _publish_status(self, now: float) -> None:
        if self._status_fn is None:
            return
        status = self._status_fn()
        self._put(STATUS, json.dumps(status, default=str).encode(), JSON, now)
        for device in DEVICES:
            entry = status.get(device)
            if isinstance(entry, dict) and isinstance(entry.get("health"), dict):
                self._put(f"{HEALTH}/{device}", json.dumps(entry["health"], default=str).encode(), JSON, now)

    def _publish_preview(self, p: Published, now: float) -> float:
        """Send a preview of ``p`` if the budget's bucket holds what it costs; the seconds to wait
        before the next try. A preview too large to be worth waiting for is not sent: the width
        shrinks and the next frame is tried."""
        budget = self.config.budget_kbit_s * 1000.0 / 8.0  # bytes/s
        rates = self._rates.rates(now)
        others = sum(v for k, v in rates.items() if not k.startswith("range/preview"))
        allowance = BUDGET_SHARE * budget - others
        if allowance <= 0:  # the summaries and status alone fill the budget: no preview, look again later
            with self._lock:
                self.preview_width = MIN_PREVIEW_WIDTH
                self.preview_interval_s = STATUS_PERIOD_S
            return STATUS_PERIOD_S
        period = 1.0 / self.config.preview_rate_hz
        # The largest preview worth sending: what the allowance gives at the slowest preview rate.
        target = min(allowance * period / SLOWEST_SHARE, self._bucket.capacity)
        rng, colour = preview_images(p, self.preview_width, self.config.preview_quality)
        size = len(rng) + len(colour)
        self._bucket.refill(now)
        if size > self._bucket.level:
            smaller = next_preview_width(self.preview_width, size, target, self.config.preview_width)
            if size > target and smaller < self.preview_width:  # shrink, and try with the next frame
                with self._lock:
                    self.preview_width = smaller
                return 0.0
            return min((size - self._bucket.level) / max(allowance, 1.0), STATUS_PERIOD_S)
        self._put(PREVIEW_RANGE, rng, PNG, now)
        self._put(PREVIEW_COLOUR, colour, JPEG, now)
        wait = max(period, size / allowance)
        width = next_preview_width(self.preview_width, size, target, self.config.preview_width)
        with self._lock:
            self.previews += 1
            self.preview_width = width
            self.preview_interval_s = wait
        return wait
