"""Benchmark: the operator page open in headless Chromium on the embedded default rig.

`uwcam run` (no configuration: the default simulated rig) in its own process. First the daemon
alone; then with ``--clients`` plain WebSocket clients consuming ``/api/v1/view`` as the page does
(decode, acknowledge each frame), which separates the daemon's own cost of serving pages from the
browser's (a topside browser does not share the daemon's cores, as here); then with the page open
in Debian's Chromium driven by Playwright; each phase for the same time. Prints the daemon's
processed fps, frames dropped, capture → publish latency (p50/p99) and CPU per phase, the
clients' frames received and their age, and for the page: frames painted per second, the share
of the daemon's frames it painted, and the painted frames' age (capture → painted, from the
page's own record) p50/p99.

    python3 bench/bench_page.py [--seconds 30] [--clients 3] [--step 2] [--chromium /usr/bin/chromium]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
import urllib.request

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
from tests.ports import free_port  # noqa: E402


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


def view_clients(url: str, count: int, step: int, stop, received: list) -> list:
    """``count`` threads, each a plain WebSocket client of /api/v1/view that acknowledges every
    frame at once; each appends (frame age in ms, bytes) to ``received``."""
    import struct
    import threading

    import websockets.sync.client

    def client() -> None:
        with websockets.sync.client.connect(url.replace("http", "ws") + f"/api/v1/view?step={step}",
                                            max_size=2**27) as ws:
            ws.recv(timeout=10)  # hello
            while not stop.is_set():
                try:
                    message = ws.recv(timeout=1)
                except TimeoutError:
                    continue
                (length,) = struct.unpack_from("<I", message, 4)
                header = json.loads(message[8 : 8 + length])
                received.append((time.time_ns() / 1e6 - header["capture_time_ns"] / 1e6, len(message)))
                ws.send(json.dumps({"ack": header["frame"]}))

    threads = [threading.Thread(target=client, daemon=True) for _ in range(count)]
    for t in threads:
        t.start()
    return threads


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--chromium", default="/usr/bin/chromium")
    parser.add_argument("--clients", type=int, default=3, help="plain WebSocket clients of /api/v1/view (0: none)")
    parser.add_argument("--step", type=int, default=2, choices=(1, 2, 4), help="the clients' view resolution step")
    args = parser.parse_args()
    import threading
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
        clients, received = None, []
        if args.clients:
            stop = threading.Event()
            threads = view_clients(url, args.clients, args.step, stop, received)
            time.sleep(3)
            received.clear()
            clients = daemon_phase(url, args.seconds, proc.pid)
            stop.set()
            for t in threads:
                t.join(10)
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
        phases = [("daemon alone", alone), ("page open", with_page)]
        if clients is not None:
            phases.insert(1, (f"{args.clients} WS clients", clients))
        for name, phase in phases:
            lat = phase["latency_ms"] or {}
            print(f"  {name:13s}: {phase['fps']:5.1f} fps processed, {phase['dropped']} of {phase['captured']} captured "
                  f"frames dropped, capture→publish p50 {lat.get('p50', float('nan')):.1f} ms, p99 {lat.get('p99', float('nan')):.1f} ms; "
                  f"CPU: daemon {phase['daemon_cores']:.2f} cores (simulated camera included), browser {phase['browser_cores']:.2f}")
        share = painted / max(with_page["processed"], 1)
        print(f"  page         : {painted / args.seconds:5.1f} frames painted/s ({100 * share:.0f} % of the frames processed), "
              f"age capture→painted p50 {np.percentile(ages, 50):.0f} ms, p99 {np.percentile(ages, 99):.0f} ms")
        if clients is not None and received:
            age = np.array([a for a, _ in received])
            print(f"  WS clients   : {len(received) / args.seconds / args.clients:5.1f} frames/s each, "
                  f"{np.mean([b for _, b in received]) / 1e3:.0f} kB per frame (step {args.step}), age on arrival "
                  f"p50 {np.percentile(age, 50):.0f} ms, p99 {np.percentile(age, 99):.0f} ms")
            print(f"  ratio        : daemon fps with {args.clients} WS clients / alone = {clients['fps'] / max(alone['fps'], 1e-9):.3f}; "
                  f"daemon CPU per client {(clients['daemon_cores'] - alone['daemon_cores']) / args.clients:.3f} cores")
        print(f"  ratio        : daemon fps with the page / alone = {with_page['fps'] / max(alone['fps'], 1e-9):.3f} "
              f"on {os.cpu_count()} cores shared by the daemon, its simulated camera and the browser")
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    return 0


if __name__ == "__main__":
    sys.exit(main())
