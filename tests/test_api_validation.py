"""Request validation of the state-changing routes: every number checked, bad input a 4xx that
changes nothing, boundaries exactly where the documentation puts them."""

from __future__ import annotations

import json

import pytest

from tests.served import Server
from tests.test_auth import TOKEN, config
from tests.waiting import wait_for

AUTH = {"Authorization": f"Bearer {TOKEN}"}


@pytest.fixture(scope="module")
def server():
    with Server(config(TOKEN)) as s:
        yield s


def put_lamp(s: Server, body) -> "object":
    return s.http.put("/api/v1/lamp", content=json.dumps(body), headers={**AUTH, "Content-Type": "application/json"})


@pytest.mark.parametrize("intensity", [0, 0.0, 37.5, 100, 100.0])
def test_lamp_intensity_accepted_from_0_to_100_percent(server, intensity):
    try:
        r = put_lamp(server, {"intensity": intensity})
        assert r.status_code == 200, r.text
        assert r.json()["intensity"] == round(intensity)
    finally:
        put_lamp(server, {"on": True, "intensity": 100})  # the module's other tests expect lit frames


@pytest.mark.parametrize("body", [
    {"intensity": -0.001}, {"intensity": 100.001}, {"intensity": 1e9}, {"intensity": float("nan")},
    {"intensity": float("inf")}, {"intensity": float("-inf")}, {"intensity": [50]}, {"intensity": "lots"},
    {"on": 2}, {"colour": "red"}, [], "on",
])
def test_bad_lamp_commands_are_refused_and_change_nothing(server, body):
    before = server.http.get("/api/v1/lamp").json()
    r = put_lamp(server, body)
    assert r.status_code == 422, (body, r.status_code, r.text)
    after = server.http.get("/api/v1/lamp").json()
    assert (after["on"], after["intensity"]) == (before["on"], before["intensity"])


def test_lamp_switches_and_reports_back(server):
    try:
        r = put_lamp(server, {"on": False})
        assert r.status_code == 200 and r.json()["on"] is False
        r = put_lamp(server, {"on": True, "intensity": 60})
        assert r.status_code == 200 and r.json()["on"] is True and r.json()["intensity"] == 60
        assert put_lamp(server, {}).json()["on"] is True  # nothing asked, nothing changed
    finally:
        put_lamp(server, {"on": True, "intensity": 100})


def patch(s: Server, body):
    return s.http.patch("/api/v1/config", content=json.dumps(body), headers={**AUTH, "Content-Type": "application/json"})


@pytest.mark.parametrize("body, message", [
    ({"smoothing": "gaussian"}, "smoothing"),
    ({"smoothing_stage": "during"}, "smoothing_stage"),
    ({"smoothing_target": 0.0}, "greater than or equal to 0.001"),
    ({"smoothing_target": 0.7}, "less than or equal to 0.5"),
    ({"smoothing_target": float("nan")}, "smoothing_target"),
    ({"pair": ["R", "X"]}, "pair needs two different channels"),
    ({"pair": ["G", "G"]}, "pair needs two different channels"),
    ({"pair": ["R"]}, "pair"),
    ({"pair": ["R", "G", "B"]}, "pair"),
    ({"path_length_bounds": [5.0, 1.0]}, "min < max"),
    ({"path_length_bounds": [2.0, 2.0]}, "min < max"),
    ({"path_length_bounds": [-1.0, 5.0]}, "greater than or equal to 0"),
    ({"path_length_bounds": [0.0, 0.0]}, "path_length_bounds"),
    ({"path_length_bounds": [float("nan"), 5.0]}, "path_length_bounds"),
    ({"path_length_bounds": [0.0, float("nan")]}, "path_length_bounds"),
    ({"lamp_off_interval": -1}, "greater than or equal to 0"),
    ({"lamp_off_interval": 1.5}, "lamp_off_interval"),
    ({"fuse": "maybe"}, "fuse"),
    ({"patch": {"region": [0, 0, 4, 4]}}, "path_length_m"),
    ({"patch": {"region": [0, 0, 0, 4], "path_length_m": 1.0}}, "greater than 0"),
    ({"patch": {"region": [0, 0, 4, 4], "path_length_m": -1.0}}, "greater than 0"),
    ({"colour": 1}, "colour"),
    ({"exposure": {"target": 2.0}}, "target"),
    ({"exposure": {"max_step": float("nan")}}, "max_step"),
    ({"exposure": {"min_exposure_us": 100.0, "max_exposure_us": 10.0}}, "min_exposure_us must be less"),
    ({"exposure": {"auto": True}}, "auto"),
])
def test_bad_processing_settings_are_refused_with_the_reason(server, body, message):
    before = server.http.get("/api/v1/config").json()
    r = patch(server, body)
    assert r.status_code == 422, (body, r.status_code, r.text)
    assert message in json.dumps(r.json()), r.text
    assert server.http.get("/api/v1/config").json() == before


