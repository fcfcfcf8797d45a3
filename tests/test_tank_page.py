"""The tank calibration on the operator page, in Debian's Chromium driven by Playwright, against
``uwcam run --simulate tank`` started as a user starts it (a real process, its own port): the
whole workflow through the page's controls (rail, distance, capture, fit, report, accept), then
the plate at a fourth distance ranged within 2 %; a reload and a daemon restart mid-session,
resumed by the page; no capture offered while no plate is in view."""

from __future__ import annotations

import io
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from tests.test_page import browser  # noqa: F401  (the module's Chromium, a fixture)
from tests.waiting import wait_for
from uwcam.optics.geometry import Intrinsics, pixel_rays, plane_camera_range

pytestmark = [pytest.mark.browser, pytest.mark.slow]


@pytest.fixture(autouse=True)
def no_leaked_threads():
    """Playwright's driver runs in its own process; the browser fixture below outlives single tests."""
    yield


class TankDaemon:
    """``uwcam run --simulate tank`` in its own process; ``restart()`` stops it (SIGINT, as Ctrl-C)
    and starts it again on the same port with the same state folder."""

    def __init__(self, state_home: Path) -> None:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            self.port = s.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}"
        self.env = {**os.environ, "XDG_STATE_HOME": str(state_home)}
        self.proc: subprocess.Popen | None = None
        self.http = httpx.Client(base_url=self.url, timeout=30.0)

    def start(self) -> None:
        self.proc = subprocess.Popen([sys.executable, "-m", "uwcam", "run", "--simulate", "tank", "--port", str(self.port)],
                                     env=self.env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)

        def serving() -> bool:
            assert self.proc.poll() is None, self.proc.stdout.read()
            try:
                return self.http.get("/api/v1/status").json()["frames"]["processed"] > 2
            except httpx.HTTPError:
                return False

        assert wait_for(serving, 180.0, 0.5), "uwcam run --simulate tank did not start serving"

    def stop(self) -> None:
        if self.proc and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(30.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10.0)
        if self.proc:
            self.proc.stdout.close()

    def restart(self) -> None:
        self.stop()
        self.start()


@pytest.fixture
def daemon(tmp_path):
    d = TankDaemon(tmp_path / "state")
    d.start()
    yield d
    d.stop()
    d.http.close()


def open_page(browser, url: str):
    page = browser.new_page(viewport={"width": 1400, "height": 1000})
    page.errors = []
    page.on("pageerror", lambda e: page.errors.append(str(e)))
    page.goto(url + "/")
    assert wait_for(lambda: page.locator("#tank-rail").is_visible(), 30.0), "no rail control in the simulated tank"
    return page


def text(page, selector: str) -> str:
    return page.inner_text(selector)


def move_rail(page, distance: float) -> None:
    page.fill("#tank-rail-distance", str(distance))
    page.click("#tank-rail-move")
    assert wait_for(lambda: text(page, "#tank-rail-state") == f"plate at {distance:g} m", 120.0, 0.1), \
        text(page, "#message")


def capture_at(page, distance: float, held_back: bool = False, times: dict | None = None) -> None:
    """As the engineer does: move the plate, type its distance, wait for the checks, press Capture.
    ``times``: seconds spent moving, waiting for the checks and capturing are added to it."""
    t0 = time.monotonic()
    move_rail(page, distance)
    t1 = time.monotonic()
    page.fill("#tank-distance", str(distance))
    page.set_checked("#tank-held-back", held_back)
    assert wait_for(lambda: page.locator("#tank-capture").is_enabled(), 30.0, 0.1), text(page, "#tank-why-not")
    checks = text(page, "#tank-checks")
    assert "Plate found" in checks and "✗" not in checks, checks
    rows = page.locator("#tank-captures tr").count()
    t2 = time.monotonic()
    page.click("#tank-capture")
    assert wait_for(lambda: page.locator("#tank-captures tr").count() == max(rows, 1) + 1, 60.0, 0.1), text(page, "#message")
    if times is not None:
        for key, seconds in (("move", t1 - t0), ("checks", t2 - t1), ("capture", time.monotonic() - t2)):
            times[key] = times.get(key, 0.0) + seconds


