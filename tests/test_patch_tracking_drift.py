"""Live patch tracking where it matters: the simulated water drifts (its attenuation changes over
minutes, ``simulation.drift``), and the attenuation differences tracked from a patch of known
path length reach the estimator on the frame they are measured in, appear in that frame's
ranging record, and keep the range right where the calibration's values go wrong."""

from __future__ import annotations

import time

import numpy as np
import pytest

from tests.waiting import wait_for
from tests.queued_camera import QueuedCamera
from uwcam.config import PatchConfig, ProcessingConfig
from uwcam.drivers.base import Frame
from uwcam.drivers.sim import RigState, SimulatedRig
from uwcam.optics.geometry import pixel_rays
from uwcam.recording.records import ranging_record
from uwcam.runtime.pipeline import FramePipeline
from uwcam.ranging.estimator import RangeEstimator
from uwcam.simulation import CameraModel, Lamp, water_preset
from uwcam.simulation.options import check_simulation_options
from uwcam.simulation.tank import calibrate_in_simulation

SIZE = (160, 120)
DRIFT = (0.06, 0.02, 0.0)  # 1/m: red and green absorb more (a plume), blue as before
PERIOD_S = 240.0
BOX = (74, 54, 12, 12)  # the patch: grey seabed at the image centre


def test_drift_is_a_checked_option_of_static_scenes():
    assert check_simulation_options({"scene": "seabed", "drift": [0.05, 0.02, 0.0], "drift_period": 600})["drift"] == (0.05, 0.02, 0.0)
    with pytest.raises(ValueError, match="drift"):
        check_simulation_options({"scene": "seabed", "drift": [5.0, 0.0, 0.0]})
    with pytest.raises(ValueError, match="only to static scenes"):
        check_simulation_options({"scene": "survey", "drift": [0.05, 0.0, 0.0]})


@pytest.fixture(scope="module")
def drifting():
    """A grey seabed 3 m away in clear water (no scattering: the drift alone moves the range) that drifts, a profile calibrated in the undrifted
    water, and frames at rig times from the start to the drift's peak (lamp at 70 %: the patch, the
    brightest part of the view, stays clear of saturation)."""
    rig = SimulatedRig(scene="seabed", distance=3.0, size=SIZE, water="ideal", material="grey", drift=DRIFT,
                       drift_period=PERIOD_S, lamp_offset=(0.2, 0.0, 0.0))
    profile = calibrate_in_simulation(water_preset("ideal", [675.0, 575.0, 475.0]), Lamp(position=(0.2, 0.0, 0.0)),
                                      SIZE, CameraModel(), frames_per_distance=2)
    times = [0.0, 30.0, 60.0, 90.0, 110.0, 120.0, 120.1]
    frames = [rig.render(RigState(True, 0.7, t), k).copy() for k, t in enumerate(times)]  # render reuses its buffer
    truth = rig.world.camera_range
    # Lamp → patch → camera path length at the patch: the mean over its pixels.
    intr = profile.camera_intrinsics()
    x, y, w, h = BOX
    u = pixel_rays(intr, SIZE[1], SIZE[0])[y : y + h, x : x + w].reshape(-1, 3)
    dc = truth[y : y + h, x : x + w].reshape(-1)
    path = float(np.mean(dc + np.linalg.norm(dc[:, None] * u - np.array([0.2, 0.0, 0.0]), axis=-1)))
    return rig, profile, times, frames, truth, path


def run(profile, frames, processing):
    camera = QueuedCamera()
    pipeline = FramePipeline(camera, profile, processing)
    published = []
    pipeline.subscribe(published.append)
    pipeline.start()
    try:
        for k, data in enumerate(frames):  # one at a time: none is skipped as stale
            camera.put(Frame(data=data, sequence=k, host_monotonic_ns=time.monotonic_ns(), wall_time=time.time(),
                             lamp_on=True))
            assert wait_for(lambda: len(published) == k + 1, 60.0)
    finally:
        pipeline.stop()
    return published


def patch_estimate(profile, data, path):
    """c_k − c_ref from the patch's mean light, docs/physics.md §6, written out here."""
    x, y, w, h = BOX
    e = data[y : y + h, x : x + w].reshape(-1, 3).astype(np.float64).mean(axis=0) - profile.array("dark_level")
    ref = profile.reference_index
    v = (profile.array("log_constant") - (np.log(e) - np.log(e[ref]))) / path
    v[ref] = 0.0
    return v


@pytest.mark.slow
def test_tracked_values_reach_the_estimator_on_their_frame_and_its_record(drifting):
    rig, profile, times, frames, truth, path = drifting
    assert np.allclose(rig.water_change(120.0), DRIFT) and np.allclose(rig.water_change(0.0), 0.0)
    processing = ProcessingConfig(patch=PatchConfig(region=BOX, path_length_m=path, smoothing=1.0, max_step=1.0))
    tracked = run(profile, frames, processing)
    still = run(profile, frames, ProcessingConfig())

    # The profile knows the water's light: the loop subtracts it (uwcam.water.frame_compensator), so the
    # range these values give is the compensated one.
    from uwcam.water.frame_compensator import BackscatterCompensator, compensation
    from uwcam.ranging.estimator import range_frame

    comp = BackscatterCompensator(profile, frames[0].shape[:2], 2)
    for p, data in zip(tracked, frames):
        v = patch_estimate(profile, data, path)
        np.testing.assert_allclose(p.attenuation_differences, v, rtol=0, atol=1e-12)
        # The range of this frame is the one these values give, not the last frame's.
        est = RangeEstimator(profile)
        est.set_attenuation_differences(v)
        expected = range_frame(est, data, transform=compensation(comp, est), water=comp.water)
        assert np.array_equal(p.result.range, expected.range, equal_nan=True)
        record = ranging_record(p, profile, processing)
        np.testing.assert_allclose(record["attenuation_differences"], v, rtol=0, atol=1e-12)
    # The two last frames, 0.1 s apart, were measured apart: each frame carries its own values.
    assert tracked[-1].attenuation_differences != tracked[-2].attenuation_differences

    def error(p):
        return float(np.nanmedian(np.abs(p.result.range - truth) / truth))

    at_peak = [i for i, t in enumerate(times) if t >= 110.0]
    with_tracking = np.mean([error(tracked[i]) for i in at_peak])
    without = np.mean([error(still[i]) for i in at_peak])
    print(f"median |range error| at the drift's peak: {100 * with_tracking:.2f} % tracked, {100 * without:.2f} % not")
    assert abs(error(tracked[0]) - error(still[0])) < 0.01  # undrifted water: the same either way
    assert without > 4.0 * with_tracking, (with_tracking, without)

    # σ stays honest on the tracked values (the estimator's doubt is still the profile's): the
    # z-scores against the simulator's truth at every drift, the peak included.
    for t, p in zip(times, tracked):
        ok = np.isfinite(p.result.range) & (p.result.variance > 0)
        z = (p.result.range[ok] - truth[ok]) / np.sqrt(p.result.variance[ok])
        assert ok.mean() > 0.95 and abs(z.mean()) < 0.4 and 0.8 < z.std() < 1.5, (t, ok.mean(), z.mean(), z.std())
