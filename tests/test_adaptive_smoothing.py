"""Adaptive spatial windows (``smoothing: adaptive``) on the simulator's scenes, against its true
range of every pixel: σ stays honest, the far and dark parts keep more pixels and reach the
target, pixels already within the target are untouched bit for bit, and a range step is not
smeared. The window means are checked against a plain loop over windows written apart from the
code; the command line, the frame loop and ``uwcam reprocess`` agree in tests/test_one_ranging_path.py."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from uwcam.api.settings import ProcessingPatch
from uwcam.cli import main
from uwcam.calibration.profile import save_profile
from uwcam.config import ProcessingConfig
from uwcam.optics.validity import Reason
from uwcam.ranging.adaptive import adaptive_windows
from uwcam.ranging.smoothing import window_light
from uwcam.ranging.result import RangeResult
from uwcam.ranging.images import range_images
from uwcam.simulation import CameraModel, Lamp, SimulatedWorld, water_preset
from uwcam.simulation.tank import calibrate_in_simulation

SIZE = (160, 120)
WATER = water_preset("jerlov-IA", [675.0, 575.0, 475.0])
LAMP = Lamp(position=(0.3, 0.0, 0.0))
CAMERA = CameraModel()
NEAR, FAR = 2.0, 10.0
"""A grey seabed 2 m away sets the exposure; one 8 m away in the same frame is dark: most of its
single pixels' σ is above 2 % of the range and some have no range. (Clear water: in the
scattering jerlov-II the far pixels' σ is mostly the calibration's and the backscatter model's,
which neighbours share and no window averages down.)"""
EDGE = SIZE[0] // 2
"""Near seabed left of this column, far seabed from it on."""


@pytest.fixture(scope="module")
def profile():
    """A calibration in the simulated water with the simulated camera's own noise model (read noise
    with the dark current's shot noise, shot gain, PRNU): what is tested here is the windows' σ, and
    the calibration's noise fit from two frames of a bright plate is loose (read noise anywhere from
    0 to 30 DN, shot gain 0.9 to 2.5 DN/e against 3.3), which a dark pixel's σ depends on."""
    fitted = calibrate_in_simulation(WATER, LAMP, SIZE, CAMERA, frames_per_distance=2)
    g = CAMERA.gain_dn_per_e
    noise = dict(read_noise=float(g * np.sqrt(CAMERA.read_noise_e**2 + CAMERA.dark_current_e)), shot_gain=float(g),
                 fixed_pattern=float(CAMERA.prnu))
    return fitted.model_copy(update={"channels": [c.model_copy(update=noise) for c in fitted.channels]})


def world(distance: float, exposure: float | None = None, seed: int = 5) -> SimulatedWorld:
    return SimulatedWorld(scene="seabed", distance=distance, size=SIZE, water=WATER, lamp=LAMP, camera=CAMERA,
                          material="grey", seed=seed, fixed_exposure=exposure)


@pytest.fixture(scope="module")
def scene(profile):
    """Frames of the near and far seabeds side by side (one sensor, one exposure), the truth, an
    open-water frame, and their ranging with no smoothing, the 3×3 mean and adaptive windows (2 %)."""
    near = world(NEAR)
    far = world(FAR, near.exposure, seed=7)
    left = (np.arange(SIZE[0]) < EDGE)[None, :]
    mean = np.where(left[..., None], near.expected()[0], far.expected()[0]).astype(np.float32)
    std = np.where(left[..., None], near.expected()[1], far.expected()[1]).astype(np.float32)
    truth = np.where(left, near.camera_range, far.camera_range)
    water = SimulatedWorld(scene="open-water", distance=4.0, size=SIZE, water=WATER, lamp=LAMP, camera=CAMERA,
                           fixed_exposure=near.exposure, seed=6).frame(0)
    frames = [CAMERA.digitise(mean, std, 11, k) for k in range(3)]
    results = {kind: [range_images(profile, [f], smoothing=kind, open_water=water) for f in frames]
               for kind in ("none", "mean", "adaptive")}
    return truth, frames, water, results


FAR_REGION = (np.arange(SIZE[0]) >= EDGE + 17)[None, :].repeat(SIZE[1], axis=0)
"""The far seabed clear of the edge by a largest window."""


def pooled(results, truth, region):
    r = np.stack([x.range for x in results]).astype(np.float64)
    v = np.stack([x.variance for x in results]).astype(np.float64)
    t = np.broadcast_to(truth, r.shape)
    on = np.isfinite(r) & np.isfinite(t) & region[None]
    return r, v, t, on


