"""The black patch's forward-scatter spill: its offset on the calibration's G − B attenuation
difference against the patch's size, position and the calibration distances (docs/calibration.md,
"Backscatter at the black patch").

Noise-free frames of the grey plate in a simulated water, calibrated through uwcam's own
black-patch estimate (:func:`uwcam.calibration.black_patch.backscatter_at_black_patch`) with the
water's forward blur and without it (B = 0: the forward-scattered light stays in its pixel, so
nothing crosses from plate to patch). The offset is the difference of the two slopes of the
plate's log light between the distances, G minus B, as a share of the blur-free G − B.

    python3 bench/black_patch_spill.py [--water jerlov-II] [--size 320x240]
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from uwcam.calibration.black_patch import backscatter_at_black_patch, locate_black_patch  # noqa: E402
from uwcam.calibration.fit import box_mask, project_plate_box  # noqa: E402
from uwcam.calibration.rig import builtin_rig_path, load_rig  # noqa: E402
from uwcam.simulation import CameraModel, Lamp, SimulatedWorld, water_preset  # noqa: E402
from uwcam.simulation.world import Channels  # noqa: E402

CASES = (  # patch size (m), patch centre on the plate (m), distances (m)
    (0.05, (0.0, 0.0), (1.0, 2.0)),
    (0.10, (0.0, 0.0), (1.0, 2.0)),
    (0.20, (0.0, 0.0), (1.0, 2.0)),
    (0.10, (-0.125, -0.125), (1.0, 2.0)),  # the grey-plate rig's patch
    (0.10, (-0.125, -0.125), (0.75, 1.5)),
)


def slope_offset(water_name: str, size: tuple[int, int], patch_m: float, centre_m: tuple[float, float],
                 distances: tuple[float, float]) -> float:
    """Offset of the G − B slope (ln/m) from the forward blur, as a share of the blur-free G − B."""
    channels = Channels()
    lamp, camera = Lamp(position=(0.3, 0.0, 0.0)), CameraModel(peak_code=0.7 * 2**CameraModel().bits)
    water = water_preset(water_name, list(channels.wavelengths_nm))
    rig = load_rig(builtin_rig_path("grey-plate"))
    patch = rig.plate.black_patch.model_copy(update={"size_m": (patch_m, patch_m), "centre_m": centre_m})
    rig = rig.model_copy(update={"plate": rig.plate.model_copy(update={"black_patch": patch})})
    reflectance = np.full(len(channels.names), rig.plate.reflectance), np.full(len(channels.names), patch.reflectance)
    slopes = {}
    for blur in (0.0, water.forward_blur):
        exposure, logs = None, []
        for d in distances:
            world = SimulatedWorld(scene="plate", distance=d, size=size, channels=channels, rig=rig, lamp=lamp,
                                   water=water.with_overrides(forward_blur=blur), camera=camera,
                                   fixed_exposure=exposure, seed=1)
            exposure = world.exposure  # held from the first distance, as a calibration holds it
            frame = world.noise_free_frame().astype(np.float64) - camera.dark_level_dn
            shape = frame.shape[:2]
            target = box_mask(shape, project_plate_box((0, 0), rig.plate.size_m, d, world.intrinsics), "plate")
            black = box_mask(shape, project_plate_box(patch.centre_m, patch.size_m, d, world.intrinsics), "patch")
            target &= ~black
            black = locate_black_patch(frame, black, target)
            target &= ~black
            logs.append(backscatter_at_black_patch(frame, black, target, reflectance[1], reflectance[0]).plate_log)
        slopes[blur] = (logs[1] - logs[0]) / (distances[1] - distances[0])
    g, b = channels.names.index("G"), channels.names.index("B")
    offset = slopes[water.forward_blur] - slopes[0.0]
    return float((offset[g] - offset[b]) / (slopes[0.0][g] - slopes[0.0][b]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--water", default="jerlov-II")
    parser.add_argument("--size", default="320x240")
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    print(f"{args.water}, {args.size}, noise-free: offset of the calibration's G − B from the black patch's spill")
    for patch_m, centre, distances in CASES:
        share = slope_offset(args.water, size, patch_m, centre, distances)
        print(f"  patch {100 * patch_m:.0f} cm at ({centre[0]:+.3f}, {centre[1]:+.3f}) m, calibrated at "
              f"{distances[0]:g} and {distances[1]:g} m: {100 * share:+.1f} % of G − B")


if __name__ == "__main__":
    main()
