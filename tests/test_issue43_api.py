"""Issue #43, items 14-17 and 21: inputs refused rather than coerced, profiles checked at upload as
at activation, the stream's query numbers, Zenoh endpoints in the configuration, a recording on a
full disk, and the lamp's status codes as docs/api.md gives them."""

from __future__ import annotations

import asyncio
import json
import os
import subprocess

import pytest
import websockets

from tests.served import Server
from tests.test_api import small_config
from tests.test_hardening_second import active_profile, altered
from tests.waiting import wait_for
from uwcam.cli import main
from uwcam.config import RecordingConfig, load_config
from uwcam.fileio import UserInputError

JSON = {"Content-Type": "application/json"}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    cfg = small_config()
    cfg.recording = RecordingConfig(folder=str(tmp_path_factory.mktemp("issue43") / "recordings"), chunk_kb=64)
    with Server(cfg) as s:
        assert wait_for(lambda: s.daemon.pipeline.processed > 2, 60.0), "the frame loop did not start"
        yield s


def send(s: Server, method: str, path: str, body) -> "object":
    return s.http.request(method, path, content=json.dumps(body), headers=JSON)


def detail_names(r, field: str) -> bool:
    """Whether a 422's detail names ``field`` (pydantic's list of errors, or one sentence)."""
    detail = r.json()["detail"]
    if isinstance(detail, list):
        return any(field in [str(p) for p in e["loc"]] for e in detail)
    return field in detail


# ---------------------------------------------------------------- 14: numbers are not coerced

@pytest.mark.parametrize("body", [{"distance_m": True}, {"distance_m": "2"}, {"distance_m": "2.0"},
                                  {"distance_m": False}])
def test_a_plate_distance_that_is_not_a_number_is_refused(server, body):
    r = send(server, "PUT", "/api/v1/simulation/plate", body)
    assert r.status_code == 422 and detail_names(r, "distance_m"), (body, r.status_code, r.text)


def test_a_whole_plate_distance_is_a_number(server):
    # Validated as a number and passed on: this camera is not the simulated tank, so no plate to move.
    r = send(server, "PUT", "/api/v1/simulation/plate", {"distance_m": 2})
    assert r.status_code == 404 and "not the tank" in r.json()["detail"], r.text


@pytest.mark.parametrize("body", [{"timeout_s": "5"}, {"timeout_s": True}, {"frames": "4"}, {"frames": True}])
def test_open_water_numbers_that_are_not_numbers_are_refused(server, body):
    before = server.http.get("/api/v1/backscatter").json()
    r = send(server, "POST", "/api/v1/backscatter/open-water", body)
    assert r.status_code == 422 and detail_names(r, next(iter(body))), (body, r.status_code, r.text)
    after = server.http.get("/api/v1/backscatter").json()
    assert after.get("capture") == before.get("capture") and after.get("open_water") == before.get("open_water")


@pytest.mark.parametrize("key, value", [
    ("recording.budget_mb_s", '"40"'), ("recording.budget_mb_s", "true"), ("recording.max_size_mb", '"100"'),
    ("recording.queue_frames", "true"), ("recording.queue_frames", "32.0"), ("recording.results", "1"),
    ("recording.preview_quality", '"80"'), ("foxglove.port", '"8765"'), ("foxglove.enabled", "1"),
    ("mounting.translation_m", '["0", 0, 0]'), ("mavlink.rate_hz", '"10"'), ("mavlink.sensor_id", "false"),
    ("mavlink.obstacle_distance", '"yes"'), ("api.cockpit_actions_token", "1"),
])
def test_configuration_numbers_and_flags_are_not_coerced(tmp_path, key, value):
    section, field = key.split(".")
    path = tmp_path / "uwcam.yaml"
    path.write_text(f"{section}:\n  {field}: {value}\n")
    with pytest.raises(UserInputError, match=f"key '{key}"):
        load_config(path)


def test_whole_numbers_where_the_configuration_takes_any_number(tmp_path):
    path = tmp_path / "uwcam.yaml"
    path.write_text("recording:\n  budget_mb_s: 40\n  max_size_mb: 100\n  chunk_kb: 512\nmavlink:\n  rate_hz: 10\n")
    cfg = load_config(path)
    assert (cfg.recording.budget_mb_s, cfg.recording.max_size_mb, cfg.mavlink.rate_hz) == (40, 100, 10)


# --------------------------------------------------- 15: a profile is checked at upload in full



