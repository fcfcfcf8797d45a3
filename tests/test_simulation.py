"""The simulated underwater world: physical limits, noise statistics, determinism, ground truth."""

import math

import jerlov
import numpy as np
import pytest

from uwcam.fileio import UserInputError
from uwcam.simulation import CameraModel, Lamp, SimulatedWorld, build_scene, water_preset
from uwcam.simulation.camera import TARGET_CODE

SIZE = (96, 72)


def water(c=(0.46, 0.11, 0.06), g=None, b=0.0, beta=0.0):
    base = water_preset("ideal", [675, 575, 475])
    return base.with_overrides(attenuation=np.array(c), forward_blur=b,
                               scatter_attenuation=np.array(c if g is None else g), backscatter=beta)


def world(**kw):
    args = dict(scene="seabed", distance=2.0, size=SIZE, water=water(), lamp=Lamp(position=(0.2, 0.0, 0.0)))
    args.update(kw)
    return SimulatedWorld(**args)


def test_without_water_direct_light_is_the_lamp_model():
    w = world(water=water(c=(0.0, 0.0, 0.0)), material="grey")
    direct = w.components().direct
    lamp = w.lamp
    # Independent computation for every pixel of the seabed plane z = 2.
    p = w.camera_range[..., None] * w.rays
    to_lamp = np.array(lamp.position) - p
    ds = np.linalg.norm(to_lamp, axis=-1)
    cos_gamma = -to_lamp[..., 2] / ds  # seabed normal (0, 0, −1): cos γ = n·(S − P)/d_s
    cos_theta = -to_lamp[..., 2] / ds
    beam = np.exp(-math.log(2) * (1 - cos_theta) / (1 - math.cos(math.radians(lamp.beam_half_angle_deg))))
    r = lamp.effective_radius
    expected = beam * (r / (ds + r)) ** 2 * cos_gamma / math.pi * 0.25  # grey: ρ = 0.25
    np.testing.assert_allclose(direct[..., 0], expected, rtol=1e-9)
    assert np.all(w.components().forward == 0) and np.all(w.components().backscatter == 0)


def test_attenuation_follows_beer_lambert():
    clear = world(water=water(c=(0.0, 0.0, 0.0)))
    murky = world(water=water(c=(0.46, 0.11, 0.06)))
    path = murky.camera_range + np.linalg.norm(murky.camera_range[..., None] * murky.rays - np.array(murky.lamp.position), axis=-1)
    ratio = murky.components().direct / clear.components().direct
    np.testing.assert_allclose(ratio, np.exp(-np.array([0.46, 0.11, 0.06]) * path[..., None]), rtol=1e-9)


def test_zero_blur_forward_term_is_the_weighted_surface_term():
    c, g = np.array([0.46, 0.11, 0.06]), np.array([0.40, 0.08, 0.04])
    w = world(water=water(c=c, g=g, b=0.0))
    comp = w.components()
    d = w.camera_range[..., None]
    np.testing.assert_allclose(comp.forward, comp.direct * (np.exp((c - g) * d) - 1.0), rtol=1e-9)


def test_blur_conserves_forward_light_and_spreads_it():
    c, g = np.array([0.46, 0.11, 0.06]), np.array([0.40, 0.08, 0.04])
    sharp = world(scene="plate", distance=3.0, water=water(c=c, g=g, b=0.0), size=(160, 120)).components().forward
    blurred = world(scene="plate", distance=3.0, water=water(c=c, g=g, b=0.02), size=(160, 120)).components().forward
    np.testing.assert_allclose(blurred.sum(axis=(0, 1)), sharp.sum(axis=(0, 1)), rtol=0.02)
    outside = sharp[..., 0] == 0  # open water around the plate receives blurred plate light
    assert blurred[..., 0][outside].max() > 0


def test_no_backscatter_without_beta_and_gating_removes_most():
    assert np.all(world(water=water(beta=0.0)).components().backscatter == 0)
    full = world(water=water(beta=0.002)).components().backscatter
    gated = world(water=water(beta=0.002), gate_width=0.05).components().backscatter
    assert np.all(full > 0)
    assert gated.sum() < 0.05 * full.sum()


def test_the_surface_alone_is_the_frame_of_the_same_world_without_the_waters_light():
    """noise_free_frame(backscatter=False) in scattering water is the frame that water gives with β = 0
    (same exposure, per channel too): the surface's direct and forward light, the dark level, the
    sensor's gain map; and less than the whole frame by the backscatter."""
    murky = world(water=water(g=(0.4, 0.08, 0.04), b=0.01, beta=0.002))
    murky.set_exposure_scale((1.0, 0.5, 2.0))
    clear = world(water=water(g=(0.4, 0.08, 0.04), b=0.01, beta=0.0), fixed_exposure=murky.exposure)
    clear.set_exposure_scale((1.0, 0.5, 2.0))
    surface = murky.noise_free_frame(backscatter=False)
    np.testing.assert_allclose(surface, clear.noise_free_frame(), rtol=1e-5)
    assert np.all(surface < murky.noise_free_frame())


