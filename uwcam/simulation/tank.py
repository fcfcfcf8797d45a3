"""Calibrating in simulated water, as a crew would in a tank: the grey rig plate (with its
black patch) at known distances, one fixed exposure, plate and patch found by projection."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from uwcam.calibration.fit import CalibrationInputs, calibrate, project_plate_box
from uwcam.calibration.profile import CalibrationProfile
from uwcam.calibration.rig import Rig, builtin_rig_path, load_rig
from uwcam.simulation.camera import CameraModel
from uwcam.simulation.render import Lamp
from uwcam.simulation.water import Water
from uwcam.simulation.world import Channels, SimulatedWorld


def calibrate_in_simulation(
    water: Water,
    lamp: Lamp,
    size: tuple[int, int],
    camera: CameraModel | None = None,
    *,
    gate_width: float | None = None,
    noise_free: bool = False,
    distances: tuple[float, ...] = (1.0, 2.0),
    seed_base: int = 0,
    channels: Channels | None = None,
    name: str = "simulated tank calibration",
    frames_per_distance: int = 1,
    record_exposure: bool = False,
    linearise: bool = True,
    rig: Rig | None = None,
) -> CalibrationProfile:
    """A calibration profile from the grey plate at ``distances`` (m) in ``water``.

    camera: its peak_code (auto-exposure target) defaults to 70 % of full scale so the flat
    plate does not clip; the first plate's exposure is then held for the others (absolute
    attenuation needs that). noise_free: use expected values instead of noisy frames.
    Frame k at distance d uses seed ``seed_base + int(d)``. frames_per_distance: noisy frames
    taken at each distance (averaged by the calibration, their differences give the temporal noise).
    linearise: for a camera with a tone curve, calibrate on frames linearised through it and keep
    the curve in the profile (False: take its codes as linear, the mistake the curve corrects).
    rig: the plate imaged (its size and black patch); None: the built-in grey plate.
    record_exposure: record the held exposure in the profile as each channel's ``exposure_us``,
    in the simulator's unit (electrons per unit radiance, the unit of :attr:`SimulatedWorld.exposure`):
    frames of worlds exposed differently are then ranged with their exposure in the same unit.
    """
    if frames_per_distance < 1:
        raise ValueError(f"frames_per_distance must be at least 1, got {frames_per_distance}")
    channels = channels or Channels()
    camera = camera or CameraModel()
    if camera.peak_code is None:
        camera = replace(camera, peak_code=0.7 * 2**camera.bits)
    plate = rig or load_rig(builtin_rig_path("grey-plate"))
    frames, exposure, at = [], None, []
    for d in distances:
        world = SimulatedWorld(scene="plate", distance=d, size=tuple(size), channels=channels, water=water, lamp=lamp,
                               camera=camera, gate_width=gate_width, fixed_exposure=exposure, seed=seed_base + int(d),
                               rig=plate)
        exposure = world.exposure
        for k in range(1 if noise_free else frames_per_distance):
            frames.append(world.noise_free_frame() if noise_free else world.frame(k))
            at.append(d)
    intr, patch = world.intrinsics, plate.plate.black_patch
    n = len(channels.names)
    curve = None
    if camera.response != "linear" and linearise:  # a gamma camera is calibrated on linearised frames (uwcam.imaging.response)
        from uwcam.imaging.response import ResponseCurve

        curve = ResponseCurve.standard(camera.response, camera.bits, n)
        frames = [f if noise_free else curve.linearise(f) for f in frames]
    profile = calibrate(frames, at, CalibrationInputs(
        channel_names=list(channels.names), wavelengths_nm=list(channels.wavelengths_nm),
        target_reflectance=np.full(n, 0.18), black_reflectance=np.full(n, 0.03),
        lamp_position_m=tuple(lamp.position), intrinsics=intr,
        target_boxes=[project_plate_box((0, 0), plate.plate.size_m, d, intr) for d in at],
        black_boxes=[project_plate_box(patch.centre_m, patch.size_m, d, intr) for d in at],
        dark_level=np.full(n, world.camera.dark_level_dn), saturation_level=2**camera.bits - 1,
        lamp_radius_m=lamp.effective_radius, name=name, target_description="grey plate in the simulated water",
        quantisation_step=0.0 if curve is not None else 1.0,
    ))
    if curve is not None:
        from uwcam.calibration.profile import ResponseRecord

        profile = profile.model_copy(update={"response": ResponseRecord(**curve.to_record())})
    if not record_exposure:
        return profile
    return profile.model_copy(update={"channels": [c.model_copy(update={"exposure_us": float(exposure)})
                                                   for c in profile.channels]})
