"""The simulated rig's calibration and scene facts: the simulated water calibrated as a crew would
in a tank (grey plate at 1 m and 2 m), kept in the cache or shipped with uwcam, and where the
scene's calibration patch and its bracket appear in the image."""

from __future__ import annotations

import glob
import json
import logging
import os
from typing import TYPE_CHECKING

import numpy as np

from uwcam.calibration.fit import project_plate_box
from uwcam.config import DaemonConfig, PatchConfig
from uwcam.fileio import UserInputError
from uwcam.calibration.profile import CalibrationProfile, load_profile, save_profile

# The simulation (renderer, water models) is imported only where a simulated device is
# configured, so that a real rig does not carry it in memory.
if TYPE_CHECKING:
    from uwcam.drivers.sim import SimulatedRig

log = logging.getLogger(__name__)

SHIPPED_CALIBRATIONS = "calibrations"
"""Folder of :mod:`uwcam.simulation` holding the simulated calibrations that ship with uwcam
(the embedded default rig's), named by :func:`simulated_calibration_conditions`."""
CALIBRATION_RIG = "grey-plate-large-patch"
"""The built-in rig the simulated tank calibration images (see :func:`calibrate_simulated_water`)."""
CALIBRATION_WIDTH = 640
"""Simulated tank calibration renders the plate at most this wide (same field of view): the
physics does not depend on the pixel count, and start-up stays short."""
CALIBRATION_MIN_WIDTH = 160
"""...and at least this wide: the plate of :data:`CALIBRATION_RIG` at 2 m needs 80 pixels or more
across the view to leave plate pixels around its black patch (a camera of 64×48 has too few)."""
SIMULATED_CALIBRATIONS_KEPT = 8
"""Simulated calibrations kept in the cache folder (other rigs, other versions), newest first."""
PATCH_SCENES = ("seabed-patch", "survey")
"""Simulated scenes with the calibration patch (and its marker) on a bracket in view."""


def cache_dir() -> str:
    """Where uwcam keeps what it can compute again: $UWCAM_CACHE_DIR, else $XDG_CACHE_HOME/uwcam,
    else ~/.cache/uwcam."""
    if os.environ.get("UWCAM_CACHE_DIR"):
        return os.environ["UWCAM_CACHE_DIR"]
    return os.path.join(os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "uwcam")


def simulated_calibration_conditions(rig: SimulatedRig) -> str:
    """What a simulated calibration's physics depends on: the rig's water, lamp, image size and
    bit depth, and the calibration's own plate and image width (a short hash)."""
    import hashlib

    return hashlib.sha256(json.dumps({"water": rig.water, "lamp": [float(v) for v in rig.lamp_offset],
                                      "size": [int(v) for v in rig.size], "bits": int(rig.bits),
                                      "width": list(calibration_size(rig)), "plate": CALIBRATION_RIG}).encode()).hexdigest()[:16]


def simulated_calibration_key(rig: SimulatedRig) -> str:
    """The cache key of a simulated calibration: its conditions, and uwcam's own code and
    built-in rig files (a changed simulator never reuses an old result)."""
    import hashlib

    import uwcam
    from uwcam.calibration.rig import builtin_rig_path

    digest = hashlib.sha256(simulated_calibration_conditions(rig).encode())
    package = os.path.dirname(os.path.abspath(uwcam.__file__))
    sources = sorted(glob.glob(os.path.join(package, "**", "*.py"), recursive=True))
    sources += sorted(glob.glob(os.path.join(os.path.dirname(builtin_rig_path("grey-plate")), "*.yaml")))
    for path in sources:
        with open(path, "rb") as fh:
            digest.update(os.path.relpath(path, package).encode() + b"\0" + fh.read())
    return digest.hexdigest()[:24]


def shipped_calibration_path(rig: SimulatedRig) -> str:
    """Where uwcam ships the calibration of this rig's simulated water (it may not exist)."""
    from importlib import resources

    folder = resources.files("uwcam.simulation") / SHIPPED_CALIBRATIONS
    return str(folder / f"simulated-{simulated_calibration_conditions(rig)}.yaml")


