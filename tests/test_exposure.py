"""Every channel in range: per-channel exposure in frames, profiles and the estimator, and the
radiometric exposure controller on the simulated camera."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from tests.synthetic import make_profile, plate_frame
from uwcam.config import ExposureConfig, ProcessingConfig
from uwcam.drivers.base import Frame
from uwcam.drivers.sim import SimulatedCamera
from uwcam.runtime.stages.exposure import ExposureController, next_exposure, Metering
from uwcam.calibration.profile import profile_from_mapping, profile_to_yaml
from uwcam.ranging.estimator import RangeEstimator
from uwcam.simulation import CameraModel, Lamp, water_preset
from uwcam.simulation.tank import calibrate_in_simulation

C = np.array([0.46, 0.11, 0.06])  # 1/m, R G B
B = np.array([0.0, -0.3, 0.2])
DARK = 100.0
READ, SHOT = 3.0, 0.5


def profile_with(exposure_us=None, gain_db=None, **noise):
    p = make_profile(C, B, dark_level=DARK, **noise)
    if exposure_us is None and gain_db is None:
        return p
    channels = [c.model_copy(update={"exposure_us": None if exposure_us is None else exposure_us[k],
                                     "gain_db": None if gain_db is None else gain_db[k]})
                for k, c in enumerate(p.channels)]
    return p.model_copy(update={"channels": channels})


def scene(distance=3.0):
    """Dark-corrected light E (H, W, 3) of a plate at ``distance`` m, the lamp at the camera, and its camera range."""
    light, dc = plate_frame(distance, C, np.exp(B), np.ones(3))
    return light * (20000.0 / light.max()), dc


@pytest.mark.parametrize("recorded", [True, False])
def test_a_channel_exposed_m_times_ranges_exactly_as_at_the_calibration_exposure(recorded):
    profile = profile_with((1000.0,) * 3 if recorded else None)
    light, truth = scene()
    m = np.array([4.0, 1.0, 0.25])
    at_calibration = RangeEstimator(profile)(light + DARK)
    est = RangeEstimator(profile)
    est.set_exposure(1000.0 * m)
    exposed = est(light * m + DARK)
    valid = np.isfinite(truth)
    np.testing.assert_allclose(exposed.range[valid], at_calibration.range[valid], rtol=1e-5)  # float32 outputs
    np.testing.assert_allclose(exposed.range[valid], truth[valid], rtol=1e-5)
    # Without the correction the same frame ranges wrongly: the test can fail.
    assert np.nanmax(np.abs(RangeEstimator(profile)(light * m + DARK).range - truth)) > 0.1


def test_integer_frames_at_other_exposures_use_the_same_correction_in_the_lookup_path():
    profile = profile_with((1000.0,) * 3)
    light, truth = scene(2.0)
    m = np.array([3.0, 1.0, 0.5])
    counts = np.rint(light * m + DARK).astype(np.uint16)
    est = RangeEstimator(profile)
    est.set_exposure(1000.0 * m)
    table = est(counts)
    arrays = est(counts.astype(np.float64))  # the array path, with the same integer values
    np.testing.assert_allclose(table.range, arrays.range, rtol=1e-5)
    assert np.nanmedian(np.abs(table.range / truth - 1)) < 1e-3


def test_the_variance_is_that_of_the_raw_counts():
    """Pair R/B, lamp at the camera: d_c = d_T/2 and var d_T = (σ_R²/E_R² + σ_B²/E_B²)/(c_R − c_B)²,
    σ² = read² + shot_gain·E + 1/12 evaluated on the counts the sensor delivered."""
    profile = profile_with((1000.0,) * 3, read_noise=READ, shot_gain=SHOT)
    light, _ = scene(4.0)
    m = np.array([8.0, 1.0, 1.0])
    raw = light * m
    est = RangeEstimator(profile, pair=("R", "B"))
    est.set_exposure(1000.0 * m)
    out = est(raw + DARK)
    sigma2 = READ**2 + SHOT * raw + 1.0 / 12.0
    expected = (sigma2[..., 0] / raw[..., 0] ** 2 + sigma2[..., 2] / raw[..., 2] ** 2) / (C[0] - C[2]) ** 2 / 4.0
    np.testing.assert_allclose(out.variance, expected, rtol=1e-4)
    # Red exposed 8 times longer carries less relative noise than at the calibration's exposure.
    plain = RangeEstimator(profile, pair=("R", "B"))(light + DARK)
    assert np.all(out.variance < plain.variance)


def test_gain_scales_the_signal_and_the_noise_in_counts():
    profile = profile_with((1000.0,) * 3, (0.0,) * 3, read_noise=READ, shot_gain=SHOT)
    light, truth = scene(3.0)
    gain = 20 * np.log10(2.0)  # ×2 in red
    raw = light * np.array([2.0, 1.0, 1.0])
    est = RangeEstimator(profile, pair=("R", "B"))
    est.set_exposure((1000.0,) * 3, (gain, 0.0, 0.0))
    out = est(raw + DARK)
    np.testing.assert_allclose(out.range, truth, rtol=1e-5)
    sigma2_r = (2 * READ) ** 2 + 2 * SHOT * raw[..., 0] + 1.0 / 12.0  # amplified read and shot noise
    sigma2_b = READ**2 + SHOT * raw[..., 2] + 1.0 / 12.0
    expected = (sigma2_r / raw[..., 0] ** 2 + sigma2_b / raw[..., 2] ** 2) / (C[0] - C[2]) ** 2 / 4.0
    np.testing.assert_allclose(out.variance, expected, rtol=1e-4)


def test_bad_exposures_are_refused():
    est = RangeEstimator(profile_with())
    for bad in ([1.0, 2.0], [1.0, 0.0, 1.0], [1.0, float("nan"), 1.0]):
        with pytest.raises(ValueError):
            est.set_exposure(bad)


def test_the_profile_keeps_the_exposure_it_was_calibrated_at():
    p = profile_with((1000.0, 2000.0, 500.0), (0.0, 6.0, 0.0))
    again = profile_from_mapping(__import__("yaml").safe_load(profile_to_yaml(p)), "test")
    t, g = again.calibration_exposure()
    assert list(t) == [1000.0, 2000.0, 500.0] and list(g) == [0.0, 6.0, 0.0]
    assert "exposure_us" not in profile_to_yaml(profile_with())  # not recorded: not written
    data = __import__("yaml").safe_load(profile_to_yaml(p))
    data["channels"][1]["exposure_us"] = -1.0
    with pytest.raises(Exception, match="exposure_us"):
        profile_from_mapping(data, "test")


def test_frames_give_one_exposure_per_channel():
    data = np.zeros((2, 2, 3), np.uint16)
    f = Frame(data, 1, 0, 0.0, exposure_us=500.0, gain_db=1.0)
    assert f.exposures() == ((500.0,) * 3, (1.0,) * 3)
    f = Frame(data, 1, 0, 0.0, exposure_us=500.0, channel_exposure_us=(1.0, 2.0, 3.0))
    assert f.exposures() == ((1.0, 2.0, 3.0), None)


@pytest.mark.parametrize("bad", [
    {"target": 1.5}, {"target": float("nan")}, {"high_percentile": 101}, {"low_percentile": 60},
    {"min_exposure_us": 0}, {"max_exposure_us": float("inf")}, {"min_exposure_us": 5000.0, "max_exposure_us": 1000.0},
    {"max_step": 1.0}, {"tolerance": -0.1}, {"speed": 2},
])
def test_exposure_settings_are_validated(bad):
    with pytest.raises(ValidationError):
        ProcessingConfig(exposure=bad)


def test_one_exposure_for_all_channels_keeps_the_strongest_below_saturation():
    config = ExposureConfig(max_step=100.0)
    metering = Metering(high=np.array([1100.0, 30000.0, 65535.0]), low=np.array([5.0, 500.0, 5000.0]))
    new, states = next_exposure(metering, np.full(3, 1000.0), np.full(3, 100.0), np.full(3, 20.0), 65535.0, config,
                                per_channel=False)
    assert np.all(new == new[0]) and new[0] < 1000.0  # the saturated channel sets the one exposure
    assert states[2] == "ok" and states[0] == "held back"
    new, states = next_exposure(metering, np.full(3, 1000.0), np.full(3, 100.0), np.full(3, 20.0), 65535.0, config)
    # Per channel: red gets (0.8·65535 − 100)/1000 ≈ 52 times its exposure, blue steps down.
    assert new[0] == pytest.approx(1000.0 * (0.8 * 65535 - 100) / 1000.0) and new[2] == pytest.approx(10.0)


@pytest.fixture(scope="module")
def sim_profile():
    return calibrate_in_simulation(water_preset("jerlov-IB", [675.0, 575.0, 475.0]), Lamp(position=(0.3, 0.0, 0.0)),
                                   (64, 48), CameraModel(), frames_per_distance=2)


def run(camera: SimulatedCamera, controller: ExposureController, est: RangeEstimator, frames: int) -> list:
    """Read ``frames`` frames, ranging each at its own exposure and applying the controller's requests."""
    history = []
    for _ in range(frames):
        f = camera.read(1.0)
        exposure, gain = f.exposures()
        est.set_exposure(exposure, gain)
        result = est(f.data)
        wanted = controller.update(f.data, exposure, f.lamp_on, est.dark, est.floor, est.profile.saturation_level)
        history.append((exposure, dict(controller.last), float(np.isfinite(result.range).mean())))
        if wanted is not None:
            camera.set_exposure(wanted)
    return history


