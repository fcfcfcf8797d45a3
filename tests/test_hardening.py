"""Regression tests for every fault found by trying to break the daemon (issue 12): a real uvicorn
server on an ephemeral port, real HTTP and WebSocket clients, simulated devices with faults."""

from __future__ import annotations

import asyncio
import json
import sys
import threading
import time

import httpx
import numpy as np
import pytest
import websockets
import yaml

from tests.served import Server
from tests.test_api import small_config
from tests.waiting import wait_for
from uwcam.api.limits import DEFAULT_BODY_LIMIT
from uwcam.api.profiles import MAX_PROFILE_BYTES
from uwcam.config import DaemonConfig
from uwcam.drivers.sim import SimulatedCamera
from uwcam.fileio import UserInputError


@pytest.fixture(autouse=True)
def no_leaked_threads():
    """Server threads (uvicorn's worker pool) outlive a test by design here; see test_api."""
    yield


@pytest.fixture(scope="module")
def server():
    with Server(small_config()) as s:
        assert wait_for(lambda: s.daemon.pipeline.processed > 2, 60.0)
        yield s


def status(s) -> dict:
    return s.http.get("/api/v1/status").json()


# -- security ---------------------------------------------------------------------------------

def test_empty_host_is_refused_and_only_explicit_loopback_is_loopback():
    with pytest.raises(ValueError, match="at least 1 character"):
        DaemonConfig.model_validate({"api": {"host": ""}})
    from uwcam.api import create_app

    for host in ("0.0.0.0", "::", "10.0.0.2", "vehicle.local"):
        config = small_config()
        config.api.host = host
        with pytest.raises(UserInputError, match="without a token"):
            create_app(config)


def test_cross_origin_state_change_is_refused(server):
    own = f"http://127.0.0.1:{server.port}"
    server.http.patch("/api/v1/config", json={"smoothing": "median"})
    server.http.patch("/api/v1/config", json={"smoothing": "mean"})
    evil = server.http.post("/api/v1/config/restore", headers={"Origin": "http://evil.example"})
    assert evil.status_code == 403 and "may not change" in evil.json()["detail"]
    assert server.http.post("/api/v1/config/restore", headers={"Origin": "null"}).status_code == 403
    assert server.http.get("/api/v1/config").json()["smoothing"] == "mean"  # nothing restored
    ok = server.http.post("/api/v1/config/restore", headers={"Origin": own})
    assert ok.status_code == 200 and ok.json()["smoothing"] == "median"
    server.http.patch("/api/v1/config", json={"smoothing": "none"})


def test_websocket_from_a_foreign_origin_is_refused(server):
    async def connect(origin):
        async with websockets.connect(f"ws://127.0.0.1:{server.port}/api/v1/stream", origin=origin) as ws:
            return json.loads(await asyncio.wait_for(ws.recv(), 10.0))["type"]

    with pytest.raises(websockets.exceptions.InvalidStatus) as refused:
        asyncio.run(connect("http://evil.example"))
    assert refused.value.response.status_code == 403
    assert asyncio.run(connect(f"http://127.0.0.1:{server.port}")) == "hello"


def test_unknown_host_names_are_refused(server):
    rebound = server.http.get("/api/v1/status", headers={"Host": "evil.example"})
    assert rebound.status_code == 421 and "api.allowed_hosts" in rebound.json()["detail"]
    for host in (f"127.0.0.1:{server.port}", f"localhost:{server.port}", "blueos.local", "[::1]:8080"):
        assert server.http.get("/api/v1/status", headers={"Host": host}).status_code == 200, host


def test_allowed_hosts_admit_a_reverse_proxy_name():
    config = small_config()
    config.api.allowed_hosts = ["*.vehicle.example"]
    with Server(config) as s:
        assert s.http.get("/api/v1/config", headers={"Host": "cam.vehicle.example"}).status_code == 200
        assert s.http.get("/api/v1/config", headers={"Host": "vehicle.example.evil"}).status_code == 421


