"""The independent forward model (bench/independent_world.py) against closed forms derived by hand.

Nothing here ranges: these tests pin the world that bench/independent_study.py shows uwcam, so that a
surprise in the study is uwcam's and not the world's.
"""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "bench"))

import independent_world as iw  # noqa: E402

ROOT = os.path.join(os.path.dirname(__file__), "..")
RIG = os.path.join(ROOT, "calibration_rigs", "grey-plate-large-patch.yaml")
SMALL = iw.Camera(width=40, height=30)


def no_scatter(water: iw.Water) -> iw.Water:
    return iw.with_water(water, scattering_per_m=(0.0, 0.0, 0.0))


def test_presets_are_physical_and_red_fades_fastest():
    for water in iw.WATERS.values():
        assert np.all(water.a > 0) and np.all(water.b > 0)
        assert np.allclose(water.c, water.a + water.b)
        assert water.c[0] > water.c[1] > water.c[2]  # R > G > B in oceanic water
    assert np.allclose(iw.WATERS["jerlov-II-like"].c, (0.40, 0.075, 0.055))


def test_hg_phase_function_is_normalised_and_peaks_forward():
    mu = np.linspace(-1.0, 1.0, 200001)
    for g in (0.0, 0.5, 0.9):
        p = iw.henyey_greenstein(mu, g)
        # ∫ P dΩ = 2π ∫ P dμ = 1
        integral = 2 * np.pi * np.sum(0.5 * (p[1:] + p[:-1]) * np.diff(mu))
        assert integral == pytest.approx(1.0, rel=2e-3)
    assert iw.henyey_greenstein(-1.0, 0.9) == pytest.approx((1 - 0.81) / (4 * np.pi * 1.9**3))
    assert iw.henyey_greenstein(0.0, 0.0) == pytest.approx(1 / (4 * np.pi))


def test_lamp_irradiance_inverse_square_beam_and_attenuation():
    water = iw.WATERS["jerlov-II-like"]
    lamp = iw.Lamp(position_m=(0.3, 0.0, 0.0), sigma_beam_deg=30.0, intensity=(2.0, 1.0, 0.5))
    # 2 m straight ahead of the lamp: on the beam's axis
    e, w, d = iw.lamp_irradiance(np.array([0.3, 0.0, 2.0]), lamp, water)
    assert d == pytest.approx(2.0)
    assert np.allclose(w, (0, 0, 1))
    assert np.allclose(e, np.array([2.0, 1.0, 0.5]) * np.exp(-water.c * 2.0) / 4.0)
    # 30° off the beam's axis (one σ) at 1 m: exp(−1/2)
    p = np.array([0.3 + np.sin(np.radians(30)), 0.0, np.cos(np.radians(30))])
    e, _, d = iw.lamp_irradiance(p, lamp, water)
    assert d == pytest.approx(1.0)
    assert np.allclose(e, np.array([2.0, 1.0, 0.5]) * np.exp(-0.5) * np.exp(-water.c))


def test_plate_ratio_of_two_channels_follows_the_path_length_exactly_without_scattering():
    """b = 0: (E_i / E_j) = (I_i ρ_i / I_j ρ_j) · exp(−(c_i − c_j) d_T), d_T = |x − S| + |x| per pixel."""
    water = no_scatter(iw.WATERS["jerlov-II-like"])
    lamp = iw.Lamp(position_m=(0.3, -0.1, 0.05), intensity=(1.3, 1.0, 0.8))
    camera = iw.Camera(width=40, height=30, vignetting=True)
    for z in (1.0, 2.5):
        scene = iw.Scene("seabed", z, reflectance=(0.3, 0.2, 0.15))
        rendered = iw.render(camera, scene, lamp, water, exposure=1e6)
        signal = iw.mean_frame(rendered.radiance, camera, 1e6, prnu=False) - camera.dark_level_dn
        rays = iw.pixel_rays(camera)
        points = rays * (z / rays[..., 2])[..., None]
        d_t = np.linalg.norm(points - np.array(lamp.position_m), axis=-1) + np.linalg.norm(points, axis=-1)
        for i, j in ((0, 1), (0, 2), (1, 2)):
            expected = (lamp.intensity[i] * scene.reflectance[i]) / (lamp.intensity[j] * scene.reflectance[j]) \
                * np.exp(-(water.c[i] - water.c[j]) * d_t)
            assert np.allclose(signal[..., i] / signal[..., j], expected, rtol=1e-12)


