"""Benchmark: a new user's first five minutes, from a fresh copy of this checkout.

Runs the README's set-up command as written (``bash deploy/install.sh && .venv/bin/uwcam run``,
its own .venv, so an empty numba cache; an empty home, so an empty ~/.cache/uwcam; pip's and
uv's download caches kept) and prints the seconds from the command to: the install's end, the
daemon serving, the first range, the first frame painted by the operator page in Debian's
Chromium, and the end of the compilation of every other setting's kernels in the background.
Then stops the daemon with Ctrl-C, starts it again from the same install with an empty
~/.cache/uwcam, and prints the same for that start.

    .venv/bin/python bench/bench_first_start.py [--chromium /usr/bin/chromium]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.fresh_install import UserDaemon, copy_checkout, readme_run_command  # noqa: E402


def processed(daemon: UserDaemon) -> int:
    return json.loads(daemon.get("/api/v1/status"))["frames"]["processed"]


def page_painted(daemon: UserDaemon, chromium: str) -> float:
    """Seconds since the command started when the page in Chromium painted its first frame."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium, args=["--headless", "--no-sandbox"])
        page = browser.new_page(viewport={"width": 1400, "height": 900})
        daemon.wait_until(lambda: page.goto(daemon.url + "/") is not None, 600, "the page")
        # Polled from here: the page's content security policy forbids evaluating strings in it.
        at = daemon.wait_until(lambda: page.evaluate("window.uwcam ? window.uwcam.stats.displayed : 0") > 0,
                               600, "a painted frame")
        browser.close()
    return at


def measure(daemon: UserDaemon, chromium: str, label: str) -> None:
    serving = daemon.wait_until(lambda: daemon.get("/api/v1/status") is not None, 1800, "an answer")
    first_range = daemon.wait_until(lambda: processed(daemon) > 0, 600, "first range")
    painted = page_painted(daemon, chromium)
    installed = daemon.seconds_until("uwcam installed in")
    started = installed or 0.0
    print(f"{label}:")
    if installed is not None:
        print(f"  install (uv, or pip where uv cannot be had): {installed:6.1f} s")
    print(f"  daemon answering:                {serving - started:6.1f} s after `uwcam run` started")
    print(f"  first range:                     {first_range - started:6.1f} s after `uwcam run` started")
    print(f"  page painted its first frame:    {painted - started:6.1f} s after `uwcam run` started"
          f"   ({painted:.1f} s after the command)")
    if daemon.seconds_until("compiling the kernels of every setting in the background") is None:
        print("  background compilation:          not started (numba's cache is marked full)")
        return
    done = daemon.wait_until(lambda: "the kernels of every setting are compiled" in daemon.output
                             or "in the background failed" in daemon.output, 1800, "the background compilation's end")
    print(f"  background compilation ended:    {done - started:6.1f} s after `uwcam run` started "
          f"({'done' if 'are compiled' in daemon.output else 'FAILED'}; the frame loop ran on meanwhile)")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--chromium", default="/usr/bin/chromium")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        clone = copy_checkout(Path(tmp) / "clone")
        command = readme_run_command()
        daemon = UserDaemon(clone, Path(tmp) / "home", command)
        try:
            measure(daemon, args.chromium, f"README command `{command}` in a fresh clone")
            print(f"  Ctrl-C: exit status {daemon.ctrl_c()}")
        finally:
            daemon.kill()
        again = UserDaemon(clone, Path(tmp) / "home2", ".venv/bin/uwcam run")
        try:
            measure(again, args.chromium, "second start from the same install, empty ~/.cache/uwcam")
        finally:
            again.kill()
    return 0


if __name__ == "__main__":
    sys.exit(main())
