"""``uwcam monitor``: the topside fleet view. Subscribes to ``uwcam/**`` on Zenoh (peers given
with ``--connect``, or found on the LAN by scouting) and serves a page listing every vehicle heard
— name, last seen, fps, calibration age, devices, centre and minimum range with their age, active
alerts, the live preview — greyed when nothing has come from it for ``--stale-s`` seconds, with a
link to the vehicle's own page when it publishes one (``zenoh.page_url``). docs/deployment.md,
"Topside".

:class:`Fleet` holds what was heard (Zenoh's threads write, the web server's threads read, under
one lock); it never blocks on anything but that lock. The web routes are plain ``def``: FastAPI
runs them in its thread pool, off the event loop.
"""

from __future__ import annotations

import json
import math
import threading
import time
from datetime import datetime
from importlib import resources

from fastapi import FastAPI, HTTPException
from fastapi.responses import HTMLResponse, Response


TOPICS = ("status", "range/summary", "range/preview/colour", "range/preview/range", "alerts")
DEVICES = ("camera", "lamp", "rangefinder")
QUERY_TIMEOUT_S = 3.0
"""The start's query for every vehicle's latest values waits this long for answers."""
WEB = resources.files("uwcam") / "web"
CSP = "default-src 'self'; img-src 'self' blob: data:; style-src 'self'; connect-src 'self'; frame-ancestors 'self'"


def split_key(key: str, root: str = "uwcam") -> tuple[str, str] | None:
    """``uwcam/rov1/range/summary`` → ("uwcam/rov1", "range/summary"); None for keys that are
    not a vehicle's (another root, an unknown topic)."""
    if not key.startswith(root + "/"):
        return None
    if "/health/" in key:
        prefix, _, device = key.rpartition("/health/")
        topic = f"health/{device}" if device in DEVICES else None
    else:
        topic = next((t for t in TOPICS if key.endswith("/" + t)), None)
        prefix = key[: -len(topic) - 1] if topic else ""
    # the prefix names a vehicle under the root: uwcam/<vehicle>, never the root alone
    return (prefix, topic) if topic and prefix.startswith(root + "/") else None


def _age_days(created: str | None, wall: float) -> float | None:
    try:
        return None if not created else round((wall - datetime.fromisoformat(created).timestamp()) / 86400.0, 2)
    except ValueError:
        return None


class Vehicle:
    def __init__(self, prefix: str) -> None:
        self.prefix = prefix
        self.heard_at = 0.0  # monotonic s of the newest sample
        self.status: dict | None = None
        self.summary: dict | None = None
        self.health: dict[str, dict] = {}
        self.alerts: list[dict] = []
        self.preview: bytes | None = None
        self.previews = 0
        self.samples = 0


class Fleet:
    """Every vehicle heard, by key prefix."""

    def __init__(self, stale_s: float = 5.0, root: str = "uwcam") -> None:
        self.stale_s = stale_s
        self.root = root
        self._lock = threading.Lock()
        self._vehicles: dict[str, Vehicle] = {}
        self.bad_samples = 0

    def receive(self, key: str, payload: bytes, now: float) -> None:
        """One sample (Zenoh's thread): ``now`` monotonic s."""
        split = split_key(key, self.root)
        if split is None:
            return
        prefix, topic = split
        try:
            doc = None if topic.startswith("range/preview") else json.loads(payload)
        except ValueError:
            with self._lock:
                self.bad_samples += 1
            return
        with self._lock:
            v = self._vehicles.setdefault(prefix, Vehicle(prefix))
            v.heard_at, v.samples = now, v.samples + 1
            if topic == "status":
                v.status = doc
            elif topic == "range/summary":
                v.summary = doc
            elif topic == "alerts":
                v.alerts = list(doc.get("active") or [])
            elif topic.startswith("health/"):
                v.health[topic.split("/", 1)[1]] = doc
            elif topic == "range/preview/colour":
                v.preview, v.previews = bytes(payload), v.previews + 1

    def preview(self, prefix: str) -> bytes | None:
        with self._lock:
            v = self._vehicles.get(prefix)
            return None if v is None else v.preview

    def snapshot(self, now: float, wall: float) -> list[dict]:
        """Every vehicle, by name: ``now`` monotonic s, ``wall`` Unix s of the same moment."""
        with self._lock:
            vehicles = sorted(self._vehicles.values(), key=lambda v: v.prefix)
            return [self._describe(v, now, wall) for v in vehicles]

    def _describe(self, v: Vehicle, now: float, wall: float) -> dict:
        status = v.status or {}
        frames = status.get("frames") or {}
        calibration = status.get("calibration") or {}
        devices = {}
        for device in DEVICES:
            health = v.health.get(device) or ((status.get(device) or {}).get("health"))
            if health:
                devices[device] = health.get("state")
        summary = v.summary or {}
        capture = summary.get("time")
        age = now - v.heard_at
        return {
            "name": v.prefix.removeprefix(self.root + "/"),
            "prefix": v.prefix,
            "last_seen_s": round(age, 2),
            "stale": age > self.stale_s,
            "fps": frames.get("fps"),
            "calibration": calibration.get("name"),
            "calibration_age_days": _age_days(calibration.get("created"), wall),
            "devices": devices,
            "centre_m": summary.get("centre_m"),
            "minimum_m": summary.get("minimum_m"),
            "valid_fraction": summary.get("valid_fraction"),
            "range_age_s": None if capture is None or not math.isfinite(capture) else round(wall - capture, 2),
            "alerts": [{"key": a.get("key"), "severity": a.get("severity"), "message": a.get("message")}
                       for a in v.alerts],
            "previews": v.previews,
            "page_url": (status.get("zenoh") or {}).get("page_url"),
        }


