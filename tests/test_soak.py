"""Fault-injection soak: the daemon under random device faults and bad API input for a couple of
minutes, checking after every step that it still tells the truth and still ranges.

Invariants checked throughout:

* no request ever gets a 5xx, whatever it sends (except the lamp's own endpoints saying the
  lamp does not answer, while a lamp fault is injected);
* the stream never sends a frame it sent before, nor one older than the last (no stale frame as new);
* status is truthful: while the camera is gone, fps falls to 0 and the time since the last
  processed frame grows; a silent lamp shows as unhealthy;
* after every fault is cleared, the camera is healthy again and ranging resumes.

``UWCAM_SOAK_S`` sets the duration (default 120 s); the seed is printed so a failure replays.
"""

from __future__ import annotations

import asyncio
import json
import os
import random
import threading
import time

import pytest
import websockets

from tests.served import Server
from tests.test_api import small_config
from tests.waiting import wait_for
from uwcam.api import HEADER
from uwcam.drivers.sim import SimulatedCamera

SERIAL = "SIM-API"  # small_config's camera

BAD_REQUESTS = [
    ("PATCH", "/api/v1/config", '{"path_length_bounds": [0, NaN]}', {}),
    ("PATCH", "/api/v1/config", '{"path_length_bounds": [5, 1]}', {}),
    ("PATCH", "/api/v1/config", '{"lamp_off_interval": 9223372036854775808}', {}),
    ("PATCH", "/api/v1/config", '{"lamp_off_interval": ' + "9" * 5000 + "}", {}),
    ("PATCH", "/api/v1/config", "[" * 20000 + "]" * 20000, {}),
    ("PATCH", "/api/v1/config", '{"pair": ["G", "Q"]}', {}),
    ("PATCH", "/api/v1/config", '{"patch": {"marker": {"id": 1, "offset": [NaN, 0], "size": [1, 1]}, "path_length_m": 1}}', {}),
    ("PATCH", "/api/v1/config", "not json", {}),
    ("PUT", "/api/v1/lamp", '{"intensity": false}', {}),
    ("PUT", "/api/v1/lamp", '{"intensity": Infinity}', {}),
    ("PUT", "/api/v1/lamp", '{"on": "yes"}', {}),
    ("PUT", "/api/v1/calibration/profiles/.hidden", "a: 1", {}),
    ("PUT", "/api/v1/calibration/profiles/deep", "[" * 50000, {}),
    ("PUT", "/api/v1/calibration/profiles/huge", "format: " + "7" * 6000, {}),
    ("PUT", "/api/v1/calibration/profiles/bin", "\x00\xff: [", {}),
    ("POST", "/api/v1/calibration/profiles/nope/activate", "", {}),
    ("POST", "/api/v1/config/restore", "", {"Origin": "http://evil.example"}),
    ("GET", "/api/v1/status", "", {"Host": "evil.example"}),
    ("GET", "/api/v1/snapshot/range?format=png", "", {}),
    ("GET", "/api/v1/snapshot/pointcloud", "", {}),
    ("GET", "/api/v1/lamp", "", {}),
    ("PATCH", "/api/v1/config", '{"smoothing": "mean"}', {}),
    ("PATCH", "/api/v1/config", '{"smoothing": "none"}', {}),
]


@pytest.fixture(autouse=True)
def no_leaked_threads():
    """uvicorn's worker threads outlive the server by design; see test_api."""
    yield


