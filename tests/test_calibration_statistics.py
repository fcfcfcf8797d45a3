"""Honest calibration statistics: noise model with fixed pattern, repeated frames, the
calibration's covariance and its propagation, black-patch backscatter, and the crash on
noise-free frames (issue: pydantic traceback on a NaN standard deviation)."""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from uwcam.calibration.fit import CalibrationInputs, calibrate_with_details, project_plate_box
from uwcam.calibration.line_fit import fit_attenuation_differences
from uwcam.calibration.noise_fit import fit_noise, noise_point
from uwcam.cli import main
from uwcam.optics.calibration_variance import calibration_path_variance
from uwcam.optics.fusion import fused_path_length
from uwcam.calibration.profile import load_profile
from uwcam.calibration.rig import builtin_rig_path, load_rig
from uwcam.simulation import CameraModel, Lamp, SimulatedWorld, water_preset

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "bench"))

WAVELENGTHS = [675.0, 575.0, 475.0]
LAMP = Lamp(position=(0.3, 0.0, 0.0))


# --- noise model -----------------------------------------------------------------------------

def synthetic_levels(read, gain, fpn, frames, rng, levels=(300.0, 1500.0, 6000.0, 20000.0, 45000.0), side=48):
    """Flat regions of known signal, each with its own fixed-pattern map and fresh temporal noise per frame."""
    points, truth = [], []
    for e in levels:
        pattern = e * (1.0 + fpn * rng.standard_normal((side, side, 1)))
        temporal_sd = np.sqrt(read**2 + gain * pattern)
        stack = [pattern + temporal_sd * rng.standard_normal(pattern.shape) for _ in range(frames)]
        points.append(noise_point(stack, np.ones((side, side), bool)))
        truth.append(e)
    return points, np.array(truth)


@settings(max_examples=25, deadline=None, derandomize=True)
@given(read=st.floats(2.0, 30.0), gain=st.floats(0.3, 5.0), fpn=st.floats(0.0, 0.02), seed=st.integers(0, 2**31))
def test_repeated_frames_separate_read_shot_and_fixed_pattern(read, gain, fpn, seed):
    rng = np.random.default_rng(seed)
    points, e = synthetic_levels(read, gain, fpn, 4, rng)
    fit = fit_noise(points, quantisation_step=0.0)
    # Closed forms: temporal σ² = read² + gain·E, fixed pattern σ² = (fpn·E)².
    temporal_fit = fit.read_noise[0] ** 2 + fit.shot_gain[0] * e
    np.testing.assert_allclose(temporal_fit, read**2 + gain * e, rtol=0.1)
    assert abs(fit.fixed_pattern[0] - fpn) < 0.002  # 300 random cases: worst 0.0013
    assert np.all(np.isfinite([fit.read_noise, fit.shot_gain, fit.fixed_pattern]))


@settings(max_examples=15, deadline=None, derandomize=True)
@given(read=st.floats(2.0, 30.0), gain=st.floats(0.3, 5.0), fpn=st.floats(0.0, 0.02), seed=st.integers(0, 2**31))
def test_single_frames_give_the_total_variance(read, gain, fpn, seed):
    rng = np.random.default_rng(seed)
    points, e = synthetic_levels(read, gain, fpn, 1, rng, side=64)
    fit = fit_noise(points, quantisation_step=0.0)
    total = fit.read_noise[0] ** 2 + fit.shot_gain[0] * e + (fit.fixed_pattern[0] * e) ** 2
    # One 64×64 region per level: each variance is good to ~3 % (second differences of 4096 pixels),
    # and three terms are fitted to five levels, so the extremes may be off by a few times that.
    np.testing.assert_allclose(total, read**2 + gain * e + (fpn * e) ** 2, rtol=0.15)


def test_zero_variance_gives_a_zero_model_not_nan():
    flat = [np.full((20, 20, 3), 1000.0)] * 3
    fit = fit_noise([noise_point(flat, np.ones((20, 20), bool))], quantisation_step=1.0)
    assert np.all(fit.read_noise == 0) and np.all(fit.shot_gain == 0) and np.all(fit.fixed_pattern == 0)