def ranged_error(daemon: TankDaemon, distance: float) -> float:
    """Median relative range error over the plate's middle in the daemon's newest range map; the truth
    from the simulated camera's geometry (60° horizontal field of view, plate square to the axis)."""
    rng = np.load(io.BytesIO(daemon.http.get("/api/v1/snapshot/range", params={"format": "npy"}).content))
    h, w = rng.shape
    fx = (w / 2) / np.tan(np.radians(60.0) / 2)
    half = int(0.2 * fx / distance)  # the middle 0.4 m of the plate
    ys, xs = slice(h // 2 - half, h // 2 + half), slice(w // 2 - half, w // 2 + half)
    truth = plane_camera_range(distance, pixel_rays(Intrinsics(fx, fx, (w - 1) / 2, (h - 1) / 2), h, w))[ys, xs]
    measured = rng[ys, xs]
    ok = np.isfinite(measured)
    assert ok.mean() > 0.9
    return float(np.median(measured[ok] - truth[ok]) / distance)


def test_whole_tank_calibration_through_the_page(daemon, browser):
    page = open_page(browser, daemon.url)
    try:
        t0, times = time.monotonic(), {}
        page.click("#tank-start")
        assert wait_for(lambda: page.locator("#tank-steps").is_visible(), 15.0), text(page, "#message")
        assert "Step 1 of 4" in text(page, "#tank-now")
        for d in (1.0, 1.5, 2.0):
            capture_at(page, d, times=times)
        assert "Step 2 of 4" in text(page, "#tank-now")
        capture_at(page, 1.75, held_back=True, times=times)
        assert "Step 3 of 4" in text(page, "#tank-now")
        t_fit = time.monotonic()
        page.click("#tank-fit")
        assert wait_for(lambda: page.locator("#tank-fit-result .validation").count() == 1, 120.0, 0.2), text(page, "#message")
        times["fit"] = time.monotonic() - t_fit
        fit = text(page, "#tank-fit-result")
        assert "passed" in page.inner_text("#tank-fit-result .validation") and "Good fit" in fit, fit
        assert "attenuation difference" in fit and "residual at" in fit
        assert wait_for(lambda: page.evaluate("[...document.querySelectorAll('#tank-fit-result img')]"
                                              ".every(i => i.complete && i.naturalWidth > 100)"), 60.0)
        assert page.locator("#tank-fit-result img").count() == 5
        with page.expect_download() as download:
            page.click("#tank-report")
        assert Path(download.value.path()).read_text().startswith("<!DOCTYPE html>")
        assert "Step 4 of 4" in text(page, "#tank-now")
        page.fill("#tank-name", "from-the-page")
        page.click("#tank-accept")
        assert wait_for(lambda: "from-the-page is active" in text(page, "#message"), 60.0), text(page, "#message")
        elapsed = time.monotonic() - t0
        assert wait_for(lambda: "from-the-page" in text(page, "#profiles"), 10.0)
        assert page.locator("#tank-intro").is_visible()  # the session ended
        print(f"\npage workflow (start to accept, scripted): {elapsed:.0f} s; of which moving the plate "
              f"{times['move']:.0f} s, waiting for the checks {times['checks']:.0f} s, capturing {times['capture']:.0f} s, "
              f"fitting {times['fit']:.0f} s (4 distances)")

        # A fourth distance, never captured, moved from the page: ranged within 2 %.
        move_rail(page, 1.25)
        time.sleep(1.0)  # a few frames of the moved plate ranged
        error = ranged_error(daemon, 1.25)
        assert abs(error) < 0.02, f"median range error {error:+.2%} at 1.25 m"
        assert page.errors == [], page.errors
    finally:
        page.close()


def test_reload_and_restart_mid_session_resume_and_no_plate_no_capture(daemon, browser):
    page = open_page(browser, daemon.url)
    try:
        page.click("#tank-start")
        assert wait_for(lambda: page.locator("#tank-steps").is_visible(), 15.0), text(page, "#message")
        capture_at(page, 1.0)

        # No plate in view (the rail pulls it right up to the lens): no capture offered, and why.
        move_rail(page, 0.5)
        page.fill("#tank-distance", "0.5")
        assert wait_for(lambda: "plate not found" in text(page, "#tank-why-not") or "runs off" in text(page, "#tank-why-not"),
                        20.0, 0.1), text(page, "#tank-why-not")
        for _ in range(5):
            assert page.locator("#tank-capture").is_disabled()
            time.sleep(0.3)

        page.reload()
        assert wait_for(lambda: page.locator("#tank-steps").is_visible(), 15.0), "the page did not resume the session"
        assert page.locator("#tank-captures tr").count() == 2  # header and the 1 m capture
        capture_at(page, 1.5)

        daemon.restart()
        # The same page, not reloaded: it finds the session again, captures kept.
        assert wait_for(lambda: page.locator("#tank-steps").is_visible() and page.locator("#tank-captures tr").count() == 3,
                        60.0, 0.2)
        capture_at(page, 2.0)
        assert "Step 2 of 4" in text(page, "#tank-now")

        page.click("#tank-cancel")
        assert page.locator("#tank-steps").is_visible()  # one press only arms it
        page.click("#tank-cancel")
        assert wait_for(lambda: page.locator("#tank-intro").is_visible(), 15.0)
        assert daemon.http.get("/api/v1/calibration/session").status_code == 404
        assert page.errors == [], page.errors
    finally:
        page.close()