@pytest.mark.parametrize("path, value, words", [
    (("intrinsics", "fx"), 1e-300, "do not suit the camera's 160×120 image"),  # in bounds, not for this camera
    (("intrinsics", "fx"), True, "intrinsics.fx"),
    (("intrinsics", "fx"), "1108", "intrinsics.fx"),
    (("quantisation_step",), 0, "quantisation_step 0"),
    (("saturation_level",), "65535", "saturation_level"),
    (("channels", 0, "read_noise"), False, "channels.0.read_noise"),
    (("provenance", "frames_per_distance"), [True], "provenance.frames_per_distance.0"),
])
def test_a_profile_that_activation_would_refuse_is_refused_at_upload(server, path, value, words):
    name, original = active_profile(server)
    assert original["intrinsics"] is not None
    r = send(server, "PUT", "/api/v1/calibration/profiles/upload-43", altered(original, path, value))
    assert r.status_code == 422, (path, value, r.status_code, r.text)
    assert words in r.json()["detail"] and "\n" not in r.json()["detail"], r.text
    assert "upload-43" not in server.daemon.profiles  # not stored
    assert server.http.get("/api/v1/calibration/profiles/upload-43").status_code == 404
    assert server.daemon.profile_name == name


def test_a_profile_that_fits_is_still_stored_without_being_activated(server):
    name, original = active_profile(server)
    r = send(server, "PUT", "/api/v1/calibration/profiles/fits-43", dict(original, name="fits 43"))
    assert r.status_code == 200 and r.json()["active"] is False, r.text
    assert server.daemon.profile_name == name and "fits-43" in server.daemon.profiles


# ------------------------------------------------------------- 16: the stream's query numbers

async def first_message(port: int, query: str):
    async with websockets.connect(f"ws://127.0.0.1:{port}/api/v1/stream?{query}") as ws:
        return json.loads(await asyncio.wait_for(ws.recv(), 10.0))


@pytest.mark.parametrize("query", ["rate=nan", "rate=NaN", "rate=inf", "rate=-inf", "rate=0", "rate=-5"])
def test_a_stream_rate_that_is_not_a_finite_positive_number_is_refused(server, query):
    with pytest.raises(websockets.exceptions.InvalidStatus) as refused:
        asyncio.run(first_message(server.port, query))
    assert refused.value.response.status_code == 403  # as a bad encoding is: refused before accepting


def test_a_good_stream_rate_is_in_the_hello_as_valid_json(server):
    hello = asyncio.run(first_message(server.port, "rate=2.5"))
    assert hello["type"] == "hello" and hello["rate_hz"] == 2.5
    capped = asyncio.run(first_message(server.port, "rate=1000"))
    assert capped["rate_hz"] == server.app.state.config.api.stream_rate_hz


# ----------------------------------------------------------- 17: Zenoh endpoints in the config

@pytest.mark.parametrize("endpoint, words", [
    ("tcp/127.0.0.1:99999", "port 99999 is not 1–65535"),
    ("tcp/127.0.0.1:0", "port 0 is not 1–65535"),
    ("tcp/127.0.0.1:65536", "port 65536"),
    ("tcp/127.0.0.1", "not a Zenoh endpoint"),
    ("tcp/127.0.0.1:", "not a Zenoh endpoint"),
    ("tcp/:7447", "not a Zenoh endpoint"),
    ("tcp/300.1.1.1:7447", "300.1.1.1 is not an IP address"),
    ("http/127.0.0.1:7447", "with a protocol of tcp, udp, tls, quic, ws, unixsock-stream"),
    ("serial//dev/ttyUSB0", "with a protocol of"),
])
@pytest.mark.parametrize("key", ["listen", "connect"])
def test_zenoh_endpoints_zenoh_cannot_open_fail_the_config_check(tmp_path, capsys, key, endpoint, words):
    path = tmp_path / "uwcam.yaml"
    path.write_text(f"zenoh:\n  scouting: false\n  {key}: ['{endpoint}']\n")
    with pytest.raises(UserInputError, match=f"key 'zenoh.{key}.0'") as refused:
        load_config(path)
    assert words in str(refused.value) and "\n" not in str(refused.value)
    capsys.readouterr()
    assert main(["config", "check", str(path)]) == 2
    assert words in capsys.readouterr().err


@pytest.mark.parametrize("endpoint", [
    "tcp/0.0.0.0:7447", "tcp/127.0.0.1:1", "tcp/192.168.2.1:65535", "tcp/[::1]:7447", "tcp/[fe80::1%eth0]:7447",
    "udp/224.0.0.224:7446#iface=eth0", "tls/rov1.example.org:7447", "quic/10.0.0.2:7447", "ws/rov1.local:8000",
    "tcp/rov-1:7447?prio=1", "unixsock-stream//tmp/zenoh.sock",
])
def test_zenoh_endpoints_as_the_docs_write_them_pass(tmp_path, endpoint):
    path = tmp_path / "uwcam.yaml"
    path.write_text(f"zenoh:\n  listen: ['{endpoint}']\n  connect: ['{endpoint}']\n")
    z = load_config(path).zenoh
    assert z.listen == z.connect == [endpoint]