# --- covariance of the fit and its propagation --------------------------------------------------

def test_joint_covariance_matches_the_spread_of_repeated_fits():
    """Monte Carlo: the GLS covariance of [V, b] is the covariance of the estimates."""
    rng = np.random.default_rng(5)
    d = np.array([1.0, 1.7, 2.4, 3.5])
    v_true, b_true = np.array([0.0, -0.35, -0.40]), np.array([0.0, 0.3, 0.1])
    lv = rng.uniform(1e-5, 4e-5, (4, 3))
    a = rng.normal(size=4)  # each distance's common level (exposure, spreading): cancels
    mean = a[:, None] + b_true - np.outer(d, v_true)
    estimates, covs = [], []
    for _ in range(3000):
        fit = fit_attenuation_differences(mean + np.sqrt(lv) * rng.standard_normal(lv.shape), d, 0, lv)
        estimates.append(np.r_[fit.attenuation_difference[1:], fit.log_constant[1:]])
        covs.append(fit.covariance)
    empirical = np.cov(np.array(estimates).T)
    # The stated variances fix the covariance; only fits with significantly too much scatter (about
    # 5 % of them by chance) are scaled up by their χ².
    reported = np.median(covs, axis=0)
    scaled = np.mean([not np.allclose(c, reported) for c in covs])
    assert 0.02 < scaled < 0.08
    np.testing.assert_allclose(np.sqrt(np.diag(reported)), np.sqrt(np.diag(empirical)), rtol=0.06)
    corr = lambda m: m / np.sqrt(np.outer(np.diag(m), np.diag(m)))  # noqa: E731
    np.testing.assert_allclose(corr(reported), corr(empirical), atol=0.06)


@settings(max_examples=40, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**31), path=st.floats(0.5, 25.0))
def test_calibration_variance_matches_a_finite_difference_reference(seed, path):
    """Var = J C Jᵀ with J the numerical derivative of the reference fusion (optics.fusion) in V and b."""
    rng = np.random.default_rng(seed)
    n = 3
    c = np.array([0.46, 0.11, 0.06])
    b = np.array([0.0, 0.3, -0.2])
    signal = np.exp(b - c * path) * 1e4 * rng.uniform(0.5, 2.0)
    variance = rng.uniform(0.2, 5.0, n) * signal  # any noise: only the weights matter
    a = rng.normal(size=(2 * (n - 1), 2 * (n - 1)))
    cov = a @ a.T * 1e-4
    q = n - 1
    cvv, cvb, cbb = np.zeros((n, n)), np.zeros((n, n)), np.zeros((n, n))
    cvv[1:, 1:], cvb[1:, 1:], cbb[1:, 1:] = cov[:q, :q], cov[:q, q:], cov[q:, q:]

    def d_t(theta):
        cc = c.copy()
        bb = b.copy()
        cc[1:] = c[1:] + theta[:q]
        bb[1:] = b[1:] + theta[q:]
        return fused_path_length(signal, cc, bb, variance)[0]

    h = 1e-6
    jac = np.array([(d_t(h * e) - d_t(-h * e)) / (2 * h) for e in np.eye(2 * q)])
    reference = jac @ cov @ jac
    w = signal**2 / variance
    got = calibration_path_variance(w, c, fused_path_length(signal, c, b, variance)[0], cvv, cvb, cbb)
    np.testing.assert_allclose(got, reference, rtol=1e-4, atol=1e-14)


# --- the calibration as a whole -------------------------------------------------------------------