def test_non_ascii_tokens_are_wrong_tokens_not_errors(monkeypatch):
    with Server(small_config(token="s3cret")) as s:
        bad = s.http.put("/api/v1/lamp", json={"on": True}, headers={"Authorization": "Bearer sécret".encode()})
        assert bad.status_code == 401
        latin = s.http.put("/api/v1/lamp", json={"on": True}, headers={"Authorization": b"Bearer \xff\xfe"})
        assert latin.status_code == 401
        assert s.http.post("/api/v1/session", json={"token": "sécret"}).status_code == 401
    monkeypatch.setenv("UWCAM_TOKEN", "sécret-ü")
    with Server(small_config()) as s:
        assert s.http.put("/api/v1/lamp", json={"on": True}, headers={"Authorization": b"Bearer x"}).status_code == 401
        good = s.http.put("/api/v1/lamp", json={"on": True}, headers={"Authorization": "Bearer sécret-ü".encode()})
        assert good.status_code == 200, good.text
        assert s.http.post("/api/v1/session", json={"token": "sécret-ü"}).status_code == 200


# -- every number finite and in range ---------------------------------------------------------

@pytest.mark.parametrize("processing, key", [
    ({"patch": {"marker": {"id": 1, "offset": [float("nan"), 0], "size": [1, 1]}, "path_length_m": 1}}, "offset"),
    ({"patch": {"region": [0, 0, 4, 4], "path_length_m": float("inf")}}, "path_length_m"),
    ({"path_length_bounds": [0, float("inf")]}, "path_length_bounds"),
    ({"lamp_off_interval": 2 ** 63}, "lamp_off_interval"),
    ({"lamp_off_interval": True}, "lamp_off_interval"),
    ({"patch": {"region": [0, 0, 4, 4], "path_length_m": "1.0"}}, "path_length_m"),
])
def test_config_refuses_non_finite_and_out_of_range_numbers(tmp_path, processing, key):
    from uwcam.config import load_config

    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump({"version": 1, "processing": processing}))
    with pytest.raises(UserInputError, match=key):
        load_config(path)


def test_yaml_nan_and_infinity_spellings_are_refused(tmp_path):
    from uwcam.config import load_config

    path = tmp_path / "rig.yaml"
    path.write_text("version: 1\nprocessing:\n  path_length_bounds: [0, .inf]\n")
    with pytest.raises(UserInputError, match="finite number"):
        load_config(path)
    path.write_text("version: 1\ncamera: {watchdog_s: .nan}\n")
    with pytest.raises(UserInputError, match="finite number"):
        load_config(path)


def test_api_refuses_nan_infinity_bools_and_huge_numbers(server):
    before = server.http.get("/api/v1/config").json()
    headers = {"content-type": "application/json"}
    for body in ('{"path_length_bounds": [0, NaN]}', '{"path_length_bounds": [0, Infinity]}',
                 '{"lamp_off_interval": 9223372036854775808}', '{"lamp_off_interval": 1e400}',
                 '{"patch": {"region": [0, 0, 4, 4], "path_length_m": NaN}}', '{"fuse": 1}'):
        r = server.http.patch("/api/v1/config", content=body, headers=headers)
        assert r.status_code == 422, (body, r.status_code, r.text)
        json.loads(r.text)  # valid JSON: no bare NaN echoed back
    huge = server.http.patch("/api/v1/config", content='{"lamp_off_interval": ' + "9" * 5000 + "}", headers=headers)
    assert 400 <= huge.status_code < 500
    deep = server.http.patch("/api/v1/config", content="[" * 50000 + "]" * 50000, headers=headers)
    assert 400 <= deep.status_code < 500
    lamp = server.daemon.lamp.last_status.percent
    for body in ({"intensity": False}, {"intensity": "50"}, {"on": 1}, {"intensity": float("nan")}):
        text = json.dumps(body)  # json.dumps writes NaN for nan
        r = server.http.put("/api/v1/lamp", content=text, headers=headers)
        assert r.status_code == 422, (body, r.text)
    assert server.daemon.lamp.last_status.percent == lamp
    assert server.http.get("/api/v1/config").json() == before


