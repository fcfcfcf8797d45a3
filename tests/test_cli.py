"""The command line: calibrate then range on real image files, and clear errors."""

import subprocess
import sys

import cv2
import numpy as np
import pytest
import tifffile

from tests.synthetic import RGB_ATTENUATION, plate_frame
from uwcam.cli import main
from uwcam.imaging.imageio import read_frame, write_frame
from uwcam.optics import Intrinsics

SHAPE = (90, 120)
FOV = 40.0
INTR = Intrinsics.from_fov(SHAPE[1], SHAPE[0], FOV)
CONSTANT = np.array([0.8, 1.0, 0.9]) * 2e5
PLATE = np.full(3, 0.18)
READ, GAIN = 3.0, 0.2


def noisy_counts(distance, rng, reflectance=PLATE):
    f, dc = plate_frame(distance, RGB_ATTENUATION, CONSTANT, reflectance, SHAPE, fov_deg=FOV)
    f = f + np.sqrt(READ**2 + GAIN * f) * rng.standard_normal(f.shape)
    return np.clip(np.rint(f), 0, 65535).astype(np.uint16), dc


def save(path, frame):
    """Write with each format's own library, not uwcam's, so reading is tested independently."""
    suffix = path.suffix
    if suffix == ".npy":
        np.save(path, frame)
    elif suffix == ".tif":
        tifffile.imwrite(path, frame, photometric="rgb")
    else:
        cv2.imwrite(str(path), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))


@pytest.mark.parametrize("suffix", [".npy", ".tif", ".png"])
def test_calibrate_then_range_round_trip(tmp_path, suffix, capsys):
    rng = np.random.default_rng(4)
    near, _ = noisy_counts(1.0, rng)
    far, _ = noisy_counts(2.0, rng)
    scene, truth = noisy_counts(1.6, rng)
    for name, frame in (("near", near), ("far", far), ("scene", scene)):
        save(tmp_path / f"{name}{suffix}", frame)
        assert np.array_equal(read_frame(tmp_path / f"{name}{suffix}"), frame)  # R,G,B order and full depth kept
    profile = tmp_path / "profile.yaml"
    intr = f"{INTR.fx},{INTR.fy},{INTR.cx},{INTR.cy}"
    assert main([
        "calibrate", str(tmp_path / f"near{suffix}"), str(tmp_path / f"far{suffix}"),
        "--distance", "1.0", "--distance", "2.0", "--intrinsics", intr, "--target-reflectance", "0.18,0.18,0.18",
        "-o", str(profile),
    ]) == 0
    assert "wrote" in capsys.readouterr().out
    out, var, reasons = tmp_path / "range.npy", tmp_path / "var.tif", tmp_path / "reasons.npy"
    assert main(["range", str(profile), str(tmp_path / f"scene{suffix}"), "-o", str(out),
                 "--variance", str(var), "--reasons", str(reasons)]) == 0
    rng_map = np.load(out)
    var_map = tifffile.imread(var)
    assert rng_map.dtype == np.float32 and rng_map.shape == SHAPE
    assert (np.load(reasons) == 0).all()
    error = rng_map - truth
    predicted = np.sqrt(np.mean(var_map))
    rms = np.sqrt(np.mean(error**2))
    assert abs(np.mean(error)) < 0.01 * 1.6
    assert 0.6 * predicted < rms < 1.6 * predicted  # calibration noise adds a little


def test_pair_option_and_console_script(tmp_path):
    rng = np.random.default_rng(8)
    for name, d in (("a", 1.0), ("b", 2.5), ("s", 1.8)):
        np.save(tmp_path / f"{name}.npy", noisy_counts(d, rng)[0])
    profile = tmp_path / "p.yaml"
    run = [sys.executable, "-m", "uwcam"]
    subprocess.run([*run, "calibrate", str(tmp_path / "a.npy"), str(tmp_path / "b.npy"), "--distance", "1",
                    "--distance", "2.5", "--roi", "50,35,20,20", "--channels", "R:675,G:575,B:475", "-o", str(profile)],
                   check=True, capture_output=True)
    subprocess.run([*run, "range", str(profile), str(tmp_path / "s.npy"), "--pair", "G,B", "-o", str(tmp_path / "r.tif")],
                   check=True, capture_output=True)
    centre = tifffile.imread(tmp_path / "r.tif")[40:50, 55:65]
    assert abs(np.median(centre) - 1.8) < 0.15  # G/B pair is the noisiest, but unbiased


@pytest.fixture
def calibrated(tmp_path):
    rng = np.random.default_rng(9)
    for name, d in (("a", 1.0), ("b", 2.0)):
        np.save(tmp_path / f"{name}.npy", noisy_counts(d, rng)[0])
    profile = tmp_path / "p.yaml"
    assert main(["calibrate", str(tmp_path / "a.npy"), str(tmp_path / "b.npy"), "--distance", "1", "--distance", "2", "-o", str(profile)]) == 0
    return tmp_path, profile


