"""A tank calibration session kept on disk until it is accepted or cancelled, so that neither a
page reload nor a daemon restart loses the engineer's captures.

One folder holds one session: ``session.json`` (what the session is: rig, intrinsics, settings,
exposure, and each capture's distance and plate pose), ``base.yaml`` (the profile active when it
started, whose channels, dark level and floor the checks and the fit use) and ``capture-N.npy``
(the N-th capture's frames, (frames, H, W, channels) as the camera gave them). Every file is
written atomically, captures before the JSON that lists them, so a kill at any moment leaves the
previous complete session. A fit is not kept: a restored session is fitted again (seconds).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time

import numpy as np

from uwcam.calibration.session import Capture, CalibrationSession
from uwcam.fileio import atomic_write
from uwcam.optics.geometry import Intrinsics
from uwcam.calibration.plate import PlatePose
from uwcam.calibration.profile import load_profile, save_profile
from uwcam.calibration.rig import builtin_rig_path, load_rig

log = logging.getLogger(__name__)
STORE_VERSION = 1
SESSION_FILE = "session.json"
BASE_FILE = "base.yaml"


def _capture_file(index: int) -> str:
    return f"capture-{index}.npy"


def _pose_to_json(pose: PlatePose) -> dict:
    return {"distance_m": pose.distance_m, "tilt_deg": pose.tilt_deg, "markers_found": list(pose.markers_found),
            "reprojection_px": pose.reprojection_px, "target_box": list(pose.target_box),
            "black_box": None if pose.black_box is None else list(pose.black_box),
            "plate_polygon": pose.plate_polygon.tolist(), "target_polygon": pose.target_polygon.tolist(),
            "coverage": pose.coverage, "target_in_view": pose.target_in_view}


def _pose_from_json(data: dict) -> PlatePose:
    return PlatePose(float(data["distance_m"]), float(data["tilt_deg"]), [int(i) for i in data["markers_found"]],
                     float(data["reprojection_px"]), tuple(int(v) for v in data["target_box"]),
                     None if data["black_box"] is None else tuple(int(v) for v in data["black_box"]),
                     np.asarray(data["plate_polygon"], np.float64), np.asarray(data["target_polygon"], np.float64),
                     float(data["coverage"]), bool(data["target_in_view"]))


def save_session(session: CalibrationSession, folder: str) -> None:
    """Write what is new of ``session`` into ``folder`` (created if needed); captures already there are kept."""
    os.makedirs(folder, exist_ok=True)
    base = os.path.join(folder, BASE_FILE)
    if not os.path.exists(base):
        save_profile(session.base, base)
    captures = []
    for i, c in enumerate(session.captures):
        path = os.path.join(folder, _capture_file(i))
        if not os.path.exists(path):
            with atomic_write(path, "wb") as fh:
                np.save(fh, np.stack(c.frames), allow_pickle=False)
        captures.append({"file": _capture_file(i), "distance_m": c.distance_m, "held_back": c.held_back,
                         "rangefinder_m": c.rangefinder_m, "exposure_us": c.exposure_us, "drift": c.drift,
                         "pose": _pose_to_json(c.pose)})
    i = session.intrinsics
    record = {"format": "uwcam-calibration-session", "version": STORE_VERSION, "id": session.id, "rig": session.rig_name,
              "intrinsics": [i.fx, i.fy, i.cx, i.cy], "frames_per_capture": session.frames_per_capture,
              "distance_tolerance_m": session.distance_tolerance_m, "exposure": session.exposure,
              "ignore_ids": list(session.ignore_ids), "ignore_regions": [list(b) for b in session.ignore_regions],
              "captures": captures}
    with atomic_write(os.path.join(folder, SESSION_FILE), "w") as fh:
        json.dump(record, fh, indent=1)


def load_session(folder: str, frame_shape: tuple[int, ...] | None = None) -> CalibrationSession | None:
    """The session kept in ``folder``; None when there is none. A folder that cannot be read, or
    whose captures are not of ``frame_shape`` (H, W, N: the camera now in use, when known), is set
    aside (renamed, never deleted: it holds someone's captures) and logged, and None returned."""
    path = os.path.join(folder, SESSION_FILE)
    if not os.path.exists(path):
        return None
    try:
        with open(path, encoding="utf-8") as fh:
            record = json.load(fh)
        if record.get("format") != "uwcam-calibration-session" or record.get("version") != STORE_VERSION:
            raise ValueError(f"not a version-{STORE_VERSION} calibration session")
        session = CalibrationSession(
            record["rig"], load_rig(builtin_rig_path(record["rig"])), Intrinsics(*map(float, record["intrinsics"])),
            load_profile(os.path.join(folder, BASE_FILE)), int(record["frames_per_capture"]),
            float(record["distance_tolerance_m"]), dict(record["exposure"]), id=str(record["id"]),
            ignore_ids=tuple(int(v) for v in record["ignore_ids"]),
            ignore_regions=tuple(tuple(int(v) for v in b) for b in record["ignore_regions"]))
        for c in record["captures"]:
            frames = np.load(os.path.join(folder, os.path.basename(c["file"])), allow_pickle=False)
            if frame_shape is not None and tuple(frames.shape[1:]) != tuple(frame_shape):
                raise ValueError(f"its captures are {frames.shape[2]}×{frames.shape[1]} images, the camera now gives "
                                 f"{frame_shape[1]}×{frame_shape[0]}")
            session.captures.append(Capture(float(c["distance_m"]), list(frames), bool(c["held_back"]),
                                            _pose_from_json(c["pose"]), c["rangefinder_m"], c["exposure_us"],
                                            float(c.get("drift", 0.0))))
        return session
    except Exception as exc:  # a damaged session must not stop the daemon, nor be silently lost
        stem = f"{folder.rstrip(os.sep)}.unreadable-{time.strftime('%Y%m%dT%H%M%S')}"
        aside = next(p for p in (stem, *(f"{stem}-{n}" for n in range(1, 1000))) if not os.path.exists(p))
        log.warning("cannot resume the calibration session in %s (%s); moved it to %s", folder,
                    str(exc).splitlines()[0] if str(exc) else type(exc).__name__, aside)
        try:
            os.replace(folder, aside)
        except OSError:
            pass
        return None


def remove_session(folder: str) -> None:
    """Forget the kept session (after it is accepted or cancelled)."""
    shutil.rmtree(folder, ignore_errors=True)
