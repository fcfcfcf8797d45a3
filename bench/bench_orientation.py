"""Benchmark: incidence angles per pixel block (Kirlin's step in the loop) on a 1280×720 frame.

The simulator's plane tilted 30° at 2 m in water without scattering, the lamp at the camera
(Kirlin's model), calibrated in the same simulated water. Prints ms/frame of the orientation
step (block means, noise model, Gauss–Newton) as a ratio to ranging the same frame
(``range_frame``), measured in the same run, for several block sizes; and the accuracy against
the simulator's normals: the fraction of blocks with an angle, the median and 80th percentile
of |error|, the fraction within 2°. The absolute scale comes from the simulator's truth at the
image centre (in the daemon, from the rangefinder's footprint).

    python3 bench/bench_orientation.py [--size WxH] [--repeat N] [--blocks 8,16,32]
"""

from __future__ import annotations

import argparse
import os
import sys
from types import SimpleNamespace

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.dirname(__file__))

from timing import best_time  # noqa: E402
from uwcam.config import OrientationConfig  # noqa: E402
from uwcam.optics.orientation import beam_pattern, block_means  # noqa: E402
from uwcam.runtime.stages.orientation import OrientationEstimator  # noqa: E402
from uwcam.ranging.estimator import RangeEstimator, range_frame  # noqa: E402
from uwcam.simulation.render import Lamp  # noqa: E402
from uwcam.simulation.tank import calibrate_in_simulation  # noqa: E402
from uwcam.simulation.water import water_preset  # noqa: E402
from uwcam.simulation.world import SimulatedWorld  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="1280x720")
    ap.add_argument("--repeat", type=int, default=10)
    ap.add_argument("--blocks", default="8,16,32")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    water = water_preset("ideal", [675.0, 575.0, 475.0])
    lamp = Lamp(position=(0.0, 0.0, 0.0))
    world = SimulatedWorld(scene="tilted-plane", distance=2.0, size=(w, h), water=water, lamp=lamp)
    intr = world.intrinsics
    profile = calibrate_in_simulation(water, lamp, (320, 240), noise_free=True).model_copy(
        update={"intrinsics": {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy}})
    estimator = RangeEstimator(profile)
    estimator.warm_up()
    frame = world.frame(0)
    result = range_frame(estimator, frame, "none", "after")
    ranging, _ = best_time(lambda: range_frame(estimator, frame, "none", "after"), args.repeat)
    # The absolute scale from the simulator's truth at the centre pixel.
    cy, cx = h // 2, w // 2
    u, d = world.rays[cy, cx], world.camera_range[cy, cx]
    cos = abs(float(world.hit.normal[cy, cx] @ u))
    e = world.noise_free_frame()[cy - 4:cy + 5, cx - 4:cx + 5].reshape(-1, 3).mean(axis=0) - world.camera.dark_level_dn
    scale = e / (beam_pattern(u, lamp.beam_half_angle_deg) * cos * np.exp(-2 * water.attenuation * d)
                 / (d + lamp.effective_radius) ** 2)
    corrector = SimpleNamespace(scale=scale, state="correcting")
    truth_cos = np.abs(np.sum(world.hit.normal * world.rays, axis=-1))
    print(f"{w}x{h}, best of {args.repeat}: ranging (range_frame) {ranging * 1e3:.1f} ms/frame")
    print("block  ms/frame  × ranging  blocks with angle  |error| median  80th pct  within 2°")
    for block in (int(b) for b in args.blocks.split(",")):
        orientation = OrientationEstimator(OrientationConfig(block=block, beam_half_angle_deg=lamp.beam_half_angle_deg),
                                           profile)
        incidence = orientation.estimate(frame, result, corrector)
        took, _ = best_time(lambda: orientation.estimate(frame, result, corrector), args.repeat)
        truth = np.degrees(np.arccos(block_means(truth_cos, np.isfinite(world.camera_range), block)))
        error = np.abs(incidence - truth)
        found = np.isfinite(incidence)
        print(f"{block:5d}  {took * 1e3:8.2f}  {took / ranging:9.2f}  {found.mean():17.1%}  "
              f"{np.nanmedian(error):13.2f}°  {np.nanpercentile(error, 80):7.2f}°  {np.mean(error[found] < 2.0):8.1%}")


if __name__ == "__main__":
    main()
