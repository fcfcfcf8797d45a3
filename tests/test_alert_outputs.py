"""Alerts of a running daemon, end to end: the simulated seabed brought close and taken away again,
the camera unplugged and plugged back, a disk rule that holds from the start; each alert raised once
and cleared once, seen the same way at GET /api/v1/alerts, on Zenoh ``alerts`` (a real Zenoh peer
session), as MAVLink STATUSTEXT (pymavlink's own mavutil on loopback UDP) and in /metrics."""

from __future__ import annotations

import json
import threading
import time

import pytest

from tests.served import Server
from tests.test_api import SERIAL, small_config
from tests.test_mavlink_mavutil import free_udp_port
from tests.test_zenoh import free_port, topside
from tests.waiting import wait_for
from uwcam.config import AlertsConfig, DeviceAlertConfig, MavlinkConfig, RangeAlertConfig, ZenohConfig
from uwcam.drivers.sim import SimulatedCamera

PREFIX = "uwcam/alert-rov"
CLOSE_M, FAR_M, BELOW_M = 1.0, 2.0, 1.5


class StatusTexts:
    """Every STATUSTEXT mavutil decodes on a UDP port, in a thread: (severity, text)."""

    def __init__(self, mavutil, port: int) -> None:
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", dialect="common")
        self.got: list[tuple[int, str]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="statustext-listener")
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.conn.recv_match(type="STATUSTEXT", blocking=True, timeout=0.2)
            if msg is not None:
                self.got.append((msg.severity, msg.text))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.conn.close()


@pytest.fixture
def mavutil(monkeypatch):
    monkeypatch.setenv("MAVLINK20", "1")
    from pymavlink import mavutil as module

    return module


def active_keys(server) -> set[str]:
    return {a["key"] for a in server.http.get("/api/v1/alerts").json()["active"]}


