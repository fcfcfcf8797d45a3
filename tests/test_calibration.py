"""Calibration recovers the simulated water and camera (docs/physics.md §4)."""

import numpy as np
import pytest

from tests.synthetic import RGB_ATTENUATION, plate_frame
from uwcam.calibration.fit import CalibrationInputs, calibrate, project_plate_box
from uwcam.calibration.line_fit import absolute_attenuation, fit_attenuation_differences
from uwcam.calibration.noise_fit import fit_noise_model
from uwcam.fileio import UserInputError
from uwcam.optics import Intrinsics, signal_variance, reflectance_ratio_from_range, surface_log_constant
from uwcam.ranging.estimator import RangeEstimator

CONSTANT = np.array([0.7, 1.0, 0.85]) * 4e5
PLATE = np.array([0.3, 0.25, 0.2])  # a plate that is not grey
SHAPE = (96, 128)
FOV = 50.0
INTR = Intrinsics.from_fov(SHAPE[1], SHAPE[0], FOV)
LAMP = np.array([0.2, -0.15, 0.0])


def inputs(**kw):
    base = dict(
        channel_names=["R", "G", "B"], wavelengths_nm=[None] * 3, target_reflectance=PLATE,
        lamp_position_m=tuple(LAMP), intrinsics=INTR, saturation_level=1e12, quantisation_step=0.0,
    )
    base.update(kw)
    return CalibrationInputs(**base)


def frames(distances, noise=None, rng=None, peak=None):
    out = []
    for d in distances:
        f, _ = plate_frame(d, RGB_ATTENUATION, CONSTANT, PLATE, SHAPE, LAMP, fov_deg=FOV)
        if noise is not None:
            read, gain = noise
            f = f + np.sqrt(read**2 + gain * f) * rng.standard_normal(f.shape)
        out.append(f)
    return out


@pytest.mark.parametrize("distances", [[1.0, 2.0], [0.8, 1.2, 1.6, 2.2, 3.0]])
def test_noise_free_calibration_recovers_attenuation_differences(distances):
    profile = calibrate(frames(distances), distances, inputs(lamp_radius_m=0.15))
    v = profile.array("attenuation_difference")
    np.testing.assert_allclose(v, RGB_ATTENUATION - RGB_ATTENUATION[0], rtol=2e-4, atol=2e-5)
    b = profile.array("log_constant")
    want_b = np.log(CONSTANT * PLATE) - np.log(CONSTANT[0] * PLATE[0])
    np.testing.assert_allclose(b, want_b, atol=5e-4)
    np.testing.assert_allclose(profile.array("attenuation"), RGB_ATTENUATION, rtol=2e-3)
    assert profile.provenance.method.startswith("two-distance" if len(distances) == 2 else "generalised least squares")
    assert len(profile.provenance.residuals["G"]) == len(distances)


def test_noisy_five_distance_calibration_reports_honest_uncertainty():
    rng = np.random.default_rng(1)
    distances = [0.8, 1.2, 1.6, 2.2, 3.0]
    profile = calibrate(frames(distances, (5.0, 0.5), rng), distances, inputs())
    v = profile.array("attenuation_difference")
    v_std = profile.array("attenuation_difference_std")
    truth = RGB_ATTENUATION - RGB_ATTENUATION[0]
    assert np.all(v_std[1:] > 0)
    assert np.all(np.abs(v - truth)[1:] < 5 * v_std[1:] + 1e-4)
    np.testing.assert_allclose(v, truth, atol=2e-3)


def test_noise_model_is_estimated_from_the_target_region():
    rng = np.random.default_rng(2)
    distances = [0.8, 1.5, 2.5]
    read, gain = 6.0, 0.4
    f = frames(distances, (read, gain), rng)
    profile = calibrate(f, distances, inputs())
    # One frame per distance: read, shot and fixed pattern are told apart only by how the spread
    # grows with signal, so what must be right is the total variance over the signals seen.
    lo = np.min([np.percentile(x.reshape(-1, 3), 1, axis=0) for x in f], axis=0)
    hi = np.max([np.percentile(x.reshape(-1, 3), 99, axis=0) for x in f], axis=0)
    signal = np.linspace(lo, hi, 50)  # (50, 3): each channel over the signals it showed
    predicted = signal_variance(signal, profile.array("read_noise"), profile.array("shot_gain"), 0.0,
                                profile.array("fixed_pattern"))
    np.testing.assert_allclose(predicted, read**2 + gain * signal, rtol=0.1)
    np.testing.assert_allclose(profile.array("shot_gain"), gain, rtol=0.2)