def test_a_channel_pushed_below_its_floor_comes_back(sim_profile):
    camera = SimulatedCamera(fps=1000.0, size=(64, 48), scene="seabed", distance=5.0, water="jerlov-IB", material="grey")
    camera.open()
    camera.start()
    try:
        controller = ExposureController(ExposureConfig(), ("R", "G", "B"), camera.exposure_control)
        est = RangeEstimator(sim_profile)
        settled = run(camera, controller, est, 12)[-1]
        assert all(ch["state"] == "ok" for ch in settled[1].values()), settled
        valid_before = settled[2]
        assert valid_before > 0.9
        # Red pushed down 400 times: below its floor, and ranging loses the pixels that need it.
        pushed = tuple(v / 400 if k == 0 else v for k, v in enumerate(settled[0]))
        camera.set_exposure(pushed)
        history = run(camera, controller, est, 12)
        first = history[0]
        assert first[0] == pytest.approx(pushed) and first[1]["R"]["state"] == "below floor"
        assert first[1]["R"]["low_dn"] <= first[1]["R"]["floor_dn"]
        # Bounded steps: at most ×2 a frame; back within the 12 frames (400 = 2^8.6).
        steps = [h[0][0] / g[0][0] for g, h in zip(history, history[1:])]
        assert max(steps) <= 2.0 + 1e-9
        back = [k for k, h in enumerate(history) if h[1]["R"]["state"] == "ok"]
        assert back and back[0] <= 11
        assert history[-1][1]["R"]["low_dn"] > history[-1][1]["R"]["floor_dn"]
        assert history[-1][2] >= valid_before - 0.02
        # The other channels were left where they were.
        assert history[-1][0][1:] == pytest.approx(settled[0][1:], rel=0.11)
    finally:
        camera.close()


