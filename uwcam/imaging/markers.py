"""Finding ArUco markers in a frame: the calibration plate's and the vehicle patch's.

One home for the detector, so that the calibration session and the live patch tracker find a
marker under the same rules.

A marker printed on a white plate that stands out from a dark background (a patch on its
bracket before the open water, a plate in a tank) gives OpenCV two nested square contours:
the marker's black border and the plate's own outline. OpenCV groups candidates whose corners
lie within ``minMarkerDistanceRate`` × the smaller perimeter (default 0.125) and keeps the
outer one, which is the plate: no marker in it, so none is found (opencv_contrib#2913). On the
simulated vehicle that lost the patch marker in 1 to 6 frames in 100, depending only on how
dark the seabed behind the bracket was. A quiet zone is at least one marker cell wide, i.e.
1/6 of a 4×4 marker's side, 1/24 of its perimeter; 0.02 groups only contours closer than
that, so the plate's outline stays a candidate of its own (rejected: it holds no code) and the
marker is found."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

MARKER_DISTANCE_RATE = 0.02
"""Candidates whose mean corner distance is below this fraction of the smaller perimeter are
one contour seen twice (OpenCV's ``minMarkerDistanceRate``); see the module docstring."""


def marker_detector(dictionary: str) -> cv2.aruco.ArucoDetector:
    """A detector for ``dictionary`` (an OpenCV ArUco dictionary name such as "DICT_4X4_50"); a new
    one on every call (about a microsecond), as the frame loop and the calibration session detect
    from their own threads and none is shared."""
    parameters = cv2.aruco.DetectorParameters()
    parameters.minMarkerDistanceRate = MARKER_DISTANCE_RATE
    return cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)), parameters)


def grey_for_detection(frame: NDArray) -> NDArray[np.uint8]:
    """The brightest channel of ``frame`` (H, W, N) stretched to 8 bits, (H, W): markers are black
    on a lit plate, and the brightest channel shows them with the least noise."""
    data = np.asarray(frame)
    k = int(np.argmax(data.reshape(-1, data.shape[-1])[::97].mean(axis=0)))
    channel = data[:, :, k].astype(np.float32)
    top = float(np.percentile(channel[::4, ::4], 99.5)) or 1.0
    return np.clip(channel * (255.0 / top), 0, 255).astype(np.uint8)


def find_markers(frame: NDArray, dictionary: str) -> tuple[list[NDArray[np.float32]], list[int]]:
    """The markers of ``dictionary`` in ``frame`` (H, W, N): each one's four image corners (4, 2)
    in pixels, in OpenCV's order (top-left, top-right, bottom-right, bottom-left of the marker),
    and its id."""
    corners, ids, _ = marker_detector(dictionary).detectMarkers(grey_for_detection(frame))
    if ids is None:
        return [], []
    return [c.reshape(4, 2) for c in corners], [int(i) for i in ids.ravel()]