def tank_frames(water, distances, frames_per_distance, noise_free=False, camera=None, size=(240, 180), seed=0):
    camera = camera or CameraModel(peak_code=0.7 * 65536)
    plate = load_rig(builtin_rig_path("grey-plate"))
    out, at, exposure = [], [], None
    for d in distances:
        world = SimulatedWorld(scene="plate", distance=d, size=size, water=water, lamp=LAMP, camera=camera,
                               fixed_exposure=exposure, seed=seed + int(10 * d))
        exposure = world.exposure
        for k in range(frames_per_distance):
            out.append(world.noise_free_frame() if noise_free else world.frame(k))
            at.append(d)
    intr, patch = world.intrinsics, plate.plate.black_patch
    inputs = CalibrationInputs(
        channel_names=["R", "G", "B"], wavelengths_nm=WAVELENGTHS, target_reflectance=np.full(3, 0.18),
        black_reflectance=np.full(3, 0.03), lamp_position_m=LAMP.position, intrinsics=intr,
        target_boxes=[project_plate_box((0, 0), plate.plate.size_m, d, intr) for d in at],
        black_boxes=[project_plate_box(patch.centre_m, patch.size_m, d, intr) for d in at],
        dark_level=np.full(3, camera.dark_level_dn), saturation_level=65535.0,
        quantisation_step=0.0 if noise_free else 1.0,
    )
    return out, at, inputs


def test_no_phantom_backscatter_on_noise_free_scatter_free_frames():
    water = water_preset("ideal", WAVELENGTHS)
    frames, at, inputs = tank_frames(water, (1.0, 2.0), 1, noise_free=True, camera=CameraModel(prnu=0.0, peak_code=45000))
    details = calibrate_with_details(frames, at, inputs)
    for g in details.groups:
        assert np.all(np.abs(g.backscatter.level) <= 1.0), g.backscatter.level
    v = details.profile.array("attenuation_difference")
    np.testing.assert_allclose(v[1:], [0.11 - 0.46, 0.06 - 0.46], rtol=1e-3)


@pytest.mark.parametrize("beta", [0.001, 0.01])
def test_attenuation_differences_within_0_3_percent_with_backscatter(beta):
    """The accuracy study's water: forward blur 0.010, backscatter β, not gated, noise-free frames."""
    from accuracy_study import study_water

    frames, at, inputs = tank_frames(study_water(0.010, beta), (1.0, 2.0), 1, noise_free=True,
                                     camera=CameraModel(prnu=0.0, peak_code=45000))
    v = calibrate_with_details(frames, at, inputs).profile.array("attenuation_difference")
    np.testing.assert_allclose(v[1:], [0.11 - 0.46, 0.06 - 0.46], rtol=0.003)


def test_repeated_distances_are_averaged_and_give_the_noise_model():
    water = water_preset("ideal", WAVELENGTHS)
    camera = CameraModel(peak_code=0.7 * 65536)
    frames, at, inputs = tank_frames(water, (1.0, 2.0), 3, camera=camera)
    details = calibrate_with_details(frames, at, inputs)
    profile = details.profile
    assert profile.provenance.distances_m == [1.0, 2.0] and profile.provenance.frames_per_distance == [3, 3]
    assert "temporal from repeated frames" in profile.provenance.method
    g = camera.gain_dn_per_e
    # The simulated sensor: shot noise g·E, dark-current shot noise and read noise constant, 1 % fixed pattern.
    np.testing.assert_allclose(profile.array("shot_gain"), g, rtol=0.1)
    np.testing.assert_allclose(profile.array("fixed_pattern"), camera.prnu, rtol=0.15)
    # Read noise hides under shot noise at every signal the plate shows, so what must be right is
    # the temporal variance over those signals: g·E + dark-current shot noise + read noise.
    constant = camera.dark_current_e * g**2 + (camera.read_noise_e * g) ** 2
    for _, point in details.noise_points:
        model = profile.array("read_noise") ** 2 + profile.array("shot_gain") * point.mean
        # A variance from n pixels × 2 degrees of freedom is good to about sqrt(1/n) (3σ allowed).
        np.testing.assert_allclose(model, constant + g * point.mean, rtol=max(0.05, 3 / np.sqrt(point.count)))
    cov = np.array(profile.covariance.matrix)
    np.testing.assert_allclose(np.sqrt(np.diag(cov))[:2], profile.array("attenuation_difference_std")[1:])


def test_calibration_study_goals_hold_on_a_few_trials():
    """The statistical goals, on 10 calibrations (bench/calibration_study.py runs 40): looser bounds."""
    from calibration_study import run_study

    res = run_study(trials=10, frames=4, size=(160, 120), ranges=(2.0, 6.0, 10.0))
    assert 0.75 < res.z_sd < 1.35, res
    assert abs(res.z_mean) < 0.3, res
    assert np.all((res.sigma_ratio > 0.5) & (res.sigma_ratio < 2.0)), res