def test_json_bodies_have_a_size_limit(server):
    big = b'{"smoothing": "mean", "pad": "' + b"x" * (DEFAULT_BODY_LIMIT + 10) + b'"}'
    r = server.http.patch("/api/v1/config", content=big, headers={"content-type": "application/json"})
    assert r.status_code == 413 and str(DEFAULT_BODY_LIMIT) in r.json()["detail"]

    def chunked():  # no Content-Length: counted as it arrives
        yield b'{"smoothing": "mean", "pad": "'
        for _ in range(100):
            yield b"x" * 4096
        yield b'"}'

    r = server.http.patch("/api/v1/config", content=chunked(), headers={"content-type": "application/json"})
    assert r.status_code == 413
    assert server.http.get("/api/v1/config").json()["smoothing"] == "none"


# -- profiles: validated completely, then applied at once --------------------------------------

def active_profile(s) -> dict:
    name = next(p["name"] for p in s.http.get("/api/v1/calibration/profiles").json() if p["active"])
    return s.http.get(f"/api/v1/calibration/profiles/{name}").json()


def test_profile_changes_are_validated_completely_then_applied(server):
    original = active_profile(server)
    name = next(p["name"] for p in server.http.get("/api/v1/calibration/profiles").json() if p["active"])
    pipeline_profile = server.daemon.pipeline.profile
    # Renamed channels: the pair setting G,B cannot be ranged with it.
    mapping = dict(zip(["R", "G", "B"], ["X", "Y", "Z"]))

    def rename(value):  # every channel name, wherever the profile keys or names by it
        if isinstance(value, dict):
            return {mapping.get(k, k): (mapping.get(v, v) if k in ("name", "reference_channel") else rename(v))
                    for k, v in value.items()}
        if isinstance(value, list):
            return [rename(v) for v in value]
        if isinstance(value, str) and value[:2] in ("V:", "b:"):  # covariance parameters, e.g. "V:G"
            return value[:2] + mapping.get(value[2:], value[2:])
        return value

    renamed = rename(original)
    up = server.http.put("/api/v1/calibration/profiles/renamed", content=yaml.safe_dump(renamed))
    assert up.status_code == 200, up.text
    assert server.http.patch("/api/v1/config", json={"pair": ["G", "B"]}).status_code == 200
    try:
        refused = server.http.post("/api/v1/calibration/profiles/renamed/activate")
        assert refused.status_code == 422 and "pair" in refused.json()["detail"]
        assert server.daemon.pipeline.profile is pipeline_profile  # the loop never switched
        assert status(server)["calibration"]["name"] == name
        # Over the active profile with PUT: the same check, and nothing changes when it fails.
        over = server.http.put(f"/api/v1/calibration/profiles/{name}", content=yaml.safe_dump(renamed))
        assert over.status_code == 422
        assert server.daemon.pipeline.profile is pipeline_profile
        assert server.http.get(f"/api/v1/calibration/profiles/{name}").json() == original
    finally:
        server.http.patch("/api/v1/config", json={"fuse": True})
    n = server.daemon.pipeline.processed
    assert wait_for(lambda: server.daemon.pipeline.processed > n + 2)  # ranging all along


def test_profile_names_starting_with_a_dot_are_refused(server):
    body = yaml.safe_dump(active_profile(server))
    for name in (".hidden", "..", ".x.yaml.tmp"):
        r = server.http.put(f"/api/v1/calibration/profiles/{name}", content=body)
        assert r.status_code in (404, 422), (name, r.status_code)
        assert name not in server.daemon.profiles


