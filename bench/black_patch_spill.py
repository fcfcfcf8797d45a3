"""The black patch's forward-scatter spill: its offset on the calibration's G − B attenuation
difference against the patch's size, position and the calibration distances (docs/calibration.md,
"Backscatter at the black patch").

uwcam's own calibration of noise-free frames of the grey plate in a simulated water
(:func:`uwcam.simulation.tank.calibrate_in_simulation`), with the water's forward blur and
without it (B = 0: the forward-scattered light stays in its pixel, so nothing crosses from plate
to patch). The offset is the difference of the two calibrations' G − B, as a share of the
blur-free one.

    python3 bench/black_patch_spill.py [--water jerlov-II] [--size 320x240]
"""

from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from uwcam.calibration.rig import builtin_rig_path, load_rig  # noqa: E402
from uwcam.simulation import Lamp, water_preset  # noqa: E402
from uwcam.simulation.tank import calibrate_in_simulation  # noqa: E402
from uwcam.simulation.world import Channels  # noqa: E402

CASES = (  # patch size (m), patch centre on the plate (m), distances (m)
    (0.05, (0.0, 0.0), (1.0, 2.0)),
    (0.10, (0.0, 0.0), (1.0, 2.0)),
    (0.20, (0.0, 0.0), (1.0, 2.0)),
    (0.10, (-0.125, -0.125), (1.0, 2.0)),  # the grey-plate rig's patch
    (0.10, (-0.125, -0.125), (0.75, 1.5)),
)


def green_blue(water_name: str, size: tuple[int, int], patch_m: float, centre_m: tuple[float, float],
               distances: tuple[float, float], blur: float | None) -> float:
    """The calibration's G − B attenuation difference (1/m); blur: the water's forward blur (None: its own)."""
    channels = Channels()
    water = water_preset(water_name, list(channels.wavelengths_nm))
    rig = load_rig(builtin_rig_path("grey-plate"))
    patch = rig.plate.black_patch.model_copy(update={"size_m": (patch_m, patch_m), "centre_m": centre_m})
    rig = rig.model_copy(update={"plate": rig.plate.model_copy(update={"black_patch": patch})})
    profile = calibrate_in_simulation(water.with_overrides(forward_blur=blur), Lamp(position=(0.3, 0.0, 0.0)), size,
                                      noise_free=True, distances=distances, channels=channels, rig=rig)
    v = profile.array("attenuation_difference")
    return float(v[channels.names.index("G")] - v[channels.names.index("B")])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--water", default="jerlov-II")
    parser.add_argument("--size", default="320x240")
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    print(f"{args.water}, {args.size}, noise-free: offset of the calibration's G − B from the black patch's spill")
    for patch_m, centre, distances in CASES:
        free = green_blue(args.water, size, patch_m, centre, distances, blur=0.0)
        share = green_blue(args.water, size, patch_m, centre, distances, blur=None) / free - 1.0
        print(f"  patch {100 * patch_m:.0f} cm at ({centre[0]:+.3f}, {centre[1]:+.3f}) m, calibrated at "
              f"{distances[0]:g} and {distances[1]:g} m: {100 * share:+.1f} % of G − B")


if __name__ == "__main__":
    main()