def calibrate_simulated_water(rig: SimulatedRig) -> CalibrationProfile:
    """Calibrate in the rig's simulated water: the grey plate with a 20 cm black patch at its centre
    (the built-in rig :data:`CALIBRATION_RIG`) at 1 m and 2 m, with the rig's lamp, four frames at
    each distance as a crew would take (their differences give the temporal noise, so the reported σ
    is honest). Deterministic: the same rig and code give the same profile.

    The large patch is the plate docs/calibration.md gives for scattering water: a 10 cm patch
    collects enough of the plate's forward-scattered light to leave the green-blue attenuation
    difference about 3 % low in Jerlov II, and a seabed at 7 m ranged about 3 % long."""
    from uwcam.calibration.rig import builtin_rig_path, load_rig
    from uwcam.simulation import Lamp, water_preset
    from uwcam.simulation.camera import CameraModel
    from uwcam.simulation.tank import calibrate_in_simulation

    water = water_preset(rig.water, [675.0, 575.0, 475.0])
    # The plate's exposure is recorded (in the simulator's unit: electrons per unit radiance) so that
    # :func:`simulated_calibration` can say it in the rig camera's µs: the water's light the
    # calibration measured is then scaled to each frame's exposure, as for a real camera.
    return calibrate_in_simulation(water, Lamp(position=tuple(rig.lamp_offset)), calibration_size(rig),
                                   CameraModel(bits=rig.bits), seed_base=11, frames_per_distance=4, record_exposure=True,
                                   rig=load_rig(builtin_rig_path(CALIBRATION_RIG)))


