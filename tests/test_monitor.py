"""The topside fleet view, ``uwcam monitor`` (uwcam/fleet/monitor.py): its key parsing and staleness on
made-up samples, its command-line checks, and end to end: three simulated daemons publishing on
Zenoh and the monitor (the real command, in a process of its own) as Zenoh peers on loopback with
explicit endpoints, its page in Debian's Chromium listing all three with live values; one vehicle
stopped goes stale and comes back when restarted; an alert raised and cleared on one vehicle shows
and goes."""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
import time

import httpx
import pytest

from tests.test_api import small_config
from tests.test_page import browser, open_page  # noqa: F401 (the module's Chromium fixture)
from tests.test_zenoh import free_port
from tests.waiting import wait_for
from uwcam.cli import main
from uwcam.config import AlertsConfig, CameraConfig, RangeAlertConfig, ZenohConfig
from uwcam.runtime.daemon import Daemon
from uwcam.fleet.monitor import Fleet, split_key


def test_keys_are_split_into_vehicle_and_topic():
    assert split_key("uwcam/rov1/range/summary") == ("uwcam/rov1", "range/summary")
    assert split_key("uwcam/site/rov-2/status") == ("uwcam/site/rov-2", "status")
    assert split_key("uwcam/rov1/health/lamp") == ("uwcam/rov1", "health/lamp")
    assert split_key("uwcam/rov1/alerts") == ("uwcam/rov1", "alerts")
    assert split_key("uwcam/status") is None  # no vehicle segment
    assert split_key("uwcam/rov1/health/toaster") is None and split_key("other/rov1/status") is None
    assert split_key("fleet/rov1/status", root="fleet") == ("fleet/rov1", "status")


def test_the_fleet_keeps_the_last_figures_and_says_when_a_vehicle_went_stale():
    fleet = Fleet(stale_s=5.0)
    status = {"frames": {"fps": 9.5}, "calibration": {"name": "tank", "created": "2026-11-15T12:00:00+00:00"},
              "camera": {"health": {"state": "ok"}}, "lamp": None, "zenoh": {"page_url": "http://rov1.local:8080/"}}
    fleet.receive("uwcam/rov1/status", json.dumps(status).encode(), now=100.0)
    fleet.receive("uwcam/rov1/range/summary", json.dumps({"time": 1_795_000_000.0, "centre_m": 2.0,
                                                          "minimum_m": 1.5}).encode(), now=101.0)
    fleet.receive("uwcam/rov1/health/camera", b'{"state": "recovering"}', now=101.5)
    fleet.receive("uwcam/rov1/alerts", b'{"event": null, "active": [{"key": "disk", "severity": "warning", '
                                       b'"message": "recording disk 3 % free"}]}', now=102.0)
    fleet.receive("uwcam/rov1/status", b"not json", now=103.0)
    (rov1,) = fleet.snapshot(now=104.0, wall=1_795_000_001.0)
    assert rov1["name"] == "rov1" and rov1["fps"] == 9.5 and not rov1["stale"] and rov1["last_seen_s"] == 2.0
    assert rov1["devices"] == {"camera": "recovering"}  # health/<device> is newer than the status's
    assert rov1["centre_m"] == 2.0 and rov1["minimum_m"] == 1.5 and rov1["range_age_s"] == 1.0
    assert rov1["calibration_age_days"] == pytest.approx((1_795_000_001.0 - 1_794_744_000.0) / 86400, abs=0.01)
    assert rov1["alerts"] == [{"key": "disk", "severity": "warning", "message": "recording disk 3 % free"}]
    assert rov1["page_url"] == "http://rov1.local:8080/" and fleet.bad_samples == 1
    (later,) = fleet.snapshot(now=107.5, wall=1_795_000_005.0)
    assert later["stale"] and later["centre_m"] == 2.0 and later["last_seen_s"] == 5.5