def run_error(args, capsys):
    code = main(args)
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1, err
    return err


def test_range_errors_write_nothing(calibrated, capsys):
    tmp, profile = calibrated
    out = tmp / "out.npy"
    np.save(tmp / "four.npy", np.ones((5, 5, 4), np.uint16))
    err = run_error(["range", str(profile), str(tmp / "four.npy"), "-o", str(out)], capsys)
    assert "the image has 4 channel(s) but the calibration profile has 3 (R,G,B)" in err
    (tmp / "junk.png").write_bytes(b"\x89PNG not really")
    assert "cannot read image" in run_error(["range", str(profile), str(tmp / "junk.png"), "-o", str(out)], capsys)
    np.save(tmp / "mono.npy", np.ones((5, 5), np.uint16))
    assert "ranging needs a colour image" in run_error(["range", str(profile), str(tmp / "mono.npy"), "-o", str(out)], capsys)
    assert "does not exist" in run_error(["range", str(profile), str(tmp / "nope.tif"), "-o", str(out)], capsys)
    assert "must end in .npy, .tif or .tiff" in run_error(["range", str(profile), str(tmp / "a.npy"), "-o", str(tmp / "r.png")], capsys)
    assert "cannot read calibration profile" in run_error(["range", str(tmp / "none.yaml"), str(tmp / "a.npy"), "-o", str(out)], capsys)
    assert "--pair needs two different channel names" in run_error(
        ["range", str(profile), str(tmp / "a.npy"), "--pair", "R,R", "-o", str(out)], capsys)
    assert not out.exists()
    assert sorted(p.name for p in tmp.iterdir()) == ["a.npy", "b.npy", "four.npy", "junk.png", "mono.npy", "p.yaml"]


def test_calibrate_errors_write_nothing(calibrated, capsys):
    tmp, _ = calibrated
    out = tmp / "new.yaml"
    a, b = str(tmp / "a.npy"), str(tmp / "b.npy")
    assert "got 2 image(s) but 1 --distance value(s)" in run_error(["calibrate", a, b, "--distance", "1", "-o", str(out)], capsys)
    assert "--distance must be a positive number of metres, got -2.0" in run_error(
        ["calibrate", a, b, "--distance", "1", "--distance", "-2", "-o", str(out)], capsys)
    assert "does not lie inside the 120×90 image" in run_error(
        ["calibrate", a, b, "--distance", "1", "--distance", "2", "--roi", "200,0,10,10", "-o", str(out)], capsys)
    assert "is saturated in channel" in run_error(
        ["calibrate", a, b, "--distance", "1", "--distance", "2", "--saturation", "100", "-o", str(out)], capsys)
    assert "--target-reflectance needs 3 comma-separated numbers" in run_error(
        ["calibrate", a, b, "--distance", "1", "--distance", "2", "--target-reflectance", "0.2,0.3", "-o", str(out)], capsys)
    assert "--roi must be X,Y,WIDTH,HEIGHT" in run_error(
        ["calibrate", a, b, "--distance", "1", "--distance", "2", "--roi", "1,2,0,4", "-o", str(out)], capsys)
    np.save(tmp / "dark.npy", np.zeros((90, 120, 3), np.uint16))
    assert "has no signal in channel" in run_error(
        ["calibrate", a, str(tmp / "dark.npy"), "--distance", "1", "--distance", "2", "-o", str(out)], capsys)
    assert not out.exists()


def test_rig_with_black_patch_measures_a_floor(tmp_path):
    rng = np.random.default_rng(12)
    from uwcam.calibration.fit import project_plate_box
    from uwcam.calibration.rig import builtin_rig_path, load_rig

    rig = load_rig(builtin_rig_path("grey-plate"))
    patch = rig.plate.black_patch
    paths = []
    for d in (1.0, 2.0):
        frame, _ = plate_frame(d, RGB_ATTENUATION, CONSTANT, PLATE, SHAPE, fov_deg=FOV)
        x, y, w, h = project_plate_box(patch.centre_m, patch.size_m, d, INTR)
        frame[y : y + h, x : x + w] *= 0.03 / 0.18
        frame += 20.0 + 3.0 * rng.standard_normal(frame.shape)
        paths.append(tmp_path / f"{d}.tif")
        write_frame(paths[-1], np.clip(np.rint(frame), 0, 65535).astype(np.uint16))
    profile = tmp_path / "p.yaml"
    intr = f"{INTR.fx},{INTR.fy},{INTR.cx},{INTR.cy}"
    assert main(["calibrate", *map(str, paths), "--distance", "1", "--distance", "2", "--rig", str(builtin_rig_path()),
                 "--intrinsics", intr, "-o", str(profile)]) == 0
    from uwcam.calibration.profile import load_profile

    loaded = load_profile(profile)
    assert np.all(loaded.array("noise_floor") > 20) and np.all(loaded.array("noise_floor") < 45)
    assert loaded.provenance.target == "rig grey-plate"