def test_profile_uploads_are_bounded_and_bad_yaml_is_a_4xx(server):
    declared = server.http.put("/api/v1/calibration/profiles/big", content=b"a: " + b"1" * MAX_PROFILE_BYTES)
    assert declared.status_code == 413

    def endless():
        for _ in range(4 * MAX_PROFILE_BYTES // 65536):
            yield b"#" * 65536

    streamed = server.http.put("/api/v1/calibration/profiles/big", content=endless())
    assert streamed.status_code == 413 and "big" not in server.daemon.profiles
    deep = server.http.put("/api/v1/calibration/profiles/deep", content=b"[" * 100000 + b"]" * 100000)
    assert deep.status_code == 422 and "nested" in deep.json()["detail"]
    huge = server.http.put("/api/v1/calibration/profiles/huge", content=b"format: " + b"7" * 6000)
    assert huge.status_code == 422


def test_a_slow_upload_does_not_freeze_the_api(server):
    """Parsing a large upload runs in a worker thread: status answers meanwhile."""
    body = yaml.safe_dump({f"key{k}": [k, k + 0.5, "text"] for k in range(20000)}).encode()
    assert len(body) < MAX_PROFILE_BYTES
    done = threading.Event()
    result = {}

    def upload():
        with httpx.Client(base_url=server.url, timeout=120.0) as c:
            start = time.monotonic()
            result["status"] = c.put("/api/v1/calibration/profiles/slow", content=body).status_code
            result["seconds"] = time.monotonic() - start
        done.set()

    worst = 0.0
    thread = threading.Thread(target=upload)
    thread.start()
    try:
        while not done.is_set():
            start = time.monotonic()
            server.http.get("/api/v1/status")
            worst = max(worst, time.monotonic() - start)
    finally:
        thread.join()
    assert result["status"] == 422  # not a profile, but read in full
    print(f"upload parsed in {result['seconds']:.2f} s; slowest status meanwhile {worst:.2f} s")
    assert worst < max(0.5, result["seconds"] / 3)


# -- ranging must not stop ---------------------------------------------------------------------

def processed_rate(s, seconds: float) -> float:
    n, t = s.daemon.pipeline.processed, time.monotonic()
    time.sleep(seconds)
    return (s.daemon.pipeline.processed - n) / (time.monotonic() - t)


def test_a_silent_lamp_does_not_stop_ranging():
    config = small_config()
    config.processing.lamp_off_interval = 4
    with Server(config) as s:
        assert wait_for(lambda: s.daemon.pipeline.stats()["ambient_frames"] >= 1, 60.0)
        baseline = processed_rate(s, 3.0)
        device = s.daemon.lamp.device
        device.received = lambda data: None  # the lamp hears nothing and says nothing
        try:
            assert wait_for(lambda: status(s)["lamp"]["health"]["state"] != "ok", 20.0)
            silent = processed_rate(s, 3.0)
            lamp = status(s)["lamp"]
            assert lamp["commands"]["consecutive_failures"] >= 1 and "no complete reply" in lamp["health"]["reason"]
            assert status(s)["frames"]["fps"] > 0
            start = time.monotonic()
            r = s.http.get("/api/v1/lamp")
            assert r.status_code == 503 and "does not answer" in r.json()["detail"]
            assert time.monotonic() - start < 5.0
        finally:
            del device.received
        print(f"frames per second: {baseline:.1f} before, {silent:.1f} with the lamp silent")
        # Before the fix each frame waited ~1 s for the lamp: about 1 fps.
        assert silent >= 0.5 * baseline and silent > 1.5
        ambient = s.daemon.pipeline.stats()["ambient_frames"]
        assert wait_for(lambda: status(s)["lamp"]["health"]["state"] == "ok", 30.0)
        assert wait_for(lambda: s.daemon.pipeline.stats()["ambient_frames"] > ambient, 30.0)  # the cycle resumes
        assert wait_for(lambda: s.daemon.rig.lamp_on, 10.0)


def test_fps_is_zero_when_nothing_is_processed(server):
    assert wait_for(lambda: status(server)["frames"]["fps"] > 0, 20.0)
    SimulatedCamera.stall("SIM-API")
    try:
        assert wait_for(lambda: status(server)["frames"]["fps"] == 0, 10.0)
        a = status(server)["frames"]["since_last_processed_s"]
        time.sleep(0.5)
        b = status(server)["frames"]["since_last_processed_s"]
        assert b >= a + 0.4 and b >= 2.0
    finally:
        SimulatedCamera.stall("SIM-API", False)
    assert wait_for(lambda: status(server)["frames"]["fps"] > 0, 20.0)
    assert status(server)["frames"]["since_last_processed_s"] < 2.0


# -- a slow WebSocket client gets the newest frame, never a queue ------------------------------

def test_a_slow_websocket_client_only_gets_fresh_frames():
    """A client reading one message every 0.5 s: every frame it gets is at most a couple of its
    own read periods old (what its own small buffers hold), not minutes (kernel buffers full of
    old frames, as before)."""
    import socket

    from uwcam.api import HEADER

    config = small_config()
    config.simulation["size"] = [320, 240]  # 150 kB per frame: the kernel buffers would hold dozens
    read_every = 0.5

    async def slow_client(port):
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 16384)  # the client keeps little
        sock.connect(("127.0.0.1", port))
        sock.setblocking(False)
        ages = []
        async with websockets.connect(f"ws://127.0.0.1:{port}/api/v1/stream?rate=30", sock=sock, max_queue=1,
                                      max_size=None) as ws:
            await ws.recv()  # hello
            end = time.monotonic() + 12.0
            while time.monotonic() < end:
                await asyncio.sleep(read_every)
                msg = await asyncio.wait_for(ws.recv(), 10.0)
                if isinstance(msg, bytes):
                    captured = HEADER.unpack_from(msg)[2]
                    ages.append((time.time_ns() - captured) / 1e9)
        return ages

    with Server(config) as s:
        assert wait_for(lambda: s.daemon.pipeline.processed > 5, 60.0)
        ages = asyncio.run(slow_client(s.port))
    print("ages of received frames (s):", " ".join(f"{a:.2f}" for a in ages))
    assert len(ages) >= 8
    assert max(ages[2:]) < 4 * read_every + 0.5, ages


