"""Benchmark: the whole daemon with a WebSocket client.

`uwcam run` as its own process (a simulated 1280×720 three-channel camera at 30 fps; fusion,
variance and patch tracking) and one WebSocket client in this process. Over the run: processed fps, frames dropped (queue overflow or skipped
for a newer one), latency from capture to WebSocket send (from the stream's own header),
CPU use and resident memory sampled through the run. Then short runs at 1920×1080 with rising
frame rates, to find the highest rate sustained without drops.

    python3 bench/bench_daemon.py [--seconds 60] [--trial-seconds 10]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import time

import numpy as np
import websockets

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from uwcam.api import HEADER  # noqa: E402


def proc_figures(pid: int) -> tuple[float, float]:
    """(CPU seconds used, resident MB) of a process, from /proc."""
    with open(f"/proc/{pid}/stat") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    cpu = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    with open(f"/proc/{pid}/status") as fh:
        rss = next(int(line.split()[1]) for line in fh if line.startswith("VmRSS:")) / 1024.0
    return cpu, rss


def write_config(path: str, size, fps, port: int) -> None:
    import yaml

    yaml.safe_dump({
        "version": 1,
        "camera": {"driver": "sim", "options": {"fps": float(fps)}, "queue_size": 4},
        "lamp": {"driver": "sim"}, "rangefinder": {"driver": "sim-ping1d"},
        "simulation": {"scene": "seabed-patch", "distance": 2.0, "size": list(size), "water": "jerlov-IB",
                       "lamp_offset": [0.3, 0.0, 0.0], "material": "grey"},
        "api": {"host": "127.0.0.1", "port": port, "stream_rate_hz": 120.0},
    }, open(path, "w"))


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run(size, fps, seconds, sample_every_s=10.0):
    """Start `uwcam run` as its own process, stream from it, and measure it."""
    import json
    import subprocess
    import tempfile
    import urllib.request

    port = free_port()
    with tempfile.TemporaryDirectory() as tmp:
        cfg = os.path.join(tmp, "rig.yaml")
        write_config(cfg, size, fps, port)
        proc = subprocess.Popen([sys.executable, "-m", "uwcam", "run", "--config", cfg],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            status_url = f"http://127.0.0.1:{port}/api/v1/status"
            deadline = time.monotonic() + 120
            while True:
                try:
                    json.load(urllib.request.urlopen(status_url))
                    break
                except OSError:
                    if time.monotonic() > deadline or proc.poll() is not None:
                        raise RuntimeError("uwcam run did not start") from None
                    time.sleep(0.2)

            def status():
                return json.load(urllib.request.urlopen(status_url))

            latencies, received, samples = [], 0, []

            async def client():
                nonlocal received
                async with websockets.connect(f"ws://127.0.0.1:{port}/api/v1/stream?rate=120", max_size=None) as ws:
                    await ws.recv()  # hello
                    # Warm-up: until frames have flowed for 3 s (the camera renders its scene first).
                    warm, t_end = 0, None
                    while t_end is None or time.monotonic() < t_end:
                        if isinstance(await ws.recv(), bytes):
                            warm += 1
                            if warm == 5:
                                t_end = time.monotonic() + 3.0
                    first = await asyncio.to_thread(status)
                    t0 = time.monotonic()
                    cpu0, _ = proc_figures(proc.pid)
                    next_sample = t0
                    while time.monotonic() - t0 < seconds:
                        msg = await ws.recv()
                        if isinstance(msg, bytes):
                            _, _, captured, sent, *_ = HEADER.unpack_from(msg)
                            latencies.append((sent - captured) / 1e6)
                            received += 1
                        if time.monotonic() >= next_sample:
                            samples.append((round(time.monotonic() - t0), round(proc_figures(proc.pid)[1], 1)))
                            next_sample += sample_every_s
                    wall = time.monotonic() - t0
                    cpu1, _ = proc_figures(proc.pid)
                    return first, await asyncio.to_thread(status), wall, cpu1 - cpu0

            start, end, wall, cpu = asyncio.run(client())
        finally:
            proc.terminate()
            proc.wait(timeout=30)
    f0, f1 = start["frames"], end["frames"]
    processed = f1["processed"] - f0["processed"]
    return {
        "processed_fps": processed / wall, "captured": f1["captured"] - f0["captured"], "processed": processed,
        "dropped": f1["dropped"] - f0["dropped"], "sent_to_client": received,
        "latency_ms": (np.percentile(latencies, 50), np.percentile(latencies, 99)) if latencies else (np.nan, np.nan),
        "cpu_percent": 100 * cpu / wall, "rss_mb": samples,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--trial-seconds", type=float, default=10.0)
    args = parser.parse_args()
    r = run((1280, 720), 30, args.seconds)
    print(f"1280x720x3 at 30 fps for {args.seconds:g} s (fusion + variance + patch tracking + 1 WebSocket client), "
          f"{os.cpu_count()} CPUs:")
    print(f"  processed {r['processed_fps']:.1f} fps ({r['processed']} of {r['captured']} captured), dropped {r['dropped']}, "
          f"sent to client {r['sent_to_client']}")
    print(f"  latency capture → WebSocket send: p50 {r['latency_ms'][0]:.1f} ms, p99 {r['latency_ms'][1]:.1f} ms "
          f"(goal p99 < 50 ms: {'met' if r['latency_ms'][1] < 50 else 'NOT met'}); drops goal: "
          f"{'met' if r['dropped'] == 0 else 'NOT met'}")
    print(f"  daemon CPU {r['cpu_percent']:.0f} % of one core (simulated camera included); resident memory MB over time (s, MB): {r['rss_mb']}")
    best = None
    for fps in (10, 15, 20, 25, 30):
        t = run((1920, 1080), fps, args.trial_seconds, sample_every_s=1e9)
        ok = t["dropped"] == 0 and t["processed_fps"] >= 0.95 * fps
        print(f"  1920x1080 at {fps} fps: processed {t['processed_fps']:.1f} fps ({t['processed']} of {t['captured']}), "
              f"dropped {t['dropped']}, "
              f"p99 {t['latency_ms'][1]:.1f} ms -> {'sustained' if ok else 'not sustained'}")
        if not ok:
            break
        best = fps
    print(f"highest 1920x1080 rate sustained without drops: {best} fps")


if __name__ == "__main__":
    main()
