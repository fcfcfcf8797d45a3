"""The calibration's share of the variance is computed on 8×8-pixel blocks, as docs/calibration.md
states (its accuracy and cost, which bench/bench_fusion.py prints, are quoted for that size)."""

from __future__ import annotations

import numpy as np

from tests.test_calibration_variance_weights import C, covariance_profile
from uwcam.ranging.estimator import RangeEstimator


def test_the_frames_share_is_computed_on_the_documented_8_pixel_blocks():
    profile = covariance_profile(read_noise=5.0, shot_gain=0.3)
    h, w = 64, 80  # 8 × 10 blocks of 8 pixels; blocks of 7 or 9 pixels would give another grid
    i, j = np.mgrid[0:h, 0:w]
    path = 2.0 + 6.0 * ((j / w) ** 2 + 0.5 * (i / h) ** 3)  # curved, so that block averages differ by size
    frame = 4e4 * np.exp(-C * path[..., None])
    est = RangeEstimator(profile)
    got = est(frame).common_variance
    np.testing.assert_array_equal(got, est.calibration_variance(frame, block=8))
    for other in (7, 9):  # the comparison can tell the block size
        assert np.abs(est.calibration_variance(frame, block=other) - got).max() > 1e-6 * got.max()
