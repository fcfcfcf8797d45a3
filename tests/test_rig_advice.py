"""A calibration whose black patch cannot keep the ranges within 2 % in the water it was taken in
says so, with the rig to use (#41). The expected spills are `bench/black_patch_spill.py`'s figures
(uwcam's simulator, noise-free, plate at 1 and 2 m), not the rule's own."""

from __future__ import annotations

import numpy as np
import pytest

from uwcam.calibration.rig_advice import LARGE_PATCH_RIG, predicted_spill, rig_advice


@pytest.mark.parametrize("side, measured", [(0.05, 0.058), (0.10, 0.030), (0.20, 0.018)])
def test_the_predicted_spill_follows_the_measured_one_in_jerlov_ii(side, measured):
    # Jerlov II: the water's light at the patch is 0.107 of the plate's in blue at 2 m.
    assert predicted_spill(0.107, side) == pytest.approx(measured, rel=0.15)


def test_the_advice_names_the_rig_where_it_helps_and_says_so_where_none_does():
    assert rig_advice(0.001, 0.10) is None  # clear water, a tank
    assert rig_advice(0.098, 0.20) is None  # Jerlov II with the large patch
    advice = rig_advice(0.107, 0.10)  # Jerlov II with the 10 cm patch
    assert LARGE_PATCH_RIG in advice and "3%" in advice
    murky = rig_advice(0.21, 0.20)  # Jerlov III: even 20 cm leaves 3 %
    assert "no built-in rig" in murky and "nearer" in murky
    assert rig_advice(float("nan"), 0.1) is None and rig_advice(0.5, 0.0) is None


def details_of_simulated_calibration(monkeypatch, water_name: str, rig_name: str):
    """uwcam's own calibration of simulated plate frames (320×240, lamp 0.3 m aside, 1 and 2 m),
    with everything it measured on the way."""
    import uwcam.simulation.tank as tank
    from uwcam.calibration.fit import calibrate_with_details
    from uwcam.calibration.rig import builtin_rig_path, load_rig
    from uwcam.simulation import CameraModel, Lamp, water_preset
    from uwcam.simulation.world import Channels

    captured = []

    def calibrate(frames, distances, inputs):
        captured.append(calibrate_with_details(frames, distances, inputs))
        return captured[-1].profile

    monkeypatch.setattr(tank, "calibrate", calibrate)
    rig = load_rig(builtin_rig_path(rig_name))
    tank.calibrate_in_simulation(water_preset(water_name, list(Channels().wavelengths_nm)), Lamp(position=(0.3, 0.0, 0.0)),
                                 (320, 240), CameraModel(), frames_per_distance=2, rig=rig)
    return captured[-1], rig


@pytest.mark.parametrize("water_name, rig_name, advised", [
    ("jerlov-II", "grey-plate", True), ("jerlov-II", LARGE_PATCH_RIG, False), ("jerlov-I", "grey-plate", False)])
def test_a_calibration_in_scattering_water_with_a_small_patch_is_told_the_rig(monkeypatch, water_name, rig_name, advised):
    from uwcam.calibration.report import html_report
    from uwcam.calibration.rig_advice import calibration_rig_advice

    details, rig = details_of_simulated_calibration(monkeypatch, water_name, rig_name)
    advice = calibration_rig_advice(details, rig)
    assert (advice is not None) == advised, advice
    if advised:
        assert LARGE_PATCH_RIG in advice
        assert "The rig for this water" in html_report(details, advice=advice)
    assert calibration_rig_advice(details, None) is None  # a region given by hand: its size is not known
    assert np.isfinite(details.profile.array("attenuation_difference")).all()