# --- the crash of the issue ------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", ["float32", "uint16"])
def test_noise_free_uniform_frames_calibrate_without_a_traceback(tmp_path, dtype, capsys):
    """Regression: uniform plate regions have zero variance; the fit divided by it and wrote NaN."""
    rho, black_rho = 0.18, 0.03
    files = []
    for name, d, e in (("near", 1.0, np.array([9000.0, 20000.0, 25000.0])), ("far", 2.0, np.array([3000.0, 14000.0, 19000.0]))):
        f = np.zeros((60, 80, 3)) + e
        f[20:36, 10:26] = e * black_rho / rho
        path = tmp_path / f"{name}.npy"
        np.save(path, f.astype(dtype))
        files.append(str(path))
    out = tmp_path / "p.yaml"
    rc = main(["calibrate", *files, "--distance", "1", "--distance", "2", "--roi", "0,0,80,60",
               "--black-roi", "10,20,16,16", "--target-reflectance", "0.18,0.18,0.18", "-o", str(out)])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert "Traceback" not in captured.err
    profile = load_profile(out)
    for field in ("attenuation_difference_std", "log_constant_std", "read_noise", "shot_gain", "fixed_pattern"):
        assert np.all(np.isfinite(profile.array(field)))
    assert np.all(np.isfinite(profile.covariance.matrix))


# --- profile versions ------------------------------------------------------------------------------

def test_version_1_profile_loads_with_a_diagonal_covariance(tmp_path):
    v1 = {"format": "uwcam-calibration-profile", "version": 1, "name": "old", "reference_channel": "R",
          "saturation_level": 65535.0, "provenance": {"created": "2025-01-01T00:00:00+00:00", "method": "two-distance"},
          "channels": [{"name": "R", "attenuation_difference": 0.0, "log_constant": 0.0},
                       {"name": "G", "attenuation_difference": -0.35, "attenuation_difference_std": 0.002,
                        "log_constant": 0.3, "log_constant_std": 0.01},
                       {"name": "B", "attenuation_difference": -0.4, "attenuation_difference_std": 0.003,
                        "log_constant": 0.2, "log_constant_std": 0.02}]}
    path = tmp_path / "old.yaml"
    path.write_text(yaml.safe_dump(v1))
    profile = load_profile(path)
    assert profile.version == 2
    assert profile.covariance.parameters == ["V:G", "V:B", "b:G", "b:B"]
    np.testing.assert_allclose(np.array(profile.covariance.matrix), np.diag([0.002, 0.003, 0.01, 0.02]) ** 2)
    assert profile.array("fixed_pattern").tolist() == [0.0, 0.0, 0.0]


def test_a_bad_covariance_is_explained(tmp_path):
    from uwcam.fileio import UserInputError

    water = water_preset("ideal", WAVELENGTHS)
    frames, at, inputs = tank_frames(water, (1.0, 2.0), 1, size=(160, 120))
    data = calibrate_with_details(frames, at, inputs).profile.model_dump(mode="json")
    data["covariance"]["matrix"][0][0] = -1.0
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(UserInputError, match="positive semi-definite"):
        load_profile(path)


# --- the calibration's variance in ranging, and the report -------------------------------------

def covariance_profile(lamp=(0.3, 0.0, 0.0), shape=(120, 160)):
    from tests.synthetic import make_profile
    from uwcam.optics import Intrinsics
    from uwcam.calibration.profile import CalibrationCovariance

    intr = Intrinsics.from_fov(shape[1], shape[0], 60.0)
    base = make_profile([0.46, 0.11, 0.06], [0.0, 0.0, 0.0], read_noise=5.0, shot_gain=0.3, lamp=lamp, intrinsics=intr)
    a = np.random.default_rng(3).normal(size=(4, 4)) * np.array([3e-4, 3e-4, 2e-3, 2e-3])
    cov = CalibrationCovariance(parameters=["V:G", "V:B", "b:G", "b:B"], matrix=(a @ a.T).tolist())
    return base, base.model_copy(update={"covariance": cov}), intr


