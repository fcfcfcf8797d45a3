"""Benchmark: backscatter compensation's time per frame, against plain ranging of the same frame.

A grey seabed in the simulator's Jerlov II water (lamp 0.3 m beside the camera), 1280×720 by
default, with sixteen open-water frames (the model's pattern and each pixel's response): the
median ms per frame of :meth:`uwcam.water.frame_compensator.BackscatterCompensator.range` (every
pass, the model's share of the variance included) and of the estimator alone on the same frame
(the lookup-table kernel), and their ratio, at each distance. Both are timed in the same run,
alternating, after a warm-up.

    python3 bench/bench_compensation.py [--size 1280x720] [--frames 40] [--distances 3,7]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from uwcam.ranging.estimator import RangeEstimator  # noqa: E402
from uwcam.simulation import CameraModel, Lamp, SimulatedWorld, water_preset  # noqa: E402
from uwcam.simulation.tank import calibrate_in_simulation  # noqa: E402
from uwcam.water.frame_compensator import BackscatterCompensator  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="1280x720")
    ap.add_argument("--frames", type=int, default=40, help="frames timed each way, per distance")
    ap.add_argument("--distances", default="3,7", help="seabed distances, m, comma-separated")
    ap.add_argument("--water", default="jerlov-II")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    water = water_preset(args.water, [675.0, 575.0, 475.0])
    lamp, camera = Lamp(position=(0.3, 0.0, 0.0)), CameraModel()
    started = time.monotonic()
    profile = calibrate_in_simulation(water, lamp, (min(w, 640), min(h, 640 * h // w)), camera, frames_per_distance=2)
    print(f"{args.water}, lamp 0.3 m aside, grey seabed, {w}×{h}; median of {args.frames} frames each way "
          f"(calibrated in {time.monotonic() - started:.0f} s)")
    print(f"{'distance':>9} {'plain ms':>9} {'compensated ms':>15} {'ratio':>6} {'valid %':>8}")
    for d in (float(v) for v in args.distances.split(",")):
        scene = SimulatedWorld(scene="seabed", distance=d, size=(w, h), water=water, lamp=lamp, camera=camera,
                               material="grey", seed=5)
        ow_world = SimulatedWorld(scene="open-water", distance=d, size=(w, h), water=water, lamp=lamp, camera=camera,
                                  fixed_exposure=scene.exposure, seed=6)
        open_water = np.stack([ow_world.frame(k) for k in range(16)])
        profile_here = profile.model_copy(update={"intrinsics": {"fx": scene.intrinsics.fx, "fy": scene.intrinsics.fy,
                                                                 "cx": scene.intrinsics.cx, "cy": scene.intrinsics.cy}})
        estimator = RangeEstimator(profile_here)
        comp = BackscatterCompensator(profile_here, (h, w), 2, open_water)
        frames = [scene.frame(k) for k in range(4)]
        for frame in frames:  # warm-up: kernels compiled or loaded, tables built
            estimator(frame)
            comp.range(frame, estimator.attenuation, estimator.effective_log_constant)
        plain, compensated, valid = [], [], []
        for k in range(args.frames):
            frame = frames[k % len(frames)]
            t0 = time.perf_counter()
            estimator(frame)
            t1 = time.perf_counter()
            result = comp.range(frame, estimator.attenuation, estimator.effective_log_constant)
            t2 = time.perf_counter()
            plain.append(t1 - t0)
            compensated.append(t2 - t1)
            valid.append(np.isfinite(result.range).mean())
        p, c = 1e3 * np.median(plain), 1e3 * np.median(compensated)
        print(f"{d:8g}m {p:9.2f} {c:15.2f} {c / p:6.1f} {100 * np.mean(valid):8.1f}")


if __name__ == "__main__":
    main()
