"""The vehicle's patch marker is found in every frame, whatever the seabed behind its white plate.

The marker is printed on a white plate that stands out from the darker seabed; OpenCV's default
detector then keeps the plate's outline and drops the marker inside it (opencv_contrib#2913).
On the simulated survey at 640×360 that lost the marker whenever the seabed behind the bracket
was dark (t = 25 s and 142 s: none of 40 noisy frames; a CI run lost it in five frames in a row).
The calibration session (sight_plate) and the live patch tracker both find markers through
find_markers. The truth is the bracket's geometry: a marker of side MARKER_SIDE_M centred at MARKER_CENTRE_M,
PATCH_DISTANCE_M in front of the camera, projected through the pinhole by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from uwcam.imaging.markers import find_markers
from uwcam.simulation.scene import MARKER_CENTRE_M, MARKER_ID, MARKER_SIDE_M, PATCH_DISTANCE_M
from uwcam.simulation.survey import SurveyWorld

WIDTH, HEIGHT = 640, 360


def marker_corners_by_hand() -> np.ndarray:
    """The marker's four outer corners (top-left, top-right, bottom-right, bottom-left), pixels."""
    f = (WIDTH / 2) / math.tan(math.radians(60.0) / 2)  # 60° across, square pixels
    cx, cy = (WIDTH - 1) / 2, (HEIGHT - 1) / 2  # pixel centres at whole numbers
    (x, y), s, z = MARKER_CENTRE_M, MARKER_SIDE_M / 2, PATCH_DISTANCE_M
    return np.array([[cx + f * (x + dx) / z, cy + f * (y + dy) / z] for dx, dy in ((-s, -s), (s, -s), (s, s), (-s, s))])


@pytest.fixture(scope="module")
def survey():
    return SurveyWorld(size=(WIDTH, HEIGHT))


@pytest.mark.parametrize("t", [0.0, 25.0, 110.0, 142.0])
def test_the_patch_marker_is_found_whatever_lies_behind_its_plate(survey, t):
    expected = marker_corners_by_hand()
    for index in range(6):
        corners, ids = find_markers(survey.frame(t, index), "DICT_4X4_50")
        assert ids.count(MARKER_ID) == 1, (t, index, ids)
        found = corners[ids.index(MARKER_ID)]
        # Whole-pixel corners (no refinement) of a border the simulator shades every 4 pixels and
        # interpolates: within 3 pixels of the truth, a third of one of the marker's 9-pixel cells.
        assert np.max(np.abs(found - expected)) < 3.0, (t, index, found, expected)

