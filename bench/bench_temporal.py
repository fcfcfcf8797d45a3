"""Benchmark: temporal fusion in the daemon's frame loop, holding station over a still scene.

Starts the daemon on a simulated camera and lamp looking at a grey seabed (by default 7 m away in
the simulator's Jerlov II water, the lamp 0.3 m beside the camera), ranges it frame by frame with
fusion off, then switches fusion on and, after ``--seconds`` of fusion, compares with the
simulator's true range of every pixel: the share of pixels with a range, the median and rms of
the relative error, the sd of z = error/σ (1 when σ is honest), the median σ and frames per
pixel, the latency (capture → published, median of the pooled frames) and the fusion stage's ms
per frame. Ratios are of the same run.

    python3 bench/bench_temporal.py [--distance 7] [--water jerlov-II] [--size 640x360] [--seconds 2] [--smoothing mean]
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from uwcam.config import CameraConfig, DaemonConfig, DeviceConfig, ProcessingConfig, TemporalConfig  # noqa: E402
from uwcam.runtime.daemon import Daemon  # noqa: E402


def figures(frames: list, truth: np.ndarray) -> dict:
    """Accuracy of the ranges of ``frames`` against the truth, pooled over frames and pixels."""
    r = np.stack([p.result.range for p in frames]).astype(np.float64)
    v = np.stack([p.result.variance for p in frames]).astype(np.float64)
    on = np.isfinite(truth)[None] & np.isfinite(r)
    error = (r[on] - np.broadcast_to(truth, r.shape)[on]) / np.broadcast_to(truth, r.shape)[on]
    z = (r[on] - np.broadcast_to(truth, r.shape)[on]) / np.sqrt(v[on])
    counts = [p.frames[p.frames > 0] for p in frames if p.frames is not None]
    return {"valid": on.sum() / (len(frames) * np.isfinite(truth).sum()),
            "median": np.median(error) if error.size else np.nan, "rms": np.sqrt(np.mean(error**2)) if error.size else np.nan,
            "z_sd": np.std(z) if z.size else np.nan, "sigma": np.median(np.sqrt(v[on]) / np.broadcast_to(truth, r.shape)[on])
            if error.size else np.nan, "frames": np.median(np.concatenate(counts)) if counts and sum(c.size for c in counts) else 1,
            "latency_ms": 1e3 * float(np.median([p.latency_s for p in frames])),
            "reasons": np.bincount(np.stack([p.result.reasons for p in frames]).ravel(), minlength=7) / (len(frames) * truth.size)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--distance", type=float, default=7.0)
    ap.add_argument("--water", default="jerlov-II")
    ap.add_argument("--size", default="640x360")
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--seconds", type=float, default=2.0, help="of fusion before the figures are taken")
    ap.add_argument("--max-frames", type=int, default=32)
    ap.add_argument("--frames", type=int, default=8, help="frames the figures pool, each way")
    ap.add_argument("--open-water", action="store_true", help="first take an open-water frame (the view turned to water)")
    ap.add_argument("--smoothing", default="mean", choices=("none", "mean", "median", "adaptive"),
                    help="the range map's smoothing (default: the 3×3 mean of the embedded default rig and of the water study)")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    config = DaemonConfig(camera=CameraConfig(driver="sim", options={"fps": args.fps}), lamp=DeviceConfig(driver="sim"),
                          processing=ProcessingConfig(smoothing=args.smoothing),
                          simulation={"scene": "seabed", "material": "grey", "distance": args.distance, "size": [w, h],
                                      "water": args.water, "lamp_offset": [0.3, 0.0, 0.0], "seed": 0})
    daemon = Daemon(config)
    daemon.start()
    frames: list = []
    lock = threading.Lock()

    def keep(published) -> None:
        with lock:
            frames.append(published)

    def take(n: int) -> list:
        with lock:
            start = len(frames)
        while len(frames) < start + n:
            time.sleep(0.01)
        with lock:
            return frames[start:start + n]

    try:
        pipeline = daemon.pipeline
        pipeline.subscribe(keep)
        take(30)  # the loop settled
        if args.open_water:
            daemon.rig.show("open-water")
            take(3)
            assert pipeline.request_open_water(frames=8, timeout_s=60.0).wait(90.0), "no open-water frame"
            daemon.rig.show("seabed")
            take(3)
        truth = daemon.rig.world.camera_range.astype(np.float64)
        single = take(args.frames)
        pipeline.reconfigure(pipeline.processing.model_copy(update={"temporal": TemporalConfig(max_frames=args.max_frames)}))
        time.sleep(args.seconds)
        fused = take(args.frames)
        stats = pipeline.stats()
        ms = stats["temporal"]["ms_per_frame"]
    finally:
        daemon.stop()
    print(f"grey seabed at {args.distance:g} m, {args.water}, lamp 0.3 m aside, {w}×{h} at {args.fps:g} fps"
          f"{', open-water frame taken' if args.open_water else ''}; "
          f"fusion for {args.seconds:g} s, max_frames {args.max_frames}; {args.frames} frames pooled each way")
    print(f"{'':22} {'valid':>7} {'median':>8} {'rms':>7} {'z sd':>6} {'σ/r':>7} {'frames':>7} {'latency':>8}")
    for name, got in (("one frame", figures(single, truth)), ("fused", figures(fused, truth))):
        print(f"{name:22} {got['valid']:7.1%} {got['median']:+8.2%} {got['rms']:7.2%} {got['z_sd']:6.2f} {got['sigma']:7.2%} "
              f"{got['frames']:7.0f} {got['latency_ms']:5.1f} ms   reasons " + " ".join(f"{k}:{x:.0%}" for k, x in enumerate(got["reasons"]) if x))
    print(f"fusion stage: {ms} ms per frame")


if __name__ == "__main__":
    main()