def test_noise_model_fit_handles_degenerate_points():
    read, gain = fit_noise_model(np.array([[100.0, 50.0], [400.0, 50.0]]), np.array([[29.0, -1.0], [89.0, 9.0]]), 0.0)
    np.testing.assert_allclose([read[0], gain[0]], [3.0, 0.2])
    assert gain[1] == 0.0 and read[1] >= 0.0


def test_black_patch_gives_the_noise_floor():
    rng = np.random.default_rng(3)
    distances = [1.0, 2.0]
    black_rho = 0.02
    out = []
    boxes = [project_plate_box((0.1, 0.1), (0.12, 0.12), d, INTR) for d in distances]
    for f, box in zip(frames(distances), boxes):
        x, y, w, h = box
        f[y : y + h, x : x + w] *= black_rho / PLATE
        f += 30.0 + 2.0 * rng.standard_normal(f.shape)  # backscatter-like offset plus noise
        out.append(f)
    profile = calibrate(out, distances, inputs(black_boxes=boxes, black_reflectance=np.full(3, black_rho)))
    floor = profile.array("noise_floor")
    assert np.all(floor > 30.0) and np.all(floor < 30.0 + 3 * 2.0 * 1.5 + 5)


def test_two_point_closed_form_matches_design_formula():
    e1, e2 = np.array([100.0, 300.0]), np.array([40.0, 200.0])
    fit = fit_attenuation_differences(np.log([e1, e2]), [2.0, 4.0])
    v_design = np.log((e1[0] / e2[0]) / (e1[1] / e2[1])) / (2.0 - 4.0)
    assert fit.attenuation_difference[1] == pytest.approx(v_design)
    u_design = (e1[1] / e1[0]) * np.exp(v_design * 2.0)
    assert np.exp(fit.log_constant[1]) == pytest.approx(u_design)


def test_absolute_attenuation_two_point_formula():
    c, r = 0.3, 0.1
    ds = np.array([1.0, 3.0])
    d_t = 2 * ds
    e = (r / (ds + r)) ** 2 * np.exp(-c * d_t)
    got, _ = absolute_attenuation(np.log(e)[:, None] + 2 * np.log(ds + r)[:, None], d_t)
    assert got[0] == pytest.approx(c)


def test_reflectance_ratio_from_known_range():
    # A surface redder than the calibration plate, seen at known ranges.
    surface = np.array([0.5, 0.25, 0.2])
    path = np.array([2.0, 3.0, 4.5])
    signal = CONSTANT * surface * np.exp(-RGB_ATTENUATION * path[:, None]) * np.array([[0.3], [0.7], [1.0]])
    b_target = np.log(CONSTANT * PLATE)
    ratio = reflectance_ratio_from_range(signal, path, RGB_ATTENUATION, b_target)
    want = (surface / surface[0]) / (PLATE / PLATE[0])
    np.testing.assert_allclose(ratio, want, rtol=1e-12)
    b = surface_log_constant(signal, path, RGB_ATTENUATION)
    np.testing.assert_allclose(b, np.log(CONSTANT * surface) - np.log(CONSTANT[0] * surface[0]), atol=1e-12)


def test_surface_of_another_hue_ranges_correctly_once_its_reflectance_is_known():
    distances = [1.0, 2.0]
    profile = calibrate(frames(distances), distances, inputs())
    surface = np.array([0.5, 0.25, 0.2])
    f, dc = plate_frame(1.7, RGB_ATTENUATION, CONSTANT, surface, SHAPE, LAMP, fov_deg=FOV)
    wrong = RangeEstimator(profile)(f).range
    right = RangeEstimator(profile, surface_reflectance=surface)(f).range
    assert np.nanmax(np.abs(right - dc)) < 2e-3
    assert np.nanmean(np.abs(wrong - dc)) > 0.1


