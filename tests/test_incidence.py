"""Incidence angles per pixel block (Kirlin's step in the loop) and the absolute scale they need.

Expected values come from the model written out here on its own (closed forms), from a plain
loop over blocks, from the tested :func:`kirlin_estimate`, and from the simulator's ground truth
(the tilted plane's normals).
"""

from __future__ import annotations

import io

import numpy as np
import pytest

from tests.served import Server
from tests.waiting import wait_for
from uwcam.config import ApiConfig, CameraConfig, DaemonConfig, DeviceConfig
from uwcam.optics.orientation import (beam_pattern, block_irradiance, block_means, incidence_from_blocks, kirlin_estimate,
                                      plane_normal, surface_scale)

ALPHA = np.array([0.46, 0.11, 0.06])  # 1/m, Jerlov II-like red, green, blue


def model(scale, cos, d, alpha=ALPHA, r=0.0):
    """E_k = s_k · cos γ · exp(−2 α_k d) / (d + r)², written apart from the code under test."""
    d = np.asarray(d, float)[..., None]
    return np.asarray(scale, float) * np.asarray(cos, float)[..., None] * np.exp(-2 * alpha * d) / (d + r) ** 2


@pytest.mark.parametrize("r", [0.0, 0.037])
def test_block_solver_recovers_range_and_angle_of_exact_model_data(r):
    rng = np.random.default_rng(1)
    d = rng.uniform(0.8, 6.0, 500)
    gamma = rng.uniform(0.0, 75.0, 500)
    scale = np.array([3e4, 2e4, 1e4])
    e = model(scale, np.cos(np.radians(gamma)), d, r=r)
    # Seeded with a range 5 % off, as a fused range may be.
    got_d, got_g = incidence_from_blocks(e, d * rng.uniform(0.95, 1.05, 500), ALPHA, scale, r, iterations=20)
    assert np.all(np.isfinite(got_g))
    np.testing.assert_allclose(got_g, gamma, atol=1e-4)
    np.testing.assert_allclose(got_d, d, rtol=1e-6)


def test_block_solver_agrees_with_kirlin_estimate_for_a_point_source():
    rng = np.random.default_rng(2)
    d = rng.uniform(1.0, 4.0, 50)
    gamma = rng.uniform(5.0, 60.0, 50)
    scale = np.array([1.5, 1.0, 0.7])
    e = model(scale, np.cos(np.radians(gamma)), d) * rng.normal(1.0, 0.001, (50, 3))  # 0.1 % noise
    seed = d * 1.03
    ref_d, ref_g, converged = kirlin_estimate(e, ALPHA, scale, seed, gamma + 2.0, iterations=50)
    got_d, got_g = incidence_from_blocks(e, seed, ALPHA, scale, 0.0, iterations=50, tolerance_m=1e-6)
    both = converged & np.isfinite(got_g)
    assert both.mean() > 0.9
    np.testing.assert_allclose(got_g[both], ref_g[both], atol=1e-3)
    np.testing.assert_allclose(got_d[both], ref_d[both], rtol=1e-5)


def test_block_solver_reports_nan_for_missing_or_impossible_blocks():
    scale = np.array([3e4, 2e4, 1e4])
    e = model(scale, np.array([0.9, 0.9, 0.9, 0.9]), np.array([2.0, 2.0, 2.0, 2.0]))
    e[1, 2] = np.nan  # a channel missing
    e[2] *= 3.0  # three times brighter than a surface facing the lamp squarely: no angle
    seed = np.array([2.0, 2.0, 2.0, np.nan])  # no fused range
    _, g = incidence_from_blocks(e, seed, ALPHA, scale)
    assert np.isfinite(g[0]) and abs(g[0] - np.degrees(np.arccos(0.9))) < 1e-3
    assert np.isnan(g[1:]).all()


def test_surface_scale_inverts_the_model():
    rng = np.random.default_rng(3)
    d = rng.uniform(1.8, 2.2, 81)
    cos = rng.uniform(0.8, 0.9, 81)
    beam = rng.uniform(0.9, 1.0, 81)
    scale = np.array([5e4, 4e4, 3e4])
    e = model(scale, cos * beam, d, r=0.05)
    np.testing.assert_allclose(surface_scale(e, d, ALPHA, cos, 0.05, beam), scale, rtol=1e-12)
    with pytest.raises(ValueError):
        surface_scale(e[:, :2], d, ALPHA, cos)


