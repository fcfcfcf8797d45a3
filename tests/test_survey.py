"""The surveying vehicle (scene ``survey``): geometry against independent ray casting, ranges
from the simulated calibration against ground truth, numpy twins, the rig's devices, config."""

import math

import numpy as np
import pytest

from uwcam.config import DaemonConfig, default_config
from uwcam.drivers import registry
from uwcam.drivers.sim import SimulatedCamera, SimulatedRig
from uwcam.ranging.estimator import RangeEstimator
from uwcam.simulation import CameraModel, Lamp, water_preset
from uwcam.simulation.survey import SurveyWorld
from uwcam.simulation.terrain import CELL_M, SurveyMotion, Terrain, build_terrain
from uwcam.simulation.tank import calibrate_in_simulation
from tests.waiting import wait_for

WL = [675.0, 575.0, 475.0]
LAMP = Lamp(position=(0.3, -0.8, 0.0))
SIZE = (320, 180)


@pytest.fixture(scope="module")
def terrain():
    return build_terrain(0, ["R", "G", "B"], WL)


def flat_terrain(depth=0.0, reflectance=0.25):
    data = np.zeros((200, 100, 6), np.float32)
    data[..., 0] = depth
    data[..., 3:] = reflectance
    return Terrain(data, CELL_M, -0.5)


def unit_rays(world):
    """Rays of every pixel from the pinhole model, written here apart from the renderer."""
    w, h = world.size
    f = (w / 2) / math.tan(math.radians(world.fov_deg) / 2)
    x = (np.arange(w) - (w - 1) / 2) / f
    y = (np.arange(h) - (h - 1) / 2) / f
    rays = np.stack(np.broadcast_arrays(x[None, :], y[:, None], 1.0), axis=-1)
    return rays / np.linalg.norm(rays, axis=-1, keepdims=True)


@pytest.mark.parametrize("altitude", [1.5, 2.5, 4.0])
def test_flat_seabed_range_is_the_ray_plane_intersection(altitude):
    world = SurveyWorld(size=SIZE, lamp=LAMP, motion=SurveyMotion(altitude=(altitude, altitude)),
                        terrain=flat_terrain(0.3), bracket=False)
    t = 7.0
    _, _, z0 = world.pose(t)
    truth = (0.3 - z0) / unit_rays(world)[..., 2]  # seabed plane z = 0.3 m (world), camera at depth z0
    rendered = world.camera_range(t)
    np.testing.assert_allclose(rendered[2:-2, 2:-2], truth[2:-2, 2:-2], rtol=1e-4)
    np.testing.assert_allclose(rendered, truth, rtol=5e-3)  # the outermost two pixels hold the nearest values
    assert world.axis_range(t) == pytest.approx(0.3 - z0, abs=1e-6)  # the height map holds float32


