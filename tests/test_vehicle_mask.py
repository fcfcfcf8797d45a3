"""The vehicle in view (the patch's bracket): no range there, never an obstacle.

The default simulated rig carries the calibration patch and its marker plate on a bracket
0.8 m in front of the camera, in a seabed 2 m away. Without a mask the bracket is the nearest
"surface" in every frame: the page's minimum range and an autopilot's obstacle distance would
read 0.8 m whatever the vehicle does.
"""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from tests.test_mavlink import SEABED_M, Listener, rig_config
from tests.waiting import wait_for
from uwcam.config import ProcessingConfig
from uwcam.runtime.daemon import Daemon
from uwcam.optics.validity import Reason
from uwcam.ranging.result import RangeResult
from uwcam.ranging.estimator import mask_vehicle


def test_mask_marks_its_boxes_clipped_to_the_image_and_nothing_else():
    h, w = 6, 8
    result = RangeResult(np.full((h, w), 2.0, np.float32), np.full((h, w), 1e-4, np.float32), np.zeros((h, w), np.uint8))
    mask_vehicle(result, [(1, 2, 2, 3), (6, 4, 10, 10)])  # the second runs off the image's corner
    expected = np.zeros((h, w), bool)
    expected[2:5, 1:3] = True
    expected[4:, 6:] = True
    assert np.array_equal(result.reasons == 6, expected) and int(Reason.VEHICLE) == 6
    assert np.all(np.isnan(result.range[expected])) and np.all(np.isnan(result.variance[expected]))
    assert np.all(result.range[~expected] == 2.0) and np.all(result.reasons[~expected] == 0)


@pytest.mark.parametrize("mask", [[[-1, 0, 4, 4]], [[0, 0, 0, 4]], [[0, 0, 4.5, 4]], [[0, 0, 4]], [[0, 0, 1, 1]] * 65])
def test_bad_masks_are_refused(mask):
    with pytest.raises(ValidationError):
        ProcessingConfig.model_validate({"vehicle_mask": mask})


@pytest.mark.slow
def test_default_rig_masks_the_bracket_so_minimum_distance_is_the_seabed():
    """DISTANCE_SENSOR's minimum over the whole image: the seabed (2 m), not the bracket (0.8 m);
    with the mask cleared live, the bracket is back (so the mask, not luck, kept it out)."""
    with Listener() as ear:
        d = Daemon(rig_config(ear.port, region=None, orientation="PITCH_270", statistic="minimum"))
        try:
            d.start()
            assert wait_for(lambda: len(ear.of("DISTANCE_SENSOR")) > 3, 30.0)
            published = d.pipeline.latest
            truth = d.rig.world.camera_range
            masked = ear.of("DISTANCE_SENSOR")[-1].current_distance
            mask = d.pipeline.processing.vehicle_mask
            d.pipeline.reconfigure(d.pipeline.processing.model_copy(update={"vehicle_mask": []}))
            start = len(ear.of("DISTANCE_SENSOR"))
            assert wait_for(lambda: len(ear.of("DISTANCE_SENSOR")) > start + 3, 30.0)
            unmasked = ear.of("DISTANCE_SENSOR")[-1].current_distance
        finally:
            d.stop()
    bracket = truth < 1.0  # the simulator's own geometry: where the rays end on the bracket
    reasons = published.result.reasons
    assert bracket.sum() > 50 and mask
    assert np.all(reasons[bracket] == Reason.VEHICLE), "a bracket pixel escaped the mask"
    assert (reasons == Reason.VEHICLE).sum() < 3 * bracket.sum(), "the mask swallows much more than the bracket"
    assert np.nanpercentile(published.result.range, 1) > 1.5  # single noisy corner pixels may read short
    # The seabed is 2 m along the axis everywhere; the smallest tile median comes from a corner,
    # where the simulated ranging reads up to ~15 % short (see tests/test_mavlink.py).
    assert 0.8 * 100 * SEABED_M < masked <= 1.05 * 100 * SEABED_M
    assert unmasked < 100


def test_range_frame_masks_before_smoothing_so_the_vehicle_lends_no_range():
    from tests.synthetic import RGB_ATTENUATION, make_profile
    from uwcam.ranging.estimator import RangeEstimator, range_frame

    def light(path_m):  # a grey surface at this lamp → surface → camera path
        e = np.exp(np.log([0.6, 1.0, 0.9]) - RGB_ATTENUATION * path_m)
        return 3000.0 * e / e.max()

    frame = np.full((6, 8, 3), light(4.0), np.float32)
    frame[:, :2] = light(1.6)  # the bracket, nearer
    est = RangeEstimator(make_profile(RGB_ATTENUATION, np.log([0.6, 1.0, 0.9]), read_noise=2.0), calibration_variance=False)
    plain = range_frame(est, frame, "mean", "after")
    masked = range_frame(est, frame, "mean", "after", vehicle_mask=[(0, 0, 2, 6)])
    assert np.all(masked.reasons[:, :2] == Reason.VEHICLE) and np.all(np.isnan(masked.range[:, :2]))
    # Next to the bracket, the mean no longer mixes in its (shorter) range.
    assert np.allclose(masked.range[:, 2:], masked.range[0, 5], rtol=1e-5)
    assert np.all(plain.range[:, 2] < masked.range[:, 2] - 1e-3)
