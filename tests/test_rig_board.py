"""The marker plate rig: schema, printable artwork at true scale, and finding the plate by its markers."""

import re

import cv2
import numpy as np
import pytest

from uwcam.cli import main
from uwcam.calibration.plate import locate_plate
from uwcam.calibration.rig import builtin_rig_path, load_rig
from uwcam.calibration.artwork import write_artwork
from uwcam.simulation import Lamp, SimulatedWorld


@pytest.fixture(scope="module")
def rig():
    return load_rig(builtin_rig_path("charuco-plate"))


def test_artwork_pdf_is_the_plate_at_true_scale(tmp_path, rig, capsys):
    out = tmp_path / "board.pdf"
    assert main(["rig", "print", "charuco-plate", "-o", str(out)]) == 0
    box = re.search(rb"/MediaBox \[\s*0 0 ([0-9.]+) ([0-9.]+)\s*\]", out.read_bytes())
    points_per_metre = 72 / 0.0254
    assert float(box.group(1)) == pytest.approx(rig.plate.size_m[0] * points_per_metre, abs=0.01)
    assert float(box.group(2)) == pytest.approx(rig.plate.size_m[1] * points_per_metre, abs=0.01)
    assert "true scale" in capsys.readouterr().out


def test_every_marker_of_the_artwork_is_found_where_the_rig_says(tmp_path, rig):
    out = tmp_path / "board.png"
    dpi = 60.0
    write_artwork(rig, out, dpi=dpi)
    image = cv2.imread(str(out), cv2.IMREAD_GRAYSCALE)
    board = rig.plate.markers
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary)),
                                       cv2.aruco.DetectorParameters())
    corners, ids, _ = detector.detectMarkers(image)
    assert sorted(ids.ravel().tolist()) == sorted(m.id for m in board.markers)
    px_per_m = dpi / 0.0254
    for c, i in zip(corners, ids.ravel()):
        centre = c.reshape(4, 2).mean(axis=0)
        want = next(m.centre_m for m in board.markers if m.id == i)
        expected = (np.array(want) + np.array(rig.plate.size_m) / 2) * px_per_m
        np.testing.assert_allclose(centre, expected, atol=2.0)


def test_bad_output_for_rig_print_is_explained(tmp_path, capsys):
    assert main(["rig", "print", "charuco-plate", "-o", str(tmp_path / "board.svg")]) == 2
    assert "must be a .pdf file" in capsys.readouterr().err
    assert main(["rig", "print", "no-such-rig", "-o", str(tmp_path / "b.pdf")]) == 2
    assert "known rigs" in capsys.readouterr().err


@pytest.mark.parametrize("distance", [1.0, 2.5])  # at 2.5 m a marker is 9 pixels wide
def test_plate_pose_from_markers_in_a_simulated_frame(rig, distance):
    world = SimulatedWorld(scene="plate", distance=distance, size=(320, 240), rig=rig, lamp=Lamp(position=(0.3, 0, 0)))
    pose = locate_plate(world.frame(0), rig, world.intrinsics)
    assert pose is not None and len(pose.markers_found) >= len(rig.plate.markers.markers) - 2
    assert pose.distance_m == pytest.approx(distance, rel=0.01)
    assert pose.tilt_deg < 4.0  # square to the axis, within what 9-pixel markers can tell
    # The target box lies on plate pixels (the truth: finite range at the plate's distance).
    x, y, w, h = pose.target_box
    truth = world.camera_range[y : y + h, x : x + w]
    assert np.all(np.isfinite(truth))


def test_a_frame_without_the_plate_finds_nothing(rig):
    world = SimulatedWorld(scene="seabed", distance=2.0, size=(160, 120))
    assert locate_plate(world.frame(0), rig, world.intrinsics) is None


def test_marker_outside_the_plate_is_refused(tmp_path):
    from uwcam.fileio import UserInputError

    text = builtin_rig_path("charuco-plate").read_text().replace("{id: 0, centre_m: [-0.3, -0.3]}",
                                                                   "{id: 0, centre_m: [-0.34, -0.3]}")
    path = tmp_path / "r.yaml"
    path.write_text(text)
    with pytest.raises(UserInputError, match="marker 0 reaches beyond the plate's edge"):
        load_rig(path)