# -- the command line and the configuration ----------------------------------------------------

def run_cli(*args: str, env: dict | None = None, timeout: float = 120.0):
    import os
    import subprocess
    import sys

    environment = {k: v for k, v in os.environ.items() if k != "UWCAM_TOKEN"} | (env or {})
    return subprocess.run([sys.executable, "-m", "uwcam", *args], capture_output=True, text=True, timeout=timeout,
                          env=environment)


def one_line_error(result, *fragments: str) -> None:
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2, (result.returncode, result.stderr)
    assert len(lines) == 1 and "Traceback" not in result.stderr, result.stderr
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])


def test_bad_port_and_busy_port_are_one_line_errors():
    import socket

    one_line_error(run_cli("run", "--port", "80808"), "--port", "65535", "80808")
    with socket.create_server(("127.0.0.1", 0)) as busy:
        port = busy.getsockname()[1]
        one_line_error(run_cli("run", "--port", str(port)), f"cannot listen on 127.0.0.1:{port}")


@pytest.mark.parametrize("text, fragments", [
    ("camera: {driver: simm}\ncalibration: p.yaml\n", ["unknown camera driver 'simm'", "known camera drivers", "sim"]),
    ("camera: {driver: sim, options: {fsp: 10}}\n", ["'fsp'", "unknown key", "fps"]),
    ("camera: {driver: sim, options: {fps: .nan}}\n", ["'fps'", "finite"]),
    ("camera: {driver: v4l2, options: {device: /dev/video0, fourcc: YUYV, exposure: 3}}\ncalibration: p.yaml\n",
     ["camera driver 'v4l2'", "'exposure'"]),
    ("camera: {driver: multi, options: {sensors: [{driver: sim, fsp: 1}, {driver: sim}]}}\ncalibration: p.yaml\n",
     ["'fsp'"]),
    ("camera: {driver: sim}\nsimulation: {water: jerlov-XX}\n", ["unknown water 'jerlov-XX'", "jerlov-IB"]),
    ("camera: {driver: sim}\nsimulation: {watter: jerlov-IB}\n", ["watter: unknown key"]),
    ("camera: {driver: sim}\nlamp: {driver: serial, options: {port: /dev/x, baud: true}}\n", ["'baud'"]),
    ("camera: {driver: sim}\nrangefinder: {driver: ping1d, options: {port: /dev/x, speed_of_sound: 15000}}\n",
     ["speed_of_sound"]),
    ("camera: {driver: sim}\nprocessing: {lamp_off_interval: 4}\n", ["lamp_off_interval needs a lamp"]),
    ("api: {port: 80808}\n", ["api.port"]),
])
def test_config_check_validates_drivers_and_their_options(tmp_path, text, fragments):
    path = tmp_path / "rig.yaml"
    path.write_text("version: 1\n" + text)
    from uwcam.cli import main

    import contextlib
    import io

    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        assert main(["config", "check", str(path)]) == 2
    line = err.getvalue().strip()
    assert len(line.splitlines()) == 1, line
    for fragment in fragments:
        assert fragment in line, (fragment, line)