@pytest.mark.parametrize("body", [{"smoothing_target": 0.7}, {"path_length_bounds": [5.0, 1.0]}])
def test_settings_refused_as_a_whole_name_the_field_and_do_not_echo_the_settings(server, body):
    """Checked once merged with the settings in use (the bounds and the order of the bounds are the
    whole settings' rules): the 422 names the field and the rule, without quoting back the input,
    which is the whole merged settings there."""
    r = patch(server, body)
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert detail and all(set(error) == {"type", "loc", "msg"} for error in detail), detail
    field = next(iter(body))
    assert any(field in error["loc"] or field in error["msg"] for error in detail), detail


def test_good_processing_settings_apply_and_restore(server):
    before = server.http.get("/api/v1/config").json()
    try:
        r = patch(server, {"pair": ["R", "G"], "path_length_bounds": [0.5, 30.0], "smoothing": "median"})
        assert r.status_code == 200, r.text
        assert r.json()["pair"] == ["R", "G"] and r.json()["path_length_bounds"] == [0.5, 30.0]
        assert server.http.get("/api/v1/config").json()["smoothing"] == "median"
        r = patch(server, {"fuse": True})
        assert r.status_code == 200 and r.json()["pair"] is None and r.json()["smoothing"] == "median"
        r = patch(server, {"fuse": False, "lamp_off_interval": 0})
        assert r.status_code == 200 and r.json()["pair"] is None
        r = patch(server, {"path_length_bounds": [0.0, 1e-9]})
        assert r.status_code == 200, r.text  # tiny but ordered and positive
        restored = server.http.post("/api/v1/config/restore", headers=AUTH)
        assert restored.status_code == 200 and restored.json()["path_length_bounds"] == [0.5, 30.0]  # before the last change
    finally:
        patch(server, {k: v for k, v in before.items() if k in ("smoothing", "smoothing_stage", "path_length_bounds",
                                                                "lamp_off_interval")} | {"fuse": True})


def test_adaptive_windows_switch_on_live_and_the_loop_ranges_with_them(server):
    before = server.http.get("/api/v1/config").json()
    try:
        r = patch(server, {"smoothing": "adaptive", "smoothing_target": 0.05})
        assert r.status_code == 200 and r.json()["smoothing"] == "adaptive" and r.json()["smoothing_target"] == 0.05, r.text
        assert server.daemon.pipeline.processing.smoothing_target == 0.05
        n = server.daemon.pipeline.processed
        assert wait_for(lambda: server.daemon.pipeline.processed > n + 2, timeout_s=30)  # the loop ranges on
    finally:
        patch(server, {k: v for k, v in before.items() if k in ("smoothing", "smoothing_target")})


def test_exposure_control_switches_on_live_and_reports_in_the_status(server):
    try:
        assert put_lamp(server, {"on": True, "intensity": 100}).status_code == 200  # the controller meters lit frames only
        r = patch(server, {"exposure": {"max_step": 4.0}})
        assert r.status_code == 200 and r.json()["exposure"]["max_step"] == 4.0, r.text
        assert wait_for(lambda: server.http.get("/api/v1/status").json()["exposure"]["frames_metered"] > 2, timeout_s=30)
        status = server.http.get("/api/v1/status").json()["exposure"]
        assert status["enabled"] and status["control"] == "per-channel" and set(status["channels"]) == {"R", "G", "B"}
        r = patch(server, {"exposure": None})
        assert r.status_code == 200 and r.json()["exposure"] is None
        assert server.http.get("/api/v1/status").json()["exposure"]["enabled"] is False
    finally:
        patch(server, {"exposure": None})