@pytest.mark.parametrize("argv, message", [
    (["--connect", "7447"], "--connect 7447: not a Zenoh endpoint"),
    (["--connect", "tcp/127.0.0.1:7447", "--stale-s", "nan"], "--stale-s nan"),
    (["--connect", "tcp/127.0.0.1:7447", "--port", "70000"], "--port 70000"),
    (["--connect", "tcp/127.0.0.1:7447", "--root", "uwcam/*"], "--root uwcam/*"),
    (["--no-scouting"], "nothing to listen to"),
])
def test_monitor_options_are_checked(argv, message, capsys):
    assert main(["monitor", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


NAMES = ("rov-a", "rov-b", "rov-c")
BUDGET_KBIT_S = 48.0
DISTANCES_M = {"rov-a": 1.8, "rov-b": 2.0, "rov-c": 2.4}


def vehicle_config(name: str, endpoint: str):
    """A light simulated vehicle: 160×120 frames at 4 fps, small slow previews."""
    cfg = small_config()
    return cfg.model_copy(update={
        "camera": CameraConfig(driver="sim", options={"fps": 4.0, "serial_number": f"SIM-{name}"}, watchdog_s=2.0),
        "simulation": {**cfg.simulation, "distance": DISTANCES_M[name]},
        "zenoh": ZenohConfig(listen=[endpoint], scouting=False, key_prefix=f"uwcam/{name}", budget_kbit_s=BUDGET_KBIT_S,
                             preview_rate_hz=0.5,
                             preview_width=48, page_url=f"http://127.0.0.1:9/{name}/" if name == "rov-a" else None),
        "alerts": AlertsConfig(range=RangeAlertConfig(below_m=1.5, for_s=0.5), clear_s=0.5),
    })


@contextlib.contextmanager
def monitor_process(endpoints: list[str], port: int):
    proc = subprocess.Popen([sys.executable, "-m", "uwcam", "monitor", "--connect", *endpoints, "--no-scouting",
                             "--port", str(port), "--stale-s", "3"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    try:
        url = f"http://127.0.0.1:{port}"

        def up() -> bool:
            try:
                return httpx.get(url + "/api/fleet", timeout=2.0).status_code == 200
            except httpx.HTTPError:
                return False

        assert wait_for(up, 60.0, 0.2), proc.stdout.read() if proc.poll() is not None else "monitor did not answer"
        yield url, proc
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        proc.stdout.close()


def rows(page) -> dict[str, dict]:
    """The fleet page's rows as shown: name → its cells' text and whether it is greyed."""
    out = {}
    for row in page.locator("#fleet tbody tr").all():
        cells = {c: row.locator(f"td.{c}").inner_text() for c in ("last-seen", "fps", "centre", "minimum", "alerts",
                                                                  "devices", "calibration")}
        out[row.get_attribute("data-name")] = {**cells, "stale": row.get_attribute("class") == "stale",
                                               "link": row.locator("td.name a").count() == 1,
                                               "preview": row.locator("td.preview img").count() == 1}
    return out


def metres(text: str) -> float | None:
    return None if text == "—" else float(text.removesuffix(" m"))


@pytest.mark.slow
@pytest.mark.browser
def test_three_vehicles_on_one_fleet_page_stale_and_back_with_alerts(browser):  # noqa: F811
    endpoints = {name: f"tcp/127.0.0.1:{free_port()}" for name in NAMES}
    daemons = {}
    try:
        for name in NAMES:
            daemons[name] = Daemon(vehicle_config(name, endpoints[name]))
            daemons[name].start()
        with monitor_process(list(endpoints.values()), free_port()) as (url, proc):
            page = open_page(browser, url + "/", url)
            try:
                def all_live() -> bool:
                    r = rows(page)
                    return set(r) == set(NAMES) and all(not v["stale"] and metres(v["centre"]) and v["preview"]
                                                        for v in r.values())

                assert wait_for(all_live, 60.0, 0.3), rows(page)
                shown = rows(page)
                for name in NAMES:  # each vehicle's own figures, from its own simulated water
                    assert metres(shown[name]["centre"]) == pytest.approx(DISTANCES_M[name], rel=0.06), shown[name]
                    assert 0 < metres(shown[name]["minimum"]) <= metres(shown[name]["centre"]) * 1.01
                    assert float(shown[name]["fps"]) > 0 and "camera ok" in shown[name]["devices"]
                    assert shown[name]["calibration"].startswith("simulated tank calibration")
                assert shown["rov-a"]["link"] and not shown["rov-b"]["link"]
                for name, d in daemons.items():  # each vehicle within its link's budget, previews included
                    z = d.status()["zenoh"]
                    assert not z["over_budget"] and z["previews"] > 0, (name, z)
                    assert sum(z["bytes_per_s"].values()) * 8 / 1000 <= BUDGET_KBIT_S, (name, z["bytes_per_s"])
                assert page.locator('tr[data-name="rov-a"] td.name a').get_attribute("href") == "http://127.0.0.1:9/rov-a/"
                # live: the figures move on (the last-seen age stays short while frames keep coming)
                assert wait_for(lambda: float(rows(page)["rov-b"]["last-seen"].split()[0]) < 2.0, 10.0, 0.3)

                # An alert on one vehicle: rov-b's seabed brought within 1.5 m, then taken back.
                daemons["rov-b"].rig.place(1.0)
                assert wait_for(lambda: "critical: range" in rows(page)["rov-b"]["alerts"], 30.0, 0.3), rows(page)
                assert rows(page)["rov-a"]["alerts"] == "" and rows(page)["rov-c"]["alerts"] == ""
                daemons["rov-b"].rig.place(2.0)
                assert wait_for(lambda: rows(page)["rov-b"]["alerts"] == "", 30.0, 0.3), rows(page)

                # rov-c stops: greyed, its last figures kept; the others stay live.
                daemons["rov-c"].stop()
                assert wait_for(lambda: rows(page)["rov-c"]["stale"], 30.0, 0.3), rows(page)
                stale = rows(page)
                assert metres(stale["rov-c"]["centre"]) == pytest.approx(DISTANCES_M["rov-c"], rel=0.06)
                assert not stale["rov-a"]["stale"] and not stale["rov-b"]["stale"]

                # restarted on the same endpoint: back, live.
                daemons["rov-c"] = Daemon(vehicle_config("rov-c", endpoints["rov-c"]))
                daemons["rov-c"].start()
                assert wait_for(lambda: not rows(page)["rov-c"]["stale"], 60.0, 0.3), rows(page)

                # The monitor itself gone: the page no longer shows anything as live.
                proc.terminate()
                proc.wait(timeout=20)
                assert wait_for(lambda: all(v["stale"] for v in rows(page).values()), 15.0, 0.3), rows(page)
                assert page.locator("#connection").inner_text() == "the monitor does not answer"
                assert [e for e in page.errors if "Failed to load resource" not in e and "Failed to fetch" not in e] == []
            finally:
                page.close()
    finally:
        for d in daemons.values():
            d.stop()


@pytest.mark.slow
def test_a_vehicle_behind_nat_connects_to_a_listening_monitor():
    """The other direction (docs/deployment.md): the monitor listens, the vehicle connects to it."""
    from uwcam.fleet.monitor import ZenohListener

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    fleet = Fleet(stale_s=5.0)
    listener = ZenohListener(fleet, connect=[], listen=[endpoint], scouting=False)
    listener.start()
    cfg = vehicle_config("rov-a", f"tcp/127.0.0.1:{free_port()}")
    cfg = cfg.model_copy(update={"zenoh": cfg.zenoh.model_copy(update={"listen": [], "connect": [endpoint]})})
    d = Daemon(cfg)
    try:
        d.start()

        def heard():
            vehicles = fleet.snapshot(time.monotonic(), time.time())
            return len(vehicles) == 1 and vehicles[0]["centre_m"] is not None and vehicles[0]["fps"] is not None

        assert wait_for(heard, 60.0, 0.2), fleet.snapshot(time.monotonic(), time.time())
        (rov,) = fleet.snapshot(time.monotonic(), time.time())
        assert rov["name"] == "rov-a" and rov["centre_m"] == pytest.approx(DISTANCES_M["rov-a"], rel=0.06)
        assert not rov["stale"] and rov["devices"]["camera"] == "ok"
    finally:
        d.stop()
        listener.close()
