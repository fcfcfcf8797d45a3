"""The Zenoh publisher (uwcam/outputs/zenoh_publisher.py) against a real Zenoh subscriber session:
a daemon on the simulated rig, both sides Zenoh peers on explicit loopback TCP endpoints, multicast
scouting off (so that nothing else on the machine joins in)."""

import contextlib
import json
import socket
import sys
import threading
import time

import cv2
import numpy as np
import pytest
import zenoh

from tests.test_api import small_config
from tests.waiting import wait_for
from uwcam.config import ZenohConfig, load_config
from uwcam.runtime.daemon import Daemon
from uwcam.drivers.base import Frame
from uwcam.fileio import UserInputError
from uwcam.outputs.zenoh_publisher import QUEUE_FRAMES, ByteBucket, ByteRates, area_mean, next_preview_width, range_summary
from uwcam.runtime.published import Published
from uwcam.ranging.result import RangeResult
from tests.ports import free_port

PREFIX = "uwcam/test-rov"
SEABED_M = 2.0  # the simulated seabed-patch scene of small_config is a plane at this distance
KEYS = {"status": "application/json", "alerts": "application/json", "range/summary": "application/json",
        "range/preview/range": "image/png", "range/preview/colour": "image/jpeg",
        "health/camera": "application/json", "health/lamp": "application/json",
        "health/rangefinder": "application/json"}


@contextlib.contextmanager
def vehicle(**zenoh_options):
    """A daemon on the simulated rig publishing on Zenoh; yields (daemon, its endpoint)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    cfg = small_config()
    cfg.zenoh = ZenohConfig(listen=[endpoint], scouting=False, key_prefix=PREFIX, **zenoh_options)
    d = Daemon(cfg)
    try:
        d.start()
        assert wait_for(lambda: d.pipeline.processed >= 3, 60.0), "the frame loop did not start"
        yield d, endpoint
    finally:
        d.stop()


@contextlib.contextmanager
def topside(endpoint: str):
    """A Zenoh peer session of the test's own, connected to ``endpoint`` only."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("listen/endpoints", json.dumps(["tcp/127.0.0.1:0"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    try:
        yield session
    finally:
        session.close()


class Received:
    """Every sample of a subscriber: (key under the prefix, encoding, payload, arrival time)."""

    def __init__(self, session) -> None:
        self._lock = threading.Lock()
        self.samples: list[tuple[str, str, bytes, float]] = []
        self.subscriber = session.declare_subscriber(f"{PREFIX}/**", self._on_sample)

    def _on_sample(self, sample) -> None:  # Zenoh's thread
        item = (str(sample.key_expr).removeprefix(PREFIX + "/"), str(sample.encoding),
                sample.payload.to_bytes(), time.monotonic())
        with self._lock:
            self.samples.append(item)

    def copy(self) -> list[tuple[str, str, bytes, float]]:
        with self._lock:
            return list(self.samples)

    def keys(self) -> set[str]:
        return {k for k, *_ in self.copy()}


def latest(samples, key):
    return [s for s in samples if s[0] == key][-1]


def get_all(session, selector: str) -> dict[str, tuple[str, bytes]]:
    replies = {}
    for reply in session.get(selector, timeout=10.0):
        assert reply.ok is not None, f"error reply: {reply.err}"
        replies[str(reply.ok.key_expr).removeprefix(PREFIX + "/")] = (str(reply.ok.encoding),
                                                                       reply.ok.payload.to_bytes())
    return replies


