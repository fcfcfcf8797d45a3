"""Benchmark: adaptive spatial windows (``smoothing: adaptive``) against none and the 3×3 mean.

The scene of tests/test_adaptive_smoothing.py at any size: a grey seabed 2 m away (it sets the
exposure) beside one 10 m away (dark: most single pixels' σ above 2 % of the range, a quarter with
no range), in the simulator's clear Jerlov IA water, the lamp 0.3 m beside the camera; the
profile calibrated in that water with the simulated camera's own noise model. It is ranged as the
frame loop ranges it (backscatter compensated, judged against an open-water frame's light) with
no smoothing, the 3×3 mean of the range map and adaptive windows. Prints, for each, ms per frame
(best and median of --repeat; the estimator, compensator and open-water light built once, as the
loop has them) and the ratio of the smoothing's own cost (its time less that of no smoothing) to
the 3×3 mean's, measured in the same run; then, pooled over --frames frames, against the
simulator's true range of each pixel of the far seabed (clear of the edge by 17 pixels): the
share with a range, the median and rms relative error, the sd of z = error/σ (1 when σ is
honest), the share of |z| > 3 and the share of valid pixels whose σ is within the target.

    python3 bench/bench_adaptive_smoothing.py [--size 1280x720] [--near 2] [--far 10] [--water jerlov-IA]
                                              [--target 0.02] [--repeat 3] [--frames 2]
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
    ap.add_argument("--near", type=float, default=2.0)
    ap.add_argument("--far", type=float, default=10.0)
    ap.add_argument("--water", default="jerlov-IA")
    ap.add_argument("--target", type=float, default=0.02)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--frames", type=int, default=2)
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    water = water_preset(args.water, [675.0, 575.0, 475.0])
    lamp = Lamp(position=(0.3, 0.0, 0.0))
    camera = CameraModel()
    # Calibrated at 160 pixels wide or so (as the daemon's simulated rigs are, smaller), the
    # intrinsics then the frame's; the noise model the simulated camera's own.
    factor = max(1, w // 160)
    fitted = calibrate_in_simulation(water, lamp, (max(w // factor, 2), max(h // factor, 2)), camera, frames_per_distance=2)
    g = camera.gain_dn_per_e
    noise = dict(read_noise=float(g * np.sqrt(camera.read_noise_e**2 + camera.dark_current_e)), shot_gain=float(g),
                 fixed_pattern=float(camera.prnu))
    near = SimulatedWorld(scene="seabed", distance=args.near, size=(w, h), water=water, lamp=lamp, camera=camera,
                          material="grey", seed=5)
    far = SimulatedWorld(scene="seabed", distance=args.far, size=(w, h), water=water, lamp=lamp, camera=camera,
                         material="grey", seed=7, fixed_exposure=near.exposure)
    intr = near.intrinsics
    profile = fitted.model_copy(update={"intrinsics": {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy},
                                        "channels": [c.model_copy(update=noise) for c in fitted.channels]})
    edge = w // 2
    left = (np.arange(w) < edge)[None, :]
    mean = np.where(left[..., None], near.expected()[0], far.expected()[0]).astype(np.float32)
    std = np.where(left[..., None], near.expected()[1], far.expected()[1]).astype(np.float32)
    truth = np.where(left, near.camera_range, far.camera_range)
    open_water = SimulatedWorld(scene="open-water", distance=4.0, size=(w, h), water=water, lamp=lamp, camera=camera,
                                fixed_exposure=near.exposure, seed=6).frame(0)
    estimator = RangeEstimator(profile)
    comp = BackscatterCompensator(profile, (h, w), compensation_iterations(2, profile), open_water)
    transform, light = compensation(comp, estimator), comp.water
    frames = [camera.digitise(mean, std, 11, k) for k in range(args.frames)]

    def ranged(kind: str, frame: np.ndarray):
        return range_frame(estimator, frame, kind, "after", None, (), transform, light, None, None, args.target)

    for kind in KINDS:  # compile and warm every path first
        ranged(kind, frames[0])
    print(f"{w}x{h}: grey seabed {args.near:g} m | {args.far:g} m, {args.water}, lamp 0.3 m aside, "
          f"target σ {args.target:.1%} of range")
    times = {}
    print(f"{'smoothing':<10} {'ms best':>8} {'median':>8}")
    for kind in KINDS:
        best, median = best_time(lambda: ranged(kind, frames[0]), args.repeat)
        times[kind] = best
        print(f"{kind:<10} {1e3 * best:8.1f} {1e3 * median:8.1f}")
    own = {k: times[k] - times["none"] for k in ("mean", "adaptive")}
    ratio = f"{own['adaptive'] / own['mean']:.0f}× the mean's" if own["mean"] > 1e-4 else "the mean's within the noise"
    print(f"smoothing's own cost: 3×3 mean {1e3 * own['mean']:.1f} ms, adaptive {1e3 * own['adaptive']:.1f} ms "
          f"({ratio}); whole frame adaptive/mean {times['adaptive'] / times['mean']:.2f}×")
    region = np.isfinite(truth) & (np.arange(w) >= edge + 17)[None, :]
    print(f"far seabed: {'smoothing':<10} {'valid':>7} {'median':>8} {'rms':>7} {'z sd':>6} {'|z|>3':>7} {'σ≤target':>9}")
    for kind in KINDS:
        results = [ranged(kind, f) for f in frames]
        r = np.stack([x.range for x in results]).astype(np.float64)
        v = np.stack([x.variance for x in results]).astype(np.float64)
        t = np.broadcast_to(truth, r.shape)
        on = np.isfinite(r) & region[None]
        error = r[on] / t[on] - 1.0
        z = (r[on] - t[on]) / np.sqrt(v[on])
        reached = np.sqrt(v[on]) <= args.target * r[on] * (1 + 1e-6)
        print(f"{'':<12}{kind:<10} {on.sum() / (len(frames) * region.sum()):7.1%} {np.median(error):+8.2%} "
              f"{np.sqrt(np.mean(error**2)):7.2%} {np.std(z):6.2f} {np.mean(np.abs(z) > 3):7.2%} {reached.mean():9.1%}")


if __name__ == "__main__":
    main()