def calibration_size(rig: SimulatedRig) -> tuple[int, int]:
    """(width, height) pixels of the simulated calibration's frames for ``rig``: the rig camera's
    field of view, from :data:`CALIBRATION_MIN_WIDTH` to :data:`CALIBRATION_WIDTH` wide (the
    camera's own size where it lies between: a larger one reduced by a whole factor)."""
    w, h = (int(v) for v in rig.size)
    if w < CALIBRATION_MIN_WIDTH:
        factor = CALIBRATION_MIN_WIDTH / w
        return CALIBRATION_MIN_WIDTH, max(int(round(h * factor)), 2)
    factor = max(1, -(-w // CALIBRATION_WIDTH))
    return max(w // factor, 2), max(h // factor, 2)


def in_rig_pixels(profile: CalibrationProfile, rig: SimulatedRig) -> CalibrationProfile:
    """``profile`` (calibrated at :func:`calibration_size`) with its black-patch pixels and
    intrinsics in the rig camera's pixels: the same field of view, sampled by another count of
    pixels (a pixel's centre x maps to (x + ½)·s − ½, s the ratio of the widths)."""
    intr = rig.world.intrinsics
    updates: dict = {"intrinsics": {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy}}
    if profile.backscatter is not None:
        (cw, ch), (w, h) = calibration_size(rig), (int(v) for v in rig.size)
        sx, sy = w / cw, h / ch
        pixels = [((x + 0.5) * sx - 0.5, (y + 0.5) * sy - 0.5) for x, y in profile.backscatter.patch_pixels]
        updates["backscatter"] = profile.backscatter.model_copy(update={"patch_pixels": pixels})
    return profile.model_copy(update=updates)


def ship_simulated_calibration(config: DaemonConfig) -> str:
    """Write the calibration of ``config``'s simulated water into the package (for uwcam's own
    developers, after a change to the simulator or the calibration); its path."""
    from uwcam.drivers.sim import SimulatedRig

    rig = SimulatedRig(**config.simulation)
    path = shipped_calibration_path(rig)
    save_profile(calibrate_simulated_water(rig), path)
    return path


def simulated_calibration(rig: SimulatedRig) -> CalibrationProfile:
    """The rig's simulated-water calibration (:func:`calibrate_simulated_water`); the profile's
    intrinsics are the rig camera's.

    The embedded default rig's ships with uwcam (tests/test_shipped_calibration.py checks it
    against a fresh one), so its first start ranges at once. Any other rig is calibrated at its
    first start (seconds) and kept in :func:`cache_dir`, keyed by :func:`simulated_calibration_key`."""
    shipped = shipped_calibration_path(rig)
    if os.path.exists(shipped):
        profile = load_profile(shipped)
        log.info("using the calibration of the simulated water that ships with uwcam")
    else:
        path = os.path.join(cache_dir(), f"simulated-calibration-{simulated_calibration_key(rig)}.yaml")
        try:
            profile = load_profile(path)
            log.info("using the calibration of the simulated water made at an earlier start (%s)", path)
        except UserInputError:  # not there yet, or unreadable: calibrate (again) and keep it
            log.info("calibrating in the simulated water (first start with this rig or uwcam version: seconds)")
            profile = calibrate_simulated_water(rig)
            try:
                os.makedirs(os.path.dirname(path), exist_ok=True)
                save_profile(profile, path)
                # Each new version of uwcam (or rig) keys its own file: keep only the newest few.
                kept = sorted(glob.glob(os.path.join(os.path.dirname(path), "simulated-calibration-*.yaml")),
                              key=os.path.getmtime, reverse=True)
                for old in kept[SIMULATED_CALIBRATIONS_KEPT:]:
                    os.remove(old)
            except OSError as exc:  # a read-only home: calibrate at every start, as before
                log.info("cannot keep the simulated calibration in %s (%s)", path, exc.strerror)
    profile = in_rig_pixels(profile, rig)
    return profile.model_copy(update={"channels": rig_exposures(profile, rig.world.exposure)})


def rig_exposures(profile: CalibrationProfile, world_exposure: float) -> list:
    """The channels of a simulated calibration with their exposure said in the simulated camera's µs.

    The simulated camera reports NOMINAL_EXPOSURE_US at its world's own auto-exposure
    (``world_exposure``, electrons per unit radiance, set by the scene), and the calibration recorded
    the plate's exposure in that unit: the plate was exposed NOMINAL_EXPOSURE_US × plate / world µs.
    Without it a frame's light could not be compared with the light the calibration measured (the
    water's own light, judged and subtracted per frame): the seabed at 2 m is exposed 4.7 times the
    plate, a scene with the bright patch bracket 0.69 times. A profile that did not record its
    exposure (calibrated before it was) is returned as it is."""
    from uwcam.drivers.sim import NOMINAL_EXPOSURE_US

    if any(c.exposure_us is None for c in profile.channels):
        return list(profile.channels)
    return [c.model_copy(update={"exposure_us": NOMINAL_EXPOSURE_US * c.exposure_us / world_exposure})
            for c in profile.channels]


def simulated_patch(rig: SimulatedRig) -> PatchConfig:
    """Where the calibration patch on the bracket appears (scenes seabed-patch and survey), and its path length."""
    from uwcam.simulation.scene import PATCH_CENTRE_M, PATCH_DISTANCE_M, PATCH_SIZE_M

    intr = rig.world.intrinsics
    x, y, w, h = project_plate_box(PATCH_CENTRE_M, (PATCH_SIZE_M, PATCH_SIZE_M), PATCH_DISTANCE_M, intr)
    inset = max(1, min(w, h) // 5)  # keep clear of the patch's blurred edges
    centre = np.array([*PATCH_CENTRE_M, PATCH_DISTANCE_M])
    path = float(np.linalg.norm(centre) + np.linalg.norm(centre - np.array(rig.lamp_offset)))
    return PatchConfig(region=(int(x + inset), int(y + inset), int(w - 2 * inset), int(h - 2 * inset)), path_length_m=path)


def simulated_vehicle_mask(rig: SimulatedRig) -> list[tuple[int, int, int, int]]:
    """The bracket carrying the calibration patch and its marker plate (scenes seabed-patch and
    survey), as one box with a margin for the blur of its edges in the water."""
    from uwcam.simulation.scene import (MARKER_CENTRE_M, MARKER_SIDE_M, PATCH_CENTRE_M, PATCH_DISTANCE_M,
                                        PATCH_SIZE_M)

    marker_half, patch_half = 0.75 * MARKER_SIDE_M, PATCH_SIZE_M / 2  # the marker plate has a quiet zone
    x0 = min(MARKER_CENTRE_M[0] - marker_half, PATCH_CENTRE_M[0] - patch_half)
    x1 = max(MARKER_CENTRE_M[0] + marker_half, PATCH_CENTRE_M[0] + patch_half)
    y0 = min(MARKER_CENTRE_M[1] - marker_half, PATCH_CENTRE_M[1] - patch_half)
    y1 = max(MARKER_CENTRE_M[1] + marker_half, PATCH_CENTRE_M[1] + patch_half)
    x, y, w, h = project_plate_box(((x0 + x1) / 2, (y0 + y1) / 2), (x1 - x0, y1 - y0), PATCH_DISTANCE_M, rig.world.intrinsics)
    margin = max(2, round(0.01 * rig.size[0]))
    return [(max(x - margin, 0), max(y - margin, 0), w + 2 * margin, h + 2 * margin)]