class ZenohListener:
    """The Zenoh session of the monitor: a subscriber on ``<root>/**`` and, once at start, a query
    for the latest of every key (so vehicles that publish rarely are listed at once)."""

    def __init__(self, fleet: Fleet, connect: list[str], listen: list[str], scouting: bool) -> None:
        self.fleet, self.connect, self.listen, self.scouting = fleet, connect, listen, scouting
        self._session = None
        self._subscriber = None
        self._query_thread: threading.Thread | None = None

    def start(self) -> None:
        from uwcam.outputs.zenoh_publisher import open_session

        self._session = open_session("peer", self.listen, self.connect, self.scouting, "check --connect and --listen")
        selector = f"{self.fleet.root}/**"
        self._subscriber = self._session.declare_subscriber(selector, self._on_sample)
        self._query_thread = threading.Thread(target=self._query, args=(selector,), name="monitor-query", daemon=True)
        self._query_thread.start()

    def _on_sample(self, sample) -> None:  # Zenoh's thread
        self.fleet.receive(str(sample.key_expr), sample.payload.to_bytes(), time.monotonic())

    def _query(self, selector: str) -> None:
        try:
            for reply in self._session.get(selector, timeout=QUERY_TIMEOUT_S):
                if reply.ok is not None:
                    self.fleet.receive(str(reply.ok.key_expr), reply.ok.payload.to_bytes(), time.monotonic())
        except Exception:  # the session closed while asking: nothing to fill
            pass

    def close(self) -> None:
        from uwcam.outputs.zenoh_publisher import close_session

        if self._query_thread is not None:
            self._query_thread.join(timeout=QUERY_TIMEOUT_S + 2.0)
            self._query_thread = None
        close_session(self._session, self._subscriber)
        self._session = self._subscriber = None


def create_monitor_app(fleet: Fleet, listener: ZenohListener | None = None) -> FastAPI:
    """The fleet page and its JSON. ``listener`` is started and closed with the app."""
    from contextlib import asynccontextmanager

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        if listener is not None:
            listener.start()
        try:
            yield
        finally:
            if listener is not None:
                listener.close()

    app = FastAPI(title="uwcam monitor", lifespan=lifespan, docs_url=None, redoc_url=None, openapi_url=None)

    def asset(name: str, media: str) -> Response:
        return Response((WEB / name).read_bytes(), media_type=media,
                        headers={"Cache-Control": "no-cache", "Content-Security-Policy": CSP})

    @app.get("/", response_class=HTMLResponse)
    def page() -> Response:
        return asset("monitor.html", "text/html; charset=utf-8")

    @app.get("/static/monitor.js")
    def script() -> Response:
        return asset("monitor.js", "text/javascript")

    @app.get("/static/monitor.css")
    def style() -> Response:
        return asset("monitor.css", "text/css")

    @app.get("/api/fleet")
    def vehicles() -> dict:
        """Every vehicle heard, with its figures and whether it is stale."""
        return {"vehicles": fleet.snapshot(time.monotonic(), time.time()), "stale_s": fleet.stale_s,
                "bad_samples": fleet.bad_samples}

    @app.get("/api/fleet/preview.jpg")
    def preview(prefix: str) -> Response:
        """The newest colour preview of the vehicle publishing under ``prefix``."""
        data = fleet.preview(prefix)
        if data is None:
            raise HTTPException(status_code=404, detail=f"no preview heard from {prefix}")
        return Response(data, media_type="image/jpeg", headers={"Cache-Control": "no-store"})

    return app


def run_monitor(connect: list[str], listen: list[str], scouting: bool, host: str, port: int, stale_s: float,
                root: str = "uwcam") -> None:
    """Serve the fleet view until interrupted."""
    import uvicorn

    fleet = Fleet(stale_s=stale_s, root=root)
    app = create_monitor_app(fleet, ZenohListener(fleet, connect, listen, scouting))
    uvicorn.run(app, host=host, port=port, log_level="warning")