@pytest.mark.parametrize("lamp, near, far, intrinsics", [
    ((0.3, 0.0, 0.0), 3.0, 9.0, None),
    # A lamp close beside and above, surfaces near (its direction matters most there), non-square
    # pixels and an off-centre principal point: the block centres' rays must be the right ones.
    ((0.4, -0.35, 0.05), 1.0, 2.5, (150.0, 118.0, 71.3, 66.8)),
])
def test_ranging_adds_the_calibration_variance_and_smoothing_keeps_it(lamp, near, far, intrinsics):
    from uwcam.optics import Intrinsics
    from uwcam.ranging.smoothing import smooth_range_map
    from uwcam.ranging.estimator import RangeEstimator

    shape = (120, 160)
    base, with_cov, intr = covariance_profile(lamp=lamp, shape=shape)
    if intrinsics is not None:
        intr = Intrinsics(*intrinsics)
        k = {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy}
        base, with_cov = (p.model_copy(update={"intrinsics": k}) for p in (base, with_cov))
    yy, _ = np.mgrid[0 : shape[0], 0 : shape[1]]
    path = near + (far - near) * yy / shape[0]
    clean = 5e4 * np.exp(-np.array([0.46, 0.11, 0.06]) * path[..., None])
    frame = np.clip(np.rint(clean + np.sqrt(25 + 0.3 * clean) * np.random.default_rng(1).standard_normal(clean.shape)),
                    0, 65535).astype(np.uint16)
    plain = RangeEstimator(base)(frame)
    full = RangeEstimator(with_cov)(frame)
    assert plain.common_variance is None
    np.testing.assert_array_equal(full.range, plain.range)
    np.testing.assert_allclose(full.variance - plain.variance, full.common_variance, rtol=1e-5, atol=1e-12)
    # Reference: every pixel's own sensitivity from its expected signal, by the formula written out here.
    c = np.array([0.46, 0.11, 0.06])
    w = clean**2 / (25 + 0.3 * clean + 1 / 12)
    cw = (w * c).sum(-1, keepdims=True) / w.sum(-1, keepdims=True)
    h = w * (c - cw) / (w * (c - cw) ** 2).sum(-1, keepdims=True)
    cvv, cvb, cbb = with_cov.covariance_blocks()
    hv = np.einsum("...k,...kl->...l", h, cbb - path[..., None, None] * (cvb + cvb.T) + path[..., None, None] ** 2 * cvv)
    var_path = (hv * h).sum(-1)
    from uwcam.optics import camera_range_derivative, pixel_rays

    deriv = camera_range_derivative(path, with_cov.lamp_position_m, pixel_rays(intr, *shape))
    expected = deriv**2 * var_path
    inner = (slice(8, -8), slice(8, -8))  # the outermost blocks extrapolate
    np.testing.assert_allclose(full.common_variance[inner], expected[inner], rtol=0.03)
    smoothed = smooth_range_map(full, "mean")
    # Averaging 9 pixels divides the pixel noise by 9 but leaves the calibration's share whole.
    np.testing.assert_allclose(smoothed.variance[inner], (plain.variance[inner] / 9 + full.common_variance[inner]),
                               rtol=0.05)