def test_run_reports_a_device_that_cannot_work_in_one_line(tmp_path):
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump({"version": 1, "camera": {"driver": "sim", "options": {"fps": 5}},
                                    "lamp": {"driver": "serial", "options": {"port": str(tmp_path / "no-such-tty")}},
                                    "api": {"port": 0}}))
    one_line_error(run_cli("run", "--config", str(path)), "cannot open serial port", "no-such-tty")


def test_deploy_files_need_the_token_from_the_environment_only():
    from pathlib import Path

    deploy = Path(__file__).resolve().parent.parent / "deploy"
    for name in ("v4l2-rig.yaml", "gige-rig.yaml"):
        assert "token" not in yaml.safe_load((deploy / name).read_text())["api"]
        refused = run_cli("config", "check", str(deploy / name))
        one_line_error(refused, "UWCAM_TOKEN", "docs/deployment.md")
        assert run_cli("config", "check", str(deploy / name), env={"UWCAM_TOKEN": "t0ken"}).returncode == 0
    unit = (deploy / "uwcam.service").read_text()
    exec_start = next(line for line in unit.splitlines() if line.startswith("ExecStart="))
    assert "/usr/local/bin" not in exec_start and "/.venv/bin/uwcam run" in exec_start


# -- state that survives a restart -------------------------------------------------------------

class DaemonProcess:
    """``uwcam run`` in a subprocess, as systemd runs it."""

    def __init__(self, config_path, tmp_dir) -> None:
        import socket

        self.tmp_dir = str(tmp_dir)  # the simulated devices' pty folders: a SIGKILL leaves them

        with socket.socket() as probe:
            probe.bind(("127.0.0.1", 0))
            self.port = probe.getsockname()[1]
        self.config_path = config_path

    def __enter__(self) -> "DaemonProcess":
        import os
        import subprocess
        import sys

        env = {k: v for k, v in os.environ.items() if k != "UWCAM_TOKEN"} | {"TMPDIR": self.tmp_dir}
        self.process = subprocess.Popen([sys.executable, "-m", "uwcam", "run", "--config", str(self.config_path),
                                         "--port", str(self.port)], env=env,
                                        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        self.http = httpx.Client(base_url=f"http://127.0.0.1:{self.port}", timeout=10.0)

        def up():
            try:
                return self.http.get("/api/v1/status").json()["frames"]["processed"] > 0
            except httpx.HTTPError:
                assert self.process.poll() is None, self.process.stderr.read().decode()
                return False

        assert wait_for(up, 120.0, 0.2), "daemon did not come up"
        return self

    def kill(self) -> None:
        import signal

        self.process.send_signal(signal.SIGKILL)  # no orderly shutdown: as a power cut
        self.process.wait(timeout=30)

    def __exit__(self, *exc) -> None:
        self.http.close()
        if self.process.poll() is None:
            self.process.terminate()
            self.process.wait(timeout=30)
        self.process.stderr.close()


def test_settings_profile_and_lamp_survive_a_kill(tmp_path):
    profiles = tmp_path / "profiles"
    config = tmp_path / "rig.yaml"
    config.write_text(yaml.safe_dump({
        "version": 1, "camera": {"driver": "sim", "options": {"fps": 10}}, "lamp": {"driver": "sim"},
        "simulation": {"scene": "seabed", "distance": 2.0, "size": [96, 72], "water": "jerlov-IB"},
        "profiles_dir": str(profiles)}))
    with DaemonProcess(config, tmp_path) as d:
        active = next(p for p in d.http.get("/api/v1/calibration/profiles").json() if p["active"])
        body = d.http.get(f"/api/v1/calibration/profiles/{active['name']}").json()
        assert d.http.put("/api/v1/calibration/profiles/tank-b", content=yaml.safe_dump(body)).status_code == 200
        assert d.http.post("/api/v1/calibration/profiles/tank-b/activate").status_code == 200
        assert d.http.patch("/api/v1/config", json={"smoothing": "median", "path_length_bounds": [0.5, 30]}).status_code == 200
        assert d.http.put("/api/v1/lamp", json={"intensity": 70}).status_code == 200
        d.kill()
    # What a kill in the middle of an atomic write leaves behind.
    (profiles / ".tank-b.yaml.x1y2z3.tmp").write_text("half a profi")
    with DaemonProcess(config, tmp_path) as d:
        settings = d.http.get("/api/v1/config").json()
        assert settings["smoothing"] == "median" and settings["path_length_bounds"] == [0.5, 30.0]
        assert d.http.get("/api/v1/status").json()["calibration"]["name"] == "tank-b"
        assert d.http.get("/api/v1/lamp").json()["intensity"] == 70
        assert not list(profiles.glob(".*.tmp"))
        assert {p.name for p in profiles.iterdir()} == {"tank-b.yaml", "uwcam-state.json"}


def test_a_corrupt_state_file_is_ignored_not_fatal(tmp_path):
    from uwcam.runtime.state import STATE_FILE

    config = small_config()
    config.profiles_dir = str(tmp_path)
    (tmp_path / STATE_FILE).write_text('{"version": 1, "processing": {"smoothing": "gaussian"}, "lamp_percent": 700}')
    with Server(config) as s:
        assert s.http.get("/api/v1/config").json()["smoothing"] == "none"
        assert s.http.patch("/api/v1/config", json={"smoothing": "mean"}).status_code == 200
    assert json.loads((tmp_path / STATE_FILE).read_text())["processing"]["smoothing"] == "mean"


def test_simulated_serial_devices_leave_no_folders_behind(tmp_path, monkeypatch):
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))  # a temp dir of our own: others share /tmp

    def folders():
        return set(tmp_path.glob("uwcam-pty-*"))

    before = folders()
    with Server(small_config()) as s:
        assert wait_for(lambda: s.daemon.pipeline.processed > 0, 60.0)
        assert len(folders() - before) == 2  # the lamp's and the sonar's
    assert folders() - before == set()