def test_rays_meet_the_height_map_where_it_is_smooth(terrain):
    """At every pixel the rendered point lies on the height map: D(X, Y) = Z to within a few mm,
    except where the ray grazes a steep side (a small fraction of the image)."""
    world = SurveyWorld(size=SIZE, lamp=LAMP, terrain=terrain, bracket=False, step=1)
    for t in (0.0, 13.0, 47.0, 70.0):
        x0, y0, z0 = world.pose(t)
        rng = world.shade(t)[2]
        p = rng[..., None] * unit_rays(world)
        depth = terrain.sample(x0 + p[..., 0], y0 + p[..., 1])[..., 0]
        residual = np.abs(depth - z0 - p[..., 2])
        assert np.mean(residual < 0.003) > 0.97, f"t={t}: {np.mean(residual < 0.003):.3f}"
        assert world.axis_range(t) == pytest.approx(rng[SIZE[1] // 2, SIZE[0] // 2], abs=0.01)


def test_the_vehicle_moves_and_its_altitude_changes_slowly(terrain):
    world = SurveyWorld(size=SIZE, lamp=LAMP, terrain=terrain, motion=SurveyMotion(speed=0.5, altitude=(1.5, 4.0),
                                                                                   altitude_period=100.0))
    assert world.pose(10.0)[1] - world.pose(12.0)[1] == pytest.approx(1.0)  # 0.5 m/s toward the image top
    alts = [world.motion.position(t)[2] for t in np.arange(0, 100, 0.5)]
    assert min(alts) == pytest.approx(1.5) and max(alts) == pytest.approx(4.0, abs=1e-3)
    assert max(abs(a - b) for a, b in zip(alts, alts[1:])) < 0.1  # slowly: < 0.2 m/s
    a, b = world.frame(10.0, 1), world.frame(12.0, 1)
    assert np.mean(np.abs(a.astype(float) - b)) > 5 * np.mean(np.abs(a.astype(float) - world.frame(10.0, 2)))


@pytest.mark.slow
@pytest.mark.parametrize("case", ["no backscatter, tank calibration", "daemon's calibration, 1280x720"])
def test_ranges_from_the_simulated_calibration_match_the_truth(case):
    """The tank calibration (static renderer, grey plate at 1 and 2 m) and the survey renderer
    model the same water: the estimator's ranges on survey frames of a flat seabed agree with
    ray/plane ranges at several altitudes. First without backscatter (the two renderers'
    consistency alone), then as the daemon calibrates at start (simulated_calibration: a
    smaller plate image, the rig camera's intrinsics) in Jerlov IA with its backscatter."""
    from uwcam.runtime.simulated_rig import simulated_calibration

    if case.startswith("no backscatter"):
        size, tolerance = SIZE, 0.006
        water = water_preset("jerlov-IA", WL).with_overrides(backscatter=0.0)
        profile = calibrate_in_simulation(water, LAMP, size, CameraModel(), seed_base=11)
    else:
        size, tolerance = (1280, 720), 0.01
        water = water_preset("jerlov-IA", WL)
        profile = simulated_calibration(SimulatedRig(scene="survey", size=size, water="jerlov-IA",
                                                     lamp_offset=LAMP.position))
    estimator = RangeEstimator(profile)
    for altitude in (1.5, 2.5, 4.0):
        world = SurveyWorld(size=size, water=water, lamp=LAMP, motion=SurveyMotion(altitude=(altitude, altitude)),
                            terrain=flat_terrain(0.0), bracket=False)
        t = 5.0
        _, _, z0 = world.pose(t)
        truth = -z0 / unit_rays(world)[..., 2]
        estimate = estimator(world.frame(t, 3)).range
        w, h = size
        centre = (slice(h // 4, 3 * h // 4), slice(w // 4, 3 * w // 4))
        error = np.nanmedian(estimate[centre] - truth[centre]) / np.median(truth[centre])
        assert abs(error) < tolerance, f"altitude {altitude} m: median error {100 * error:.2f} %"
        # Off the axis too (the lamp sits forward and to the side): each quadrant's median error.
        relative = estimate / truth - 1
        for rows in (slice(0, h // 2), slice(h // 2, h)):
            for cols in (slice(0, w // 2), slice(w // 2, w)):
                bias = np.nanmedian(relative[rows, cols])
                assert abs(bias) < 2 * tolerance, f"altitude {altitude} m, quadrant {rows}, {cols}: {100 * bias:.2f} %"


def test_numpy_twins_give_the_same_frames(terrain):
    args = dict(size=(96, 54), lamp=LAMP, terrain=terrain, water=water_preset("jerlov-IB", WL))
    fast, slow = SurveyWorld(**args, use_numba=True), SurveyWorld(**args, use_numba=False)
    for t in (3.0, 41.0):
        for a, b in zip(fast.shade(t), slow.shade(t)):
            np.testing.assert_allclose(a, b, rtol=2e-5, atol=1e-12)
    assert fast.exposure == pytest.approx(slow.exposure, rel=1e-5)
    slow._exposure = fast.exposure
    fa, sa = fast.frame(3.0, 5, level=0.7), slow.frame(3.0, 5, level=0.7)
    differ = fa.astype(int) - sa
    assert np.abs(differ).max() <= 1 and np.mean(differ != 0) < 1e-3  # rounding ties from float32 shading only


def test_expose_twins_are_identical_on_the_same_radiance():
    from uwcam.simulation.camera import frame_key
    from uwcam.simulation.survey_kernels import NOISE_BLOCK, _expose, expose_numpy, noise_pool

    rng = np.random.default_rng(1)
    radiance = rng.uniform(0, 2e-5, 3 * 7777).astype(np.float32)  # several noise blocks and a partial one
    gain = rng.uniform(0.98, 1.02, radiance.size).astype(np.float32)
    a, b = np.empty(radiance.size, np.uint16), np.empty(radiance.size, np.uint16)
    args = (1e9, 40.0, 65535 / 20000, (5.0 * 65535 / 20000) ** 2, frame_key(3, 4), 65535.0, noise_pool())
    _expose(radiance, gain, *args, a)
    expose_numpy(radiance, gain, *args, b, chunk=NOISE_BLOCK + 100)
    assert np.array_equal(a, b)


def test_survey_noise_has_the_camera_models_mean_and_variance_and_is_new_every_frame():
    """Shot and read noise of the survey's exposure against the camera model written out here:
    mean (E + dark)·g DN and variance (E + dark)·g² + (read·g)² DN², for a flat radiance; frames
    with other keys get independent noise; neighbouring pixels are uncorrelated."""
    from uwcam.simulation.camera import frame_key
    from uwcam.simulation.survey_kernels import _expose, expose_numpy, noise_pool

    n, g, dark, read = 400_000, 65535 / 20000, 40.0, 5.0
    electrons = 3000.0
    radiance = np.full(n, electrons / 1e9, np.float32)
    gain = np.ones(n, np.float32)
    mean_dn = (electrons + dark) * g
    var_dn = (electrons + dark) * g * g + (read * g) ** 2 + 1.0 / 12.0  # + rounding to whole codes
    frames = []
    for kernel in (_expose, expose_numpy):
        for index in (4, 5):
            out = np.empty(n, np.uint16)
            kernel(radiance, gain, 1e9, dark, g, (read * g) ** 2, frame_key(3, index), 65535.0, noise_pool(), out)
            frames.append(out.astype(np.float64))
    for f in frames:
        # Standard errors: of the mean sqrt(var/n) ≈ 0.25 DN; of the variance var·sqrt(2/n) ≈ 0.2 %.
        assert abs(f.mean() - mean_dn) < 5 * np.sqrt(var_dn / n)
        assert abs(f.var() / var_dn - 1.0) < 5 * np.sqrt(2.0 / n)
        lag1 = np.corrcoef(f[:-1], f[1:])[0, 1]
        assert abs(lag1) < 5 / np.sqrt(n)
    assert abs(np.corrcoef(frames[0], frames[1])[0, 1]) < 5 / np.sqrt(n)  # frame 4 against frame 5
    np.testing.assert_array_equal(frames[0], frames[2])  # the two kernels, frame 4


def test_noise_pool_is_standard_normal():
    from statistics import NormalDist

    from uwcam.simulation.survey_kernels import NOISE_BLOCK, NOISE_POOL_SIZE, noise_pool

    pool = noise_pool()
    z = pool[:NOISE_POOL_SIZE].astype(np.float64)
    assert pool.dtype == np.float32 and pool.size == NOISE_POOL_SIZE + NOISE_BLOCK
    np.testing.assert_array_equal(pool[NOISE_POOL_SIZE:], pool[:NOISE_BLOCK])  # runs never wrap
    assert abs(z.mean()) < 1e-6 and abs(z.std() - 1.0) < 1e-6
    # The share beyond 1, 2 and 3 σ against the normal distribution's (binomial standard errors).
    for k in (1.0, 2.0, 3.0):
        p = 2 * (1 - NormalDist().cdf(k))
        assert abs(np.mean(np.abs(z) > k) - p) < 5 * np.sqrt(p * (1 - p) / z.size)


def test_rig_devices_see_the_moving_survey():
    """Camera and Ping1D share the moving world: the sonar reads the range under the vehicle now."""
    now = [0.0]
    rig = SimulatedRig(scene="survey", size=(160, 90), water="jerlov-IA", lamp_offset=(0.3, -0.8, 0.0),
                       altitude=(1.5, 4.0), altitude_period=60.0, clock=lambda: now[0])
    ranger = registry.create("rangefinder", "sim-ping1d", rig=rig, rate_hz=50)
    camera = SimulatedCamera(rig, fps=1000.0, serial_number="SIM-SURVEY")
    with ranger:
        camera.open()
        camera.start()
        try:
            first = camera.read(1.0).data.astype(float)
            assert wait_for(lambda: ranger.fresh() is not None)
            low = ranger.fresh().range_m
            assert low == pytest.approx(rig.true_range(), abs=0.002)
            now[0] = 30.0  # half an altitude cycle later: at the top
            assert wait_for(lambda: ranger.fresh() is not None and ranger.fresh().range_m > low + 1.5, 5.0)
            assert ranger.fresh().range_m == pytest.approx(rig.true_range(), abs=0.002)
            later = camera.read(1.0).data.astype(float)
            assert later[..., 0].mean() < 0.5 * first[..., 0].mean()  # higher: the red fades
        finally:
            camera.close()


def test_a_lamp_switched_while_a_frame_renders_keeps_the_frames_label():
    """Regression (flaky registry test): a frame rendered lit was labelled dark when the lamp went
    off during rendering, because the label was read after the render. Deterministic here: the
    lamp goes off inside every render."""
    for scene in ("seabed", "survey"):
        rig = SimulatedRig(scene=scene, size=(64, 36), water="jerlov-IA")
        camera = SimulatedCamera(rig, fps=1000.0, serial_number=f"SIM-RACE-{scene}")
        camera.open()
        camera.start()
        try:
            dark = camera.rig.world.camera.dark_level_dn
            render = rig.render

            def render_then_switch_off(state, index):
                frame = render(state, index)
                rig.set_lamp(on=False)  # the lamp thread acts while the camera still holds the frame
                return frame

            rig.render = render_then_switch_off
            rig.set_lamp(on=True)
            lit = camera.read(1.0)
            assert lit.lamp_on is True and lit.data.mean() > 3 * dark
            unlit = camera.read(1.0)
            assert unlit.lamp_on is False and unlit.data.mean() < 1.5 * dark
        finally:
            camera.close()


def test_simulation_options_are_checked():
    ok = DaemonConfig(simulation={"scene": "survey", "speed": 0.2, "altitude": [2, 3], "seed": 4})
    assert ok.simulation["altitude"] == (2.0, 3.0)
    cases = [
        ({"scene": "survey", "sped": 1}, "sped: unknown key; remove it or check its spelling"),
        ({"scene": "survey", "speed": float("nan")}, "speed: Input should be a finite number"),
        ({"scene": "survey", "speed": 9}, "speed: Input should be less than or equal to 5"),
        ({"scene": "survey", "altitude": [4, 1.5]}, "altitude must be [lowest, highest]"),
        ({"scene": "survey", "altitude": [1.5, float("inf")]}, "altitude.1: Input should be a finite number"),
        ({"scene": "seabed", "speed": 1}, "'speed' applies only to scene: survey"),
        ({"scene": "survey", "distance": 2}, "'distance' applies only to static scenes"),
        ({"scene": "reef"}, "unknown scene 'reef'; known: survey, seabed"),
        ({"water": "jerlov-XX"}, "water: unknown water 'jerlov-XX'; known: ideal, jerlov-I"),
        ({"material": "gold"}, "material: unknown material 'gold'; known: sand, brick, pipe"),
        ({"lamp_offset": [0, 0, 9]}, "lamp_offset.2: Input should be less than or equal to 3"),
    ]
    for options, message in cases:
        with pytest.raises(ValueError) as info:
            DaemonConfig(simulation=options)
        assert message in str(info.value)


def test_config_file_errors_are_one_line(tmp_path):
    from uwcam.config import load_config
    from uwcam.fileio import UserInputError

    path = tmp_path / "rig.yaml"
    path.write_text("camera: {driver: sim}\nsimulation: {scene: survey, altitude_periood: 60}\n")
    with pytest.raises(UserInputError) as info:
        load_config(path)
    text = str(info.value)
    assert "\n" not in text and "simulation" in text and "altitude_periood: unknown key" in text


def test_default_and_example_configs_are_the_survey():
    from uwcam.config import load_config

    cfg = default_config()
    assert cfg.simulation["scene"] == "survey" and cfg.simulation["size"] == (1280, 720)
    assert cfg.camera.options["fps"] == 30.0
    example = load_config(__file__.replace("tests/test_survey.py", "deploy/sim-rig.yaml"))
    assert example.model_dump() == cfg.model_dump()


def test_marker_locates_the_patch_on_survey_frames(terrain):
    """The bracket stays put while the seabed moves: the marker finds the patch where the fixed
    region says it is, frame after frame."""
    from uwcam.config import MarkerConfig, PatchConfig
    from uwcam.runtime.simulated_rig import simulated_patch
    from uwcam.runtime.stages.patch_tracker import PatchTracker
    from uwcam.simulation.scene import MARKER_CENTRE_M, MARKER_SIDE_M, PATCH_CENTRE_M, PATCH_SIZE_M

    rig = SimulatedRig(scene="survey", size=(1280, 720), water="jerlov-IA", lamp_offset=(0.3, -0.8, 0.0))
    rig._world = SurveyWorld(size=(1280, 720), water=water_preset("jerlov-IA", WL), lamp=LAMP, terrain=terrain)
    fixed = simulated_patch(rig)
    corner = np.array(MARKER_CENTRE_M) - MARKER_SIDE_M / 2
    inner = np.array(PATCH_CENTRE_M) - PATCH_SIZE_M / 2 + 0.02
    config = PatchConfig(marker=MarkerConfig(id=7, offset=tuple((inner - corner) / MARKER_SIDE_M), size=(0.75, 0.75)),
                         path_length_m=fixed.path_length_m)
    profile = calibrate_in_simulation(water_preset("jerlov-IA", WL), LAMP, (160, 90), noise_free=True)
    tracker = PatchTracker(config, profile)
    fx, fy, fw, fh = fixed.region
    for t in (0.0, 20.0, 45.0, 60.0):
        region = tracker.locate(rig.world.frame(t, 1))
        assert region is not None, f"marker not found at t={t}"
        x, y, w, h = region
        assert abs(x - fx) < 0.2 * fw and abs(y - fy) < 0.2 * fh


@pytest.mark.slow
def test_daemon_on_the_survey_tracks_the_patch_and_ranges_the_moving_seabed():
    from uwcam.config import CameraConfig, DeviceConfig
    from uwcam.runtime.daemon import Daemon

    config = DaemonConfig(
        camera=CameraConfig(driver="sim", options={"fps": 15.0, "serial_number": "SIM-SURVEY-DAEMON"}),
        lamp=DeviceConfig(driver="sim"), rangefinder=DeviceConfig(driver="sim-ping1d", options={"rate_hz": 20}),
        simulation={"scene": "survey", "size": [320, 180], "water": "jerlov-IA", "lamp_offset": [0.3, -0.8, 0.0],
                    "speed": 0.4, "altitude": [1.5, 4.0], "altitude_period": 60.0})
    daemon = Daemon(config)
    daemon.start()
    try:
        def status():
            return daemon.status()

        assert wait_for(lambda: status()["frames"]["processed"] >= 10 and (status()["calibration"]["tracking"] or {}).get("accepted", 0) >= 3, 60.0), status()
        st = status()
        assert st["calibration"]["tracking"]["state"] == "tracking"
        assert abs(st["calibration"]["tracking"]["drift"]["G"]) < 0.02
        # The range map agrees with the renderer's ground truth for the frame's moment (the survey
        # clock is the monotonic clock the frame's capture time is stamped with).
        rig = daemon.rig
        errors = []
        for _ in range(4):
            latest = daemon.pipeline.latest
            t = latest.frame.host_monotonic_ns / 1e9 - rig._t0
            truth = rig.world.camera_range(t)
            left = (slice(10, 170), slice(10, 150))  # clear of the bracket (lower right)
            errors.append(np.nanmedian(latest.result.range[left] / truth[left] - 1))
            first = latest.number
            assert wait_for(lambda: daemon.pipeline.latest.number > first + 3, 10.0)
        assert np.median(np.abs(errors)) < 0.03, errors
    finally:
        daemon.stop()


def test_without_numba_the_simulator_gives_the_same_frames(tmp_path):
    """numba is optional (no wheels on 32-bit ARM): in a process where it cannot be imported the
    numpy twins run and give the same frames as the compiled kernels here."""
    import subprocess
    import sys

    from uwcam.simulation import SimulatedWorld

    out = tmp_path / "frames.npz"
    script = (
        "import sys; sys.modules['numba'] = None\n"
        "import numpy as np\n"
        "from uwcam.simulation import SimulatedWorld, Lamp, water_preset\n"
        "from uwcam.compute.jit import HAVE_NUMBA\n"
        "from uwcam.simulation.survey import SurveyWorld\n"
        "assert not HAVE_NUMBA\n"
        "water = water_preset('jerlov-II', [675.0, 575.0, 475.0])\n"
        "static = SimulatedWorld(scene='brick', size=(64, 48), water=water, lamp=Lamp(position=(0.3, 0.0, 0.0))).frame(2)\n"
        "survey = SurveyWorld(size=(64, 36), water=water).frame(3.0, 1)\n"
        f"np.savez({str(out)!r}, static=static, survey=survey)\n"
    )
    subprocess.run([sys.executable, "-c", script], check=True, timeout=300)
    theirs = np.load(out)
    water = water_preset("jerlov-II", WL)
    static = SimulatedWorld(scene="brick", size=(64, 48), water=water, lamp=Lamp(position=(0.3, 0.0, 0.0))).frame(2)
    survey = SurveyWorld(size=(64, 36), water=water).frame(3.0, 1)
    assert np.array_equal(theirs["static"], static)
    differ = theirs["survey"].astype(int) - survey
    assert np.abs(differ).max() <= 1 and np.mean(differ != 0) < 2e-3
