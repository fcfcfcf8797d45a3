"""Response curves of 8-bit gamma cameras: standards, recovery from a bracket, the profile, ranging.

Expected values come from the standards' own formulas and tables (IEC 61966-2-1 for sRGB,
ITU-R BT.709) and from the simulator's ground truth, not from uwcam.imaging.response.
"""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from uwcam.cli import main
from uwcam.fileio import UserInputError
from uwcam.imaging.imageio import read_frame
from uwcam.calibration.profile import load_profile, profile_from_mapping, profile_to_yaml
from uwcam.ranging.estimator import RangeEstimator
from uwcam.imaging.response import ResponseCurve, encode, recover
from uwcam.simulation import CameraModel, Lamp, SimulatedWorld, water_preset
from uwcam.simulation.tank import calibrate_in_simulation


def test_standard_curves_match_their_specifications():
    srgb = ResponseCurve.standard("srgb", 8, 3)
    # IEC 61966-2-1: encoded 128/255 is linear 0.21586; 10/255 is on the linear toe, (10/255)/12.92.
    assert srgb.table[0, 128] / 255 == pytest.approx(0.21586, abs=2e-5)
    assert srgb.table[1, 10] / 255 == pytest.approx(10 / 255 / 12.92, rel=1e-9)
    rec = ResponseCurve.standard("rec709", 8, 3)
    # BT.709: V = 1.099 L^0.45 − 0.099, so V = 0.5 is L = (0.599/1.099)^(1/0.45) = 0.25958.
    v = np.arange(256) / 255
    assert np.interp(0.5, v, rec.table[0] / 255) == pytest.approx(0.25958, abs=3e-4)
    # Encoding and linearising are inverse on every code.
    codes = np.arange(256, dtype=np.uint8)[None, :, None].repeat(3, axis=2)
    assert np.array_equal(encode(srgb.linearise(codes), "srgb", 8), codes)


def test_quantisation_after_the_inverse_curve_follows_the_curve_slope():
    srgb = ResponseCurve.standard("srgb", 8, 1)
    # d(linear)/d(code) of sRGB at the top code: 2.4/1.055·((1 + 0.055)/1.055)^1.4 = 2.2749 DN per code.
    top = srgb.quantisation_variance(np.array([[255.0]]))[0, 0]
    assert np.sqrt(12 * top) == pytest.approx(2.2749, rel=0.01)
    # On the linear toe one code is 1/12.92 DN wide.
    toe = srgb.quantisation_variance(np.array([[5 / 12.92]]))[0, 0]
    assert np.sqrt(12 * toe) == pytest.approx(1 / 12.92, rel=1e-6)


def test_response_recovered_from_a_simulated_bracket_is_srgb():
    water = water_preset("jerlov-IB", [675.0, 575.0, 475.0])
    camera = CameraModel(bits=8, response="srgb", read_noise_e=2.0)
    base = SimulatedWorld(scene="seabed", distance=1.5, size=(160, 120), water=water, lamp=Lamp(), camera=camera, seed=3)
    exposures = [base.exposure * f for f in (0.125, 0.25, 0.5, 1.0, 2.0, 4.0)]
    frames = [SimulatedWorld(scene="seabed", distance=1.5, size=(160, 120), water=water, lamp=Lamp(), camera=camera,
                             seed=3, fixed_exposure=t).frame(0) for t in exposures]
    curve = recover(frames, exposures)
    truth = ((np.arange(256) / 255 + 0.055) / 1.055) ** 2.4  # IEC 61966-2-1 above the toe
    mid = slice(40, 230)
    for k in range(3):
        got = curve.table[k, mid] / curve.table[k, 255]
        assert np.median(np.abs(got / truth[mid] - 1)) < 0.08, k
    # A straight line would be wrong by 2× at mid-grey: the recovered curve is nothing like it.
    assert curve.table[1, 128] / curve.table[1, 255] < 0.3


