"""Adaptive spatial windows (``smoothing: adaptive``): on the simulator's scenes, against its true
range of every pixel — σ stays honest, the far and dark parts keep a range, pixels already within
the target are untouched, and a range step is not smeared. The window means are checked against a
plain loop over windows written apart from the code."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from uwcam.api.settings import ProcessingPatch
from uwcam.cli import main
from uwcam.calibration.profile import save_profile
from uwcam.config import ProcessingConfig
from uwcam.optics.validity import Reason
from uwcam.ranging.adaptive import window_light
from uwcam.ranging.images import range_images
from uwcam.simulation import CameraModel, Lamp, SimulatedWorld, water_preset
from uwcam.simulation.tank import calibrate_in_simulation

SIZE = (160, 120)
WATER = water_preset("jerlov-II", [675.0, 575.0, 475.0])
LAMP = Lamp(position=(0.3, 0.0, 0.0))
FAR = 6.0
"""A grey seabed this far (m) in jerlov-II is dark: most single pixels' σ is above 2 % of the range."""
NEAR = 3.0


@pytest.fixture(scope="module")
def profile():
    return calibrate_in_simulation(WATER, LAMP, SIZE, CameraModel(), frames_per_distance=2)


def world(distance: float, exposure: float | None = None, seed: int = 5, scene: str = "seabed") -> SimulatedWorld:
    return SimulatedWorld(scene=scene, distance=distance, size=SIZE, water=WATER, lamp=LAMP, camera=CameraModel(),
                          material="grey", seed=seed, fixed_exposure=exposure)


def open_water(exposure: float) -> np.ndarray:
    return SimulatedWorld(scene="open-water", distance=4.0, size=SIZE, water=WATER, lamp=LAMP, camera=CameraModel(),
                          fixed_exposure=exposure, seed=6).frame(0)


@pytest.fixture(scope="module")
def far_scene(profile):
    """The far seabed's frames (several, for statistics), its truth, its open water, and its ranging
    with no smoothing, 3×3 mean and adaptive windows (2 % target)."""
    scene = world(FAR)
    water = open_water(scene.exposure)
    frames = [scene.frame(k) for k in range(3)]
    results = {kind: [range_images(profile, [f], smoothing=kind, open_water=water) for f in frames]
               for kind in ("none", "mean", "adaptive")}
    return scene.camera_range, frames, water, results


def pooled(results, truth):
    r = np.stack([x.range for x in results]).astype(np.float64)
    v = np.stack([x.variance for x in results]).astype(np.float64)
    t = np.broadcast_to(truth, r.shape)
    on = np.isfinite(r) & np.isfinite(t)
    return r, v, t, on


@pytest.mark.slow
def test_sigma_stays_honest_with_adaptive_windows(far_scene):
    truth, _, _, results = far_scene
    r, v, t, on = pooled(results["adaptive"], truth)
    z = (r[on] - t[on]) / np.sqrt(v[on])
    assert on.sum() > 0.5 * np.isfinite(t).sum()
    assert 0.8 <= np.std(z) <= 1.25, np.std(z)
    assert np.mean(np.abs(z) > 3.0) <= 0.02, np.mean(np.abs(z) > 3.0)


@pytest.mark.slow
def test_the_far_dark_seabed_keeps_more_pixels_and_reaches_the_target(far_scene):
    truth, _, _, results = far_scene
    surface = np.isfinite(truth)
    valid = {k: np.mean([np.isfinite(x.range)[surface].mean() for x in results[k]]) for k in results}
    assert valid["adaptive"] > valid["none"] + 0.1, valid
    r, v, t, on = pooled(results["adaptive"], truth)
    reached = np.sqrt(v[on]) <= 0.02 * r[on] * (1 + 1e-6)
    assert reached.mean() > 0.9, reached.mean()
    # And the range is better for it: rms error against the truth smaller than without windows.
    rms = {}
    for k in ("none", "adaptive"):
        rk, _, tk, onk = pooled(results[k], truth)
        rms[k] = np.sqrt(np.mean((rk[onk] / tk[onk] - 1) ** 2))
    assert rms["adaptive"] < 0.5 * rms["none"], rms


@pytest.mark.slow
def test_pixels_already_within_the_target_are_unchanged_bit_for_bit(profile, far_scene):
    _, frames, water, results = far_scene
    single = results["none"][0]
    rel = np.sqrt(single.variance) / single.range
    target = float(np.nanpercentile(rel, 40))  # some pixels settled, more not
    adaptive = range_images(profile, [frames[0]], smoothing="adaptive", smoothing_target=target, open_water=water)
    settled = np.isfinite(single.range) & (single.variance.astype(np.float64) <= (target * single.range.astype(np.float64)) ** 2)
    assert 0.2 < settled.mean() < 0.6, settled.mean()
    for a, b in ((adaptive.range, single.range), (adaptive.variance, single.variance), (adaptive.reasons, single.reasons)):
        assert np.array_equal(a[settled], b[settled])
    changed = ~settled & np.isfinite(adaptive.range)
    assert changed.any() and not np.array_equal(adaptive.range[changed], single.range[changed], equal_nan=True)