class StreamWatcher:
    """A WebSocket client in its own thread, recording every frame's number and capture time."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.frames: list[tuple[int, int]] = []
        self.problems: list[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=lambda: asyncio.run(self._run()), name="soak-stream")

    async def _run(self) -> None:
        while not self._stop.is_set():
            try:
                async with websockets.connect(f"ws://127.0.0.1:{self.port}/api/v1/stream?rate=30", max_size=None) as ws:
                    json.loads(await ws.recv())
                    while not self._stop.is_set():
                        try:
                            msg = await asyncio.wait_for(ws.recv(), 0.5)
                        except TimeoutError:
                            continue
                        if isinstance(msg, bytes):
                            _, number, captured, *_ = HEADER.unpack_from(msg)
                            if self.frames and (number <= self.frames[-1][0] or captured <= self.frames[-1][1]):
                                self.problems.append(f"frame {number} (captured {captured}) after {self.frames[-1]}")
                            self.frames.append((number, captured))
            except (OSError, websockets.exceptions.WebSocketException) as exc:
                self.problems.append(f"stream dropped: {exc!r}")
                await asyncio.sleep(0.5)

    def __enter__(self) -> "StreamWatcher":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=10.0)


@pytest.mark.slow
def test_daemon_survives_random_faults_and_bad_input():
    duration = float(os.environ.get("UWCAM_SOAK_S", "120"))
    seed = int(os.environ.get("UWCAM_SOAK_SEED", str(random.SystemRandom().randrange(1 << 30))))
    rng = random.Random(seed)
    print(f"soak: {duration:g} s, seed {seed}")
    config = small_config()
    config.processing.lamp_off_interval = 5
    errors: list[str] = []
    counts: dict[str, int] = {}

    with Server(config) as s:
        d = s.daemon
        http = s.http

        def request(method: str, path: str, body: str = "", headers: dict | None = None):
            r = http.request(method, path, content=body.encode("utf-8", "surrogatepass") if body else None,
                             headers={"content-type": "application/json", **(headers or {})})
            # The lamp's own endpoints say 502/503 when the lamp refuses or does not answer (a
            # fault being injected); anything else 5xx is a daemon failure.
            lamp_fault = path == "/api/v1/lamp" and r.status_code in (502, 503)
            if r.status_code >= 500 and not lamp_fault:
                errors.append(f"{method} {path} {body[:60]!r}: {r.status_code} {r.text[:200]}")
            return r

        def status() -> dict:
            r = request("GET", "/api/v1/status")
            assert r.status_code == 200
            return r.json()

        def ranging_resumes(what: str) -> None:
            assert wait_for(lambda: status()["camera"]["health"]["state"] == "ok", 30.0), f"camera not back after {what}"
            n = d.pipeline.processed
            assert wait_for(lambda: d.pipeline.processed >= n + 3, 30.0), f"ranging did not resume after {what}"

        assert wait_for(lambda: d.pipeline.processed > 3, 60.0)
        with StreamWatcher(s.port) as stream:
            end = time.monotonic() + duration
            while time.monotonic() < end:
                fault = rng.choice(["unplug", "stall", "corrupt", "lamp-silent", "lamp-garbage", "lamp-unplug",
                                    "sonar-unplug", "sonar-garbage", "bad-input"])
                counts[fault] = counts.get(fault, 0) + 1
                hold = rng.uniform(0.5, 3.5)
                if fault in ("unplug", "stall"):
                    (SimulatedCamera.unplug if fault == "unplug" else SimulatedCamera.stall)(SERIAL)
                    try:
                        if hold > 2.5:  # long enough for status to have to say so
                            time.sleep(2.5)
                            s1 = status()
                            time.sleep(0.3)
                            s2 = status()
                            assert s2["frames"]["fps"] == 0, s2["frames"]
                            assert s2["frames"]["since_last_processed_s"] > s1["frames"]["since_last_processed_s"]
                            assert s2["camera"]["health"]["state"] != "ok"
                        else:
                            time.sleep(hold)
                    finally:
                        SimulatedCamera.plug(SERIAL)
                        SimulatedCamera.stall(SERIAL, False)
                elif fault == "corrupt":
                    for _ in range(rng.randint(1, 5)):
                        SimulatedCamera.corrupt_next(SERIAL)
                        time.sleep(0.05)
                elif fault == "lamp-silent":
                    device = d.lamp.device
                    device.received = lambda data: None
                    try:
                        if hold > 2.0:
                            assert wait_for(lambda: status()["lamp"]["health"]["state"] != "ok", 15.0), \
                                f"silent lamp looks fine: {status()['lamp']}, cycle {d.pipeline._cycle}, {d.rig.lamp_on}"
                            n = d.pipeline.processed
                            assert wait_for(lambda: d.pipeline.processed >= n + 3, 15.0), "silent lamp stopped ranging"
                        else:
                            time.sleep(hold)
                    finally:
                        del device.received
                elif fault == "lamp-garbage":
                    d.lamp.device.send_garbage()
                    d.lamp.device.truncate_next_reply()
                elif fault == "lamp-unplug":
                    d.lamp.device.disconnect()
                    time.sleep(hold)
                    d.lamp.device.reconnect()
                elif fault == "sonar-unplug":
                    d.rangefinder.device.disconnect()
                    time.sleep(hold)
                    d.rangefinder.device.reconnect()
                elif fault == "sonar-garbage":
                    d.rangefinder.device.send_garbage()
                else:
                    for _ in range(rng.randint(3, 8)):
                        request(*rng.choice(BAD_REQUESTS))
                ranging_resumes(fault)
                assert not errors, errors
            # The lamp cycle also came back: the lamp is lit again and dark frames keep coming.
            ambient = d.pipeline.stats()["ambient_frames"]
            assert wait_for(lambda: d.pipeline.stats()["ambient_frames"] > ambient, 90.0)
            assert wait_for(lambda: status()["lamp"]["health"]["state"] == "ok", 30.0)
        print(f"soak: faults {counts}; {len(stream.frames)} frames streamed; {d.pipeline.processed} processed")
        assert not errors, errors
        assert not [p for p in stream.problems if not p.startswith("stream dropped")], stream.problems
        assert len(stream.frames) > 10