def brute_force_backscatter(w, i, j, beta):
    """∫ β · lamp irradiance · exp(−c (d_s + t)) dt along pixel (i, j)'s ray, fine steps, in numpy."""
    u = w.rays[i, j]
    end = w.camera_range[i, j]
    t = np.linspace(0.05 / u[2], end, 200001)
    t = 0.5 * (t[1:] + t[:-1])
    dt = (end - 0.05 / u[2]) / 200000
    s = np.array(w.lamp.position)
    v = t[:, None] * u - s
    ds = np.linalg.norm(v, axis=-1)
    beam = np.exp(-w.lamp.beam_scale * (1 - v[:, 2] / ds))
    r = w.lamp.effective_radius
    c = w.water.attenuation
    return beta * np.sum((beam * (r / (ds + r)) ** 2)[:, None] * np.exp(-c * (ds + t)[:, None]), axis=0) * dt


def test_backscatter_matches_a_brute_force_integral():
    beta = 0.003
    w = world(water=water(beta=beta), slabs=64, size=(128, 96))
    back = w.components().backscatter
    for i, j in ((48, 64), (5, 7), (90, 120), (30, 100)):
        np.testing.assert_allclose(back[i, j], brute_force_backscatter(w, i, j, beta), rtol=0.03)


def test_camera_noise_matches_its_parameters():
    cam = CameraModel(bits=16, full_well_e=20000, read_noise_e=5.0, dark_current_e=40.0, prnu=0.0)
    radiance = np.full((200, 300, 3), 1.0)
    mean, std = cam.expected(radiance, exposure=8000.0)
    g = cam.gain_dn_per_e
    np.testing.assert_allclose(mean, (8000.0 + 40.0) * g, rtol=1e-6)
    np.testing.assert_allclose(std, np.sqrt((8000.0 + 40.0) * g * g + (5.0 * g) ** 2), rtol=1e-6)
    frames = np.stack([cam.digitise(mean, std, seed=3, frame_index=k).astype(np.float64) for k in range(4)])
    assert abs(frames.mean() - mean.mean()) < 0.01 * std.mean()
    assert frames.std() == pytest.approx(math.sqrt(std.mean() ** 2 + 1 / 12), rel=0.01)
    z = (frames - mean) / std
    assert abs(np.mean(z**3)) < 0.02 and abs(np.mean(z**4) - 3.0) < 0.05  # Gaussian shape
    dark = cam.digitise(*cam.expected(np.zeros((200, 300, 3)), exposure=8000.0), seed=4, frame_index=0)
    assert dark.mean() == pytest.approx(cam.dark_level_dn, rel=0.01)
    assert dark.astype(float).std() == pytest.approx(math.sqrt(40.0 * g * g + (5.0 * g) ** 2 + 1 / 12), rel=0.03)
    gain = CameraModel(prnu=0.01).gain_map((400, 400))
    assert gain.std() == pytest.approx(0.01, rel=0.05)


def test_frames_are_reproducible_quantised_and_saturate():
    w = world(camera=CameraModel(bits=8))
    a, b = w.frame(3), w.frame(3)
    assert a.dtype == np.uint8 and np.array_equal(a, b)
    assert not np.array_equal(a, w.frame(4))
    assert not np.array_equal(a, world(camera=CameraModel(bits=8), seed=1).frame(3))
    exposure = world(camera=CameraModel(bits=12)).exposure
    hot = world(camera=CameraModel(bits=12), fixed_exposure=3 * exposure).frame(0)
    assert hot.dtype == np.uint16 and hot.max() == 4095
    for bits in (8, 12, 16):
        peak = world(camera=CameraModel(bits=bits)).noise_free_frame().max()
        assert peak == pytest.approx(TARGET_CODE[bits], rel=1e-4)


def test_lamp_off_frame_is_dark_current_and_noise_only():
    w = world()
    dark = w.frame(0, lamp_on=False)
    assert abs(dark.mean() - w.camera.dark_level_dn) < 1.0


@pytest.mark.parametrize(
    "scene, centre_range",
    [("seabed", 2.0), ("brick", 1.90), ("pipe", 1.74), ("ball", 1.89), ("ring", 2.0), ("tilted-plane", 2.0), ("plate", 2.0)],
)
def test_scenes_give_true_ranges(scene, centre_range):
    w = world(scene=scene, size=(101, 75))
    truth = w.camera_range
    assert truth[37, 50] == pytest.approx(centre_range, abs=1e-9)
    if scene == "plate":
        assert np.isnan(truth[0, 0])  # open water around the plate
    else:
        assert np.isfinite(truth).all()


