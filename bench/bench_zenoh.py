"""Benchmark: what the Zenoh publisher sends, per key, at a few bandwidth budgets.

Starts a daemon on the simulated rig publishing on Zenoh (peer, loopback TCP, no multicast
scouting), subscribes from a second Zenoh session, and prints the payload bytes per second of
each key measured at the subscriber over ``--seconds``, the total against the budget, and the
previews' width and rate.

    python3 bench/bench_zenoh.py [--budgets 64,256,1024] [--seconds 10] [--size WxH] [--fps N]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import zenoh  # noqa: E402

from uwcam.config import CameraConfig, DaemonConfig, DeviceConfig, ZenohConfig  # noqa: E402
from uwcam.runtime.daemon import Daemon  # noqa: E402
from tests.ports import free_port  # noqa: E402

PREFIX = "uwcam/bench"


def measure(budget_kbit_s: float, seconds: float, size: tuple[int, int], fps: float, preview_hz: float,
            preview_width: int) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    cfg = DaemonConfig(
        camera=CameraConfig(driver="sim", options={"fps": fps}),
        lamp=DeviceConfig(driver="sim"), rangefinder=DeviceConfig(driver="sim-ping1d"),
        simulation={"scene": "survey", "size": list(size), "water": "jerlov-IA", "lamp_offset": [0.3, -0.8, 0.0],
                    "speed": 0.4, "altitude": [1.5, 4.0], "seed": 0},
        zenoh=ZenohConfig(listen=[endpoint], scouting=False, key_prefix=PREFIX, budget_kbit_s=budget_kbit_s,
                          preview_rate_hz=preview_hz, preview_width=preview_width))
    d = Daemon(cfg)
    d.start()
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    lock, got = threading.Lock(), []

    def on_sample(sample) -> None:
        with lock:
            got.append((str(sample.key_expr).removeprefix(PREFIX + "/"), sample.payload.to_bytes(), time.monotonic()))

    session = zenoh.open(conf)
    try:
        sub = session.declare_subscriber(f"{PREFIX}/**", on_sample)
        time.sleep(5.0)  # start-up and the budget's own measurements settle
        t0, frames0 = time.monotonic(), d.pipeline.processed
        time.sleep(seconds)
        t1, frames = time.monotonic(), d.pipeline.processed - frames0
        sub.undeclare()
    finally:
        session.close()
        d.stop()
    span = t1 - t0
    window = [(k, p) for k, p, t in got if t0 <= t < t1]
    per_key: dict[str, list[int]] = {}
    for key, payload in window:
        per_key.setdefault(key, []).append(len(payload))
    total = sum(sum(v) for v in per_key.values()) / span
    print(f"budget {budget_kbit_s:g} kbit/s, {size[0]}x{size[1]} at {frames / span:.1f} processed fps, "
          f"previews asked {preview_hz:g} Hz × {preview_width} px:")
    for key, sizes in sorted(per_key.items()):
        print(f"  {key:24s} {len(sizes) / span:6.2f} msg/s  {sum(sizes) / span:9.0f} B/s  ({np.mean(sizes):7.0f} B each)")
    widths = [cv2.imdecode(np.frombuffer(p, np.uint8), cv2.IMREAD_UNCHANGED).shape[1]
              for k, p in window if k == "range/preview/range"]
    print(f"  total {total * 8 / 1000:.1f} kbit/s of {budget_kbit_s:g} ({100 * total * 8 / 1000 / budget_kbit_s:.0f} %); "
          f"previews {len(widths) / span:.2f}/s, {min(widths, default=0)}–{max(widths, default=0)} px wide")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--budgets", default="64,256,1024", help="kbit/s, comma-separated")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--size", default="640x360")
    ap.add_argument("--fps", type=float, default=10.0)
    ap.add_argument("--preview-hz", type=float, default=2.0)
    ap.add_argument("--preview-width", type=int, default=160)
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    for budget in (float(b) for b in args.budgets.split(",")):
        measure(budget, args.seconds, (w, h), args.fps, args.preview_hz, args.preview_width)


if __name__ == "__main__":
    main()