def test_a_multi_device_rig_sets_one_exposure_per_device():
    from uwcam.drivers import registry

    sensors = [{"driver": "sim", "serial_number": f"SIM-MULTI-{k}", "fps": 1000.0, "size": [32, 24], "seed": 3,
                "material": "grey", "channel": k} for k in range(3)]
    rig = registry.create("camera", "multi", sensors=sensors, channel_names=("R", "G", "B"))
    assert rig.exposure_control == "per-channel"
    rig.open()
    rig.start()
    try:
        before = rig.read(1.0)
        assert before.exposures()[0] == (10000.0,) * 3
        rig.set_exposure((20000.0, 10000.0, 2500.0))
        after = rig.read(1.0)
        assert after.channel_exposure_us == (20000.0, 10000.0, 2500.0)
        dark = CameraModel().dark_level_dn
        ratio = (after.data.astype(float).mean(axis=(0, 1)) - dark) / (before.data.astype(float).mean(axis=(0, 1)) - dark)
        np.testing.assert_allclose(ratio, [2.0, 1.0, 0.25], rtol=0.02)
    finally:
        rig.close()


def test_hdr_takes_each_channel_from_its_longest_unsaturated_exposure():
    from uwcam.runtime.stages.hdr import merge_exposures

    short = np.full((10, 10, 3), 1000, np.uint16)
    long = np.full((10, 10, 3), 8000, np.uint16)
    long[0, 0, 2] = 65535  # one clipped pixel in 100: blue saturates in the long frame
    short[0, 0, 1] = long[0, 0, 1] = 65535  # green clipped in both: the shortest is taken
    merged, exposure, chosen = merge_exposures([short, long], [(1000.0,) * 3, (8000.0,) * 3], 65535)
    assert chosen == [1, 0, 0] and exposure == (8000.0, 1000.0, 1000.0)
    assert merged[5, 5].tolist() == [8000, 1000, 1000] and merged.dtype == np.uint16
    with pytest.raises(ValueError):
        merge_exposures([short, long], [(1000.0,) * 3], 65535)