FRAGMENT = """
import ctypes, sys
from uwcam.runtime.memory import release_free_memory

def rss_kb():
    with open("/proc/self/status") as handle:
        return next(int(line.split()[1]) for line in handle if line.startswith("VmRSS:"))

libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype = ctypes.c_void_p
libc.malloc.argtypes = [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
libc.free(libc.malloc(16 << 20))  # a freed 16 MB block: glibc raises its mmap threshold past 1 MB
before = rss_kb()
big, small = [], []
for _ in range(64):  # 1 MB blocks (as frames and encodings), from the heap
    block = libc.malloc(1 << 20)
    ctypes.memset(block, 1, 1 << 20)
    big.append(block)
    small.append(libc.malloc(100 << 10))  # stays, between the big ones: the heap cannot shrink
for block in big:
    libc.free(block)
kept = rss_kb() - before
if sys.argv[1] == "trimmed":
    release_free_memory()  # what the frame loop does about once a second
    kept = rss_kb() - before
print(kept)
"""


def test_frame_sized_blocks_freed_between_live_ones_leave_resident_memory_at_the_next_trim():
    """Frame-sized blocks come from glibc's heaps (uwcam/runtime/memory.py); freed ones between small
    live ones stay resident until the frame loop's once-a-second trim hands their pages back."""
    import subprocess
    import sys

    def kept_kb(mode: str) -> int:
        return int(subprocess.run([sys.executable, "-c", FRAGMENT, mode], check=True, capture_output=True,
                                  text=True, timeout=60).stdout)

    untrimmed, trimmed = kept_kb("untrimmed"), kept_kb("trimmed")
    print(f"resident after freeing 64 MB: {untrimmed} kB, {trimmed} kB after the trim")
    assert untrimmed > 50_000 and trimmed < 5_000