@pytest.mark.slow
def test_a_range_step_is_not_smeared(profile):
    # Two grey seabeds side by side, 3 m and 6 m away, the edge between them a straight column:
    # windows on the far side must not take the near side's (far brighter) light, nor its range.
    near, far = world(NEAR), world(FAR, seed=7)
    exposure = near.exposure
    far = world(FAR, exposure, seed=7)
    edge = SIZE[0] // 2
    left = (np.arange(SIZE[0]) < edge)[None, :]
    mean = np.where(left[..., None], near.expected()[0], far.expected()[0]).astype(np.float32)
    std = np.where(left[..., None], near.expected()[1], far.expected()[1]).astype(np.float32)
    truth = np.where(left, near.camera_range, far.camera_range)
    water = open_water(exposure)
    columns = np.abs(np.arange(SIZE[0]) - edge + 0.5)[None, :].repeat(SIZE[1], axis=0)
    band = (columns <= 4) & np.isfinite(truth)
    errors, used = [], 0
    for k in range(3):
        frame = near.camera.digitise(mean, std, 11, k)
        result = range_images(profile, [frame], smoothing="adaptive", open_water=water)
        single = range_images(profile, [frame], open_water=water)
        on = band & np.isfinite(result.range)
        errors.append(np.abs(result.range[on] / truth[on] - 1.0))
        used += int((on & (result.range != single.range)).sum())
    error = np.concatenate(errors)
    assert used > 0  # windows were used next to the edge
    assert np.mean(error > 0.02) < 0.02, (np.mean(error > 0.02), np.max(error))


def naive_window(frame, usable, size):
    h, w, n = frame.shape
    half = size // 2
    out = frame.astype(np.float64).copy()
    count = np.ones(frame.shape)
    for i in range(h):
        for j in range(w):
            for k in range(n):
                if not usable[i, j, k]:
                    continue
                block = frame[max(i - half, 0):i + half + 1, max(j - half, 0):j + half + 1, k]
                ok = usable[max(i - half, 0):i + half + 1, max(j - half, 0):j + half + 1, k] > 0
                out[i, j, k] = block[ok].mean()
                count[i, j, k] = ok.sum()
    return out, count


@pytest.mark.parametrize("size", [3, 5, 9])
def test_window_means_and_their_counts_match_a_plain_loop(size):
    rng = np.random.default_rng(3)
    frame = rng.uniform(100.0, 60000.0, (13, 17, 3)).astype(np.float32)
    usable = (rng.random((13, 17, 3)) > 0.2).astype(np.float32)
    mean, counts, light = window_light(frame, usable, None, None, size)
    ref, ref_count = naive_window(frame, usable, size)
    np.testing.assert_allclose(mean, ref, rtol=2e-6)
    np.testing.assert_array_equal(counts, ref_count)
    assert light is None
    # Values fused over time (samples s each): the mean of n of them equals n²/Σ(1/s) single noises.
    samples = rng.uniform(1.0, 8.0, frame.shape).astype(np.float32)
    _, fused, _ = window_light(frame, usable, samples, None, size)
    i, j, k = 6, 8, 1
    half = size // 2
    ok = usable[i - half:i + half + 1, j - half:j + half + 1, k] > 0
    s = samples[i - half:i + half + 1, j - half:j + half + 1, k][ok]
    if usable[i, j, k]:
        assert fused[i, j, k] == pytest.approx(len(s) ** 2 / np.sum(1.0 / s), rel=1e-5)


def test_the_target_is_checked_in_the_config_the_api_and_the_command_line(profile, tmp_path, capsys):
    assert ProcessingConfig(smoothing="adaptive", smoothing_target=0.05).smoothing_target == 0.05
    for bad in (0.0, 0.6, float("nan"), float("inf")):
        with pytest.raises(ValidationError):
            ProcessingConfig(smoothing="adaptive", smoothing_target=bad)
    with pytest.raises(ValidationError):
        ProcessingPatch(smoothing_target=float("nan"))
    save_profile(profile, tmp_path / "p.yaml")
    np.save(tmp_path / "f.npy", np.zeros((SIZE[1], SIZE[0], 3), np.uint16))
    base = ["range", str(tmp_path / "p.yaml"), str(tmp_path / "f.npy"), "-o", str(tmp_path / "r.npy")]
    for extra, says in ((["--smoothing", "adaptive", "--smoothing-target", "nan"], "finite"),
                        (["--smoothing", "adaptive", "--smoothing-target", "2"], "0.001 to 0.5"),
                        (["--smoothing-target", "0.05"], "--smoothing adaptive")):
        capsys.readouterr()
        assert main(base + extra) == 2
        err = capsys.readouterr().err.strip()
        assert says in err and len(err.splitlines()) == 1, err