def test_every_key_arrives_with_its_encoding_and_a_late_get_sees_the_latest():
    with vehicle(preview_rate_hz=2.0, preview_width=80) as (d, endpoint), topside(endpoint) as session:
        received = Received(session)
        # alerts is published when one is raised or cleared (none here): the late get below has it
        assert wait_for(lambda: set(KEYS) - {"alerts"} <= received.keys(), 30.0), f"keys heard: {sorted(received.keys())}"
        processed_before, t0 = d.pipeline.processed, time.monotonic()
        time.sleep(3.0)
        processed_during = d.pipeline.processed - processed_before
        samples = received.copy()
        heard_during = sum(1 for s in samples if s[0] == "range/summary" and s[3] > t0)

        # A late subscriber: a second session that asks once, after everything has been published.
        with topside(endpoint) as late:
            replies = get_all(late, f"{PREFIX}/**")
            one = get_all(late, f"{PREFIX}/range/summary")
        received.subscriber.undeclare()

    for key, encoding, *_ in samples:
        assert encoding == KEYS[key], f"{key} came as {encoding}"
    # every processed frame gives a summary (a few may be queued at either end of the window)
    assert heard_during >= processed_during - QUEUE_FRAMES and processed_during > 5
    status = json.loads(latest(samples, "status")[2])
    assert status["camera"]["health"]["state"] == "ok" and status["zenoh"]["key_prefix"] == PREFIX
    assert json.loads(latest(samples, "health/lamp")[2])["state"] == "ok"
    summary = json.loads(latest(samples, "range/summary")[2])
    assert summary["centre_m"] == pytest.approx(SEABED_M, rel=0.05)
    assert 0 < summary["minimum_m"] <= summary["centre_m"] * 1.01 and 0 < summary["centre_sigma_m"] < 0.2
    assert 0.5 < summary["valid_fraction"] <= 1 and abs(summary["time"] - time.time()) < 120
    rng = cv2.imdecode(np.frombuffer(latest(samples, "range/preview/range")[2], np.uint8), cv2.IMREAD_UNCHANGED)
    colour = cv2.imdecode(np.frombuffer(latest(samples, "range/preview/colour")[2], np.uint8), cv2.IMREAD_COLOR)
    assert rng.dtype == np.uint16 and rng.shape == colour.shape[:2] and rng.shape[1] <= 80
    h, w = rng.shape
    assert np.median(rng[h // 3:2 * h // 3, w // 3:2 * w // 3]) == pytest.approx(SEABED_M * 1000, rel=0.05)

    assert {k: e for k, (e, _p) in replies.items()} == KEYS
    last_heard = json.loads(latest(samples, "range/summary")[2])["frame"]
    assert json.loads(replies["range/summary"][1])["frame"] >= last_heard  # the latest, not the first
    assert list(one) == ["range/summary"]


def test_previews_shrink_and_slow_to_the_budget_and_summaries_never_stop(capsys):
    budget_kbit_s, window_s = 100.0, 8.0
    with vehicle(budget_kbit_s=budget_kbit_s, preview_rate_hz=10.0, preview_width=160) as (d, endpoint), \
            topside(endpoint) as session:
        received = Received(session)
        assert wait_for(lambda: set(KEYS) - {"alerts"} <= received.keys(), 30.0)
        time.sleep(3.0)  # the budget's measurements settle
        t0, processed0 = time.monotonic(), d.pipeline.processed
        time.sleep(window_s)
        t1, processed = time.monotonic(), d.pipeline.processed - processed0
        received.subscriber.undeclare()
        zstatus = d.status()["zenoh"]
    window = [s for s in received.copy() if t0 <= s[3] < t1]
    per_key: dict[str, int] = {}
    for key, _e, payload, _t in window:
        per_key[key.split("/")[0] if key.startswith("health/") else key] = \
            per_key.get(key.split("/")[0] if key.startswith("health/") else key, 0) + len(payload)
    with capsys.disabled():
        print(f"\nZenoh payload bytes/s at a {budget_kbit_s:g} kbit/s budget over {window_s:g} s: " +
              ", ".join(f"{k} {v / (t1 - t0):.0f}" for k, v in sorted(per_key.items())))
    largest_preview = max(len(p) for k, _e, p, _t in window if k == "range/preview/range") + \
        max(len(p) for k, _e, p, _t in window if k == "range/preview/colour")
    # Within the budget: previews are paced after they are sent, so one may run over at the end.
    assert sum(per_key.values()) <= budget_kbit_s * 1000 / 8 * (t1 - t0) + largest_preview
    previews = [p for k, _e, p, _t in window if k == "range/preview/range"]
    widths = [cv2.imdecode(np.frombuffer(p, np.uint8), cv2.IMREAD_UNCHANGED).shape[1] for p in previews]
    assert len(previews) >= 2 and max(widths) < 160  # shrunk...
    assert len(previews) < 10 * window_s * 0.8  # ...and slowed from 10 a second
    summaries = sum(1 for s in window if s[0] == "range/summary")
    assert summaries >= processed - QUEUE_FRAMES and not zstatus["over_budget"]


def test_summaries_go_on_when_the_budget_leaves_no_room_for_previews():
    with vehicle(budget_kbit_s=8.0) as (d, endpoint), topside(endpoint) as session:
        received = Received(session)
        assert wait_for(lambda: {"range/summary", "status"} <= received.keys(), 30.0)
        before = d.pipeline.processed
        time.sleep(3.0)
        heard = received.copy()
        received.subscriber.undeclare()
        processed = d.pipeline.processed - before
        zstatus = d.status()["zenoh"]
    assert sum(1 for s in heard if s[0] == "range/summary") >= processed - QUEUE_FRAMES > 0
    assert not any(s[0].startswith("range/preview") for s in heard)
    assert zstatus["over_budget"] is True


@pytest.mark.parametrize("yaml_text, message", [
    ("zenoh:\n  mode: router\n", "zenoh.mode"),
    ("zenoh:\n  budget_kbit_s: .nan\n", "zenoh.budget_kbit_s"),
    ("zenoh:\n  budget_kbit_s: 0\n", "zenoh.budget_kbit_s"),
    ("zenoh:\n  preview_rate_hz: .inf\n", "zenoh.preview_rate_hz"),
    ("zenoh:\n  preview_width: 4\n", "zenoh.preview_width"),
    ("zenoh:\n  key_prefix: uwcam/*\n", "without wildcards"),
    ("zenoh:\n  key_prefix: /uwcam/rov1\n", "without wildcards"),
    ("zenoh:\n  listen: ['7447']\n", "zenoh.listen"),
    ("zenoh:\n  connect: [tcp/10.0.0.1:7447, 'localhost']\n", "zenoh.connect"),
    ("zenoh:\n  budget: 64\n", "zenoh.budget"),
    ("zenoh:\n  scouting: 1\n", "zenoh.scouting"),
])
def test_bad_zenoh_configuration_is_refused_clearly(tmp_path, yaml_text, message):
    path = tmp_path / "uwcam.yaml"
    path.write_text(yaml_text)
    with pytest.raises(UserInputError, match=message.replace("*", r"\*")):
        load_config(path)


def test_a_good_zenoh_configuration_loads(tmp_path):
    path = tmp_path / "uwcam.yaml"
    path.write_text("zenoh:\n  mode: client\n  connect: [tcp/192.168.2.1:7447]\n  key_prefix: uwcam/rov-1\n"
                    "  budget_kbit_s: 64\n")
    z = load_config(path).zenoh
    assert (z.mode, z.connect, z.key_prefix, z.budget_kbit_s) == ("client", ["tcp/192.168.2.1:7447"], "uwcam/rov-1", 64)
    path.write_text("version: 1\n")
    assert load_config(path).zenoh is None  # off by default


def test_without_the_zenoh_library_the_daemon_says_what_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "zenoh", None)  # import zenoh now raises ImportError
    cfg = small_config()
    cfg.zenoh = ZenohConfig(scouting=False, listen=[f"tcp/127.0.0.1:{free_port()}"])
    d = Daemon(cfg)
    with pytest.raises(UserInputError, match=r"pip install 'uwcam\[zenoh\]'") as err:
        d.start()
    assert "\n" not in str(err.value)
    assert d.camera is None and d.lamp is None  # refused before any device was opened


def test_a_taken_port_is_a_one_line_error():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        cfg = small_config()
        cfg.zenoh = ZenohConfig(scouting=False, listen=[f"tcp/127.0.0.1:{taken.getsockname()[1]}"])
        d = Daemon(cfg)
        with pytest.raises(UserInputError, match="cannot open the Zenoh session .*check zenoh.listen") as err:
            d.start()
    assert "\n" not in str(err.value)


def test_byte_rates_count_per_key_over_the_window():
    rates = ByteRates(window_s=2.0)
    start = rates._started
    for i in range(40):  # 100 bytes every 0.1 s on one key, 10 on another: 1000 and 100 bytes/s
        rates.add("a", 100, start + 0.1 * i)
        rates.add("b", 10, start + 0.1 * i)
    got = rates.rates(start + 4.0)
    assert got["a"] == pytest.approx(1000, rel=0.06) and got["b"] == pytest.approx(100, rel=0.06)
    assert rates.rates(start + 10.0) == {}  # all of it older than the window


@pytest.mark.parametrize("width, sent, target, largest, expected", [
    (160, 4000, 1000, 160, 80),     # four times too big: half the width (area ∝ bytes)
    (160, 40000, 1000, 160, 80),    # far too big: at most halved a step
    (80, 1000, 4000, 160, 100),     # room to spare: grows by at most 1.25 a step
    (150, 1000, 4000, 160, 160),    # never beyond the configured width
    (20, 4000, 100, 160, 16),       # never below the smallest
    (100, 950, 1000, 160, 100),     # close enough: steady
    (100, 1000, 0, 160, 16),        # nothing left: the smallest
])
def test_next_preview_width(width, sent, target, largest, expected):
    assert next_preview_width(width, sent, target, largest) == expected


def test_area_mean_averages_the_valid_pixels_and_drops_mostly_invalid_ones():
    values = np.full((8, 8), 3.0, np.float32)
    values[:, :2] = 1.0   # the left output pixel of each row: half 1 m, half 3 m → 2 m
    values[4:, 4:] = np.nan  # bottom right: all invalid
    values[0, 4] = np.nan    # top right: one of 16 invalid, the others 3 m
    got = area_mean(values, 2, 2)
    assert got[0, 0] == pytest.approx(2.0) and got[1, 0] == pytest.approx(2.0)
    assert got[0, 1] == pytest.approx(3.0) and np.isnan(got[1, 1])


def test_byte_bucket_bounds_what_is_spent_and_keeps_bounded_debt():
    bucket = ByteBucket(rate=1000.0, capacity=2000.0)
    bucket.refill(0.0)
    bucket.refill(10.0)
    assert bucket.level == pytest.approx(2000.0)  # full, never more
    bucket.spend(2500, 10.0)
    assert bucket.level == pytest.approx(-500.0)
    bucket.spend(10_000, 11.0)  # mandatory keys beyond the budget: debt bounded by the capacity
    assert bucket.level == pytest.approx(-2000.0)
    bucket.refill(13.5)
    assert bucket.level == pytest.approx(500.0)


def synthetic_published(range_m: np.ndarray, variance_m2: np.ndarray) -> Published:
    h, w = range_m.shape
    frame = Frame(np.full((h, w, 3), 1000, np.uint16), 7, 0, 1_700_000_000.25)
    result = RangeResult(range_m.astype(np.float32), variance_m2.astype(np.float32), np.zeros((h, w), np.uint8))
    return Published(7, frame, result, 0, (0.0, 0.0))


def test_range_summary_of_a_known_map():
    # A wall at 3 m (σ 0.1 m) with a 16×16 post at 1.2 m (σ 0.05 m) off-centre and the top
    # quarter of the image invalid.
    r = np.full((120, 160), 3.0)
    v = np.full((120, 160), 0.01)
    r[80:96, 16:32], v[80:96, 16:32] = 1.2, 0.0025
    r[:30], v[:30] = np.nan, np.nan
    s = range_summary(synthetic_published(r, v))
    assert s["frame"] == 7 and s["time"] == 1_700_000_000.25
    assert s["centre_m"] == pytest.approx(3.0) and s["centre_sigma_m"] == pytest.approx(0.1, rel=1e-3)
    assert s["minimum_m"] == pytest.approx(1.2) and s["minimum_sigma_m"] == pytest.approx(0.05, rel=1e-3)
    assert s["valid_fraction"] == pytest.approx(0.75)
    # nothing valid: figures are null, never NaN (which is not JSON)
    empty = range_summary(synthetic_published(np.full((20, 20), np.nan), np.full((20, 20), np.nan)))
    assert empty["centre_m"] is None and empty["minimum_m"] is None and empty["valid_fraction"] == 0
    json.dumps(empty, allow_nan=False)


def test_foreign_puts_change_nothing_and_are_never_served():
    """Read-only: a put on the vehicle's keys (a would-be command, or a forged status) neither
    changes the daemon nor replaces what its queryable answers."""
    with vehicle() as (d, endpoint), topside(endpoint) as session:
        received = Received(session)
        assert wait_for(lambda: "status" in received.keys(), 30.0)
        session.put(f"{PREFIX}/lamp", json.dumps({"on": False, "percent": 0}), encoding="application/json")
        session.put(f"{PREFIX}/status", b"forged", encoding="text/plain")
        session.put(f"{PREFIX}/config", json.dumps({"smoothing": "mean"}), encoding="application/json")
        time.sleep(1.5)
        replies = get_all(session, f"{PREFIX}/status")
        received.subscriber.undeclare()
        lamp, smoothing = d.status()["lamp"], d.pipeline.processing.smoothing
    assert lamp["on"] is True and lamp["percent"] > 0 and smoothing == "none"
    assert replies["status"][0] == "application/json" and json.loads(replies["status"][1])["zenoh"]["key_prefix"] == PREFIX