# ------------------------------------------------- 21: a full disk, and the lamp's status codes

def recordings(s: Server) -> list[str]:
    folder = s.daemon.config.recording.folder
    return sorted(os.listdir(folder)) if os.path.isdir(folder) else []


def test_a_recording_on_a_disk_without_room_is_refused_with_507(server, monkeypatch):
    import uwcam.recording.recorder as recorder

    before = recordings(server)
    monkeypatch.setattr(recorder, "disk_space_bytes", lambda path: (4096, 10**9))  # 4 kB left
    try:
        r = server.http.post("/api/v1/recordings/start")
        assert r.status_code == 507, r.text
        assert "no room to record" in r.json()["detail"] and "MB free" in r.json()["detail"]
        assert recordings(server) == before  # no empty file left behind
        assert server.http.get("/api/v1/recordings/status").json()["state"] == "idle"
    finally:
        server.http.post("/api/v1/recordings/stop")
    monkeypatch.undo()
    started = server.http.post("/api/v1/recordings/start")  # with room: records as before
    try:
        assert started.status_code == 200 and started.json()["state"] == "recording", started.text
    finally:
        assert server.http.post("/api/v1/recordings/stop").json()["state"] == "idle"


@pytest.fixture
def full_disk(server):
    """The recordings' folder on a small tmpfs filled to the last byte (needs root: skipped otherwise)."""
    folder = server.daemon.config.recording.folder
    os.makedirs(folder, exist_ok=True)
    leftover = recordings(server)
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", folder], capture_output=True,
                             text=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here (needs root): {mounted.stderr.strip()}")
    try:
        with open(os.path.join(folder, "filler.bin"), "wb") as fh:
            try:
                while True:
                    fh.write(b"\0" * 65536)
                    fh.flush()
            except OSError:
                pass
        yield folder
    finally:
        server.http.post("/api/v1/recordings/stop")
        subprocess.run(["umount", folder], check=True)
    assert recordings(server) == leftover


def test_a_recording_on_a_full_file_system_is_refused_and_leaves_no_file(server, full_disk):
    r = server.http.post("/api/v1/recordings/start")
    assert r.status_code == 507 and "no room to record" in r.json()["detail"], r.text
    assert os.listdir(full_disk) == ["filler.bin"]  # no empty .mcap
    assert server.http.get("/api/v1/recordings/status").json()["state"] == "idle"


def test_a_disk_full_before_anything_was_written_leaves_no_empty_file(server, full_disk, monkeypatch):
    """Free space that was there at the start and gone at the first write (another writer took it)."""
    import uwcam.recording.recorder as recorder

    monkeypatch.setattr(recorder, "disk_space_bytes", lambda path: (10**9, 10**10))
    r = server.http.post("/api/v1/recordings/start")
    assert r.status_code == 200, r.text
    assert wait_for(lambda: server.http.get("/api/v1/recordings/status").json()["state"] == "idle", 30.0)
    status = server.http.get("/api/v1/recordings/status").json()
    assert status["last_stop_reason"].startswith("disk full") and "empty file was removed" in status["last_stop_reason"]
    assert os.listdir(full_disk) == ["filler.bin"]


def put_lamp(s: Server, body) -> "object":
    return send(s, "PUT", "/api/v1/lamp", body)


def test_a_silent_lamp_is_a_503_as_the_docs_say_and_get_says_so_too(server):
    device = server.daemon.lamp.device
    device.disconnect()
    try:
        r = put_lamp(server, {"on": True})
        assert r.status_code == 503 and r.json()["detail"].startswith("the lamp does not answer: "), r.text
        got = server.http.get("/api/v1/lamp")
        assert got.status_code == 503 and got.json()["detail"].startswith("the lamp does not answer: ")
    finally:
        device.reconnect()
    assert wait_for(lambda: put_lamp(server, {"on": True}).status_code == 200, 20.0)


def test_a_lamp_that_refuses_a_command_is_a_502(server, monkeypatch):
    device = server.daemon.lamp.device
    monkeypatch.setattr(device, "answer", lambda command: "ERR overheated")
    r = put_lamp(server, {"on": True})
    assert r.status_code == 502 and r.json()["detail"].startswith("lamp did not accept the command: "), r.text
    assert "overheated" in r.json()["detail"]
    monkeypatch.undo()
    assert wait_for(lambda: put_lamp(server, {"on": True, "intensity": 100}).status_code == 200, 20.0)