def figures(results, truth, region):
    """Valid share of the region's surface, median and rms relative error, sd of z and share |z| > 3."""
    r, v, t, on = pooled(results, truth, region)
    error = r[on] / t[on] - 1.0
    z = (r[on] - t[on]) / np.sqrt(v[on])
    surface = np.isfinite(truth) & region
    return dict(valid=on.sum() / (len(results) * surface.sum()), median=np.median(error), rms=np.sqrt(np.mean(error**2)),
                z_sd=np.std(z), beyond=np.mean(np.abs(z) > 3), reached=np.mean(np.sqrt(v[on]) <= 0.02 * r[on] * (1 + 1e-6)))


@pytest.mark.slow
def test_sigma_stays_honest_with_adaptive_windows(scene):
    truth, _, _, results = scene
    f = figures(results["adaptive"], truth, FAR_REGION)
    assert 0.8 <= f["z_sd"] <= 1.25, f
    assert f["beyond"] <= 0.02, f
    whole = figures(results["adaptive"], truth, np.ones(truth.shape, bool))  # near, far and the edge
    assert 0.8 <= whole["z_sd"] <= 1.25 and whole["beyond"] <= 0.02, whole


@pytest.mark.slow
def test_the_far_dark_seabed_keeps_more_pixels_reaches_the_target_and_reads_better(scene):
    truth, _, _, results = scene
    f = {k: figures(results[k], truth, FAR_REGION) for k in results}
    print({k: {a: round(float(b), 4) for a, b in v.items()} for k, v in f.items()})
    assert f["adaptive"]["valid"] > f["none"]["valid"] + 0.05, f
    assert f["none"]["reached"] < 0.05 and f["adaptive"]["reached"] > 0.8, f  # 2 %: no single pixel, most windows
    assert f["adaptive"]["rms"] < 0.5 * f["none"]["rms"], f
    assert f["adaptive"]["rms"] < f["mean"]["rms"], f


@pytest.mark.slow
def test_pixels_already_within_the_target_are_unchanged_bit_for_bit(profile, scene):
    truth, frames, water, results = scene
    single = results["none"][0]
    target = 0.02
    settled = np.isfinite(single.range) & (single.variance.astype(np.float64) <= (target * single.range.astype(np.float64)) ** 2)
    assert 0.2 < settled.mean() < 0.6, settled.mean()  # the near seabed
    adaptive = results["adaptive"][0]
    for a, b in ((adaptive.range, single.range), (adaptive.variance, single.variance), (adaptive.reasons, single.reasons)):
        assert np.array_equal(a[settled], b[settled])
    # The others mostly took a window (a pixel whose every window was given up keeps its own range).
    others = ~settled & np.isfinite(adaptive.range)
    assert others.mean() > 0.2 and np.mean(adaptive.range[others] != single.range[others]) > 0.8


@pytest.mark.slow
def test_a_range_step_is_not_smeared(scene):
    # The near seabed (2 m) beside the far one (10 m): windows on the far side must not take the near
    # side's far brighter light, nor its range. Within 4 pixels of the edge, each pixel reads its own
    # plane: within 2 %, or, where its σ is larger (a window given up at the edge), within 3σ.
    truth, _, _, results = scene
    columns = np.abs(np.arange(SIZE[0]) - EDGE + 0.5)[None, :].repeat(SIZE[1], axis=0)
    band = (columns <= 4) & np.isfinite(truth)
    for single, result in zip(results["none"], results["adaptive"]):
        on = band & np.isfinite(result.range)
        error = np.abs(result.range[on] / truth[on] - 1.0)
        sigma = np.sqrt(result.variance[on]) / truth[on]
        assert np.mean(error > np.maximum(0.02, 3 * sigma)) < 0.01, np.mean(error > np.maximum(0.02, 3 * sigma))
        windowed = on & (result.range != single.range)
        assert windowed[:, EDGE:].sum() > 50  # far pixels by the edge did use windows (small ones)
        far = windowed & (np.arange(SIZE[0]) >= EDGE)[None, :]
        assert np.median(np.abs(result.range[far] / truth[far] - 1.0)) < 0.02