def test_block_means_count_only_valid_pixels():
    rng = np.random.default_rng(4)
    values = rng.uniform(0, 100, (37, 50, 3)).astype(np.float32)
    valid = rng.uniform(size=(37, 50)) > 0.3
    valid[8:16, 8:16] = False
    valid[0:8, 0:8] = True
    got = block_means(values, valid, 8)
    assert got.shape == (4, 6, 3)
    for i in range(4):
        for j in range(6):
            m = valid[i * 8:(i + 1) * 8, j * 8:(j + 1) * 8]
            v = values[i * 8:(i + 1) * 8, j * 8:(j + 1) * 8]
            if m.mean() < 0.5:
                assert np.isnan(got[i, j]).all()
            else:
                np.testing.assert_allclose(got[i, j], v[m].mean(axis=0), rtol=1e-5)
    np.testing.assert_allclose(block_means(values[..., 0], valid, 8)[0, 0], values[:8, :8, 0].mean(), rtol=1e-5)


def test_block_irradiance_masks_dark_saturated_and_unranged_pixels_alike_on_both_paths():
    rng = np.random.default_rng(5)
    h, w, b = 40, 56, 8
    data = rng.integers(0, 4096, (h, w, 3)).astype(np.uint16)
    data[:8, :8] = 1000  # a full block, all usable
    data[8:16, :8, 1] = 4095  # saturated in green
    range_map = rng.uniform(1, 3, (h, w)).astype(np.float32)
    range_map[rng.uniform(size=(h, w)) < 0.2] = np.nan
    range_map[:8, :8] = 2.0
    dark, floor, saturation = np.array([64.0, 60.5, 70.0]), np.array([20.0, 30.0, 0.0]), 4095.0
    fast, share, mask = block_irradiance(data, range_map, dark, floor, saturation, b)
    slow, share2, mask2 = block_irradiance(data, range_map, dark, floor, saturation, b, np.zeros((h, w, 3), np.float32))
    np.testing.assert_array_equal(mask, mask2)
    np.testing.assert_allclose(fast, slow, rtol=1e-5)
    # A plain loop, written apart.
    e = data.astype(np.float64) - dark
    ok = np.isfinite(range_map) & np.all((e > floor) & (data < saturation), axis=-1)
    for i in range(h // b):
        for j in range(w // b):
            m = ok[i * b:(i + 1) * b, j * b:(j + 1) * b]
            assert share[i, j] == pytest.approx(m.mean())
            if m.mean() < 0.5:
                assert np.isnan(fast[i, j]).all()
            else:
                np.testing.assert_allclose(fast[i, j], e[i * b:(i + 1) * b, j * b:(j + 1) * b][m].mean(axis=0), rtol=1e-5)
    np.testing.assert_allclose(fast[0, 0], 1000 - dark, rtol=1e-6)
    assert share[1, 0] == 0 and np.isnan(fast[1, 0]).all()  # saturated in one channel


@pytest.mark.parametrize("tilt_deg", [0.0, 30.0, 60.0])
def test_plane_normal_of_noisy_ranges_is_unbiased(tilt_deg):
    """A plane at 2 m tilted about x, seen through a 25 × 25-pixel patch, ranges with 2.5 % noise
    along the rays (the noise of one frame): the fitted normal's angle to the truth stays small on
    average, with no drift toward steeper angles (a fit of the points' least spread tilts it by
    several degrees at this noise)."""
    t = np.radians(tilt_deg)
    normal = np.array([0.0, np.sin(t), -np.cos(t)])  # facing the camera (z forward)
    gx, gy = np.meshgrid(np.arange(25) - 12.0, np.arange(25) - 12.0)
    rays = np.stack([gx / 300.0, gy / 300.0, np.ones_like(gx)], axis=-1).reshape(-1, 3)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    exact = -2.0 / (rays @ normal)  # n·P = −2 m: the plane crosses the axis at 2/cos t
    rng = np.random.default_rng(7)
    angles, tilts = [], []
    for _ in range(200):
        r = exact * (1 + rng.normal(0, 0.025, exact.shape))
        r[rng.uniform(size=r.shape) < 0.1] = np.nan  # pixels without a range
        n = plane_normal(r, rays)
        angles.append(np.degrees(np.arccos(np.clip(n @ normal, -1, 1))))
        tilts.append(np.degrees(np.arctan2(n[1], -n[2])))
        assert abs(np.linalg.norm(n) - 1) < 1e-12
    assert np.mean(angles) < 6.0 and np.median(angles) < 6.0, np.mean(angles)
    assert abs(np.mean(tilts) - tilt_deg) < 1.0, np.mean(tilts)  # neither steeper nor shallower
    exact_n = plane_normal(exact, rays)
    np.testing.assert_allclose(exact_n, normal, atol=1e-12)
    assert plane_normal(exact[:2], rays[:2]) is None
    assert plane_normal(np.full(5, np.nan), rays[:5]) is None


def test_beam_pattern_halves_at_the_half_angle():
    a = np.radians(40.0)
    rays = np.array([[0.0, 0.0, 1.0], [np.sin(a), 0.0, np.cos(a)], [0.0, -np.sin(a), np.cos(a)]])
    np.testing.assert_allclose(beam_pattern(rays, 40.0), [1.0, 0.5, 0.5])
    np.testing.assert_allclose(beam_pattern(rays, None), 1.0)


# -- In the daemon, on the simulator's tilted plane -------------------------------------------------

TOKEN = "incidence-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
BLOCK = 16
# Water without scattering ("ideal": beam attenuation only), the lamp at the camera: the conditions
# of Kirlin's model. The simulated lamp's beam halves 50° off axis.
SIM = {"scene": "tilted-plane", "distance": 2.0, "size": [320, 240], "water": "ideal", "lamp_offset": [0.0, 0.0, 0.0]}


def config(state_dir, rangefinder: bool = True) -> DaemonConfig:
    return DaemonConfig(
        camera=CameraConfig(driver="sim", options={"fps": 10.0, "serial_number": "SIM-INCIDENCE"}, watchdog_s=2.0),
        lamp=DeviceConfig(driver="sim"),
        rangefinder=DeviceConfig(driver="sim-ping1d", options={"rate_hz": 20}) if rangefinder else None,
        simulation=SIM, api=ApiConfig(token=TOKEN), state_dir=str(state_dir))


def true_incidence(world) -> np.ndarray:
    """Per block, the mean of the simulator's cos γ (its surface normals against its rays), as degrees."""
    cos = np.abs(np.sum(world.hit.normal * world.rays, axis=-1))
    return np.degrees(np.arccos(block_means(cos, np.isfinite(world.camera_range), BLOCK)))


def newer(server, frames: int = 3):
    pipeline = server.daemon.pipeline
    n = pipeline.processed
    assert wait_for(lambda: pipeline.processed > n + frames, 30.0)
    return pipeline.latest


@pytest.mark.slow
def test_incidence_in_the_loop_on_the_tilted_plane_matches_the_simulated_truth(tmp_path):
    with Server(config(tmp_path)) as s:
        assert wait_for(lambda: s.daemon.pipeline.latest is not None, 120.0)
        off = s.http.get("/api/v1/snapshot/incidence")
        assert off.status_code == 409 and "orientation is off" in off.json()["detail"]
        assert s.http.get("/api/v1/status").json()["orientation"] == {"enabled": False}
        # Writes need the token; every number is checked.
        assert s.http.patch("/api/v1/config", json={"orientation": {}}).status_code == 401
        for bad in ({"block": 3}, {"block": 16.5}, {"block": True}, {"iterations": 0}, {"beam_half_angle_deg": 0},
                    {"beam_half_angle_deg": 181}, {"beam_half_angle_deg": "50"}, {"size": 16}):
            r = s.http.patch("/api/v1/config", json={"orientation": bad}, headers=AUTH)
            assert r.status_code == 422, (bad, r.text)
        on = s.http.patch("/api/v1/config", json={"orientation": {"block": BLOCK, "beam_half_angle_deg": 50.0}},
                          headers=AUTH)
        assert on.status_code == 200 and on.json()["orientation"]["block"] == BLOCK
        assert wait_for(lambda: s.daemon.pipeline.latest.incidence is not None, 30.0)
        published = newer(s)
        # Reads are open, as for the other snapshots.
        npy = s.http.get("/api/v1/snapshot/incidence")
        assert npy.status_code == 200 and npy.headers["x-block-size"] == str(BLOCK)
        served = np.load(io.BytesIO(npy.content))
        assert served.shape == (240 // BLOCK, 320 // BLOCK) and served.dtype == np.float32
        assert s.http.get("/api/v1/snapshot/incidence?format=tiff").headers["content-type"] == "image/tiff"
        assert s.http.get("/api/v1/snapshot/incidence?format=png").content[:4] == b"\x89PNG"
        status = s.http.get("/api/v1/status").json()["orientation"]
        assert status["enabled"] and status["state"] == "estimating" and status["ms_per_frame"] > 0
        truth = true_incidence(s.daemon.rig.world)
        footprint = s.http.get("/api/v1/status").json()["calibration"]["reflectance"]["incidence_deg"]
    # The plane is tilted 30° about x: the rangefinder's footprint (image centre) sees it at 30°.
    assert abs(footprint - 30.0) < 4.0, footprint
    error = np.abs(published.incidence - truth)
    found = np.isfinite(published.incidence)
    assert truth.min() < 15 and truth.max() > 40  # the angle varies over the view
    assert found.mean() > 0.95, found.mean()
    assert np.mean(error[found] < 2.0) > 0.8, np.nanpercentile(error, [50, 80, 95])


@pytest.mark.slow
def test_incidence_unavailable_says_why(tmp_path):
    # Without a rangefinder there is no absolute scale.
    with Server(config(tmp_path, rangefinder=False)) as s:
        assert wait_for(lambda: s.daemon.pipeline.latest is not None, 120.0)
        assert s.http.patch("/api/v1/config", json={"orientation": {}}, headers=AUTH).status_code == 200
        newer(s)
        r = s.http.get("/api/v1/snapshot/incidence")
        assert r.status_code == 409 and "rangefinder" in r.json()["detail"], r.text
        assert "rangefinder" in s.http.get("/api/v1/status").json()["orientation"]["state"]
        # A profile without absolute attenuations (relative calibration only).
        pipeline = s.daemon.pipeline
        profile = pipeline.profile
        relative = profile.model_copy(update={"channels": [c.model_copy(update={"attenuation": None})
                                                           for c in profile.channels]})
        pipeline.set_profile(relative)
        newer(s)
        state = s.http.get("/api/v1/status").json()["orientation"]["state"]
        assert state.startswith("unavailable") and "absolute attenuations" in state, state
        r = s.http.get("/api/v1/snapshot/incidence")
        assert r.status_code == 409 and "absolute attenuations" in r.json()["detail"]


def tilted_footprint():
    """A grey plane tilted 30° at 2 m in water without scattering, the lamp at the camera, a
    noise-free calibration, and a rangefinder reading the true range at the image centre:
    (profile, world, lamp, rangefinder, footprint config, reading time ns)."""
    from types import SimpleNamespace

    from uwcam.config import ReflectanceConfig
    from uwcam.drivers.base import Health, HealthState
    from uwcam.drivers.rangefinder import RangeReading
    from uwcam.simulation.render import Lamp
    from uwcam.simulation.tank import calibrate_in_simulation
    from uwcam.simulation.water import water_preset
    from uwcam.simulation.world import SimulatedWorld

    water = water_preset("ideal", [675.0, 575.0, 475.0])
    lamp = Lamp(position=(0.0, 0.0, 0.0))
    size = (160, 120)
    profile = calibrate_in_simulation(water, lamp, size, noise_free=True)
    world = SimulatedWorld(scene="tilted-plane", distance=2.0, size=size, water=water, lamp=lamp)
    w, h = size
    now = 10**12
    reading = RangeReading(float(world.camera_range[h // 2, w // 2]), 0.97, now, 0.0)
    rf = SimpleNamespace(health=Health(HealthState.OK, "reading"), latest=lambda: reading)
    return profile, world, lamp, rf, ReflectanceConfig(footprint=(w // 2 - 4, h // 2 - 4, 9, 9)), now


def test_absolute_scale_at_a_tilted_footprint_divides_by_the_range_map_normals_cos():
    """The simulator's plane tilted 30°, a rangefinder reading at the image centre: the surface's
    absolute scale (what a surface square to the lamp would return) equals the simulator's own,
    because the footprint's cos γ comes from the range map's normal. Assuming the surface square
    to the beam would make it 1/cos 30° = 15 % too bright, and every angle found with it too steep."""
    from uwcam.drivers.base import Frame
    from uwcam.runtime.stages.reflectance import ReflectanceCorrector

    profile, world, lamp, rf, footprint, now = tilted_footprint()
    water = world.water
    w, h = world.size
    truth_range = world.camera_range
    corrector = ReflectanceCorrector(footprint, profile, rf, beam_half_angle_deg=lamp.beam_half_angle_deg)
    frame = Frame(data=world.noise_free_frame(), sequence=1, host_monotonic_ns=now, wall_time=0.0)
    corrector.update(frame, profile.array("attenuation_difference"))
    assert corrector.scale is None  # no normal yet: no absolute scale rather than a wrong one
    corrector.observe(truth_range)
    corrector.update(frame, profile.array("attenuation_difference"))
    assert abs(corrector.status()["incidence_deg"] - 30.0) < 0.5
    # The simulator's truth over the footprint: E = s · beam · cos γ · exp(−2 c d) / (d + r)² per pixel
    # (its mean: the camera's fixed-pattern gain moves single pixels by about 1 %).
    box = (slice(h // 2 - 4, h // 2 + 5), slice(w // 2 - 4, w // 2 + 5))
    u = world.rays[box].reshape(-1, 3)
    d = truth_range[box].reshape(-1, 1)
    cos = np.abs(np.sum(world.hit.normal[box].reshape(-1, 3) * u, axis=1))[:, None]
    beam = np.exp(-lamp.beam_scale * (1.0 - u[:, 2:]))
    e = world.noise_free_frame()[box].reshape(-1, 3) - world.camera.dark_level_dn
    truth = (e / (beam * cos * np.exp(-2 * water.attenuation * d) / (d + lamp.effective_radius) ** 2)).mean(axis=0)
    np.testing.assert_allclose(corrector.scale, truth, rtol=0.003)


@pytest.mark.parametrize("orientation, key", [
    ({"block": 2}, "block"), ({"block": 1024}, "block"), ({"block": "16"}, "block"), ({"iterations": 0}, "iterations"),
    ({"beam_half_angle_deg": float("nan")}, "beam_half_angle_deg"), ({"beam_half_angle_deg": -5}, "beam_half_angle_deg"),
    ({"window": 7}, "window"),
])
def test_config_file_refuses_bad_orientation_settings(tmp_path, orientation, key):
    import yaml

    from uwcam.config import load_config
    from uwcam.fileio import UserInputError

    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump({"version": 1, "processing": {"orientation": orientation}}))
    with pytest.raises(UserInputError, match=key):
        load_config(path)
    path.write_text(yaml.safe_dump({"version": 1, "processing": {"orientation": {"block": 32}}}))
    assert load_config(path).processing.orientation.block == 32


def test_the_footprints_scale_and_reflectance_do_not_depend_on_the_frames_exposure():
    """The same tilted footprint exposed 0.5×, 0.8× and 0.65× per channel: with the frame's exposure
    shift ln m_k given, the surface's log constants and absolute scale are those of the frame at
    the calibration's exposure (both are kept at the calibration's exposure)."""
    from uwcam.drivers.base import Frame
    from uwcam.runtime.stages.reflectance import ReflectanceCorrector

    profile, world, lamp, rf, footprint, now = tilted_footprint()
    dark = profile.array("dark_level")
    light = world.noise_free_frame().astype(np.float64) - dark
    m = np.array([0.5, 0.8, 0.65])  # shorter: the frame is exposed near the top code already
    found = []
    for gain, shift in ((np.ones(3), None), (m, np.log(m))):
        corrector = ReflectanceCorrector(footprint, profile, rf, beam_half_angle_deg=lamp.beam_half_angle_deg)
        frame = Frame(data=(light * gain + dark).astype(np.float32), sequence=1, host_monotonic_ns=now, wall_time=0.0)
        corrector.observe(world.camera_range)
        b = corrector.update(frame, profile.array("attenuation_difference"), exposure_shift=shift)
        found.append((b, corrector.scale))
    np.testing.assert_allclose(found[1][0], found[0][0], rtol=1e-6, atol=1e-6)  # the frames are float32
    np.testing.assert_allclose(found[1][1], found[0][1], rtol=1e-5)