def test_recovery_refuses_bad_brackets():
    frame = np.zeros((8, 8, 3), np.uint8)
    with pytest.raises(UserInputError, match="two different exposures"):
        recover([frame, frame], [0.01, 0.01])
    with pytest.raises(UserInputError, match="8-bit frames with three channels"):
        recover([frame.astype(np.uint16)] * 2, [0.01, 0.02])


@pytest.fixture(scope="module")
def gamma_rig():
    water = water_preset("jerlov-IB", [675.0, 575.0, 475.0])
    lamp = Lamp(position=(0.3, 0.0, 0.0))
    camera = CameraModel(bits=8, response="srgb")
    right = calibrate_in_simulation(water, lamp, (160, 120), camera, frames_per_distance=3)
    ignored = calibrate_in_simulation(water, lamp, (160, 120), camera, frames_per_distance=3, linearise=False)
    world = SimulatedWorld(scene="plate", distance=1.5, size=(160, 120), water=water, lamp=lamp, camera=camera, seed=9)
    return right, ignored, world


def test_profile_keeps_the_curve_and_older_profiles_still_load(gamma_rig):
    right, ignored, _ = gamma_rig
    assert right.response is not None and right.response.kind == "srgb" and ignored.response is None
    again = profile_from_mapping(yaml.safe_load(profile_to_yaml(right)))
    assert again.response == right.response
    older = yaml.safe_load(profile_to_yaml(ignored))
    assert "response" not in older or older["response"] is None
    older.pop("response", None)  # a version-2 profile written before response curves existed
    assert profile_from_mapping(older).response is None


def test_an_8_bit_srgb_plate_ranges_right_only_through_the_curve(gamma_rig):
    right, ignored, world = gamma_rig
    frame = world.frame(0)
    assert frame.dtype == np.uint8
    centre = (slice(40, 80), slice(60, 100))
    truth = np.median(world.camera_range[centre])
    good = RangeEstimator(right)(frame)
    bad = RangeEstimator(ignored)(frame)
    assert abs(np.nanmedian(good.range[centre]) / truth - 1) < 0.03
    # The codes taken as linear: −5.8 % here (−1.6 % through the curve); at 1.5 m, between the
    # calibration's plates at 1 and 2 m, the interpolation hides most of the curve's error.
    assert abs(np.nanmedian(bad.range[centre]) / truth - 1) > 0.05
    # The same answer whether the estimator takes the codes (lookup tables) or linear light.
    linear = right.response_curve().linearise(frame)
    assert np.allclose(RangeEstimator(right)(linear).range, good.range, rtol=1e-4, equal_nan=True)
    # σ is honest over the plate: z = error/σ has an sd near 1.
    z = (good.range[centre] - world.camera_range[centre]) / np.sqrt(good.variance[centre])
    assert 0.7 < np.nanstd(z) < 1.4


def test_cli_simulate_calibrate_range_an_srgb_camera(tmp_path, capsys):
    common = ["--bits", "8", "--response", "srgb", "--size", "160x120", "--water", "jerlov-IB", "--exposure", "2e8",
              "--lamp-offset", "0.3,0,0"]
    for d in ("1", "2", "1.5"):
        assert main(["simulate", "--scene", "plate", "--range", d, "-o", str(tmp_path / f"p{d}.png"), *common,
                     *(["--truth", str(tmp_path / "truth.npy")] if d == "1.5" else [])]) == 0
    printed = capsys.readouterr().out.splitlines()
    intr = [line for line in printed if line.startswith("intrinsics")][0].split()[1]
    dark = [line for line in printed if line.startswith("dark level")][0].split()[2].rstrip(";")
    profile = tmp_path / "gamma.yaml"
    assert main(["calibrate", str(tmp_path / "p1.png"), str(tmp_path / "p2.png"), "--distance", "1", "--distance", "2",
                 "--rig", "grey-plate", "--intrinsics", intr, "--lamp-offset", "0.3,0,0", "--response", "srgb", "--dark-level", f"{dark},{dark},{dark}",
                 "-o", str(profile)]) == 0
    assert load_profile(profile).response.kind == "srgb"
    assert main(["range", str(profile), str(tmp_path / "p1.5.png"), "-o", str(tmp_path / "r.npy"),
                 "--compensate-backscatter"]) == 0
    got = np.load(tmp_path / "r.npy")[40:80, 60:100]
    truth = np.load(tmp_path / "truth.npy")[40:80, 60:100]
    assert abs(np.nanmedian(got) / np.median(truth) - 1) < 0.03
    assert read_frame(tmp_path / "p1.png").dtype == np.uint8