def test_ring_is_hollow_and_has_its_tube():
    w = world(scene="ring", distance=1.0, size=(301, 301), fov_deg=20)
    truth = w.camera_range
    row = truth[150]
    assert (row < 0.99).sum() > 0  # the tube stands proud of the seabed
    assert row[150] == pytest.approx(1.0)  # the hole shows the seabed


def test_jerlov_preset_uses_published_optical_properties():
    w = water_preset("jerlov-II", [675.0, 575.0, 475.0])
    ref = jerlov.water("II", source="williamson2022")
    for k, wl in enumerate((675.0, 575.0, 475.0)):
        a, b = float(ref.a(wl)), float(ref.b(wl))
        assert w.attenuation[k] == pytest.approx(a + b)
        assert w.scatter_attenuation[k] == pytest.approx(a + 0.0183 * b)
    assert np.all(w.backscatter > 0)
    with pytest.raises(UserInputError, match="unknown water 'jerlov-XX'; known: ideal, jerlov-I"):
        water_preset("jerlov-XX", [500.0, 600.0])
    with pytest.raises(UserInputError, match="unknown scene 'reef'; known scenes: seabed, brick"):
        build_scene("reef", 2.0)


def test_ambient_daylight_is_independent_of_the_lamp():
    from uwcam.simulation import Ambient

    daylight = Ambient(irradiance=(1e-6, 3e-6, 4e-6))
    lit = world(ambient=daylight).components(lamp_on=True)
    dark = world(ambient=daylight).components(lamp_on=False)
    np.testing.assert_allclose(lit.ambient, dark.ambient)
    assert np.all(dark.direct == 0) and np.all(dark.ambient > 0)
    # Blue-green daylight on a seabed looking down: brighter in B than R, as given.
    assert dark.ambient[..., 2].mean() > dark.ambient[..., 0].mean()
    w = world(ambient=daylight)
    assert w.frame(0, lamp_on=False).mean() > world().frame(0, lamp_on=False).mean()


def test_numpy_twins_of_the_render_kernels_agree():
    """Without numba the renderer runs numpy twins of its kernels: same components."""
    import importlib

    render_module = importlib.import_module("uwcam.simulation.render")
    twins = {"slab_contributions": render_module.slab_contributions_numpy,
             "backscatter_column": render_module.backscatter_column_numpy,
             "backscatter_gated": render_module.backscatter_gated_numpy,
             "bin_surface": render_module.bin_surface_numpy}
    for gate in (None, 0.05):
        w = world(scene="brick", water=water(g=(0.40, 0.08, 0.04), b=0.005, beta=0.002), gate_width=gate)
        args = (w.hit, w.reflectance, w.rays, w.intrinsics, w.water, w.lamp, None, w.slabs, w.gate_width)
        fast, slow = render_module.render(*args), render_module.render(*args, kernels=twins)
        for name in ("direct", "forward", "backscatter"):
            np.testing.assert_allclose(getattr(slow, name), getattr(fast, name), rtol=1e-9, atol=1e-15)
        assert fast.backscatter.max() > 0


def test_numpy_twin_of_the_noise_kernel_draws_the_same_deviates():
    from uwcam.simulation import camera as cam_module

    cam = CameraModel(bits=12)
    rng = np.random.default_rng(2)
    mean = rng.uniform(-50, 4200, (37, 53, 3)).astype(np.float32)  # beyond both ends: clipping too
    std = rng.uniform(0, 400, mean.shape).astype(np.float32)
    compiled = cam.digitise(mean, std, seed=9, frame_index=11)
    twin = np.empty_like(compiled)
    cam_module.digitise_numpy(mean.reshape(-1), std.reshape(-1), cam_module.frame_key(9, 11), float(cam.max_code),
                              cam_module.inverse_normal_table(), twin.reshape(-1), chunk=1000)
    assert np.array_equal(compiled, twin)
    # The tails (Acklam's formula in the extreme bins) are exercised by a million draws.
    big = np.full(1_000_001, 2000.0, np.float32)
    a, b = np.empty(big.size, np.uint16), np.empty(big.size, np.uint16)
    cam_module._digitise(big, big * 0 + 300, cam_module.frame_key(1, 2), 4095.0, cam_module.inverse_normal_table(), a)
    cam_module.digitise_numpy(big, big * 0 + 300, cam_module.frame_key(1, 2), 4095.0, cam_module.inverse_normal_table(), b)
    assert np.array_equal(a, b)
    assert (a < 2000 - 3.8 * 300).any() and (a > 2000 + 3.8 * 300).any()  # draws from both extreme bins
