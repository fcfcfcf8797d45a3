"""Snapshot hammering: resident memory of the daemon before, during and after a burst of snapshot
requests (issue: memory stayed ~85 MB above its baseline after the load ended).

    .venv/bin/python bench/bench_snapshots.py [--seconds 20] [--clients 8] [--size 640x480]

Starts ``uwcam run`` in a subprocess on the simulated rig, waits until it ranges, records RSS,
fetches range/variance/image snapshots (npy, tiff, png16, pointcloud) from several threads,
then records RSS again after a pause. Prints the figures; numbers are noisy on a shared machine.
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time

import httpx
import yaml


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as handle:
        for line in handle:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--clients", type=int, default=8)
    parser.add_argument("--size", default="640x480")
    args = parser.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    with tempfile.TemporaryDirectory() as tmp:
        config = os.path.join(tmp, "rig.yaml")
        with open(config, "w") as handle:
            yaml.safe_dump({"version": 1, "camera": {"driver": "sim", "options": {"fps": 10}}, "lamp": {"driver": "sim"},
                            "simulation": {"scene": "seabed", "distance": 2.0, "size": [w, h], "water": "jerlov-IB"},
                            "api": {"port": port}}, handle)
        env = dict(os.environ, TMPDIR=tmp)
        proc = subprocess.Popen([sys.executable, "-m", "uwcam", "run", "--config", config], env=env,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            http = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30.0)
            deadline = time.monotonic() + 180
            while time.monotonic() < deadline:
                try:
                    if http.get("/api/v1/status").json()["frames"]["processed"] > 5:
                        break
                except httpx.HTTPError:
                    pass
                time.sleep(0.5)
            time.sleep(3.0)
            baseline = rss_mb(proc.pid)
            stop = time.monotonic() + args.seconds
            count = [0]
            peak = [baseline]
            paths = ["/api/v1/snapshot/range?format=npy", "/api/v1/snapshot/variance?format=tiff",
                     "/api/v1/snapshot/range?format=png16", "/api/v1/snapshot/image?format=png",
                     "/api/v1/snapshot/pointcloud"]

            def hammer(k: int) -> None:
                with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30.0) as c:
                    i = k
                    while time.monotonic() < stop:
                        c.get(paths[i % len(paths)])
                        i += 1
                        count[0] += 1
                        peak[0] = max(peak[0], rss_mb(proc.pid))

            threads = [threading.Thread(target=hammer, args=(k,)) for k in range(args.clients)]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            time.sleep(5.0)
            after = rss_mb(proc.pid)
            print(f"snapshots: {count[0]} requests in {args.seconds:g} s from {args.clients} clients, {w}x{h}")
            print(f"RSS MB: baseline {baseline:.0f}, peak {peak[0]:.0f}, 5 s after the load {after:.0f} "
                  f"(+{after - baseline:.0f} MB, {after / baseline:.2f}x baseline)")
        finally:
            proc.terminate()
            proc.wait(timeout=30)


if __name__ == "__main__":
    main()