def test_cli_response_writes_a_curve_calibrate_accepts(tmp_path, capsys):
    water = water_preset("jerlov-IB", [675.0, 575.0, 475.0])
    camera = CameraModel(bits=8, response="srgb")
    base = SimulatedWorld(scene="seabed", distance=1.5, size=(120, 90), water=water, lamp=Lamp(), camera=camera, seed=3)
    names = []
    from uwcam.imaging.imageio import write_frame

    factors = (0.25, 0.5, 1.0, 2.0)
    for f in factors:
        frame = SimulatedWorld(scene="seabed", distance=1.5, size=(120, 90), water=water, lamp=Lamp(), camera=camera,
                               seed=3, fixed_exposure=base.exposure * f).frame(0)
        names.append(str(tmp_path / f"b{f}.png"))
        write_frame(names[-1], frame)
    out = tmp_path / "cam.yaml"
    assert main(["response", *names, "--exposure-ms", ",".join(str(10 * f) for f in factors), "-o", str(out)]) == 0
    assert "code 128 is" in capsys.readouterr().out
    from uwcam.imaging.response import load_response

    curve = load_response(str(out), 3)
    assert curve.kind == "table" and curve.table.shape == (3, 256)
    assert main(["response", *names[:2], "--exposure-ms", "1", "-o", str(out)]) == 2
    assert "--exposure-ms needs 2" in capsys.readouterr().err


def test_simulator_refuses_a_curve_on_a_deep_camera():
    with pytest.raises(UserInputError, match="8-bit cameras"):
        CameraModel(bits=16, response="srgb")
    with pytest.raises(UserInputError, match="JPEG quality must be 1 to 100"):
        CameraModel(bits=8, jpeg_quality=0)


def test_the_daemon_pipeline_ranges_a_gamma_camera_through_its_curve(gamma_rig):
    """The frame loop linearises each frame before tracking, compensation and ranging, and keeps
    the camera's own codes for what it shows and records."""
    import threading
    import time

    from tests.waiting import wait_for
    from uwcam.config import ProcessingConfig
    from uwcam.drivers.base import Frame
    from uwcam.runtime.pipeline import FramePipeline

    right, _, world = gamma_rig
    data = world.frame(1)

    class OneFrame:
        def __init__(self):
            self.frames = [Frame(data=data, sequence=1, host_monotonic_ns=time.monotonic_ns(), wall_time=time.time())]
            self.lock = threading.Lock()

        def get(self, timeout_s):
            with self.lock:
                if self.frames:
                    return self.frames.pop()
            time.sleep(min(timeout_s, 0.01))
            return None

    pipeline = FramePipeline(OneFrame(), right, ProcessingConfig(smoothing="mean", smoothing_stage="before"))
    published = []
    pipeline.subscribe(published.append)
    pipeline.start()
    try:
        assert wait_for(lambda: published, 30.0)
    finally:
        pipeline.stop()
    p = published[0]
    assert p.frame.data.dtype == np.uint8 and np.array_equal(p.frame.data, data)  # shown as the camera sent it
    centre = (slice(40, 80), slice(60, 100))
    truth = np.median(world.camera_range[centre])
    assert abs(np.nanmedian(p.result.range[centre]) / truth - 1) < 0.03
