"""The frame loop scales the water's light it subtracts to each frame's exposure, or refuses the
frame: a frame that says its exposure, ranged with the backscatter of a calibration whose exposure
is unknown, got the water's light of another exposure subtracted and ranged 19–80 % short, every
pixel valid (#41)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from tests.queued_camera import QueuedCamera
from tests.waiting import wait_for
from uwcam.config import ProcessingConfig
from uwcam.drivers.base import Frame
from uwcam.runtime.pipeline import FramePipeline
from uwcam.simulation import CameraModel, Lamp, SimulatedWorld, water_preset
from uwcam.simulation.tank import calibrate_in_simulation

SIZE = (160, 120)
WATER = water_preset("jerlov-II", [675.0, 575.0, 475.0])
LAMP = Lamp(position=(0.3, 0.0, 0.0))


def run_frames(profile, frames_and_exposures, open_water=None):
    """Feed the frames (data, exposure µs or None) to a frame loop one at a time; (published, unranged
    reasons, the backscatter status after the last)."""
    camera = QueuedCamera()
    pipeline = FramePipeline(camera, profile, ProcessingConfig(backscatter=None, smoothing="none"))
    if open_water is not None:
        pipeline.set_open_water(*open_water)
    published, unranged = [], []
    pipeline.subscribe(published.append)
    pipeline.subscribe_unranged(lambda frame, why: unranged.append(why))
    pipeline.start()
    try:
        for k, (data, exposure) in enumerate(frames_and_exposures):
            camera.put(Frame(data=data.copy(), sequence=k, host_monotonic_ns=time.monotonic_ns(),
                             wall_time=time.time(), lamp_on=True, exposure_us=exposure))
            assert wait_for(lambda: len(published) + len(unranged) == k + 1, 60.0)
        return published, unranged, pipeline.backscatter_status()
    finally:
        pipeline.stop()


def test_a_frame_whose_exposure_the_calibration_cannot_be_related_to_is_not_ranged():
    unrecorded = calibrate_in_simulation(WATER, LAMP, SIZE, CameraModel(), frames_per_distance=2)
    recorded = calibrate_in_simulation(WATER, LAMP, SIZE, CameraModel(), frames_per_distance=2, record_exposure=True)
    assert unrecorded.calibration_exposure()[0] is None and recorded.calibration_exposure()[0] is not None
    scene = SimulatedWorld(scene="seabed", distance=3.0, size=SIZE, water=WATER, lamp=LAMP, camera=CameraModel(),
                           material="grey", seed=5)
    frame = scene.frame(0)
    # The camera says its exposure, the profile's calibration does not: refused, and the status says why.
    published, unranged, status = run_frames(unrecorded, [(frame, 1000.0)])
    assert not published and unranged == ["exposure unknown to the backscatter model"]
    assert "--exposure-us" in status["refused"] and "open-water" in status["refused"]
    # A camera that does not say its exposure: taken as the calibration's, as before.
    published, unranged, status = run_frames(unrecorded, [(frame, None)])
    assert len(published) == 1 and not unranged and status["refused"] is None
    # A profile that records it (in the simulator's unit of exposure, as the scene's): scaled, ranged.
    published, unranged, status = run_frames(recorded, [(frame, scene.exposure)])
    assert len(published) == 1 and not unranged and status["refused"] is None
    ratio = scene.exposure / recorded.calibration_exposure()[0]
    assert published[0].light_scale == pytest.approx(tuple(ratio))
    assert np.isfinite(published[0].result.range).mean() > 0.5
    # An open-water frame of unknown exposure cannot relate it either.
    water = SimulatedWorld(scene="open-water", distance=3.0, size=SIZE, water=WATER, lamp=LAMP, camera=CameraModel(),
                           fixed_exposure=scene.exposure, seed=6).frame(0).astype(np.float32)
    published, unranged, status = run_frames(unrecorded, [(frame, 1000.0)], open_water=(water, {}))
    assert not published and "open-water frame does not" in status["refused"]
    published, unranged, status = run_frames(unrecorded, [(frame, 1000.0)], open_water=(water, {"exposure": [1000.0] * 3}))
    assert len(published) == 1 and status["refused"] is None

