"""The backscatter model's share of a compensated range's variance is common to neighbouring
pixels (one smooth level per block, the same in every frame): a 3×3 mean of the range map must
not divide it by nine. Checked against the model's share found the long way, pixel by pixel at
full resolution (ranged with and without the model's uncertainty), not by the compensator's own
estimate on the reduced frame."""

from __future__ import annotations

import numpy as np
import pytest

from uwcam.ranging.smoothing import smooth_range_map
from uwcam.simulation import CameraModel, Lamp, SimulatedWorld, water_preset
from uwcam.simulation.tank import calibrate_in_simulation
from uwcam.water import frame_compensator
from uwcam.water.frame_compensator import BackscatterCompensator

SIZE = (160, 120)


@pytest.fixture(scope="module")
def seabed():
    """Jerlov II, lamp 0.3 m aside, a grey seabed at 5 m: (profile, frame, 8 open-water frames, truth)."""
    water, lamp, camera = water_preset("jerlov-II", [675.0, 575.0, 475.0]), Lamp(position=(0.3, 0.0, 0.0)), CameraModel()
    profile = calibrate_in_simulation(water, lamp, SIZE, camera, frames_per_distance=2)
    scene = SimulatedWorld(scene="seabed", distance=5.0, size=SIZE, water=water, lamp=lamp, camera=camera,
                           material="grey", seed=5)
    view = SimulatedWorld(scene="open-water", distance=5.0, size=SIZE, water=water, lamp=lamp, camera=camera,
                          fixed_exposure=scene.exposure, seed=6)
    return profile, scene.frame(0), np.stack([view.frame(i) for i in range(8)]), scene.camera_range


def ranged(profile, frame, open_water, monkeypatch, uncertainty=None, tail=None):
    if uncertainty is not None:
        monkeypatch.setattr(frame_compensator, "OPEN_WATER_UNCERTAINTY", uncertainty)
    if tail is not None:
        monkeypatch.setattr(frame_compensator, "OPEN_WATER_TAIL_UNCERTAINTY", tail)
    comp = BackscatterCompensator(profile, frame.shape[:2], 2, open_water, path_length_bounds=(0.0, 100.0))
    est = comp.estimator
    return comp.range(frame, est.attenuation, est.log_constant)


def test_the_models_share_is_common_and_a_mean_keeps_it(seabed, monkeypatch):
    """With a model doubted enough to matter (2 % of its level, as uwcam took until it counted
    the open water's own level and the share beyond the surface apart), the share found on the
    reduced frame is the one found pixel by pixel; both the relative doubt and the share beyond the
    surface's (a variance per pixel) are in it."""
    profile, frame, open_water, truth = seabed
    doubted = ranged(profile, frame, open_water, monkeypatch, uncertainty=0.02)
    exact = ranged(profile, frame, open_water, monkeypatch, uncertainty=0.0, tail=0.0)
    both = np.isfinite(doubted.range) & np.isfinite(exact.range)
    assert both.mean() > 0.5
    model = (doubted.variance - exact.variance)[both]
    calibration = exact.common_variance[both]
    share = doubted.common_variance[both] - calibration
    assert np.median(model / doubted.variance[both]) > 0.3  # the model's doubt matters here
    ratio = share / model
    # Found on the reduced frame and interpolated: within 9 % of it (10th–90th percentile) here.
    assert 0.9 < np.median(ratio) < 1.1 and np.percentile(ratio, 10) > 0.8, np.percentile(ratio, [10, 50, 90])
    # A 3×3 mean keeps the common share whole and divides only the rest.
    smoothed = smooth_range_map(doubted, "mean")
    inner = both.copy()
    inner[:2], inner[-2:], inner[:, :2], inner[:, -2:] = False, False, False, False
    assert np.all(smoothed.variance[inner] >= smoothed.common_variance[inner] * (1 - 1e-5))
    # The share is smooth across the view: the neighbours' (fully correlated) shares average to the pixel's own.
    kept = smoothed.common_variance[inner] / doubted.common_variance[inner]
    assert 0.95 < np.median(kept) < 1.05 and np.percentile(kept, 1) > 0.8, np.percentile(kept, [1, 50, 99])
