"""Finding a rig's calibration plate in a frame by its markers, and its pose.

The markers' corners are known on the plate (plate coordinates: metres from its centre,
x right, y down, z = 0 on the plate); cv2.solvePnP with the camera intrinsics gives the
plate's rotation and position in the camera frame (x right, y down, z forward). From them:
the distance along the optical axis to the plate's plane (what ``uwcam calibrate
--distance`` means), the plate's tilt from square to the axis, and where the target
region and black patch fall in the image.

Only the plate's own markers count. Any other marker in view — the vehicle's calibration
patch carries one (ArUco id 7 of DICT_4X4_50 on the simulated vehicle), a tank wall may carry
others — can share the plate's dictionary and ids, so a marker alone is not the plate: the
plate is found by at least MIN_MARKERS of its markers whose corners one flat plate explains
(rms reprojection within MAX_REPROJECTION_PX), and markers the caller knows to be someone
else's (an id, or a region of the image such as the vehicle mask) are left out first.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from uwcam.imaging.markers import find_markers
from uwcam.optics.geometry import Intrinsics
from uwcam.calibration.rig import Area, Rig

Box = tuple[int, int, int, int]

MIN_MARKERS = 3
"""Markers of the plate needed to call it found: one or two is what a stray marker (the vehicle's
patch marker) looks like, and three spread over the plate fix its pose without ambiguity."""
MAX_REPROJECTION_PX = 3.0
"""rms distance (pixels) between the detected corners and those of the fitted plate beyond which
the markers are not one flat plate (a stray marker taken for one of the plate's ids)."""


@dataclass(frozen=True)
class PlatePose:
    """Where the plate is: camera frame, metres and degrees; image regions in pixels."""

    distance_m: float
    """Distance along the optical axis to the plate's plane."""
    tilt_deg: float
    """Angle between the plate's normal and the optical axis."""
    markers_found: list[int]
    reprojection_px: float
    """rms distance between detected and re-projected marker corners."""
    target_box: Box
    black_box: Box | None
    plate_polygon: NDArray[np.float64]
    """(4, 2) image corners of the whole plate."""
    target_polygon: NDArray[np.float64]
    coverage: float
    """Fraction of the image the plate covers."""
    target_in_view: bool = True
    """Whether the whole target region lies inside the image (a box cut by the image's edge
    measures only part of the plate)."""


def _project(points: NDArray, rvec: NDArray, tvec: NDArray, intr: Intrinsics) -> NDArray:
    k = np.array([[intr.fx, 0, intr.cx], [0, intr.fy, intr.cy], [0, 0, 1]], dtype=np.float64)
    img, _ = cv2.projectPoints(np.asarray(points, np.float64), rvec, tvec, k, None)
    return img.reshape(-1, 2)


def _corners(area: Area) -> NDArray:
    (cx, cy), (w, h) = area.centre_m, area.size_m
    return np.array([[cx - w / 2, cy - h / 2, 0], [cx + w / 2, cy - h / 2, 0], [cx + w / 2, cy + h / 2, 0],
                     [cx - w / 2, cy + h / 2, 0]], dtype=np.float64)


def _inner_box(polygon: NDArray, shape: tuple[int, int], inset: float) -> Box | None:
    """The axis-aligned box inside a near-rectangular image quadrilateral, inset by a fraction of its size."""
    xs, ys = np.sort(polygon[:, 0]), np.sort(polygon[:, 1])
    x0, x1, y0, y1 = xs[1], xs[2], ys[1], ys[2]  # inner of the two left/right and top/bottom corners
    dx, dy = (x1 - x0) * inset, (y1 - y0) * inset
    xa, ya = int(np.ceil(max(x0 + dx, 0))), int(np.ceil(max(y0 + dy, 0)))
    xb, yb = int(np.floor(min(x1 - dx, shape[1] - 1))), int(np.floor(min(y1 - dy, shape[0] - 1)))
    if xb - xa < 3 or yb - ya < 3:
        return None
    return xa, ya, xb - xa + 1, yb - ya + 1


def _inside(point: NDArray, boxes: Sequence[Box]) -> bool:
    x, y = float(point[0]), float(point[1])
    return any(bx <= x < bx + bw and by <= y < by + bh for bx, by, bw, bh in boxes)


@dataclass(frozen=True)
class PlateSighting:
    """What one frame shows of the plate: its markers, those left out, and its pose if found."""

    markers: list[int]
    """Ids of the plate's markers taken for the pose."""
    ignored: list[int]
    """Ids of markers seen but not taken for the plate's (another's id or region, or seen twice)."""
    pose: PlatePose | None
    why_not: str | None = None
    """Why the plate is not found (None when it is), in the engineer's words."""


def locate_plate(frame: NDArray, rig: Rig, intrinsics: Intrinsics, *, ignore_ids: Iterable[int] = (),
                 ignore_regions: Sequence[Box] = ()) -> PlatePose | None:
    """The plate's pose and image regions from its markers in ``frame`` (H, W, N); None when fewer
    than MIN_MARKERS of the rig's markers are found, they do not fit one flat plate, or the target
    region does not lie in the image at all. See :func:`sight_plate`."""
    return sight_plate(frame, rig, intrinsics, ignore_ids=ignore_ids, ignore_regions=ignore_regions).pose


def sight_plate(frame: NDArray, rig: Rig, intrinsics: Intrinsics, *, ignore_ids: Iterable[int] = (),
                ignore_regions: Sequence[Box] = ()) -> PlateSighting:
    """The plate's markers in ``frame`` (H, W, N) and, from MIN_MARKERS or more of them, its pose.

    ignore_ids: marker ids (of the rig's dictionary) that belong to something else in view, such
    as the vehicle's patch marker; ignore_regions: image boxes (x, y, width, height in pixels, such
    as the vehicle mask) in which no marker is taken for the plate's."""
    board = rig.plate.markers
    if board is None:
        raise ValueError(f"rig {rig.name} has no markers to locate the plate by")
    corners, ids = find_markers(frame, board.dictionary)
    if not ids:
        return PlateSighting([], [], None, f"no marker of rig {rig.name} in view")
    ignored_ids = {int(i) for i in ignore_ids}
    known = {m.id: m for m in board.markers if m.id not in ignored_ids}
    obj, img, found, ignored = [], [], [], []
    s = board.marker_size_m / 2
    outside = [not _inside(c.mean(axis=0), ignore_regions) for c in corners]
    seen = [i for i, out in zip(ids, outside) if out]
    for c, i, out in zip(corners, ids, outside):
        # An id seen twice (outside the regions left out): one copy is not on the plate, and
        # nothing says which; use neither.
        if not out or i not in known or seen.count(i) > 1:
            ignored.append(i)
            continue
        mx, my = known[i].centre_m
        # OpenCV's corner order: top-left, top-right, bottom-right, bottom-left.
        obj += [[mx - s, my - s, 0], [mx + s, my - s, 0], [mx + s, my + s, 0], [mx - s, my + s, 0]]
        img += list(c)
        found.append(i)
    found, ignored = sorted(found), sorted(ignored)
    if len(found) < MIN_MARKERS:
        return PlateSighting(found, ignored, None, f"{len(found)} of the plate's markers in view, {MIN_MARKERS} needed")
    pose = _pose(frame.shape[:2], rig, intrinsics, np.array(obj, np.float64), np.array(img, np.float64), found)
    if pose is None:
        return PlateSighting(found, ignored, None, "the markers in view do not fit one flat plate square enough to "
                                                   "measure (seen edge-on, or not all on the plate)")
    return PlateSighting(found, ignored, pose)


def _pose(shape: tuple[int, int], rig: Rig, intrinsics: Intrinsics, obj_a: NDArray, img_a: NDArray,
          found: list[int]) -> PlatePose | None:
    k = np.array([[intrinsics.fx, 0, intrinsics.cx], [0, intrinsics.fy, intrinsics.cy], [0, 0, 1]], dtype=np.float64)
    try:
        ok, rvec, tvec = cv2.solvePnP(obj_a, img_a, k, None, flags=cv2.SOLVEPNP_IPPE)
    except cv2.error:  # degenerate corners (a marker seen edge-on): no pose from this frame
        return None
    if not ok or not np.all(np.isfinite(tvec)):
        return None
    rot, _ = cv2.Rodrigues(rvec)
    normal = rot[:, 2]
    t = tvec.ravel()
    # The optical axis (0, 0, s) meets the plate's plane n·(x − t) = 0 at s = n·t / n_z.
    if abs(normal[2]) < 1e-6:
        return None  # the plate seen edge-on
    distance = float(normal @ t / normal[2])
    tilt = float(np.degrees(np.arccos(min(abs(normal[2]), 1.0))))
    reproj = float(np.sqrt(np.mean(np.sum((_project(obj_a, rvec, tvec, intrinsics) - img_a) ** 2, axis=1))))
    if not reproj <= MAX_REPROJECTION_PX:
        return None
    h, w = shape
    plate_poly = _project(_corners(Area(size_m=rig.plate.size_m)), rvec, tvec, intrinsics)
    target_poly = _project(_corners(rig.plate.target_area()), rvec, tvec, intrinsics)
    target_box = _inner_box(target_poly, (h, w), 0.02)
    if target_box is None:
        return None
    black_box = None
    if rig.plate.black_patch is not None:
        bp = rig.plate.black_patch
        black_box = _inner_box(_project(_corners(Area(centre_m=bp.centre_m, size_m=bp.size_m)), rvec, tvec, intrinsics),
                               (h, w), 0.0)
    mask = np.zeros((h, w), np.uint8)
    cv2.fillConvexPoly(mask, np.round(plate_poly).astype(np.int32), 1)
    in_view = bool(np.all(target_poly >= 0) and np.all(target_poly[:, 0] <= w - 1) and np.all(target_poly[:, 1] <= h - 1))
    return PlatePose(distance, tilt, found, reproj, target_box, black_box, plate_poly, target_poly,
                     float(mask.mean()), in_view)
