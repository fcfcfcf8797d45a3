"""Noise-free frames from the forward model invert exactly (relative error ≤ 1e-9)."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from uwcam.optics import (
    Intrinsics,
    camera_range_from_path_length,
    fused_path_length,
    pair_path_length,
    pair_path_variance,
    path_length_from_camera_range,
    pixel_rays,
)

TOL = 1e-9

n_channels = st.integers(min_value=2, max_value=6)


@st.composite
def scenes(draw):
    """Random water, system constants, reflectances, geometry factor, lamp offset and intrinsics."""
    n = draw(n_channels)
    attenuation = np.array(draw(st.lists(st.floats(0.01, 2.0), min_size=n, max_size=n)))
    if np.ptp(attenuation) < 0.01:
        attenuation[0] += 0.05
    constant = np.array(draw(st.lists(st.floats(0.1, 1e5), min_size=n, max_size=n)))
    reflectance = np.array(draw(st.lists(st.floats(0.02, 1.0), min_size=n, max_size=n)))
    h, w = draw(st.integers(1, 12)), draw(st.integers(1, 12))
    fov = draw(st.floats(20.0, 120.0))
    intr = Intrinsics.from_fov(w, h, fov)
    lamp = np.array(draw(st.lists(st.floats(-0.8, 0.8), min_size=3, max_size=3)))
    camera_range = draw(arrays(np.float64, (h, w), elements=st.floats(0.2, 25.0)))
    # A lamp out in the scene in front of the surface on a pixel's ray makes every
    # range on that ray give the same path length; real rigs keep surfaces beyond it.
    camera_range = np.maximum(camera_range, pixel_rays(intr, h, w) @ lamp + 0.2)
    g = draw(arrays(np.float64, (h, w), elements=st.floats(1e-4, 1.0)))
    return attenuation, constant, reflectance, intr, lamp, camera_range, g


def render(attenuation, constant, reflectance, intr, lamp, camera_range, g):
    rays = pixel_rays(intr, *camera_range.shape)
    path = path_length_from_camera_range(camera_range, lamp, rays)
    signal = constant * reflectance * g[..., None] * np.exp(-attenuation * path[..., None])
    return signal, path, rays


@settings(max_examples=200, deadline=None)
@given(scenes())
def test_fusion_and_geometry_invert_forward_model(scene):
    attenuation, constant, reflectance, intr, lamp, camera_range, g = scene
    signal, path, rays = render(*scene)
    variance = 1.0 + 0.01 * signal  # any positive weights: noise-free data fit exactly
    d_t, var = fused_path_length(signal, attenuation, np.log(constant * reflectance), variance)
    np.testing.assert_allclose(d_t, path, rtol=TOL)
    assert np.all(var > 0)
    d_c = camera_range_from_path_length(d_t, lamp, rays)
    np.testing.assert_allclose(d_c, camera_range, rtol=TOL)


@settings(max_examples=200, deadline=None)
@given(scenes(), st.data())
def test_every_pair_inverts_forward_model(scene, data):
    attenuation, constant, reflectance, *_ = scene
    signal, path, _ = render(*scene)
    n = len(attenuation)
    i = data.draw(st.integers(0, n - 1))
    # A pair needs a real attenuation difference to carry range (V ~ 1e-18 carries none).
    j = data.draw(st.integers(0, n - 1).filter(lambda k: abs(attenuation[k] - attenuation[i]) >= 0.01))
    u_ij = (constant[j] * reflectance[j]) / (constant[i] * reflectance[i])
    d_t = pair_path_length(signal[..., i], signal[..., j], attenuation[j] - attenuation[i], u_ij)
    np.testing.assert_allclose(d_t, path, rtol=TOL)


@settings(max_examples=100, deadline=None)
@given(scenes(), st.data())
def test_two_channel_fusion_is_the_pair_transform(scene, data):
    attenuation, constant, reflectance, *_ = scene
    signal, _, _ = render(*scene)
    i, j = 0, 1
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    # Perturb the signal so the comparison is not just "both hit the truth".
    noisy = signal[..., [i, j]] * rng.uniform(0.8, 1.25, size=signal[..., [i, j]].shape)
    var = rng.uniform(0.5, 4.0, size=noisy.shape) * noisy
    c, b = attenuation[[i, j]], np.log(constant * reflectance)[[i, j]]
    if c[0] == c[1]:
        return
    fused, fused_var = fused_path_length(noisy, c, b, var)
    pair = pair_path_length(noisy[..., 0], noisy[..., 1], c[1] - c[0], np.exp(b[1] - b[0]))
    pair_var = pair_path_variance(noisy[..., 0], noisy[..., 1], var[..., 0], var[..., 1], c[1] - c[0])
    np.testing.assert_allclose(fused, pair, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(fused_var, pair_var, rtol=1e-9)


@given(st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3), st.floats(0.0, 0.999))
def test_path_shorter_than_lamp_offset_is_invalid(lamp, fraction):
    lamp = np.array(lamp)
    reach = np.linalg.norm(lamp) * fraction  # never longer than |S|
    assert np.isnan(camera_range_from_path_length(np.array([reach]), lamp))[0]


def test_accepts_integer_and_float32_input():
    attenuation = np.array([0.46, 0.11, 0.06])
    b = np.zeros(3)
    for dtype in (np.uint8, np.uint16, np.float32, np.float64):
        signal = np.array([[[20, 120, 200]]], dtype=dtype)
        d_t, var = fused_path_length(signal, attenuation, b, np.ones(3))
        assert d_t.dtype == np.float64 and np.isfinite(d_t).all() and np.isfinite(var).all()


def test_channels_of_equal_attenuation_give_no_range():
    signal = np.full((2, 2, 3), 100.0)
    d_t, var = fused_path_length(signal, np.array([0.1, 0.1, 0.1]), np.zeros(3), np.ones(3))
    assert np.isnan(d_t).all() and np.isnan(var).all()
    usable = np.array([True, True, False])
    d_t, _ = fused_path_length(signal, np.array([0.1, 0.1, 0.5]), np.zeros(3), np.ones(3), usable=usable)
    assert np.isnan(d_t).all()
