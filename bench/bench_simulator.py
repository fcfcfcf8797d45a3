"""Benchmark: simulator speed.

Prints (1) the time to render a new 640×480 three-channel scene with 32 backscatter slabs
(goal ≤ 1 s), split into ray casting and image formation, and (2) the rate at which a
static 1280×720 three-channel scene delivers new noisy 16-bit frames (goal ≥ 30 fps),
beside numpy drawing the same number of normal deviates in the same run.

    python3 bench/bench_simulator.py [--repeat N]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.dirname(__file__))

from timing import best_time  # noqa: E402
from uwcam.simulation import Lamp, SimulatedWorld, water_preset  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    water = water_preset("jerlov-II", [675.0, 575.0, 475.0])
    lamp = Lamp(position=(0.3, 0.0, 0.0))
    SimulatedWorld(scene="brick", distance=3.0, size=(64, 48), water=water, lamp=lamp).components()  # compile

    def new_scene(scene="brick", gate=None):
        t0 = time.perf_counter()
        w = SimulatedWorld(scene=scene, distance=3.0, size=(640, 480), water=water, lamp=lamp, slabs=32, gate_width=gate)
        t1 = time.perf_counter()
        w.components()
        return t1 - t0, time.perf_counter() - t1

    print("new 640x480x3 scene, 32 slabs, Jerlov II (backscatter and forward blur on):")
    for scene, gate in (("brick", None), ("ring", None), ("plate", None), ("brick", 0.05)):
        runs = [new_scene(scene, gate) for _ in range(args.repeat)]
        trace, form = min(r[0] for r in runs), min(r[1] for r in runs)
        label = f"{scene}{' gated' if gate else ''}"
        print(f"  {label:14s} ray casting {trace * 1e3:6.0f} ms + image formation {form * 1e3:6.0f} ms = "
              f"{(trace + form):.2f} s   goal ≤ 1 s: {'met' if trace + form <= 1 else 'NOT met'}")

    world = SimulatedWorld(scene="seabed", distance=3.0, size=(1280, 720), water=water, lamp=lamp)
    out = np.empty((720, 1280, 3), np.uint16)
    world.frame(0, out=out)
    index = iter(range(1, 10**6))
    t_frame, t_frame_med = best_time(lambda: world.frame(next(index), out=out), args.repeat * 6)
    rng = np.random.default_rng(0)
    normals = np.empty(out.size, np.float32)
    t_numpy, _ = best_time(lambda: rng.standard_normal(out.size, dtype=np.float32, out=normals), args.repeat * 6)
    print("static 1280x720x3 scene, new noisy 16-bit frames:")
    print(f"  uwcam frame {t_frame * 1e3:.1f} ms (median {t_frame_med * 1e3:.1f} ms) = {1 / t_frame:.0f} fps "
          f"(median {1 / t_frame_med:.0f} fps); goal ≥ 30 fps: {'met' if 1 / t_frame_med >= 30 else 'NOT met'}")
    print(f"  numpy drawing the same {out.size:,} normal deviates alone: {t_numpy * 1e3:.1f} ms "
          f"(uwcam's whole frame is {t_frame / t_numpy:.2f}× that)")


if __name__ == "__main__":
    main()