def test_surface_radiance_on_axis_with_the_lamp_at_the_camera():
    """Lamp at the camera, centre pixel of an odd-sized image looks straight ahead: L = I ρ/π · exp(−2cz)/z²."""
    water = no_scatter(iw.WATERS["jerlov-I-like"])
    lamp = iw.Lamp(position_m=(0.0, 0.0, 0.0), intensity=(1.0, 2.0, 3.0))
    camera = iw.Camera(width=41, height=31)
    z = 3.0
    radiance = iw.scene_radiance(camera, iw.Scene("seabed", z, reflectance=(0.18, 0.18, 0.18)), lamp, water)
    expected = np.array([1.0, 2.0, 3.0]) * 0.18 / np.pi * np.exp(-2 * water.c * z) / z**2
    assert np.allclose(radiance[15, 20], expected, rtol=1e-12)


def test_doubling_the_exposure_doubles_the_mean_above_dark():
    water = iw.WATERS["jerlov-II-like"]
    lamp = iw.Lamp()
    radiance = iw.scene_radiance(SMALL, iw.Scene("seabed", 2.0), lamp, water, steps=64)
    one = iw.mean_frame(radiance, SMALL, 1e6) - SMALL.dark_level_dn
    two = iw.mean_frame(radiance, SMALL, 2e6) - SMALL.dark_level_dn
    assert np.allclose(two, 2 * one, rtol=1e-12)
    # and the noisy frames' mean follows (16 frames, the whole image: shot and read noise average out)
    rng = np.random.default_rng(0)
    mean = iw.mean_frame(radiance, SMALL, 2e6)
    frames = np.stack([iw.noisy_frame(mean, SMALL, rng) for _ in range(16)]).astype(float)
    assert frames.mean() == pytest.approx(mean.mean(), rel=1e-3)


def test_vignetting_at_the_corner_is_cos4_of_the_corner_ray():
    camera = iw.Camera(width=160, height=120, vignetting=True)
    fx, fy, cx, cy = camera.intrinsics
    # corner pixel (0, 0): the ray (−cx/fx, −cy/fy, 1); cos α = 1/√(1 + x² + y²)
    x, y = cx / fx, cy / fy
    cos_a = 1.0 / np.sqrt(1.0 + x * x + y * y)
    assert fx == pytest.approx(80.0 / np.tan(np.radians(30.0)))
    v = iw.vignetting(camera)
    assert v[0, 0] == pytest.approx(cos_a**4, rel=1e-12)
    assert v[-1, -1] == pytest.approx(cos_a**4, rel=1e-12)
    radiance = np.ones((120, 160, 3))
    on = iw.mean_frame(radiance, camera, 1000.0, prnu=False) - camera.dark_level_dn
    off = iw.mean_frame(radiance, iw.Camera(width=160, height=120), 1000.0, prnu=False) - camera.dark_level_dn
    assert np.allclose(on[0, 0] / off[0, 0], cos_a**4)
    # by hand: x = 79.5/138.56 = 0.574, y = 59.5/138.56 = 0.429, cos²α = 1/1.514 = 0.661 (α = 35.6°)
    assert cos_a**4 == pytest.approx(0.436, abs=0.001)  # the corner gets 0.44 of the centre's light


def test_backscatter_is_zero_without_scattering():
    water = no_scatter(iw.WATERS["jerlov-II-like"])
    rays = iw.pixel_rays(SMALL)
    assert np.all(iw.backscatter_radiance(rays, np.inf, iw.Lamp(), water, steps=64) == 0)
    assert np.all(iw.scene_radiance(SMALL, iw.Scene("open-water"), iw.Lamp(), water) == 0)