def test_a_merged_bracket_ranges_exactly():
    from uwcam.runtime.stages.hdr import HdrMerger

    profile = profile_with((1000.0,) * 3)
    light, truth = scene(6.0)
    light = light * (60000.0 / light[..., 2].max())  # blue fills the short exposure; red is ~100 times weaker
    frames = [Frame(np.minimum(light * m + DARK, 65535.0), n, 0, 0.0, exposure_us=1000.0 * m, lamp_on=True)
              for n, m in ((1, 1.0), (2, 64.0))]
    merger = HdrMerger(65535.0)
    assert merger(frames[0]) is frames[0]  # nothing to merge with yet
    merged = merger(frames[1])
    red, green, blue = merged.channel_exposure_us
    assert red == 64000.0 and blue == 1000.0 and merger.merged == 1
    assert green == (64000.0 if (light[..., 1] * 64 + DARK).max() < 65535 else 1000.0)
    est = RangeEstimator(profile)
    est.set_exposure(*merged.exposures())
    np.testing.assert_allclose(est(merged.data).range, truth, rtol=1e-5)
    # Not merged: across a dropped frame, or a lamp change.
    assert merger(replace_frame(frames[0], sequence=4)).channel_exposure_us is None
    assert merger(replace_frame(frames[1], sequence=5, lamp_on=False)).channel_exposure_us is None


def replace_frame(frame: Frame, **changes) -> Frame:
    from dataclasses import replace

    return replace(frame, **changes)


