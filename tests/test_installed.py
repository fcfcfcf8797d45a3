"""What a user installs is what is tested: a fresh copy of this checkout, the README's first
set-up command run as written (its own .venv, no test extras) with an empty cache, and the daemon
checked from here as a user meets it: a plain WebSocket client, Debian's Chromium on the operator
page and on the Cockpit widget, Ctrl-C. The test environment's packages never reach the daemon.

Slow (the install is a real ``pip install``): marked ``slow`` and ``install``; CI runs it.
"""

from __future__ import annotations

import json
import re
import shutil
import struct
import subprocess
import time
import urllib.request
from pathlib import Path

import pytest
import websockets.sync.client

from tests.fresh_install import UserDaemon, copy_checkout, free_port, readme_run_command
from tests.test_page import browser  # noqa: F401  (Debian's Chromium through Playwright, a fixture)
from tests.waiting import wait_for

pytestmark = [pytest.mark.slow, pytest.mark.install]

INSTALL_TIMEOUT_S = 1200.0  # pip install into an empty .venv on a slow machine, then the first start

# Said by uvicorn when it has no WebSocket library: every WebSocket route then answers 404.
MISSING_LIBRARY = re.compile(r"No supported WebSocket library|not installed|ModuleNotFoundError|ImportError", re.I)


def status(daemon: UserDaemon) -> dict:
    return json.loads(daemon.get("/api/v1/status"))


def processed(daemon: UserDaemon) -> int:
    return status(daemon)["frames"]["processed"]


def runs_warmup(pid: int) -> bool:
    """Whether process ``pid`` is (still) a ``uwcam warmup``."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            return b"warmup" in fh.read()
    except OSError:
        return False


def log_problems(output: str) -> list[str]:
    """Warnings and errors the daemon logged, and any word of a missing library."""
    return [line for line in output.splitlines()
            if re.search(r"\b(WARNING|ERROR|CRITICAL|Traceback)\b", line) or MISSING_LIBRARY.search(line)]


@pytest.fixture(scope="module")
def clone(tmp_path_factory) -> Path:
    return copy_checkout(tmp_path_factory.mktemp("fresh-clone"))


@pytest.fixture(scope="module")
def installed(clone, tmp_path_factory):
    """The README's command, as written, on an ephemeral port, from an empty home."""
    daemon = UserDaemon(clone, tmp_path_factory.mktemp("home"), readme_run_command())
    try:
        daemon.wait_until(lambda: processed(daemon) > 0, INSTALL_TIMEOUT_S, "first range")
        yield daemon
    finally:
        daemon.kill()


def daemon_output(output: str) -> str:
    """What the daemon said: the lines after the install's own last line."""
    marker = "uwcam installed in"
    assert marker in output, output
    return output.split(marker, 1)[1].split("\n", 1)[1]


def test_the_install_is_quiet_and_the_daemon_logs_no_warning(installed):
    installed.wait_until(lambda: processed(installed) > 30, 120.0, "30 processed frames")
    out = installed.output
    print(f"README command → installed {installed.seconds_until('uwcam installed in')} s, "
          f"serving {installed.seconds_until('operator page')} s; full output:\n{out}")
    # Building and installing uwcam warns about nothing (setuptools used to print ~150 lines).
    install = out.split("uwcam installed in", 1)[0]
    assert not re.search(r"BuildBackendWarning|SetuptoolsDeprecationWarning|absent from the .packages.|"
                         r"Editable installation|Traceback", install), install
    assert log_problems(daemon_output(out)) == [], out


def test_the_first_start_compiles_every_other_setting_in_the_background(clone, installed):
    """The user's install does not wait for every kernel to compile: the first start compiles
    what its frames need and leaves the rest to a child at the lowest priority, which ends by
    marking the cache full (so the next start starts none)."""
    started = re.search(r"compiling the kernels of every setting in the background \(process (\d+)", installed.output)
    assert started, installed.output
    installed.wait_until(lambda: "the kernels of every setting are compiled" in installed.output, 900.0,
                         "the background compilation's end")
    markers = list(clone.glob(".venv/lib/python3*/site-packages/uwcam/__pycache__/warmed-up-*"))
    assert len(markers) == 1, markers


def test_runtime_environment_has_no_test_extras(clone, installed):
    """The daemon's .venv is the user's: none of the test tools that could hide a missing runtime
    dependency (the WebSocket library used to come only with them)."""
    listed = subprocess.run([str(clone / ".venv/bin/python"), "-m", "pip", "list", "--format=json"],
                            check=True, capture_output=True, text=True).stdout
    names = {p["name"].lower() for p in json.loads(listed)}
    assert {"pytest", "playwright", "httpx", "schemathesis"} & names == set()
    assert "websockets" in names  # a runtime dependency in its own right


def test_stream_delivers_range_maps_to_a_plain_websocket_client(installed):
    url = installed.url.replace("http", "ws") + "/api/v1/stream?rate=30&encoding=mm"
    with websockets.sync.client.connect(url, open_timeout=10, max_size=2**26) as ws:
        hello = json.loads(ws.recv(timeout=10))
        assert hello["type"] == "hello"
        numbers = []
        deadline = time.monotonic() + 30
        while len(numbers) < 3 and time.monotonic() < deadline:
            message = ws.recv(timeout=10)
            if isinstance(message, bytes):
                numbers.append(message)
        assert len(numbers) == 3, "fewer than 3 range maps in 30 s"
        assert len({m[:64] for m in numbers}) == 3  # three different frames (each header has its own number)