@pytest.mark.parametrize("name, status", [
    ("ok-name_1.v2", 422),  # a valid name: refused only because the body is not a profile
    ("a" * 64, 422),
    ("a" * 65, 422),
    ("bad name", 422),
    ("bad%2Fname", 404),
])
def test_profile_names_are_checked_before_the_body(server, name, status):
    r = server.http.put(f"/api/v1/calibration/profiles/{name}", content=b"{}", headers=AUTH)
    assert r.status_code == status, (name, r.status_code, r.text)
    if name in ("a" * 65, "bad name"):
        assert "profile names use letters, digits" in r.json()["detail"]
    names = [p["name"] for p in server.http.get("/api/v1/calibration/profiles").json()]
    assert name not in names


def test_oversized_and_malformed_profiles_are_refused(server):
    big = b"x: " + b"1" * (1 << 20)
    r = server.http.put("/api/v1/calibration/profiles/big", content=big, headers=AUTH)
    assert r.status_code == 413 and "larger than 1048576 bytes" in r.json()["detail"]
    for body, message in [(b"\xff\xfe", "not valid YAML or JSON"), (b"[1, 2]", "must be a mapping"),
                          (b"a: [", "not valid YAML or JSON"), (b"{}", "profile")]:
        r = server.http.put("/api/v1/calibration/profiles/junk", content=body, headers=AUTH)
        assert r.status_code == 422 and message in r.json()["detail"], (body, r.text)
    assert "junk" not in [p["name"] for p in server.http.get("/api/v1/calibration/profiles").json()]


def test_a_lamp_that_stops_answering_is_a_503_and_errors_carry_no_links(server):
    device = server.app.state.daemon.lamp.device
    device.disconnect()
    try:
        r = put_lamp(server, {"on": True})
        assert r.status_code == 503 and r.json()["detail"].startswith("the lamp does not answer: ")
    finally:
        device.reconnect()
    assert wait_for(lambda: put_lamp(server, {"on": True}).status_code == 200, 20.0)
    bad = patch(server, {"path_length_bounds": [5.0, 1.0]})
    assert bad.status_code == 422 and all("url" not in e for e in bad.json()["detail"])


def test_without_a_lamp_its_routes_say_so():
    cfg = config(TOKEN)
    cfg.lamp = None
    with Server(cfg) as s:
        assert s.http.get("/api/v1/lamp").status_code == 404
        r = s.http.put("/api/v1/lamp", json={"on": True}, headers=AUTH)
        assert r.status_code == 404 and r.json()["detail"] == "no lamp configured"
        r = s.http.patch("/api/v1/config", json={"lamp_off_interval": 4}, headers=AUTH)
        assert r.status_code == 422 and "lamp" in r.json()["detail"]


def test_settings_at_their_upper_limits_are_accepted(server):
    """The limits README.md states are inclusive through the API too: a vehicle mask of 64 boxes,
    a lamp-off interval of 100000 frames."""
    before = server.http.get("/api/v1/config").json()
    try:
        r = patch(server, {"vehicle_mask": [[i, 0, 1, 1] for i in range(64)]})
        assert r.status_code == 200 and len(r.json()["vehicle_mask"]) == 64, r.text
        assert patch(server, {"vehicle_mask": [[i, 0, 1, 1] for i in range(65)]}).status_code == 422
        r = patch(server, {"lamp_off_interval": 100000})
        assert r.status_code == 200 and r.json()["lamp_off_interval"] == 100000, r.text
    finally:
        patch(server, {"vehicle_mask": before["vehicle_mask"], "lamp_off_interval": before["lamp_off_interval"]})
    assert server.http.get("/api/v1/config").json() == before


def test_refused_settings_name_the_field_and_reason_without_echoing_the_settings(server):
    """A rule over the merged settings (min < max) fails on the whole settings object: the answer
    names the rule, and does not send back every setting as the offending input."""
    r = patch(server, {"path_length_bounds": [5.0, 1.0]})
    assert r.status_code == 422 and "min < max" in r.text
    assert all("input" not in error for error in r.json()["detail"]), r.text


@pytest.mark.parametrize("pair, message", [
    (["X" * 64, "G"], "pair needs two different channels"),  # 64 characters: checked against the profile's names
    (["R", "X" * 64], "pair needs two different channels"),
    (["X" * 65, "G"], "at most 64 characters"),  # longer: refused before any lookup
    (["R", "X" * 65], "at most 64 characters"),
])
def test_pair_names_up_to_64_characters_are_looked_up_and_longer_ones_refused(server, pair, message):
    before = server.http.get("/api/v1/config").json()
    r = patch(server, {"pair": pair})
    assert r.status_code == 422 and message in r.text, r.text
    assert server.http.get("/api/v1/config").json() == before
