"""The noise floor and backscatter samples a calibration with a black patch stores, recomputed here
from what it measured (the fitted noise model, the patch's backscatter and black levels) with the
formulas of docs/physics.md written out: σ² = read² + gain·E + (fpn·E)² (+ step²/12), floor =
max over distances of (backscatter⁺ + 3σ of the black patch's signal)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.test_calibration import INTR, PLATE, frames, inputs
from uwcam.calibration.fit import calibrate_with_details, project_plate_box
from uwcam.calibration.black_patch import backscatter_at_black_patch


def test_black_patch_floor_and_samples_are_those_of_the_measured_levels():
    rng = np.random.default_rng(3)
    distances = [1.0, 2.0]
    black_rho = 0.02
    boxes = [project_plate_box((0.1, 0.1), (0.12, 0.12), d, INTR) for d in distances]
    out = []
    for f, box in zip(frames(distances), boxes):
        x, y, w, h = box
        f[y : y + h, x : x + w] *= black_rho / PLATE
        # Backscatter-like offset, pixel noise, and a fixed pattern (1 % of the signal, per pixel).
        f *= 1.0 + 0.01 * np.random.default_rng(9).standard_normal(f.shape[:2])[..., None]
        f += 30.0 + 2.0 * rng.standard_normal(f.shape)
        out.append(f)
    details = calibrate_with_details(out, distances, inputs(black_boxes=boxes, black_reflectance=np.full(3, black_rho)))
    noise = details.noise
    assert np.all(noise.fixed_pattern > 0)
    levels = np.array([g.backscatter.level for g in details.groups])
    blacks = np.array([g.backscatter.black_mean for g in details.groups])
    sigma = np.sqrt(noise.read_noise**2 + noise.shot_gain * blacks + (noise.fixed_pattern * blacks) ** 2)
    np.testing.assert_allclose(details.profile.array("noise_floor"), (np.maximum(levels, 0) + 3 * sigma).max(axis=0), rtol=1e-9)
    samples = details.profile.backscatter
    np.testing.assert_allclose(samples.patch_pixels, [(x + w / 2 - 0.5, y + h / 2 - 0.5) for x, y, w, h in boxes])
    for k, name in enumerate(["R", "G", "B"]):
        np.testing.assert_allclose(samples.levels[name], np.maximum(levels[:, k], 0), rtol=1e-12)
        assert samples.noise_sigma[name] == pytest.approx(np.max(sigma[:, k]), rel=1e-9)
    # Each patch's backscatter variance follows from the per-pixel variance of the distance's
    # mean frame: temporal noise (one frame here) plus the fixed pattern squared.
    for g in details.groups:
        e = np.maximum(g.mean_frame, 0)
        pixel_var = noise.read_noise**2 + noise.shot_gain * e + (noise.fixed_pattern * e) ** 2
        expected = backscatter_at_black_patch(g.mean_frame, g.black, g.target, np.full(3, black_rho), PLATE, pixel_var)
        np.testing.assert_allclose(g.backscatter.variance, expected.variance, rtol=1e-9)


def test_exactly_one_percent_of_saturated_target_pixels_is_accepted_and_more_refused():
    from uwcam.calibration.fit import calibrate
    from uwcam.fileio import UserInputError

    box = (40, 30, 10, 10)  # 100 target pixels
    out = frames([1.0, 2.0])
    level = 1e6
    out[0][35, 45, 1] = level  # one pixel of 100 at the saturation level: 1 %, not more
    calibrate(out, [1.0, 2.0], inputs(target_box=box, saturation_level=level))
    out[0][36, 45, 1] = level + 1
    with pytest.raises(UserInputError, match="2% of the target region of image 1 is saturated in channel G"):
        calibrate(out, [1.0, 2.0], inputs(target_box=box, saturation_level=level))


def test_a_target_too_small_for_noise_is_named_by_its_image_or_by_its_distance():
    from uwcam.calibration.fit import calibrate
    from uwcam.fileio import UserInputError

    box = (40, 30, 2, 2)
    single = frames([1.0, 2.0])
    with pytest.raises(UserInputError, match="the target region of image 1 is too small"):
        calibrate(single, [1.0, 2.0], inputs(target_box=box))
    repeated = frames([1.0, 1.0, 2.0])
    with pytest.raises(UserInputError, match="the target region of 2 images at 1 m is too small"):
        calibrate(repeated, [1.0, 1.0, 2.0], inputs(target_box=box))


def frames_with_black_patch(distances):
    """Plate frames at these distances with a black patch (reflectance 0.02) in view, and its box per frame."""
    boxes = [project_plate_box((0.1, 0.1), (0.12, 0.12), d, INTR) for d in distances]
    out = []
    for f, (x, y, w, h) in zip(frames(distances), boxes):
        f[y : y + h, x : x + w] *= 0.02 / PLATE
        out.append(f)
    return out, boxes


def test_noise_free_frames_with_a_black_patch_and_no_backscatter_fit_the_whole_plate_at_the_floor():
    """No backscatter and no noise: nothing is measured at the patch (the level is 0 to rounding,
    below 0.1 % of the plate's light), so the whole plate is fitted; with no pixel noise each
    distance's log variance is the quantisation floor, (1/12)/E² of its mean signal."""
    distances = [1.0, 2.0]
    out, boxes = frames_with_black_patch(distances)
    details = calibrate_with_details(out, distances, inputs(black_boxes=boxes, black_reflectance=np.full(3, 0.02),
                                                            quantisation_step=1.0))
    assert "whole plate" in details.profile.provenance.method
    for g in details.groups:
        np.testing.assert_allclose(g.log_variance, (1 / 12) / np.exp(g.log_signal) ** 2, rtol=1e-9)


def test_without_intrinsics_the_path_is_taken_along_the_optical_axis():
    """No intrinsics: every pixel on the axis, d_T = d + |(0, 0, d) − S| for a lamp at S."""
    from uwcam.calibration.fit import calibrate_with_details as details_of

    lamp = np.array(inputs().lamp_position_m)  # the frames' lamp, beside the camera
    assert np.any(lamp)
    distances = [1.0, 2.0]
    details = details_of(frames(distances), distances, inputs(intrinsics=None))
    for g, d in zip(details.groups, distances):
        assert g.path_length_m == pytest.approx(d + np.linalg.norm(np.array([0.0, 0.0, d]) - lamp), rel=1e-12)


def test_each_distances_log_variance_is_the_noise_of_its_pixels_written_out():
    """Whole-plate fit, noisy frames, a target box: Var(mean ln E) = Σ share_p² σ_p²/E_p², with
    share_p = (boxes of fitted pixels holding p)/(25·P) and E_p each pixel's expected signal, the
    mean of the target's pixels in its 5×5 box (the box clipped to the target, near its edges)."""
    rng = np.random.default_rng(6)
    distances = [1.0, 2.0]
    box = (30, 20, 40, 30)
    out = frames(distances, noise=(4.0, 0.3), rng=rng)
    details = calibrate_with_details(out, distances, inputs(target_box=box))
    noise = details.noise
    for g in details.groups:
        target, used = g.target, g.fit_pixels
        count = used.sum()
        h, w = target.shape
        share = np.zeros((h, w))
        for i, j in zip(*np.nonzero(used)):
            share[max(i - 2, 0) : i + 3, max(j - 2, 0) : j + 3] += 1.0 / (25 * count)
        total = 0.0
        for i, j in zip(*np.nonzero(share)):
            rows, cols = slice(max(i - 2, 0), i + 3), slice(max(j - 2, 0), j + 3)
            e = g.mean_frame[rows, cols][target[rows, cols]].mean(axis=0)
            var = noise.read_noise**2 + noise.shot_gain * e + (noise.fixed_pattern * e) ** 2
            total = total + share[i, j] ** 2 * var / e**2
        assert target[share > 0].all() and (share > 0).sum() > count  # boxes reach the target's edge
        np.testing.assert_allclose(g.log_variance, total, rtol=1e-6)


def test_a_black_patch_needs_both_its_boxes_and_its_reflectance_to_count():
    """Boxes without a reflectance (or a reflectance without boxes): no backscatter is measured,
    no floor is set, and the patch's pixels (if boxed) are still kept out of the plate's fit."""
    distances = [1.0, 2.0]
    out, boxes = frames_with_black_patch(distances)
    boxed = calibrate_with_details(out, distances, inputs(black_boxes=boxes))
    assert all(g.backscatter is None for g in boxed.groups) and boxed.profile.backscatter is None
    x, y, w, h = boxes[0]
    assert not boxed.groups[0].target[y : y + h, x : x + w].any()
    assert np.all(boxed.profile.array("noise_floor") == 0)
    reflectance_only = calibrate_with_details(out[:1] + out[1:], distances, inputs(black_reflectance=np.full(3, 0.02)))
    assert all(g.backscatter is None for g in reflectance_only.groups)


def test_noise_points_are_named_by_distance_and_brightness_level_and_clipped_pixels_left_out():
    out = frames([1.0, 2.0])
    level = 1e6
    out[0][40, 60, 2] = level  # exactly at the saturation level: clipped
    details = calibrate_with_details(out, [1.0, 2.0], inputs(saturation_level=level))
    names = [name for name, _ in details.noise_points]
    assert names[:4] == [f"plate 1 m, level {j}" for j in (1, 2, 3, 4)]
    assert not details.groups[0].target[40, 60] and details.groups[0].target[40, 61]


def test_frames_without_channels_say_they_have_one():
    from uwcam.calibration.fit import calibrate
    from uwcam.fileio import UserInputError

    with pytest.raises(UserInputError, match=r"image 1 has 1 channel\(s\) but calibration expects 3"):
        calibrate([np.ones((4, 6)), np.ones((4, 6, 3))], [1.0, 2.0], inputs())


def test_each_black_patch_levels_standard_deviation_matches_the_spread_of_repeated_calibrations():
    """``backscatter.level_std`` says how far each patch level moves with the frames' noise: twelve
    calibrations of the same simulated water with other noise spread their levels by that much
    (within a factor of 1.6 either way, each channel and distance; twelve draws know a spread to ±20 %)."""
    from uwcam.simulation import CameraModel, Lamp, water_preset
    from uwcam.simulation.tank import calibrate_in_simulation

    water = water_preset("jerlov-II", [675.0, 575.0, 475.0])
    levels, stds = [], []
    for seed in range(0, 120, 10):
        p = calibrate_in_simulation(water, Lamp(position=(0.3, 0.0, 0.0)), (160, 120), CameraModel(),
                                    frames_per_distance=2, seed_base=seed)
        levels.append([p.backscatter.levels[k] for k in p.channel_names])
        stds.append([p.backscatter.level_std[k] for k in p.channel_names])
    ratio = np.mean(stds, axis=0) / np.std(levels, axis=0, ddof=1)
    assert np.all((ratio > 1 / 1.6) & (ratio < 1.6)), ratio