@pytest.mark.parametrize(
    "kwargs, frames_, distances, message",
    [
        ({}, "one", [1.0], "calibration needs images at two or more distances"),
        ({}, "two", [1.0], "got 2 images but 1 --distance values"),
        ({}, "two", [1.0, -2.0], "distances must be positive metres"),
        ({}, "two", [1.5, 1.5], "two or more different distances"),
        ({"target_box": (100, 10, 50, 50)}, "two", [1.0, 2.0], "does not lie inside the 128×96 image"),
        ({"saturation_level": 1000.0}, "two", [1.0, 2.0], "is saturated in channel"),
        ({}, "dark", [1.0, 2.0], "has no signal in channel"),
    ],
)
def test_bad_calibration_input_is_explained(kwargs, frames_, distances, message):
    f = frames([1.0, 2.0])
    data = {"one": f[:1], "two": f, "dark": [np.zeros_like(x) for x in f]}[frames_]
    with pytest.raises(UserInputError, match=message):
        calibrate(data, distances, inputs(**kwargs))


def test_reflectance_corrector_recovers_a_surface_of_another_hue():
    """A rangefinder reading at the footprint turns a wrong-hue range map into a right one (§8)."""
    from types import SimpleNamespace

    from uwcam.config import ReflectanceConfig
    from uwcam.drivers.base import Frame, Health, HealthState
    from uwcam.drivers.rangefinder import RangeReading
    from uwcam.runtime.stages.reflectance import ReflectanceCorrector

    distances = [1.0, 2.0]
    profile = calibrate(frames(distances), distances, inputs())
    surface = np.array([0.5, 0.25, 0.2])  # redder than the plate
    data, dc = plate_frame(1.7, RGB_ATTENUATION, CONSTANT, surface, SHAPE, LAMP, fov_deg=FOV)
    h, w = SHAPE
    centre = (w // 2 - 2, h // 2 - 2, 5, 5)
    now = 10**12
    reading = RangeReading(float(dc[h // 2, w // 2]), 0.97, now, 0.0)
    rf = SimpleNamespace(health=Health(HealthState.OK, "reading"), latest=lambda: reading)
    corrector = ReflectanceCorrector(ReflectanceConfig(footprint=centre), profile, rf)
    frame = Frame(data=data, sequence=1, host_monotonic_ns=now, wall_time=0.0)
    b = corrector.update(frame, profile.array("attenuation_difference"))
    assert corrector.status()["state"] == "correcting"
    channels = [c.model_copy(update={"log_constant": float(v)}) for c, v in zip(profile.channels, b)]
    corrected = RangeEstimator(profile.model_copy(update={"channels": channels}))(data).range
    wrong = RangeEstimator(profile)(data).range
    assert np.nanmax(np.abs(corrected - dc)) < 0.01 < np.nanmean(np.abs(wrong - dc))
    stale = Frame(data=data, sequence=2, host_monotonic_ns=now + 2 * 10**9, wall_time=0.0)
    corrector.update(stale, profile.array("attenuation_difference"))
    assert corrector.status()["state"].startswith("paused: reading 2.00 s from the frame")


@pytest.mark.parametrize("lamp, tolerance", [((0.0, 0.0, 0.0), 1e-3), ((0.1, 0.0, 0.0), 4e-3)])
def test_absolute_attenuation_in_the_simulator_equals_its_water(lamp, tolerance):
    """Water that only absorbs and scatters nothing away from the beam ("ideal": no backscatter, no
    forward scatter): the calibration's absolute c_k must be the simulator's. The plate fills less
    of the view at 2 m than at 1 m, so pixels lit by the beam's dim edge (50° half angle) take part
    at 1 m only; before they were left out the fit read the water 0.02 1/m clearer. With the lamp
    beside the camera the beam meets a pixel's spot at an angle that changes with distance: 0.003 1/m
    remain."""
    from uwcam.simulation.render import Lamp
    from uwcam.simulation.tank import calibrate_in_simulation
    from uwcam.simulation.water import water_preset

    water = water_preset("ideal", [675.0, 575.0, 475.0])
    profile = calibrate_in_simulation(water, Lamp(position=lamp), (160, 120), noise_free=True)
    np.testing.assert_allclose(profile.array("attenuation"), water.attenuation, atol=tolerance)