@pytest.mark.slow
def test_alerts_are_raised_and_cleared_once_on_every_output(mavutil):
    mav_port, endpoint = free_udp_port(), f"tcp/127.0.0.1:{free_port()}"
    texts = StatusTexts(mavutil, mav_port)
    config = small_config().model_copy(update={
        "alerts": AlertsConfig(range=RangeAlertConfig(below_m=BELOW_M, for_s=1.0), device=DeviceAlertConfig(for_s=2.0),
                               disk_free_below_percent=100.0, clear_s=0.5),
        "zenoh": ZenohConfig(listen=[endpoint], scouting=False, key_prefix=PREFIX, preview_rate_hz=0.5, preview_width=32),
        "mavlink": MavlinkConfig(connection=f"udpout:127.0.0.1:{mav_port}", rate_hz=2.0),
    })
    heard: list[dict] = []
    t_start = time.time()
    try:
        with Server(config) as s, topside(endpoint) as session:
            subscriber = session.declare_subscriber(
                f"{PREFIX}/alerts", lambda sample: heard.append(
                    {"encoding": str(sample.encoding), **json.loads(sample.payload.to_bytes())}))
            # Disk: free space is always below 100 % of the disk, so this one holds from the start.
            assert wait_for(lambda: "disk" in active_keys(s), 60.0), s.http.get("/api/v1/alerts").json()
            assert wait_for(lambda: s.daemon.pipeline.processed > 3, 30.0)

            s.daemon.rig.place(CLOSE_M)
            assert wait_for(lambda: "range" in active_keys(s), 30.0), s.http.get("/api/v1/alerts").json()
            s.daemon.rig.place(FAR_M)
            assert wait_for(lambda: "range" not in active_keys(s), 30.0)

            SimulatedCamera.unplug(SERIAL)
            try:
                assert wait_for(lambda: "device/camera" in active_keys(s), 30.0), s.http.get("/api/v1/status").json()["camera"]
            finally:
                SimulatedCamera.plug(SERIAL)
            assert wait_for(lambda: "device/camera" not in active_keys(s), 60.0), s.http.get("/api/v1/status").json()["camera"]

            # (the disk alert may come before this subscriber joined: the late get below covers that)
            assert wait_for(lambda: sum(1 for h in heard if h["event"]) >= 4, 15.0), heard
            assert wait_for(lambda: len(texts.got) >= 5, 15.0), texts.got
            alerts = s.http.get("/api/v1/alerts").json()
            metrics = s.http.get("/metrics").text
            with topside(endpoint) as late:
                replies = {str(r.ok.key_expr): (str(r.ok.encoding), r.ok.payload.to_bytes())
                           for r in late.get(f"{PREFIX}/alerts", timeout=10.0) if r.ok is not None}
            subscriber.undeclare()
    finally:
        texts.close()
    t_end = time.time()

    # GET /api/v1/alerts: each alert raised once and cleared once, in order, with its time and figures.
    history = [(e["key"], e["state"]) for e in alerts["history"]]
    assert history == [("disk", "raised"), ("range", "raised"), ("range", "cleared"),
                       ("device/camera", "raised"), ("device/camera", "cleared")], history
    events = {(e["key"], e["state"]): e for e in alerts["history"]}
    raised, cleared = events["range", "raised"], events["range", "cleared"]
    assert raised["values"]["minimum_m"] == pytest.approx(CLOSE_M, abs=0.1) and raised["values"]["below_m"] == BELOW_M
    assert cleared["values"]["minimum_m"] == pytest.approx(FAR_M, abs=0.15)
    assert raised["severity"] == "critical" and raised["time"] - raised["since"] >= 1.0
    assert t_start <= raised["since"] < raised["time"] <= cleared["since"] < cleared["time"] <= t_end
    camera = events["device/camera", "raised"]
    assert camera["severity"] == "error" and camera["values"]["state"] in ("lost", "recovering")
    assert [a["key"] for a in alerts["active"]] == ["disk"]
    assert alerts["active"][0]["values"]["free_percent"] < 100

    # Zenoh: the same events, in the same order, as JSON; a late get sees what is active now.
    assert all(h["encoding"] == "application/json" for h in heard)
    zenoh_events = [(h["event"]["key"], h["event"]["state"]) for h in heard if h["event"]]
    assert zenoh_events == history[len(history) - len(zenoh_events):] and len(zenoh_events) >= 4
    assert heard[-1]["active"][0]["key"] == "disk" and len(heard[-1]["active"]) == 1
    encoding, payload = replies[f"{PREFIX}/alerts"]
    assert encoding == "application/json" and [a["key"] for a in json.loads(payload)["active"]] == ["disk"]

    # MAVLink: one STATUSTEXT per event, with the alert's severity (cleared: INFO, 6).
    by_text = {text: severity for severity, text in texts.got}
    assert len(texts.got) == 5, texts.got
    assert by_text[f"uwcam: range {raised['values']['minimum_m']:.2f} m < {BELOW_M:g} m"] == 2  # CRITICAL
    assert sum(1 for sev, t in texts.got if t.startswith("uwcam: cleared: range") and sev == 6) == 1
    assert sum(1 for sev, t in texts.got if t.startswith("uwcam: camera ") and sev == 3) == 1  # ERROR
    assert sum(1 for sev, t in texts.got if t.startswith("uwcam: cleared: camera ") and sev == 6) == 1
    assert sum(1 for sev, t in texts.got if t.startswith("uwcam: recording disk") and sev == 4) == 1  # WARNING
    assert all(len(t.encode()) <= 50 for _s, t in texts.got)

    assert 'uwcam_alert_active{alert="disk",severity="warning"} 1.0' in metrics
    assert 'alert="range"' not in metrics


@pytest.mark.slow
def test_calibration_rules_read_a_running_daemons_profile_and_patch_tracking():
    """The calibration rules on a real status: the profile's provenance date, and the patch
    tracker's drift against the profile's σ. Limits set so low that both must hold (any age,
    any drift), which shows the figures reach the rules."""
    from uwcam.config import CalibrationAlertConfig
    from uwcam.runtime.daemon import Daemon

    config = small_config().model_copy(update={"alerts": AlertsConfig(
        calibration=CalibrationAlertConfig(max_age_days=1e-9, drift_sigmas=1e-6, drift_for_s=0.0))})
    d = Daemon(config)
    try:
        d.start()
        assert wait_for(lambda: {"calibration_age", "attenuation_drift"} <= {
            a["key"] for a in d.alerts.snapshot()["active"]}, 30.0), d.alerts.snapshot()
        status = d.status()
        snapshot = d.alerts.snapshot()
    finally:
        d.stop()
    events = {e["key"]: e for e in snapshot["active"]}
    age = events["calibration_age"]
    assert age["values"]["name"] == status["calibration"]["name"] and age["values"]["age_days"] >= 0
    assert age["values"]["created"] == status["calibration"]["created"] and age["severity"] == "notice"
    drift = events["attenuation_drift"]["values"]
    tracking = status["calibration"]["tracking"]
    assert drift["channel"] in ("G", "B") and tracking["drift_std"][drift["channel"]] > 0  # R is the reference: no σ
    # The alert says it to five decimals (0.0022451 as 0.00225): within half of the last one.
    assert drift["std_per_m"] == pytest.approx(tracking["drift_std"][drift["channel"]], abs=5e-6)
