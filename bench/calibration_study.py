"""Calibration study: are uwcam's reported uncertainties honest over many calibrations?

Each trial is an independent simulated tank calibration (its own noise and its own sensor
fixed pattern, as the plate lands on other pixels in every real session): the grey plate with
its black patch at 1 m and 2 m, ``--frames`` frames at each distance, in textbook water
(c = 0.46/0.11/0.06 1/m, no scattering), lamp 0.3 m beside the camera. The trial's profile then
ranges a grey seabed at 2–10 m. Printed:

* the z-score (estimate − truth)/σ pooled over pixels, ranges and calibrations: its sd and mean,
  with the calibration's covariance in σ (goal: sd 0.8–1.25, |mean| < 0.25) and without it;
* for each attenuation difference, the mean reported σ over its spread across calibrations
  (goal 0.7–1.43).

    python3 bench/calibration_study.py [--trials 40] [--frames 4] [--size 320x240]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import dataclass

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from uwcam.ranging.estimator import RangeEstimator  # noqa: E402
from uwcam.simulation import CameraModel, Lamp, SimulatedWorld, water_preset  # noqa: E402
from uwcam.simulation.tank import calibrate_in_simulation  # noqa: E402

LAMP = Lamp(position=(0.3, 0.0, 0.0))
WAVELENGTHS = [675.0, 575.0, 475.0]
TRUE_DIFFERENCES = np.array([0.11 - 0.46, 0.06 - 0.46])  # G−R, B−R in the "ideal" preset, 1/m


@dataclass
class StudyResult:
    z_sd: float
    z_mean: float
    z_sd_without_calibration: float
    z_mean_without_calibration: float
    sigma_ratio: np.ndarray
    """(N−1,) mean reported σ of each attenuation difference over its spread across calibrations."""
    bias: np.ndarray
    """(N−1,) mean error of each attenuation difference, 1/m."""
    z_sd_by_range: dict[float, float]
    pixels: int
    region_z_sd: float
    """sd of the z-score of each frame's mean range over a 32×32-pixel region at the image centre,
    where pixel noise averages away and the calibration's error dominates."""
    region_z_sd_without_calibration: float


def run_study(trials: int, frames: int = 4, size: tuple[int, int] = (320, 240),
              ranges: tuple[float, ...] = (2.0, 4.0, 6.0, 8.0, 10.0), pixel_step: int = 4) -> StudyResult:
    water = water_preset("ideal", WAVELENGTHS)
    z_all, z_raw_all, by_range = [], [], {r: [] for r in ranges}
    region_z, region_z_raw = [], []
    v, v_std = [], []
    for t in range(trials):
        camera = CameraModel(fixed_pattern_seed=1000 + t)
        profile = calibrate_in_simulation(water, LAMP, size, camera, distances=(1.0, 2.0), seed_base=100 * t,
                                          frames_per_distance=frames)
        v.append(profile.array("attenuation_difference")[1:])
        v_std.append(profile.array("attenuation_difference_std")[1:])
        with_cal, without = RangeEstimator(profile), RangeEstimator(profile, calibration_variance=False)
        for r in ranges:
            world = SimulatedWorld(scene="seabed", distance=r, size=size, water=water, lamp=LAMP, camera=camera,
                                   material="grey", seed=7919 * t + int(r * 10))
            frame = world.frame(0)
            truth = world.camera_range[::pixel_step, ::pixel_step]
            a = with_cal(frame)
            est = a.range[::pixel_step, ::pixel_step].astype(np.float64)
            var = a.variance[::pixel_step, ::pixel_step].astype(np.float64)
            raw = without(frame).variance[::pixel_step, ::pixel_step].astype(np.float64)
            ok = np.isfinite(est) & np.isfinite(truth) & (var > 0)
            z = (est[ok] - truth[ok]) / np.sqrt(var[ok])
            z_all.append(z)
            by_range[r].append(z)
            z_raw_all.append((est[ok] - truth[ok]) / np.sqrt(raw[ok]))
            # A region's mean: pixel noise divides by the pixel count, the calibration's part does not.
            h, w = frame.shape[:2]
            sl = (slice(h // 2 - 16, h // 2 + 16), slice(w // 2 - 16, w // 2 + 16))
            r_est, r_truth = a.range[sl].astype(np.float64), world.camera_range[sl]
            good = np.isfinite(r_est)
            cal = a.common_variance[sl][good].astype(np.float64)
            pix = a.variance[sl][good].astype(np.float64) - cal
            err = np.mean(r_est[good] - r_truth[good])
            region_z.append(err / np.sqrt(np.mean(cal) + np.mean(pix) / good.sum()))
            region_z_raw.append(err / np.sqrt(np.mean(pix) / good.sum()))
    z = np.concatenate(z_all)
    z_raw = np.concatenate(z_raw_all)
    v, v_std = np.array(v), np.array(v_std)
    return StudyResult(
        z_sd=float(z.std()), z_mean=float(z.mean()),
        z_sd_without_calibration=float(z_raw.std()), z_mean_without_calibration=float(z_raw.mean()),
        sigma_ratio=v_std.mean(axis=0) / v.std(axis=0, ddof=1),
        bias=v.mean(axis=0) - TRUE_DIFFERENCES,
        z_sd_by_range={r: float(np.concatenate(by_range[r]).std()) for r in ranges},
        pixels=int(z.size),
        region_z_sd=float(np.std(region_z)),
        region_z_sd_without_calibration=float(np.std(region_z_raw)),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=40)
    parser.add_argument("--frames", type=int, default=4, help="frames per calibration distance (default 4)")
    parser.add_argument("--size", default="320x240")
    args = parser.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    t0 = time.perf_counter()
    res = run_study(args.trials, args.frames, (w, h))
    print(f"calibration study: {args.trials} calibrations, {args.frames} frame(s) per distance, {w}x{h}, "
          f"{res.pixels} pixel estimates at 2-10 m, {time.perf_counter() - t0:.0f} s")
    print(f"z-score sd {res.z_sd:.3f} (goal 0.8-1.25), mean {res.z_mean:+.3f} (goal |mean| < 0.25)")
    print(f"  without the calibration's covariance: sd {res.z_sd_without_calibration:.3f}, "
          f"mean {res.z_mean_without_calibration:+.3f}")
    print("  z-score sd by range: " + ", ".join(f"{r:g} m {s:.3f}" for r, s in res.z_sd_by_range.items()))
    print(f"mean range of a 32x32 region: z-score sd {res.region_z_sd:.3f} with the calibration's covariance, "
          f"{res.region_z_sd_without_calibration:.3f} without")
    for name, ratio, bias in zip(("G-R", "B-R"), res.sigma_ratio, res.bias):
        print(f"attenuation difference {name}: reported sigma / spread over calibrations {ratio:.3f} "
              f"(goal 0.7-1.43); mean error {bias:+.2e} 1/m")


if __name__ == "__main__":
    main()