def test_calibrate_report_is_one_self_contained_html(tmp_path, capsys):
    import re

    water = water_preset("ideal", WAVELENGTHS)
    frames, at, inputs = tank_frames(water, (1.0, 2.0), 2, size=(160, 120))
    files, args = [], []
    for i, (f, d) in enumerate(zip(frames, at)):
        path = tmp_path / f"f{i}.npy"
        np.save(path, f)
        files.append(str(path))
        args += ["--distance", str(d)]
    intr = inputs.intrinsics
    report = tmp_path / "report.html"
    rc = main(["calibrate", *files, *args, "--rig", "grey-plate", "--intrinsics", f"{intr.fx},{intr.fy},{intr.cx},{intr.cy}",
               "--lamp-offset", "0.3,0,0", "--dark-level", ",".join([str(inputs.dark_level[0])] * 3),
               "-o", str(tmp_path / "p.yaml"), "--report", str(report)])
    assert rc == 0, capsys.readouterr().err
    text = report.read_text()
    sources = re.findall(r"src=['\"]([^'\"]+)", text)
    assert len(sources) == 5 and all(s.startswith("data:image/png;base64,") for s in sources)
    assert "href=" not in text and "<script" not in text
    for heading in ("log-ratio", "residuals", "noise", "overlay", "range-sigma"):
        assert f"<h2>{heading}</h2>" in text
    assert load_profile(tmp_path / "p.yaml").provenance.frames_per_distance == [2, 2]
    assert main(["calibrate", *files, *args, "-o", str(tmp_path / "q.yaml"), "--report", str(tmp_path / "r.pdf")]) == 2
    assert "--report" in capsys.readouterr().err and not (tmp_path / "q.yaml").exists()


def test_black_patch_edges_do_not_leak_into_the_single_frame_noise_model():
    """One frame per distance, a black patch inside the target box: the noise region keeps clear of its
    edges (the old neighbour differences across them inflated the variance about 5×)."""
    from tests.synthetic import RGB_ATTENUATION, plate_frame
    from uwcam.optics import Intrinsics, signal_variance

    shape, fov = (120, 160), 50.0
    intr = Intrinsics.from_fov(shape[1], shape[0], fov)
    rng = np.random.default_rng(8)
    read, gain = 5.0, 0.4
    frames, boxes = [], []
    for d in (1.0, 1.6, 2.4):
        f, _ = plate_frame(d, RGB_ATTENUATION, np.array([0.7, 1.0, 0.85]) * 4e5, np.full(3, 0.18), shape, fov_deg=fov)
        box = project_plate_box((0.1, 0.1), (0.12, 0.12), d, intr)
        x, y, w, h = box
        f[y : y + h, x : x + w] *= 0.03 / 0.18
        frames.append(f + np.sqrt(read**2 + gain * f) * rng.standard_normal(f.shape))
        boxes.append(box)
    inputs = CalibrationInputs(channel_names=["R", "G", "B"], wavelengths_nm=[None] * 3, target_reflectance=np.full(3, 0.18),
                               black_reflectance=np.full(3, 0.03), black_boxes=boxes, intrinsics=intr,
                               saturation_level=1e12, quantisation_step=0.0)
    details = calibrate_with_details(frames, [1.0, 1.6, 2.4], inputs)
    p = details.profile
    for _, point in details.noise_points:
        model = signal_variance(point.mean, p.array("read_noise"), p.array("shot_gain"), 0.0, p.array("fixed_pattern"))
        # Within 20 % everywhere (read noise is the least determined part, at the black patch): not 5×.
        np.testing.assert_allclose(model, read**2 + gain * point.mean, rtol=0.2)


def test_calibration_variance_blocks_use_the_rays_through_their_centres():
    """The calibration's share is evaluated on 8×8 block averages: at each block's centre pixel
    position ((j + ½)·8 − ½, (i + ½)·8 − ½), whose ray is written out here from the pinhole."""
    from uwcam.ranging.calibration_share import block_rays
    from uwcam.ranging.estimator import RangeEstimator

    fx, fy, cx, cy = 150.0, 118.0, 71.3, 66.8
    _, with_cov, _ = covariance_profile(lamp=(0.4, -0.35, 0.05))
    profile = with_cov.model_copy(update={"intrinsics": {"fx": fx, "fy": fy, "cx": cx, "cy": cy}})
    h, w, block = 120, 160, 8
    rays = block_rays(RangeEstimator(profile), h // block, w // block, h, w)
    i, j = np.mgrid[0 : h // block, 0 : w // block]
    u = np.stack([((j + 0.5) * block - 0.5 - cx) / fx, ((i + 0.5) * block - 0.5 - cy) / fy, np.ones(i.shape)], axis=-1)
    np.testing.assert_allclose(rays, u / np.linalg.norm(u, axis=-1, keepdims=True), rtol=1e-12, atol=1e-12)