@pytest.mark.slow
def test_a_smaller_step_is_not_smeared_either(profile):
    # 8 m beside 10 m, both dark (a quarter of the 8 m seabed's own exposure): the light differs by
    # a few single-pixel σ only, so the windows' ranges must give the step away.
    near = world(8.0)
    exposure = 0.25 * near.exposure
    near, far = world(8.0, exposure), world(FAR, exposure, seed=7)
    left = (np.arange(SIZE[0]) < EDGE)[None, :]
    mean = np.where(left[..., None], near.expected()[0], far.expected()[0]).astype(np.float32)
    std = np.where(left[..., None], near.expected()[1], far.expected()[1]).astype(np.float32)
    truth = np.where(left, near.camera_range, far.camera_range)
    water = SimulatedWorld(scene="open-water", distance=4.0, size=SIZE, water=WATER, lamp=LAMP, camera=CAMERA,
                           fixed_exposure=exposure, seed=6).frame(0)
    columns = np.abs(np.arange(SIZE[0]) - EDGE + 0.5)[None, :].repeat(SIZE[1], axis=0)
    for k in range(2):
        frame = CAMERA.digitise(mean, std, 11, k)
        result = range_images(profile, [frame], smoothing="adaptive", open_water=water)
        single = range_images(profile, [frame], open_water=water)
        on = (columns <= 4) & np.isfinite(truth) & np.isfinite(result.range)
        error = np.abs(result.range[on] / truth[on] - 1.0)
        sigma = np.sqrt(result.variance[on]) / truth[on]
        assert np.mean(error > np.maximum(0.02, 3 * sigma)) < 0.015, np.mean(error > np.maximum(0.02, 3 * sigma))
        assert np.mean(result.range[on] != single.range[on]) > 0.5  # windows were used there


class _Noise:
    """The estimator's noise model and channels, as adaptive_windows reads them: 100 DN of read noise."""

    dark = np.zeros(3)
    read_noise = np.full(3, 100.0)
    shot_gain = np.zeros(3)
    fixed_pattern = np.zeros(3)
    active = np.ones(3, bool)
    response = None
    profile = type("P", (), {"quantisation_step": 1.0, "saturation_level": 65535.0})()


def _light_ranged(mean, counts, light):
    """A stand-in transform: channel 0's light 1000 DN reads 5 m, 1050 DN reads 7 m (linear between,
    as mixed light reads between two surfaces), σ² 0.04 m² over the number of pixels averaged."""
    n = np.ones(mean.shape[:2]) if counts is None else counts[..., 0]
    r = 5.0 + (mean[..., 0].astype(np.float64) - 1000.0) / 25.0
    return RangeResult(r.astype(np.float32), (0.04 / n).astype(np.float32), np.zeros(mean.shape[:2], np.uint8))


def test_windows_stop_at_a_step_their_ranges_give_away_and_at_the_target():
    # A step of 50 DN in one channel (half the noise: the light test cannot see it) between surfaces
    # 5 m and 7 m away. Each pixel must take the largest window of the ladder not reaching over the
    # step, and no larger than the first one within the target (9×9 here: σ 0.022 m ≤ 0.5 % of 5 m).
    h, w, step = 40, 60, 30
    frame = np.full((h, w, 3), 1000.0, np.float32)
    frame[:, step:, 0] = 1050.0
    single = _light_ranged(frame, None, None)
    # A pixel without a range for too little light gets one; a saturated one stays as it is.
    single.range[20, 10], single.variance[20, 10], single.reasons[20, 10] = np.nan, np.nan, Reason.BACKSCATTER_ONLY
    single.range[20, 12], single.variance[20, 12], single.reasons[20, 12] = np.nan, np.nan, Reason.SATURATED
    out = adaptive_windows(single, frame, _light_ranged, _Noise(), 0.005)
    rows = slice(8, h - 8)
    for column, n in ((step - 1, 1), (step - 2, 9), (step - 3, 25), (step - 4, 25), (step - 5, 81), (8, 81)):
        np.testing.assert_array_equal(out.range[rows, column], 5.0)  # never smeared towards 7 m
        np.testing.assert_allclose(out.variance[rows, column], 0.04 / n, rtol=1e-6)
    np.testing.assert_array_equal(out.range[rows, step], 7.0)
    assert out.reasons[20, 10] == Reason.VALID and out.range[20, 10] == 5.0 and out.variance[20, 10] == pytest.approx(0.04 / 81)
    assert out.reasons[20, 12] == Reason.SATURATED and np.isnan(out.range[20, 12])


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

