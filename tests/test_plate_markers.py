"""The plate is found only by its own markers: a stray marker that shares the plate's dictionary and
an id (the vehicle's patch marker, ArUco 7 of DICT_4X4_50) is never taken for the plate, and a
plate cut by the image's edge is found but said to be out of view. Frames from the simulator; the
truth is the scene's geometry."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from uwcam.optics.geometry import Intrinsics
from uwcam.calibration.plate import MIN_MARKERS, sight_plate
from uwcam.calibration.rig import builtin_rig_path, load_rig
from uwcam.simulation import Lamp, SimulatedWorld
from uwcam.simulation.scene import MARKER_ID


@pytest.fixture(scope="module")
def rig():
    return load_rig(builtin_rig_path("charuco-plate"))


@pytest.fixture(scope="module")
def plate_frame(rig):
    world = SimulatedWorld(scene="plate", distance=1.5, size=(640, 360), rig=rig, lamp=Lamp(position=(0.3, -0.8, 0)))
    return world.frame(0), world.intrinsics


def with_stray_marker(frame, marker_id: int, x: int, y: int, side: int = 48):
    """``frame`` with a printed ArUco marker (DICT_4X4_50, white quiet zone) pasted at x, y."""
    out = frame.copy()
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    ink = cv2.aruco.generateImageMarker(d, marker_id, side).astype(np.float64) / 255.0
    quiet = side // 4
    top = float(np.percentile(frame, 99))
    out[y - quiet : y + side + quiet, x - quiet : x + side + quiet] = top
    out[y : y + side, x : x + side] = (0.05 * top + ink * 0.95 * top)[..., None].astype(out.dtype)
    return out


def test_the_vehicles_patch_marker_alone_is_not_the_plate(rig):
    # The simulated vehicle's view: seabed, the patch and its marker 7 on a bracket, no plate.
    world = SimulatedWorld(scene="seabed-patch", distance=2.0, size=(640, 480), lamp=Lamp(position=(0.3, 0, 0)))
    frame = world.frame(0)
    seen = sight_plate(frame, rig, world.intrinsics)
    assert MARKER_ID in seen.markers + seen.ignored  # it is seen, and it is one of the plate's ids
    assert seen.pose is None and seen.why_not == f"1 of the plate's markers in view, {MIN_MARKERS} needed"
    told = sight_plate(frame, rig, world.intrinsics, ignore_ids=[MARKER_ID])
    assert told.pose is None and told.markers == [] and told.ignored == [MARKER_ID]


def test_a_stray_copy_of_a_plate_id_is_used_for_neither_unless_its_region_is_known(rig, plate_frame):
    frame, intr = plate_frame
    clean = sight_plate(frame, rig, intr)
    assert clean.pose is not None and clean.markers == list(range(12))
    stray = with_stray_marker(frame, MARKER_ID, 560, 280)  # in the open water beside the plate
    seen = sight_plate(stray, rig, intr)
    assert seen.ignored == [MARKER_ID, MARKER_ID] and MARKER_ID not in seen.markers
    assert seen.pose is not None and seen.pose.distance_m == pytest.approx(1.5, abs=0.02)
    # The stray marker's region is the vehicle's (the vehicle mask): the plate's own 7 counts again.
    masked = sight_plate(stray, rig, intr, ignore_regions=[(540, 260, 100, 100)])
    assert masked.markers == list(range(12)) and masked.ignored == [MARKER_ID]
    assert masked.pose.distance_m == pytest.approx(1.5, abs=0.02)


def test_a_plate_cut_by_the_image_edge_is_found_but_not_in_view(rig, plate_frame):
    frame, intr = plate_frame
    cut = 250  # the plate's left marker column and the left of its target region leave the image
    cropped = np.ascontiguousarray(frame[:, cut:])
    shifted = Intrinsics(intr.fx, intr.fy, intr.cx - cut, intr.cy)
    seen = sight_plate(cropped, rig, shifted)
    assert seen.pose is not None and not {0, 9, 10, 11} & set(seen.markers)
    assert seen.pose.target_in_view is False
    assert sight_plate(frame, rig, intr).pose.target_in_view is True
