"""simulate → calibrate → range, as a user runs it, against the simulator's ground truth."""

import re

import numpy as np
import pytest

from uwcam.ranging.images import range_images
from uwcam.cli import main
from uwcam.ranging.estimator import RangeEstimator
from uwcam.calibration.rig import resolve_reflectance
from uwcam.simulation import CameraModel, Lamp, SimulatedWorld, water_preset
from uwcam.simulation.scene import MATERIALS
from uwcam.simulation.tank import calibrate_in_simulation

LAMP = (0.3, 0.0, 0.0)
SAND = resolve_reflectance(MATERIALS["sand"], ["R", "G", "B"], [675.0, 575.0, 475.0], "sand")
# The published study's water: c = 0.46/0.11/0.06 1/m, forward scatter B = 0.010 (G = c − 0.02).
SCATTER = "0.44,0.09,0.04"


def simulate(capsys, *args):
    assert main(["simulate", *args]) == 0
    out = capsys.readouterr().out
    intr = re.search(r"intrinsics (\S+)", out).group(1)
    dark = re.search(r"dark level (\S+) DN", out).group(1)
    return intr, dark


@pytest.mark.slow
def test_brick_at_two_metres_within_one_percent(tmp_path, capsys):
    common = ["--water", "ideal", "--forward-blur", "0.010", "--scatter-attenuation", SCATTER,
              "--lamp-offset", ",".join(map(str, LAMP))]
    plates = []
    for d in ("1", "2"):
        plates.append(str(tmp_path / f"plate{d}.tif"))
        intr, dark = simulate(capsys, "--scene", "plate", "--range", d, "--peak", "45000", "--seed", d, "-o", plates[-1], *common)
    brick, truth = tmp_path / "brick.png", tmp_path / "truth.npy"
    simulate(capsys, "--scene", "brick", "--range", "2", "--material", "sand", "--seed", "9", "-o", str(brick),
             "--truth", str(truth), *common)
    profile = tmp_path / "profile.yaml"
    assert main(["calibrate", *plates, "--distance", "1", "--distance", "2", "--rig", "grey-plate", "--intrinsics", intr,
                 "--dark-level", f"{dark},{dark},{dark}", "--lamp-offset", ",".join(map(str, LAMP)), "-o", str(profile)]) == 0
    out = tmp_path / "range.npy"
    assert main(["range", str(profile), str(brick), "-o", str(out), "--smooth", "mean",
                 "--surface-reflectance", ",".join(f"{v:.4f}" for v in SAND)]) == 0
    error = np.load(out) - np.load(truth)
    assert np.isfinite(error).mean() > 0.99
    rms = np.sqrt(np.nanmean(error**2))
    assert rms < 0.01 * 2.0, f"rms {rms:.4f} m"


def study_water(beta):
    w = water_preset("ideal", [675, 575, 475])
    return w.with_overrides(forward_blur=0.010, scatter_attenuation=w.attenuation - 0.02, backscatter=beta)


def study_world(scene, distance, beta, **kw):
    return SimulatedWorld(scene=scene, distance=distance, water=study_water(beta), lamp=Lamp(position=LAMP), **kw)


@pytest.mark.slow
def test_backscatter_compensation_halves_the_error():
    beta, distance = 0.001, 2.0
    profile = calibrate_in_simulation(study_water(beta), Lamp(position=LAMP), (640, 480), CameraModel(peak_code=45000.0))
    scene = study_world("brick", distance, beta, material="sand", seed=5)
    open_water = study_world("open-water", distance, beta, fixed_exposure=scene.exposure, seed=6)
    frame = scene.frame(0)
    raw = RangeEstimator(profile, surface_reflectance=SAND)(frame)
    fixed = range_images(profile, [frame], surface_reflectance=SAND, compensate=True, open_water=open_water.frame(0))
    truth = scene.camera_range

    def rms(r):
        e = r.range - truth
        return np.sqrt(np.nanmean(e**2))

    assert np.isfinite(fixed.range).mean() > 0.99
    assert rms(fixed) < 0.5 * rms(raw), f"compensated {rms(fixed):.3f} m vs raw {rms(raw):.3f} m"


def test_simulate_cli_lists_and_explains(tmp_path, capsys):
    assert main(["simulate", "--list"]) == 0
    listing = capsys.readouterr().out
    assert "brick" in listing and "jerlov-II" in listing and "open-water" in listing
    assert main(["simulate", "--scene", "reef", "--range", "2", "-o", str(tmp_path / "f.tif")]) == 2
    assert "unknown scene 'reef'; known scenes: seabed, brick" in capsys.readouterr().err
    assert main(["simulate", "--scene", "brick", "--range", "2", "--size", "big", "-o", str(tmp_path / "f.tif")]) == 2
    assert "--size must be WIDTHxHEIGHT" in capsys.readouterr().err
    assert main(["simulate", "--scene", "brick", "--range", "-1", "-o", str(tmp_path / "f.tif")]) == 2
    assert "--range must be a positive number of metres" in capsys.readouterr().err
    assert main(["simulate", "--scene", "brick", "--range", "2", "--backscatter", "1,2", "-o", str(tmp_path / "f.tif")]) == 2
    assert "--backscatter takes one value or 3 comma-separated values" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_simulated_frames_round_trip_through_files(tmp_path, capsys):
    for suffix in (".npy", ".tif", ".png"):
        out = tmp_path / f"f{suffix}"
        simulate(capsys, "--scene", "ball", "--range", "1.5", "--size", "64x48", "--bits", "8", "-o", str(out),
                 "--truth", str(tmp_path / "t.npy"))
        from uwcam.imaging.imageio import read_frame

        frame = read_frame(out)
        assert frame.shape == (48, 64, 3) and frame.dtype == np.uint8
    truth = np.load(tmp_path / "t.npy")
    assert truth.dtype == np.float32 and truth[24, 32] == pytest.approx(1.5 - 0.11, abs=0.01)
