"""Temporal fusion (uwcam.runtime.stages.temporal): the running per-pixel mean of the frames over
which the scene held still, ranged as one frame with its noise.

Expected values come from outside the code: the spread of single-frame ranges measured over many
independent pixels (a uniform surface: every pixel is a repeat of the same measurement), the
statistics of a mean of K independent values (σ/√K; a running average of weight 1/M: σ/√(2M − 1)),
the noise that was drawn (temporal noise of the model, and a fixed pattern drawn once), and the
scene as it was written (which pixels changed, which were saturated or dark).
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.synthetic import RGB_ATTENUATION, make_profile
from uwcam.compute.jit import HAVE_NUMBA
from uwcam.config import TemporalConfig
from uwcam.optics import Reason
from uwcam.ranging.estimator import RangeEstimator
from uwcam.runtime.stages import temporal as stage
from uwcam.runtime.stages.temporal import TemporalFuser, changed_pixels, frames_summary, fuse_step, image_shift_px

B = np.log([0.7, 1.0, 0.8])
READ, GAIN = 5.0, 1.0  # DN rms, DN per electron
SHAPE = (64, 64)
EXPOSURE = ((1000.0, 1000.0, 1000.0), None)


def scene(path_m: float, scale: float = 2.0e4) -> np.ndarray:
    """A uniform surface at lamp → surface → camera path ``path_m`` (the lamp at the camera, so the
    camera range is half of it): per channel scale·exp(b_k − c_k·d_T), (H, W, 3) float64 DN."""
    return np.broadcast_to(scale * np.exp(B - RGB_ATTENUATION * path_m), (*SHAPE, 3)).copy()


def noisy(rng, clean: np.ndarray, fixed: np.ndarray | None = None) -> np.ndarray:
    """One frame: the noise model drawn (read noise, shot noise of gain GAIN), and a fixed pattern
    (the same in every frame) when given; rounded to 16-bit codes."""
    light = clean if fixed is None else clean * fixed
    return np.clip(np.rint(light + rng.normal(0.0, 1.0, clean.shape) * np.sqrt(READ**2 + GAIN * light)), 0, 65535).astype(np.uint16)


def estimator(fixed_pattern: float = 0.0) -> RangeEstimator:
    profile = make_profile(RGB_ATTENUATION, B, read_noise=READ, shot_gain=GAIN, noise_floor=30.0)
    if fixed_pattern:
        profile = profile.model_copy(update={"channels": [c.model_copy(update={"fixed_pattern": fixed_pattern})
                                                          for c in profile.channels]})
    return RangeEstimator(profile, calibration_variance=False)


def run(fuser: TemporalFuser, est: RangeEstimator, frames) -> list:
    """Range every frame as the loop does (the fused mean with its samples); each result."""
    out = []
    for f in frames:
        data, samples = fuser.update(f, EXPOSURE, est)
        out.append(est(data, samples=samples))
    return out


@pytest.fixture(params=["compiled", "numpy"] if HAVE_NUMBA else ["numpy"])
def path(request, monkeypatch):
    """Both twins of the update: the compiled kernel and the numpy functions."""
    if request.param == "numpy":
        monkeypatch.setattr(stage, "HAVE_NUMBA", False)
    return request.param


def test_a_held_scene_fused_over_n_frames_has_its_spread_and_sigma_divided_by_root_n(path):
    rng = np.random.default_rng(1)
    est = estimator()
    clean = scene(4.0)
    assert abs(np.nanmedian(est(clean.astype(np.float32)).range) - 2.0) < 1e-4  # the scene is at 2 m
    single = est(noisy(rng, clean))
    spread_1 = np.nanstd(single.range)  # measured: 4096 independent single-frame ranges
    assert 0.01 < spread_1 < 0.2  # noisy enough to matter, not so noisy that ranges fail
    n = 16
    fuser = TemporalFuser(TemporalConfig(max_frames=64))
    fused = run(fuser, est, [noisy(rng, clean) for _ in range(n)])[-1]
    assert np.mean(fuser.count == n) > 0.99  # nothing changed: every pixel is built from all 16 frames
    valid = np.isfinite(fused.range)
    assert valid.mean() > 0.999
    spread_n = np.std(fused.range[valid])
    assert spread_n == pytest.approx(spread_1 / np.sqrt(n), rel=0.08), (spread_1, spread_n)
    z = (fused.range[valid] - 2.0) / np.sqrt(fused.variance[valid])
    assert np.std(z) == pytest.approx(1.0, abs=0.06)
    assert abs(np.mean(z)) < 0.1
    assert np.median(np.sqrt(fused.variance)) == pytest.approx(np.median(np.sqrt(single.variance)) / np.sqrt(n), rel=0.05)


def test_beyond_max_frames_a_running_average_has_the_sigma_of_two_m_minus_one_frames(path):
    rng = np.random.default_rng(2)
    est = estimator()
    clean = scene(4.0)
    spread_1 = np.nanstd(est(noisy(rng, clean)).range)
    m = 6
    fuser = TemporalFuser(TemporalConfig(max_frames=m))
    fused = run(fuser, est, [noisy(rng, clean) for _ in range(40)])[-1]
    assert np.mean(fuser.count == m) > 0.99
    valid = np.isfinite(fused.range)
    # An exponential average of weight α = 1/M has variance α/(2 − α)·σ² = σ²/(2M − 1).
    assert np.std(fused.range[valid]) == pytest.approx(spread_1 / np.sqrt(2 * m - 1), rel=0.08)
    z = (fused.range[valid] - 2.0) / np.sqrt(fused.variance[valid])
    assert np.std(z) == pytest.approx(1.0, abs=0.06)


def test_a_fixed_pattern_does_not_average_down_and_sigma_says_so(path):
    rng = np.random.default_rng(3)
    est = estimator(fixed_pattern=0.01)
    clean = scene(4.0)
    fixed = 1.0 + 0.01 * rng.standard_normal(clean.shape)  # each pixel's own response, drawn once
    fused = run(TemporalFuser(TemporalConfig(max_frames=64)), est, [noisy(rng, clean, fixed) for _ in range(32)])[-1]
    valid = np.isfinite(fused.range)
    z = (fused.range[valid] - 2.0) / np.sqrt(fused.variance[valid])
    # σ counting the fixed pattern as if it averaged would give z sd ≈ 2 here.
    assert np.std(z) == pytest.approx(1.0, abs=0.07)
    # The fixed pattern alone, ranged from noise-free frames, is a floor the fused spread stays above.
    floor = np.nanstd(est((clean * fixed).astype(np.float32)).range)
    assert np.std(fused.range[valid]) > floor


def test_a_step_in_range_restarts_those_pixels_at_once_and_not_the_others(path):
    rng = np.random.default_rng(4)
    est = estimator()
    near, far = scene(3.6), scene(4.0)  # 1.8 m and 2.0 m
    fuser = TemporalFuser(TemporalConfig(max_frames=64))
    run(fuser, est, [noisy(rng, far) for _ in range(10)])
    moved = far.copy()
    moved[:, :32] = near[:, :32]  # the left half comes 0.2 m closer
    result = run(fuser, est, [noisy(rng, moved)])[0]
    left, right = fuser.count[:, :32], fuser.count[:, 32:]
    assert np.mean(left == 1) > 0.999, np.bincount(left.ravel())
    assert np.mean(right == 11) > 0.99
    # Never a blend: the left half is ranged from the new frame alone, right to its noise.
    single = est(noisy(rng, near))
    assert np.nanmedian(result.range[:, :32]) == pytest.approx(1.8, rel=0.01)
    assert np.nanstd(result.range[:, :32]) == pytest.approx(np.nanstd(single.range), rel=0.1)
    assert np.nanmedian(result.range[:, 32:]) == pytest.approx(2.0, rel=0.005)
    frames = fuser.frames(np.isfinite(result.range))
    assert frames_summary(frames)["median_frames"] in (1, 11)  # half the image each
    assert frames_summary(frames)["p10_frames"] == 1


def test_a_pixel_invalid_in_the_new_frame_is_never_fused(path):
    rng = np.random.default_rng(5)
    est = estimator()
    clean = scene(4.0)
    fuser = TemporalFuser(TemporalConfig(max_frames=64))
    run(fuser, est, [noisy(rng, clean) for _ in range(8)])
    frame = noisy(rng, clean)
    frame[:8, :8] = 65535  # saturated
    frame[8:16, :8] = 0  # dark: the lamp's light blocked there
    frame[20, 20, 0] = 65535  # red alone saturated: ranged from green and blue, of this frame alone
    result = run(fuser, est, [frame])[0]
    assert (fuser.count[:16, :8] == 1).all() and fuser.count[20, 20] == 1
    assert result.range[20, 20] == est(frame.astype(np.float32)).range[20, 20]
    assert (result.reasons[:8, :8] == Reason.SATURATED).all() and np.isnan(result.range[:8, :8]).all()
    assert (result.reasons[8:16, :8] == Reason.BELOW_NOISE_FLOOR).all() and np.isnan(result.range[8:16, :8]).all()
    assert (fuser.frames(np.isfinite(result.range))[:16, :8] == 0).all()
    # A saturated mean is not averaged into either: the next good frame starts afresh there.
    run(fuser, est, [noisy(rng, clean)])
    assert (fuser.count[:8, :8] == 1).all() and np.mean(fuser.count[16:] == 10) > 0.99


def test_a_new_exposure_or_frame_size_restarts_every_pixel():
    rng = np.random.default_rng(6)
    est = estimator()
    fuser = TemporalFuser(TemporalConfig())
    for _ in range(4):
        fuser.update(noisy(rng, scene(4.0)), EXPOSURE, est)
    assert np.mean(fuser.count == 4) > 0.99  # (a still pixel restarts by chance once in ~5000 frames)
    fuser.update(noisy(rng, scene(4.0)), ((2000.0, 2000.0, 2000.0), None), est)
    assert (fuser.count == 1).all() and fuser.restarted == "the exposure changed"
    fuser.update(noisy(rng, scene(4.0))[:32], ((2000.0, 2000.0, 2000.0), None), est)
    assert fuser.count.shape == (32, 64) and (fuser.count == 1).all() and fuser.restarted == "the frame size changed"


def test_still_pixels_restart_by_chance_as_rarely_as_change_sigmas_says():
    # Pure noise around an unchanging mean: a channel's |difference| beyond 3σ happens with
    # probability 0.27 %, so with three channels 0.81 % of the pixels (and 0.0063 % at 4σ each).
    rng = np.random.default_rng(7)
    clean = scene(4.0)
    mean = clean.astype(np.float32)  # the exact mean: Σw² = 0
    s = np.zeros(SHAPE, np.float32)
    big = np.concatenate([noisy(rng, clean) for _ in range(40)])  # 40·64 rows
    means = np.concatenate([mean] * 40)
    rv = np.full(3, READ**2 + 1 / 12.0, np.float32)
    for sigmas, share in ((3.0, 1 - 0.9973**3), (4.0, 1 - 0.999937**3)):
        got = changed_pixels(big.astype(np.float32), means, np.concatenate([s] * 40), np.zeros(3, np.float32), rv,
                             np.full(3, GAIN, np.float32), sigmas).mean()
        assert got == pytest.approx(share, rel=0.25, abs=1e-4), (sigmas, got, share)


def test_fuse_step_is_a_plain_mean_then_a_running_average():
    frames = [np.full((2, 2, 1), v, np.float32) for v in (1.0, 2.0, 3.0, 6.0, 10.0)]
    mean = count = ws = None
    for f in frames:
        mean, count, ws = fuse_step(mean, count, ws, f, False, 3)
    # 1, 2, 3 → mean 2 (Σw² 1/3); then weight 1/3: 2 + (6 − 2)/3 = 10/3; 10/3 + (10 − 10/3)/3 = 50/9.
    assert mean[0, 0, 0] == pytest.approx(50 / 9, rel=1e-6)
    assert count[0, 0] == 3
    # Σw² of weights (4/27, 4/27, 4/27, 2/9, 1/3): 3·16/729 + 4/81 + 1/9.
    assert ws[0, 0] == pytest.approx(3 * 16 / 729 + 4 / 81 + 1 / 9, rel=1e-6)
    restart = np.array([[True, False], [False, False]])
    mean, count, ws = fuse_step(mean, count, ws, np.full((2, 2, 1), 7.0, np.float32), restart, 3)
    assert mean[0, 0, 0] == 7.0 and count[0, 0] == 1 and ws[0, 0] == 1.0 and count[1, 1] == 3


@pytest.mark.skipif(not HAVE_NUMBA, reason="numba is not installed: only the numpy twin exists")
def test_the_compiled_update_equals_its_numpy_twin(monkeypatch):
    rng = np.random.default_rng(8)
    est = estimator(fixed_pattern=0.005)
    compiled, plain = TemporalFuser(TemporalConfig(max_frames=5)), TemporalFuser(TemporalConfig(max_frames=5))
    base = rng.uniform(200.0, 30000.0, (*SHAPE, 3))
    for k in range(9):
        frame = noisy(rng, base)
        if k == 4:
            frame[:10] = np.minimum(frame[:10].astype(np.int64) + 3000, 65535)  # a change
        if k == 6:
            frame[20:22, :, 1] = 65535  # saturated
        a = compiled.update(frame, EXPOSURE, est)
        monkeypatch.setattr(stage, "HAVE_NUMBA", False)
        b = plain.update(frame, EXPOSURE, est)
        monkeypatch.setattr(stage, "HAVE_NUMBA", True)
        np.testing.assert_array_equal(compiled.count, plain.count)
        np.testing.assert_allclose(a[0], b[0], rtol=1e-6)
        np.testing.assert_allclose(compiled.weight_squares, plain.weight_squares, rtol=1e-6)
        np.testing.assert_allclose(a[1], b[1], rtol=1e-5)
        assert compiled.changed_fraction == plain.changed_fraction
    assert compiled.changed_fraction > 0  # the saturated rows restarted on the last frames


def test_fused_frames_range_the_same_with_a_background_by_the_compiled_kernel_and_numpy(path):
    # The loop's backscatter and ambient paths hand the fused mean and its samples to the
    # background kernel; the numpy terms (channel_terms) are the reference.
    from uwcam.optics import kernels

    if kernels.fuse_background is None:
        pytest.skip("numba is not installed: no compiled background kernel")
    rng = np.random.default_rng(9)
    est = estimator()
    fuser = TemporalFuser(TemporalConfig())
    for _ in range(6):
        data, samples = fuser.update(noisy(rng, scene(4.0) + 300.0), EXPOSURE, est)
    background = np.full(data.shape, 300.0, np.float32)
    got = est(data, background=background, samples=samples)
    y, weight, state = est.channel_terms(data, background, samples)
    pairs = kernels.pack_pairs(y, weight, state, 2, 3)
    want = est(data.astype(np.float64), background=None, samples=None)  # shape of the outputs
    kernels.fuse_arrays(pairs, est._c, (0.0,) * 3, est._cv, est._geo, est.bounds, want.range, want.variance, want.reasons)
    np.testing.assert_array_equal(got.reasons, want.reasons)
    np.testing.assert_allclose(got.range, want.range, rtol=2e-5, equal_nan=True)
    np.testing.assert_allclose(got.variance, want.variance, rtol=2e-4, equal_nan=True)


def test_image_shift_of_the_vehicles_motion_and_the_restart_it_makes():
    # 0.1 rad/s for 0.1 s with f = 1000 px: 0.01 rad → 10 px; 0.3 m/s for 0.1 s at 3 m: 3 cm → 10 px.
    assert image_shift_px(0.1, None, 0.1, 1000.0, 3.0) == pytest.approx(10.0)
    assert image_shift_px(None, 0.3, 0.1, 1000.0, 3.0) == pytest.approx(10.0)
    assert image_shift_px(0.1, 0.3, 0.1, 1000.0, 3.0) == pytest.approx(20.0)
    assert image_shift_px(None, None, 0.1, 1000.0, 3.0) is None
    rng = np.random.default_rng(10)
    est = estimator()
    fuser = TemporalFuser(TemporalConfig(motion_pixels=0.5))
    t = 0
    for turn in (0.0, 0.0, 0.0, 0.0004, 0.01, 0.0):  # rad/s, frames 0.1 s apart, f = 1000 px
        fuser.judge_motion(t, turn, None, 1000.0, 3.0)
        fuser.update(noisy(rng, scene(4.0)), EXPOSURE, est)
        t += 100_000_000
        if turn == 0.0004:  # 0.04 px: still
            assert np.mean(fuser.count == 4) > 0.99
        if turn == 0.01:  # 1 px
            assert (fuser.count == 1).all() and fuser.restarted == "the vehicle moved (1.0 pixels in a frame)"
    assert np.mean(fuser.count == 2) > 0.99
    off = TemporalFuser(TemporalConfig(motion_pixels=None))
    off.judge_motion(0, 1.0, 1.0, 1000.0, 1.0)
    off.judge_motion(100_000_000, 1.0, 1.0, 1000.0, 1.0)
    assert off.shift_px is None


@pytest.mark.skipif(not HAVE_NUMBA, reason="numba is not installed: only the numpy threshold exists")
@pytest.mark.parametrize("scaled", [False, True])
@pytest.mark.parametrize("with_ambient", [False, True])
def test_the_compiled_water_threshold_of_fused_values_equals_the_numpy_one(monkeypatch, scaled, with_ambient):
    # Fused frames are judged against the water's light with their own noise every frame: the
    # compiled quadratic must be the numpy one, also where a large fixed pattern leaves no threshold.
    from uwcam.water import water_light

    rng = np.random.default_rng(11)
    profile = make_profile(RGB_ATTENUATION, B, read_noise=[3.0, 4.0, 5.0], shot_gain=[0.5, 1.0, 2.0], dark_level=[10.0, 20.0, 30.0])
    profile = profile.model_copy(update={"channels": [c.model_copy(update={"fixed_pattern": f})
                                                      for c, f in zip(profile.channels, (0.01, 0.2, 0.6))]})
    est = RangeEstimator(profile)
    light = water_light.WaterLight(rng.uniform(0.0, 5000.0, (40, 60, 3)).astype(np.float32), 0.05, "test")
    ambient = rng.uniform(0.0, 100.0, (40, 60, 3)).astype(np.float32) if with_ambient else None
    scale = np.array([1.5, 0.7, 1.0]) if scaled else None
    samples = rng.uniform(0.5, 40.0, (40, 60, 3)).astype(np.float32)
    compiled = light.threshold(est, scale, ambient, samples)
    monkeypatch.setattr(water_light, "HAVE_NUMBA", False)
    plain = light.threshold(est, scale, ambient, samples)
    assert np.isinf(plain).any() and np.isfinite(plain).any()
    np.testing.assert_allclose(compiled, plain, rtol=1e-6)


def test_a_moving_edge_is_ranged_from_the_new_frames_never_a_blend(path):
    # A near surface (1.8 m) whose edge over a far one (2.0 m) moves 3 pixels a frame, as a brick
    # under a moving vehicle: pixels the edge has just passed must read 1.8 m, not 1.9 m.
    rng = np.random.default_rng(12)
    est = estimator()
    near, far = scene(3.6), scene(4.0)
    fuser = TemporalFuser(TemporalConfig(max_frames=32))
    columns = np.arange(SHAPE[1])
    for k in range(24):
        edge = 4 + 3 * max(k - 12, 0)  # still for 12 frames, then moving
        truth = np.where(columns < edge, 1.8, 2.0)[None, :].repeat(SHAPE[0], axis=0)
        clean = np.where((columns < edge)[None, :, None], near, far)
        result = run(fuser, est, [noisy(rng, clean)])[0]
        if k > 12:
            band = np.abs(columns - edge)[None, :].repeat(SHAPE[0], axis=0) <= 6
            error = np.abs(result.range[band] / truth[band] - 1.0)
            assert np.nanmedian(error) < 0.02, (k, np.nanmedian(error))
            assert np.mean(error > 0.035) < 0.01, (k, np.mean(error > 0.035))  # a blend is 5 % off either


@pytest.mark.slow
def test_a_surveying_vehicle_is_never_smeared():
    # The simulator's vehicle moving at 0.4 m/s, 2 m over a grey seabed with relief, 30 frames/s:
    # its view moves several pixels a frame. Fused or not, the errors against the rendered truth
    # are what σ says (a blend of two places would show as errors beyond 3σ).
    from uwcam.simulation import CameraModel, Lamp, water_preset
    from uwcam.simulation.survey import SurveyWorld
    from uwcam.simulation.tank import calibrate_in_simulation
    from uwcam.simulation.terrain import SurveyMotion, build_terrain

    wavelengths = [675.0, 575.0, 475.0]
    lamp, size = Lamp(position=(0.3, 0.0, 0.0)), (320, 180)
    water = water_preset("jerlov-IA", wavelengths).with_overrides(backscatter=0.0)
    est = RangeEstimator(calibrate_in_simulation(water, lamp, size, CameraModel(), seed_base=11))
    world = SurveyWorld(size=size, water=water, lamp=lamp, terrain=build_terrain(0, ["R", "G", "B"], wavelengths, material="grey"),
                        bracket=False, motion=SurveyMotion(speed=0.4, altitude=(2.0, 2.0)))
    fuser = TemporalFuser(TemporalConfig())
    single_z, fused_z, single_e, fused_e = [], [], [], []
    for k in range(30):
        t = 10.0 + k / 30.0
        frame, truth = world.frame(t, k), world.camera_range(t)
        one = est(frame)
        data, samples = fuser.update(frame, EXPOSURE, est)
        fused = est(data, samples=samples)
        if k >= 5:
            single_z.append((one.range - truth) / np.sqrt(one.variance))
            fused_z.append((fused.range - truth) / np.sqrt(fused.variance))
            single_e.append(one.range / truth - 1.0)
            fused_e.append(fused.range / truth - 1.0)
    single_z, fused_z = np.concatenate(single_z).ravel(), np.concatenate(fused_z).ravel()
    assert np.nanmedian(fuser.count) >= 2  # something was fused
    assert np.nanstd(fused_z) == pytest.approx(1.0, abs=0.08), np.nanstd(fused_z)
    # Beyond 3σ: 0.27 % for a normal distribution; one frame's measured share, and not more than
    # twice it fused.
    assert np.nanmean(np.abs(fused_z) > 3) < 2 * np.nanmean(np.abs(single_z) > 3) + 0.001
    rms = [np.sqrt(np.nanmean(np.concatenate(e) ** 2)) for e in (single_e, fused_e)]
    assert rms[1] <= rms[0], rms