def test_one_exposure_cameras_bracket_and_a_weak_channel_comes_back(sim_profile):
    from uwcam.runtime.stages.hdr import HdrMerger

    camera = SimulatedCamera(fps=1000.0, size=(64, 48), scene="seabed", distance=5.0, water="jerlov-IB", material="grey",
                             one_exposure=True, serial_number="SIM-ONE")
    assert camera.exposure_control == "common"
    with pytest.raises(Exception, match="one exposure"):
        camera.set_exposure((1000.0, 2000.0, 1000.0))
    camera.set_exposure((25.0,) * 3)  # everything far too dark
    camera.open()
    camera.start()
    try:
        controller = ExposureController(ExposureConfig(), ("R", "G", "B"), camera.exposure_control)
        assert controller.bracketing
        merger, est = HdrMerger(sim_profile.saturation_level), RangeEstimator(sim_profile)
        requests, states = [], []
        for _ in range(24):
            raw = camera.read(1.0)
            frame = merger(raw)
            est.set_exposure(*frame.exposures())
            wanted = controller.update(frame.data, frame.exposures()[0], frame.lamp_on, est.dark, est.floor,
                                       sim_profile.saturation_level, raw.exposures()[0])
            states.append({k: v["state"] for k, v in controller.last.items()})
            if wanted is not None:
                assert len(set(wanted)) == 1  # one exposure for all channels, always
                requests.append(wanted[0])
                camera.set_exposure(wanted)
        assert states[0]["R"] == "below floor"
        assert all(s == "ok" for s in states[-1].values()), states[-1]
        # Settled into a bracket: red's long exposure and blue's short one, alternating.
        short, long = controller.bracket
        assert long > 2 * short and sorted(set(round(r) for r in requests[-4:])) == [round(short), round(long)]
        assert frame.channel_exposure_us[0] == pytest.approx(long) and frame.channel_exposure_us[2] == pytest.approx(short)
        assert np.isfinite(est(frame.data).range).mean() > 0.9
    finally:
        camera.close()


class SfncNodeMap:
    """A 3-chip camera's node map as SFNC describes it: ExposureTime and Gain each hold one value
    per entry of their selector (ExposureTimeSelector: Red, Green, Blue; GainSelector: All only)."""

    class Node:
        def __init__(self, owner, name):
            self.owner, self.name = owner, name

        @property
        def value(self):
            return self.owner.read(self.name)

        @value.setter
        def value(self, v):
            self.owner.write(self.name, v)

        @property
        def symbolics(self):
            return self.owner.entries[self.name]

    def __init__(self):
        self.entries = {"ExposureTimeSelector": ["Red", "Green", "Blue"], "GainSelector": ["All"]}
        self.selected = {"ExposureTimeSelector": "Red", "GainSelector": "All"}
        self.values = {("ExposureTime", e): 1000.0 for e in self.entries["ExposureTimeSelector"]}
        self.values[("Gain", "All")] = 0.0
        for name in ("ExposureTime", "Gain", "ExposureTimeSelector", "GainSelector"):
            setattr(self, name, SfncNodeMap.Node(self, name))

    def _key(self, name):
        return (name, self.selected["ExposureTimeSelector" if name == "ExposureTime" else "GainSelector"])

    def read(self, name):
        return self.selected[name] if name in self.selected else self.values[self._key(name)]

    def write(self, name, v):
        if name in self.selected:
            assert v in self.entries[name]
            self.selected[name] = v
        else:
            self.values[self._key(name)] = v


def test_genicam_sets_each_sensors_exposure_through_the_selector():
    from uwcam.drivers.genicam import GenTLCamera, channel_selectors

    nm = SfncNodeMap()
    assert channel_selectors(nm, "ExposureTimeSelector", ("R", "G", "B")) == ["Red", "Green", "Blue"]
    assert channel_selectors(nm, "GainSelector", ("R", "G", "B")) is None  # "All" only: one gain
    assert channel_selectors(nm, "ExposureTimeSelector", ("NIR", "G", "B")) is None
    driver = GenTLCamera.__new__(GenTLCamera)
    driver.channel_names = ("R", "G", "B")
    driver._nodes = lambda: nm
    driver._selectors = {"ExposureTime": ["Red", "Green", "Blue"], "Gain": None}
    driver.set_exposure((4000.0, 1000.0, 500.0), (6.0, 6.0, 6.0))
    assert [nm.values[("ExposureTime", e)] for e in ("Red", "Green", "Blue")] == [4000.0, 1000.0, 500.0]
    assert driver._channel_exposure == (4000.0, 1000.0, 500.0) and driver._gain_db == 6.0
    with pytest.raises(Exception, match="one Gain for all channels"):
        driver.set_exposure((1.0, 1.0, 1.0), (0.0, 6.0, 0.0))


