"""Benchmark: the operator page open in headless Chromium on the embedded default rig.

`uwcam run` (no configuration: the default simulated rig) in its own process. First the daemon
alone, then with the page open in Debian's Chromium driven by Playwright, each for the same
time. Prints the daemon's processed fps, frames dropped and capture → publish latency (p50/p99)
in both phases, and for the page: frames painted per second, the share of the daemon's frames
it painted, and the painted frames' age (capture → painted, from the page's own record) p50/p99.

    python3 bench/bench_page.py [--seconds 30] [--chromium /usr/bin/chromium]
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import time
import urllib.request

import numpy as np


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def status(url: str) -> dict:
    return json.load(urllib.request.urlopen(f"{url}/api/v1/status", timeout=5))


def cpu_seconds(match) -> float:
    """CPU seconds used so far by the processes whose command line satisfies ``match``."""
    total = 0.0
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as fh:
                cmdline = fh.read().replace(b"\0", b" ").decode(errors="replace")
            if not match(pid, cmdline):
                continue
            with open(f"/proc/{pid}/stat") as fh:
                fields = fh.read().rsplit(")", 1)[1].split()
            total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        except OSError:
            continue
    return total


def daemon_phase(url: str, seconds: float, daemon_pid: int) -> dict:
    """Frames processed and dropped over ``seconds``, the latency the daemon reports at the end,
    and the share of a core used by the daemon and by the browser meanwhile."""
    daemon = lambda pid, _: int(pid) == daemon_pid  # noqa: E731
    browser = lambda _, cmd: "chromium" in cmd or "chrome" in cmd  # noqa: E731
    a = status(url)
    cpu0 = cpu_seconds(daemon), cpu_seconds(browser)
    t0 = time.monotonic()
    time.sleep(seconds)
    b = status(url)
    elapsed = time.monotonic() - t0
    cpu1 = cpu_seconds(daemon), cpu_seconds(browser)
    return {
        "fps": (b["frames"]["processed"] - a["frames"]["processed"]) / elapsed,
        "dropped": b["frames"]["dropped"] - a["frames"]["dropped"],
        "captured": b["frames"]["captured"] - a["frames"]["captured"],
        "latency_ms": b["latency_ms"],
        "processed": b["frames"]["processed"] - a["frames"]["processed"],
        "daemon_cores": (cpu1[0] - cpu0[0]) / elapsed,
        "browser_cores": (cpu1[1] - cpu0[1]) / elapsed,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--chromium", default="/usr/bin/chromium")
    args = parser.parse_args()
    from playwright.sync_api import sync_playwright

    port = free_port()
    url = f"http://127.0.0.1:{port}"
    proc = subprocess.Popen([sys.executable, "-m", "uwcam", "run", "--port", str(port)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 180
        while True:
            try:
                if status(url)["frames"]["processed"] > 30:
                    break
            except OSError:
                pass
            if time.monotonic() > deadline or proc.poll() is not None:
                raise SystemExit("uwcam run did not start")
            time.sleep(0.5)
        size = status(url)["camera"]
        alone = daemon_phase(url, args.seconds, proc.pid)
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=args.chromium, args=["--headless", "--no-sandbox"])
            page = browser.new_page(viewport={"width": 1600, "height": 1000})
            page.goto(url + "/")
            deadline = time.monotonic() + 60
            while page.evaluate("window.uwcam ? window.uwcam.stats.displayed : 0") <= 30:
                if time.monotonic() > deadline:
                    raise SystemExit("the page painted no frames")
                page.wait_for_timeout(200)
            first = page.evaluate("({n: uwcam.stats.displayed, ages: uwcam.stats.ages.length})")
            with_page = daemon_phase(url, args.seconds, proc.pid)
            last = page.evaluate("({n: uwcam.stats.displayed, ages: uwcam.stats.ages.slice(-(uwcam.stats.displayed - %d))})"
                                 % first["n"])
            browser.close()
        painted = last["n"] - first["n"]
        ages = np.array(last["ages"][-painted:]) if painted else np.array([np.nan])
        device = size["device"] if size else {}
        print(f"default rig: {device.get('model', '?')} via `uwcam run`, {args.seconds:.0f} s per phase")
        for name, phase in (("daemon alone", alone), ("page open", with_page)):
            lat = phase["latency_ms"] or {}
            print(f"  {name:13s}: {phase['fps']:5.1f} fps processed, {phase['dropped']} of {phase['captured']} captured "
                  f"frames dropped, capture→publish p50 {lat.get('p50', float('nan')):.1f} ms, p99 {lat.get('p99', float('nan')):.1f} ms; "
                  f"CPU: daemon {phase['daemon_cores']:.2f} cores (simulated camera included), browser {phase['browser_cores']:.2f}")
        share = painted / max(with_page["processed"], 1)
        print(f"  page         : {painted / args.seconds:5.1f} frames painted/s ({100 * share:.0f} % of the frames processed), "
              f"age capture→painted p50 {np.percentile(ages, 50):.0f} ms, p99 {np.percentile(ages, 99):.0f} ms")
        print(f"  ratio        : daemon fps with the page / alone = {with_page['fps'] / max(alone['fps'], 1e-9):.2f} "
              f"on {os.cpu_count()} cores shared by the daemon, its simulated camera and the browser")
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    return 0


if __name__ == "__main__":
    sys.exit(main())