def test_single_scattering_in_a_thin_slab_with_the_lamp_at_the_camera():
    """Lamp at the camera, the ray along its axis: every point is lit head-on (B = 1) and seen straight
    back (ψ = 180°), so the integrand is b·P_HG(−1)·I·exp(−2ct)/t².

    With c = 0 (a fictitious water, a = −b, that isolates the geometry) the slab t1…t2 gives exactly
    b·P(−1)·I·(1/t1 − 1/t2); with c > 0 a thin slab (10 cm at 1 m) gives b·P(−1)·I·exp(−2c·t̄)·(1/t1 − 1/t2)
    to within (cΔt)² and the slab's curvature, well under 10⁻³.
    """
    b = 0.05
    lamp = iw.Lamp(position_m=(0.0, 0.0, 0.0), intensity=(1.0, 2.0, 4.0))
    ray = np.array([[0.0, 0.0, 1.0]])
    p = (1 - 0.81) / (4 * np.pi * 1.9**3)
    clear = iw.Water("c=0", absorption_per_m=(-b, -b, -b), scattering_per_m=(b, b, b))
    t1, t2 = 1.0, 1.1
    hand = b * p * np.array([1.0, 2.0, 4.0]) * (1 / t1 - 1 / t2)
    got = iw.backscatter_radiance(ray, t2, lamp, clear, t_near=t1, steps=256)[0]
    assert np.allclose(got, hand, rtol=1e-5)
    water = iw.Water("thin", absorption_per_m=(0.4, 0.05, 0.01), scattering_per_m=(b, b, b))
    hand = b * p * np.array([1.0, 2.0, 4.0]) * np.exp(-2 * water.c * (t1 + t2) / 2) * (1 / t1 - 1 / t2)
    got = iw.backscatter_radiance(ray, t2, lamp, water, t_near=t1, steps=256)[0]
    assert np.allclose(got, hand, rtol=1e-3)
    # a semi-infinite column from t1 with c > 0, exponential integral by series: ∫ e^{−kt}/t² dt
    k = 2 * water.c[0]
    # ∫_{t1}^∞ e^{−kt}/t² dt = e^{−k t1}/t1 − k·E1(k t1); E1(x) = −γ − ln x − Σ (−x)^n/(n·n!)
    x = k * t1
    e1 = -0.5772156649015329 - np.log(x) - sum((-x) ** n / (n * np.prod(np.arange(1, n + 1, dtype=float))) for n in range(1, 40))
    column = np.exp(-x) / t1 - k * e1
    got = iw.backscatter_radiance(ray, 60.0, lamp, water, t_near=t1, steps=512)[0, 0]
    # the integral to 60 m rather than ∞ misses e^{−0.9·60}/60: nothing
    assert got == pytest.approx(b * p * 1.0 * column, rel=1e-4)


def test_backscatter_falls_with_the_lamp_farther_aside():
    water = iw.WATERS["jerlov-II-like"]
    ray = np.array([[0.0, 0.0, 1.0]])
    near = iw.backscatter_radiance(ray, np.inf, iw.Lamp(position_m=(0.1, 0, 0)), water)[0]
    far = iw.backscatter_radiance(ray, np.inf, iw.Lamp(position_m=(0.6, 0, 0)), water)[0]
    assert np.all(far < near) and np.all(far > 0)


def test_noise_has_the_shot_and_read_variance():
    camera = iw.Camera(width=64, height=64, gain_e_per_dn=2.0, read_noise_dn=4.0)
    mean = np.full((64, 64, 3), camera.dark_level_dn + 1000.0)
    rng = np.random.default_rng(1)
    frames = np.stack([iw.noisy_frame(mean, camera, rng) for _ in range(8)]).astype(float)
    # per pixel: Var = (mean − dark)/gain + read² + 1/12 (rounding) = 500 + 16 + 0.08
    var = frames.var(axis=0, ddof=1).mean()
    assert var == pytest.approx(516.08, rel=0.03)
    assert frames.mean() == pytest.approx(camera.dark_level_dn + 1000.0, abs=0.5)
    top = np.full((2, 2, 3), 1e9)
    assert np.all(iw.noisy_frame(top, camera, rng) == 65535)


def test_prnu_is_one_percent_fixed_and_seeded():
    camera = iw.Camera(width=100, height=100)
    g = iw.prnu_map(camera)
    assert np.std(g) == pytest.approx(0.01, rel=0.03)
    assert np.array_equal(g, iw.prnu_map(camera))
    assert not np.array_equal(g, iw.prnu_map(iw.Camera(width=100, height=100, prnu_seed=8)))


def test_plate_layout_from_the_rig():
    layout = iw.plate_from_rig(RIG)
    assert layout.size_m == (0.5, 0.5) and np.allclose(layout.reflectance, 0.18)
    camera = iw.Camera()
    t_hit, rho = iw.surface_map(camera, iw.Scene("plate", 1.0, layout))
    fx, _, cx, cy = camera.intrinsics
    # the plate spans 0.5·fx = 69 px at 1 m; its centre is the black patch, 0.1 m inside each side grey
    assert np.allclose(rho[60, 80], 0.03)
    assert np.allclose(rho[60, int(cx + 0.18 * fx)], 0.18)
    assert np.isinf(t_hit[2, 2]) and np.all(rho[2, 2] == 0)
    assert t_hit[60, 80] == pytest.approx(1.0 / iw.pixel_rays(camera)[60, 80, 2])


def test_png_holds_the_channels_in_rgb_order(tmp_path):
    from uwcam.imaging.imageio import read_frame

    frame = np.zeros((4, 5, 3), np.uint16)
    frame[..., 0], frame[..., 1], frame[..., 2] = 1000, 20000, 60000
    path = tmp_path / "f.png"
    iw.write_png(str(path), frame)
    assert np.array_equal(read_frame(path), frame)
    import cv2

    assert cv2.imread(str(path), cv2.IMREAD_UNCHANGED)[0, 0].tolist() == [60000, 20000, 1000]  # BGR in OpenCV