ARENAS = """
import ctypes, re, sys, tempfile, threading
from uwcam.runtime.memory import limit_malloc_arenas

if sys.argv[1] == "limited":
    assert limit_malloc_arenas()
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype = ctypes.c_void_p
libc.malloc.argtypes = [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
start = threading.Barrier(8)

def work():
    start.wait()  # all at once: contended, so glibc hands threads arenas of their own
    for _ in range(2000):
        libc.free(libc.malloc(64 << 10))

threads = [threading.Thread(target=work) for _ in range(8)]
[t.start() for t in threads]
[t.join() for t in threads]
libc.fopen.restype = ctypes.c_void_p
libc.fopen.argtypes = [ctypes.c_char_p, ctypes.c_char_p]
libc.fclose.argtypes = [ctypes.c_void_p]
libc.malloc_info.argtypes = [ctypes.c_int, ctypes.c_void_p]
with tempfile.NamedTemporaryFile(suffix=".xml") as out:
    handle = libc.fopen(out.name.encode(), b"w")
    libc.malloc_info(0, handle)
    libc.fclose(handle)
    print(len(re.findall(r"<heap nr=", open(out.name).read())))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's arenas")
def test_threads_share_at_most_two_heaps():
    """The daemon caps glibc's arenas at two (uwcam/runtime/memory.py): eight threads allocating at once
    then share two heaps instead of making one each."""
    import subprocess

    def heaps(mode: str) -> int:
        return int(subprocess.run([sys.executable, "-c", ARENAS, mode], check=True, capture_output=True,
                                  text=True, timeout=60).stdout)

    default, limited = heaps("default"), heaps("limited")
    assert limited <= 2 < default, (default, limited)


@pytest.mark.slow
def test_snapshot_benchmark_runs():
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parent.parent / "bench" / "bench_snapshots.py"
    out = subprocess.run([sys.executable, str(script), "--seconds", "3", "--clients", "2", "--size", "160x120"],
                         check=True, capture_output=True, text=True, timeout=600).stdout
    assert "RSS MB: baseline" in out and "after the load" in out


def test_an_off_acknowledged_while_frames_stay_lit_is_asked_again():
    """A lamp that says OK but stays lit (a lost command) does not stall the lamp-off cycle."""
    from types import SimpleNamespace

    from tests.synthetic import make_profile
    from uwcam.config import ProcessingConfig
    from uwcam.drivers.base import Frame
    from uwcam.runtime.pipeline import FramePipeline

    calls = []

    class StuckLamp:  # acknowledges everything, changes nothing
        last_status = None

        def on(self):
            calls.append("on")

        def off(self):
            calls.append("off")

    pipeline = FramePipeline(SimpleNamespace(), make_profile([0.46, 0.11, 0.06], [0, 0, 0]),
                             ProcessingConfig(lamp_off_interval=2), lamp=StuckLamp())
    commander = pipeline._lamp_commander
    commander.start()
    try:
        data = np.full((4, 4, 3), 1000, np.uint16)
        for k in range(20):
            pipeline._process(Frame(data=data, sequence=k, host_monotonic_ns=k, wall_time=0.0, lamp_on=True))
            assert wait_for(lambda: commander.status()["pending"] is None, 5.0)
    finally:
        commander.stop()
    assert calls.count("off") >= 2 and pipeline.processed == 20  # asked again; every frame ranged


def test_the_running_daemon_keeps_its_startup_objects_out_of_the_collectors_sight(tmp_path):
    """`uwcam run` freezes what start-up made (gc.freeze) before it serves: full collections of
    those ~10⁵ long-lived objects stopped every thread for ~50 ms, and a 60 fps loop skipped frames."""
    import signal
    import socket
    import subprocess
    import textwrap

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    config = tmp_path / "rig.yaml"
    config.write_text(yaml.safe_dump({
        "version": 1, "camera": {"driver": "sim", "options": {"fps": 10}},
        "simulation": {"scene": "seabed", "distance": 2.0, "size": [96, 72], "water": "jerlov-IB"}}))
    code = textwrap.dedent(f"""
        import gc, os, signal, sys, threading, time, urllib.request

        def probe():
            while True:
                try:
                    urllib.request.urlopen("http://127.0.0.1:{port}/api/v1/status", timeout=2)
                    break
                except OSError:
                    time.sleep(0.2)
            print("frozen", gc.get_freeze_count(), flush=True)
            os.kill(os.getpid(), signal.SIGTERM)  # an orderly stop, as systemd does

        threading.Thread(target=probe, daemon=True).start()
        from uwcam.cli import main
        sys.exit(main(["run", "--config", {str(config)!r}, "--port", "{port}"]))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=180,
                         env={k: v for k, v in __import__("os").environ.items() if k != "UWCAM_TOKEN"})
    frozen = [int(line.split()[1]) for line in out.stdout.splitlines() if line.startswith("frozen")]
    assert frozen and frozen[0] > 10_000, (out.stdout[-1000:], out.stderr[-2000:])
    # uvicorn stops in order, then lets the signal end the process as its default would.
    assert out.returncode in (0, -signal.SIGTERM), out.stderr[-2000:]