def test_view_delivers_frames_to_a_plain_websocket_client_that_acknowledges(installed):
    url = installed.url.replace("http", "ws") + "/api/v1/view?step=4"
    with websockets.sync.client.connect(url, open_timeout=10, max_size=2**26) as ws:
        json.loads(ws.recv(timeout=10))
        frames = []
        deadline = time.monotonic() + 30
        while len(frames) < 3 and time.monotonic() < deadline:
            message = ws.recv(timeout=10)
            if not isinstance(message, bytes):
                continue
            assert message[:4] == b"UWV1"
            (length,) = struct.unpack_from("<I", message, 4)
            header = json.loads(message[8 : 8 + length])
            frames.append(header["frame"])
            ws.send(json.dumps({"ack": header["frame"]}))
        assert len(frames) == 3 and frames == sorted(set(frames)), frames


def displayed(page) -> int:
    """Frames the page has painted (its own count)."""
    return page.evaluate("window.uwcam ? window.uwcam.stats.displayed : 0")


def range_pixels(page) -> list[int]:
    """A coarse sample of the range canvas's pixels (RGBA), read in the page."""
    return page.evaluate("""() => {
        const c = document.getElementById('range');
        const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
        const out = [];
        for (let i = 0; i < d.length; i += 4 * 97) out.push(d[i], d[i + 1], d[i + 2]);
        return out;
    }""")


def test_operator_page_in_chromium_shows_a_live_changing_range_picture(installed, browser):
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    errors: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(str(e)))
    try:
        page.goto(installed.url + "/")
        assert wait_for(lambda: displayed(page) > 5, 60.0), "the page painted no frames"
        assert page.inner_text("#connection").strip() == "live"
        first = range_pixels(page)
        assert len(set(zip(first[0::3], first[1::3], first[2::3]))) > 20, "the range picture is (nearly) one colour"
        shown = displayed(page)
        assert wait_for(lambda: displayed(page) > shown + 30, 60.0), "the page stopped painting"
        later = range_pixels(page)
        changed = sum(a != b for a, b in zip(first, later)) / len(first)
        assert changed > 0.05, f"only {changed:.1%} of the sampled pixels changed as the vehicle moved"
        centre = page.inner_text("#centre-range")
        assert re.fullmatch(r"\d+\.\d+ m", centre.strip()), centre
        assert errors == [], errors
    finally:
        page.close()


def test_cockpit_widget_in_chromium_shows_digits(installed, browser):
    page = browser.new_page(viewport={"width": 400, "height": 200})
    try:
        page.goto(installed.url + "/widget")
        assert wait_for(lambda: re.fullmatch(r"\d+\.\d+ m", page.inner_text("#centre").strip()), 60.0), \
            page.inner_text("#centre")
        assert not page.eval_on_selector("#digits", "e => e.classList.contains('stale')")
    finally:
        page.close()


def test_ctrl_c_stops_the_daemon_cleanly_with_the_lamp_off(clone, installed, tmp_path):
    """A second daemon from the same install (the first keeps serving the other tests)."""
    daemon = UserDaemon(clone, tmp_path, ".venv/bin/uwcam run")
    try:
        daemon.wait_until(lambda: processed(daemon) > 0, 300.0, "first range")
        lamp = json.loads(daemon.get("/api/v1/lamp"))
        assert lamp["on"] is True
        code = daemon.ctrl_c()
    finally:
        daemon.kill()
    out = daemon.output
    assert code == 0, out
    # Its background compilation, if it started one (the first daemon's may have ended), is stopped with it.
    child = re.search(r"compiling the kernels of every setting in the background \(process (\d+)", out)
    if child:
        assert not runs_warmup(int(child.group(1))), out
    # Said by the simulated lamp itself (the device on the serial line), not by the daemon.
    off = daemon.seconds_until(r"simulated lamp: OFF")
    assert off is not None, out
    assert log_problems(out) == [], out


def test_container_image_serves_the_same_live_view(clone, tmp_path):
    """The Docker image (and so the BlueOS extension) installs from the same dependency list: its
    daemon serves range maps over WebSocket too. Needs a Docker daemon, and its base image."""
    docker = shutil.which("docker")
    if docker is None:
        pytest.skip("no docker command on this machine: the container image is not tested here")
    info = subprocess.run([docker, "info"], capture_output=True, text=True)
    if info.returncode != 0:
        last = ((info.stderr or info.stdout).strip().splitlines() or ["no answer"])[-1]
        pytest.skip(f"no Docker daemon answers on this machine ({last}): the container image is not tested here")
    tag = f"uwcam-test:{int(time.time())}"
    subprocess.run([docker, "build", "-q", "-t", tag, str(clone)], check=True, timeout=INSTALL_TIMEOUT_S)
    port = free_port()
    name = tag.replace(":", "-")
    subprocess.run([docker, "run", "-d", "--rm", "--name", name, "--network", "host", "-e", f"UWCAM_PORT={port}",
                    "-e", "UWCAM_HOST=127.0.0.1", "-v", f"{tmp_path}:/etc/uwcam", tag], check=True)
    try:
        url = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            try:
                with urllib.request.urlopen(url + "/api/v1/status", timeout=5) as answer:
                    if json.loads(answer.read())["frames"]["processed"] > 0:
                        break
            except OSError:
                pass
            time.sleep(1)
        else:
            pytest.fail("the container served no range within 300 s")
        with websockets.sync.client.connect(url.replace("http", "ws") + "/api/v1/stream", open_timeout=10) as ws:
            assert json.loads(ws.recv(timeout=10))["type"] == "hello"
            assert isinstance(ws.recv(timeout=10), bytes)
        logs = subprocess.run([docker, "logs", name], capture_output=True, text=True).stderr
        assert log_problems(logs) == [], logs
    finally:
        subprocess.run([docker, "rm", "-f", name], capture_output=True)
