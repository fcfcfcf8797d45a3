"""Benchmark: adaptive spatial windows (``smoothing: adaptive``) against none and the 3×3 mean.

A grey seabed (by default 6 m away in the simulator's Jerlov II water, the lamp 0.3 m beside the
camera: dark, most single pixels' σ above 2 % of the range) is ranged as the frame loop ranges it
(backscatter compensated, judged against the open water's light), with no smoothing, the 3×3 mean
of the range map and adaptive windows. Prints, for each, ms per frame (best and median of
--repeat, the estimator, compensator and open-water light built once as the loop has them) and
the ratio of the smoothing's own cost (its time less that of no smoothing) to the 3×3 mean's in
the same run; and, pooled over --frames frames against the simulator's true range: the share of
the seabed with a range, the median and rms relative error, the sd of z = error/σ (1 when σ is
honest), the share of |z| > 3 and the share of valid pixels whose σ is within the target.

    python3 bench/bench_adaptive_smoothing.py [--size 1280x720] [--distance 6] [--target 0.02] [--repeat 3] [--frames 2]
"""

from __future__ import annotations

import argparse
import os
import sys

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.dirname(__file__))

from timing import best_time  # noqa: E402
from uwcam.ranging.estimator import RangeEstimator, range_frame  # noqa: E402
from uwcam.simulation import CameraModel, Lamp, SimulatedWorld, water_preset  # noqa: E402
from uwcam.simulation.tank import calibrate_in_simulation  # noqa: E402
from uwcam.water.frame_compensator import BackscatterCompensator, compensation, compensation_iterations  # noqa: E402

KINDS = ("none", "mean", "adaptive")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="1280x720")
    ap.add_argument("--distance", type=float, default=6.0)
    ap.add_argument("--water", default="jerlov-II")
    ap.add_argument("--target", type=float, default=0.02)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--frames", type=int, default=2)
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    water = water_preset(args.water, [675.0, 575.0, 475.0])
    lamp = Lamp(position=(0.3, 0.0, 0.0))
    # Calibrated at a quarter of the width (as the daemon's simulated rigs are), the intrinsics then the frame's.
    factor = max(1, w // 320)
    profile = calibrate_in_simulation(water, lamp, (max(w // factor, 2), max(h // factor, 2)), CameraModel(),
                                      frames_per_distance=2)
    world = SimulatedWorld(scene="seabed", distance=args.distance, size=(w, h), water=water, lamp=lamp,
                           camera=CameraModel(), material="grey", seed=5)
    intr = world.intrinsics
    profile = profile.model_copy(update={"intrinsics": {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy}})
    open_water = SimulatedWorld(scene="open-water", distance=4.0, size=(w, h), water=water, lamp=lamp, camera=CameraModel(),
                                fixed_exposure=world.exposure, seed=6).frame(0)
    estimator = RangeEstimator(profile)
    comp = BackscatterCompensator(profile, (h, w), compensation_iterations(2, profile), open_water)
    transform, light = compensation(comp, estimator), comp.water
    frames = [world.frame(k) for k in range(args.frames)]
    truth = world.camera_range

    def ranged(kind: str, frame: np.ndarray):
        return range_frame(estimator, frame, kind, "after", None, (), transform, light, None, None, args.target)

    for kind in KINDS:  # compile and warm every path first
        ranged(kind, frames[0])
    print(f"{w}x{h}, grey seabed {args.distance:g} m, {args.water}, lamp 0.3 m aside, target σ {args.target:.1%} of range")
    times = {}
    print(f"{'smoothing':<10} {'ms best':>8} {'median':>8}")
    for kind in KINDS:
        best, median = best_time(lambda: ranged(kind, frames[0]), args.repeat)
        times[kind] = best
        print(f"{kind:<10} {1e3 * best:8.1f} {1e3 * median:8.1f}")
    own = {k: times[k] - times["none"] for k in ("mean", "adaptive")}
    print(f"smoothing's own cost: 3×3 mean {1e3 * own['mean']:.1f} ms, adaptive {1e3 * own['adaptive']:.1f} ms; "
          f"adaptive/mean {own['adaptive'] / max(own['mean'], 1e-6):.1f}×, whole frame adaptive/mean "
          f"{times['adaptive'] / times['mean']:.2f}×")
    surface = np.isfinite(truth)
    print(f"{'smoothing':<10} {'valid':>7} {'median':>8} {'rms':>7} {'z sd':>6} {'|z|>3':>7} {'σ≤target':>9}")
    for kind in KINDS:
        results = [ranged(kind, f) for f in frames]
        r = np.stack([x.range for x in results]).astype(np.float64)
        v = np.stack([x.variance for x in results]).astype(np.float64)
        t = np.broadcast_to(truth, r.shape)
        on = np.isfinite(r) & np.isfinite(t)
        error = r[on] / t[on] - 1.0
        z = (r[on] - t[on]) / np.sqrt(v[on])
        reached = np.sqrt(v[on]) <= args.target * r[on]
        print(f"{kind:<10} {on.sum() / (len(frames) * surface.sum()):7.1%} {np.median(error):+8.2%} "
              f"{np.sqrt(np.mean(error**2)):7.2%} {np.std(z):6.2f} {np.mean(np.abs(z) > 3):7.2%} {reached.mean():9.1%}")


if __name__ == "__main__":
    main()
