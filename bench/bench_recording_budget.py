"""Benchmark: what recording a dive costs on disk, and what a disk budget keeps.

Renders noisy 16-bit frames of the simulated survey (a textured seabed passing under the camera,
with the simulator's shot and read noise: the noise, not the scene, decides how well raw frames
compress) at 1280×720 and 1920×1080, encodes them as the recorder does (foxglove.RawImage) and
compresses each frame with lz4 and zstd (level 3 and 1, as MCAP chunks are), timing them on one
core. Prints per frame size raw and compressed, the compression ratio and speed, and at 30
frames/s the MB/s of raw frames, of the range results (depth, variance, reasons: re-made by
``uwcam reprocess``, not stored by default), and the share of raw frames a ``recording.budget_mb_s``
keeps.

    python3 bench/bench_recording_budget.py [--frames N] [--budget MB_S]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from uwcam.recording import format as rec  # noqa: E402
from uwcam.compute.jit import set_threads  # noqa: E402
from uwcam.simulation import Lamp, water_preset  # noqa: E402
from uwcam.simulation.survey import SurveyWorld  # noqa: E402

FPS = 30.0
PREVIEW_BYTES_S = 2 * 60e3
"""Two JPEG previews a second at half of 1080p, about 60 kB each (measured by the recording tests' previews scaled)."""
SUMMARY_BYTES_S = FPS * 700
"""Metadata and ranging record of every frame, JSON, about 700 bytes each before compression."""


def frames(size: tuple[int, int], n: int) -> list[np.ndarray]:
    set_threads(1)
    water = water_preset("jerlov-IB", [675.0, 575.0, 475.0])
    world = SurveyWorld(size=size, water=water, lamp=Lamp(position=(0.3, 0.0, 0.0)))
    out = []
    for k in range(n):
        frame = np.empty((size[1], size[0], 3), np.uint16)
        world.frame(k / FPS, k, out=frame)
        out.append(frame)
    return out


def compressors():
    import lz4.frame
    import zstandard

    z3, z1 = zstandard.ZstdCompressor(level=3), zstandard.ZstdCompressor(level=1)

    def shuffled(fn):
        # High bytes apart from low bytes (what HDF5's shuffle filter does): the high bytes of a
        # 16-bit frame repeat, the low bytes are mostly noise. Not what foxglove.RawImage holds:
        # this measures what a custom encoding would gain.
        return lambda b: fn(np.frombuffer(b[len(b) % 2:], np.uint8).reshape(-1, 2).T.tobytes())

    return {"lz4": lz4.frame.compress, "zstd-1": z1.compress, "zstd-3": z3.compress,
            "shuffle+lz4": shuffled(lz4.frame.compress), "shuffle+zstd-1": shuffled(z1.compress)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--budget", type=float, default=40.0, help="recording.budget_mb_s to evaluate (MB/s)")
    args = ap.parse_args()
    squeeze = compressors()
    print(f"frames of the simulated survey, 16-bit RGB, {args.frames} per size; one core; MB = 1e6 bytes")
    for size in ((1280, 720), (1920, 1080)):
        data = [rec.raw_image(f, 0) for f in frames(size, args.frames)]
        raw = np.mean([len(d) for d in data])
        w, h = size
        results = w * h * (4 + 4 + 1)  # depth and variance float32, reasons uint8
        print(f"\n{w}×{h}: raw frame {raw / 1e6:.2f} MB → {raw * FPS / 1e6:.0f} MB/s at {FPS:.0f} fps; "
              f"results {results / 1e6:.2f} MB/frame → {results * FPS / 1e6:.0f} MB/s more if stored")
        for name, fn in squeeze.items():
            t = time.thread_time()
            sizes = [len(fn(d)) for d in data]
            cpu = (time.thread_time() - t) / len(data)
            packed = float(np.mean(sizes))
            rate = packed * FPS / 1e6
            fixed = (PREVIEW_BYTES_S + SUMMARY_BYTES_S) / 1e6
            kept = min(1.0, max(0.0, args.budget - fixed) / rate)
            print(f"  {name:14s} {packed / 1e6:5.2f} MB/frame (ratio {raw / packed:4.2f}), {cpu * 1e3:5.1f} ms/frame "
                  f"({raw / cpu / 1e6:4.0f} MB/s): {rate:5.1f} MB/s at {FPS:.0f} fps; budget {args.budget:g} MB/s keeps "
                  f"{100 * kept:3.0f} % of raw frames ({3600 * args.budget / 1e3:.0f} GB an hour)")


if __name__ == "__main__":
    main()
