"""A simulated rig's calibration is made on frames of another pixel count than the rig camera's
(at most 640, at least 160 pixels wide, the same field of view): what it measured at pixels
(the black patch's centre at each distance, where the backscatter model is scaled without an
open-water frame) must be carried into the rig camera's pixels with its intrinsics."""

from __future__ import annotations

import pytest

from uwcam.calibration.rig import builtin_rig_path, load_rig
from uwcam.config import SIMULATED_SETUPS
from uwcam.drivers.sim import SimulatedRig
from uwcam.runtime.simulated_rig import CALIBRATION_RIG, calibration_size, simulated_calibration


def projected_patch_centre(rig: SimulatedRig, distance: float) -> tuple[float, float]:
    """Where the calibration plate's black patch centre falls in the rig camera (pinhole, plate
    square to the axis on it), pixels (x, y)."""
    patch = load_rig(builtin_rig_path(CALIBRATION_RIG)).plate.black_patch
    intr = rig.world.intrinsics
    return (intr.cx + intr.fx * patch.centre_m[0] / distance, intr.cy + intr.fy * patch.centre_m[1] / distance)


@pytest.mark.parametrize("rig", [
    SimulatedRig(**SIMULATED_SETUPS["vehicle"]().simulation),  # 1280×720, calibrated at 640×360
    SimulatedRig(scene="seabed", size=(64, 48), water="jerlov-IA"),  # calibrated at 160×120
], ids=["reduced", "enlarged"])
def test_black_patch_pixels_are_in_the_rig_cameras_pixels(rig, monkeypatch, tmp_path):
    monkeypatch.setenv("UWCAM_CACHE_DIR", str(tmp_path))
    profile = simulated_calibration(rig)
    scale = rig.size[0] / calibration_size(rig)[0]
    assert scale != 1.0
    bs = profile.backscatter
    for distance, (x, y) in zip(bs.distances_m, bs.patch_pixels):
        ex, ey = projected_patch_centre(rig, distance)
        # The calibration finds the patch as a box of whole pixels: half a pixel of its own each way.
        assert abs(x - ex) <= 0.6 * scale + 0.1 and abs(y - ey) <= 0.6 * scale + 0.1, (distance, (x, y), (ex, ey))
    assert profile.intrinsics["fx"] == pytest.approx(rig.world.intrinsics.fx)


def test_calibration_frames_keep_the_field_of_view_within_their_width_limits():
    assert calibration_size(SimulatedRig(size=(1280, 720))) == (640, 360)
    assert calibration_size(SimulatedRig(size=(320, 240))) == (320, 240)
    assert calibration_size(SimulatedRig(size=(64, 48))) == (160, 120)
    assert calibration_size(SimulatedRig(size=(64, 36))) == (160, 90)