def test_the_daemon_brackets_a_one_exposure_camera_and_ranges_the_merged_frames():
    from tests.served import Server
    from tests.waiting import wait_for
    from uwcam.config import CameraConfig, DaemonConfig

    config = DaemonConfig(
        camera=CameraConfig(driver="sim", options={"fps": 20.0, "serial_number": "SIM-HDR", "one_exposure": True}),
        # 4 m: farther, the water's own light leaves red's surface light within the uncertainty of the
        # black-patch model of it toward the view's edges (where the patch's level carried across the
        # view is doubted: BackscatterModel.spread_doubt), and most pixels honestly have no range (reason 3).
        # 160×120: the rig is calibrated at its own size, and at 64×48 the calibration knows G − B
        # (0.048 ± 0.016 1/m) only to 2.9σ, too little for green and blue to range alone (reason 4).
        simulation={"scene": "seabed", "distance": 4.0, "size": [160, 120], "water": "jerlov-IB", "material": "grey"},
        processing=ProcessingConfig(exposure=ExposureConfig(max_step=4.0)),
    )
    with Server(config) as s:
        def bracketed() -> bool:
            latest = s.daemon.pipeline.latest
            exposure = None if latest is None else latest.frame.channel_exposure_us
            return exposure is not None and exposure[0] > 2 * exposure[2]  # red merged from the long exposure

        assert wait_for(bracketed, timeout_s=60), s.http.get("/api/v1/status").json()["exposure"]
        status = s.http.get("/api/v1/status").json()["exposure"]
        assert status["enabled"] and status["control"] == "common" and len(status["bracket_us"]) == 2
        latest = s.daemon.pipeline.latest
        assert np.isfinite(latest.result.range).mean() > 0.5


def test_backscatter_compensation_follows_the_frames_exposure():
    """The open-water frame is taken at one exposure, the scene at another (red 4 times longer):
    the modelled backscatter, scaled by the ratio, is subtracted as if both were alike."""
    from uwcam.water.frame_compensator import BackscatterCompensator
    from uwcam.simulation import SimulatedWorld

    water, lamp, size = water_preset("jerlov-II", [675.0, 575.0, 475.0]), Lamp(position=(0.3, 0.0, 0.0)), (96, 72)
    profile = calibrate_in_simulation(water, lamp, size, CameraModel(), frames_per_distance=2)
    scene = SimulatedWorld(scene="seabed", distance=4.0, size=size, water=water, lamp=lamp, material="grey", seed=5)
    open_water = SimulatedWorld(scene="open-water", distance=4.0, size=size, water=water, lamp=lamp,
                                fixed_exposure=scene.exposure, seed=6).frame(0)
    truth = scene.camera_range
    # One pair: with two channels the weights do not move the range, so only the subtraction can.
    comp = BackscatterCompensator(profile, truth.shape, 2, open_water, pair=("R", "B"))

    def ranged(m, scale):
        scene.set_exposure_scale(tuple(m))
        est = RangeEstimator(profile, pair=("R", "B"))
        est.set_exposure(1000.0 * np.asarray(m))
        return comp.range(scene.noise_free_frame(), est.attenuation, est.effective_log_constant, background_scale=scale).range

    alike = ranged((1.0, 1.0, 1.0), None)
    m = np.array([4.0, 1.0, 1.0])
    scaled, unscaled = ranged(m, m), ranged(m, None)
    # Compared where both have a range: the pixels near the judge's limit change validity with the
    # counts the sensor gives, which differ.
    both = np.isfinite(alike) & np.isfinite(scaled)
    assert both.mean() > 0.5
    assert np.median(scaled[both] / truth[both] - 1) == pytest.approx(np.median(alike[both] / truth[both] - 1), abs=1e-3)
    kept = np.isfinite(alike) & np.isfinite(unscaled)  # red's backscatter left at a quarter: the test can fail
    assert abs(np.median(unscaled[kept] / truth[kept] - 1) - np.median(alike[kept] / truth[kept] - 1)) > 0.01
