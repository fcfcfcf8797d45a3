"""Kirlin's step against finite differences and its convergence; normals of known planes."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from uwcam.optics.geometry import Intrinsics
from uwcam.optics.orientation import kirlin_estimate, kirlin_step, normals_from_range, sensitivity, transfer

ATTENUATION = np.array([0.46, 0.11, 0.06])  # Jerlov II at 675/575/475 nm, 1/m
SCALE = np.array([900.0, 1200.0, 700.0])


def model(d, cos_g):
    """T_k written out apart from the code under test."""
    return np.array([s * cos_g * np.exp(-2 * a * d) / d**2 for a, s in zip(ATTENUATION, SCALE)])


@given(d=st.floats(0.5, 12.0), cos_g=st.floats(0.2, 1.0))
@settings(max_examples=60, deadline=None)
def test_sensitivity_columns_are_the_derivatives_of_the_model(d, cos_g):
    g = sensitivity(ATTENUATION, SCALE, d, cos_g)
    h = 1e-5 * d
    assert np.allclose(transfer(ATTENUATION, SCALE, d, cos_g), model(d, cos_g), rtol=1e-12)
    assert np.allclose(g[:, 0], (model(d, cos_g + 1e-6) - model(d, cos_g - 1e-6)) / 2e-6, rtol=1e-6)
    assert np.allclose(g[:, 1], (model(d + h, cos_g) - model(d - h, cos_g)) / (2 * h), rtol=1e-6)
    second = (model(d + h, cos_g) - 2 * model(d, cos_g) + model(d - h, cos_g)) / h**2
    assert np.allclose(g[:, 2], 0.5 * second, rtol=1e-4)


@given(d=st.floats(0.8, 8.0), angle=st.floats(0.0, 70.0), dd=st.floats(-0.08, 0.08), dangle=st.floats(-8.0, 8.0))
@settings(max_examples=60, deadline=None)
def test_estimate_converges_to_the_truth_from_a_nearby_start(d, angle, dd, dangle):
    e = model(d, np.cos(np.radians(angle)))
    start_angle = float(np.clip(angle + dangle, 0.0, 80.0))
    r, incidence, ok = kirlin_estimate(e, ATTENUATION, SCALE, d * (1 + dd), start_angle)
    assert ok
    assert r == pytest.approx(d, rel=1e-6)
    assert np.cos(np.radians(incidence)) == pytest.approx(np.cos(np.radians(angle)), abs=1e-6)


def test_step_shapes_broadcast_over_pixels_and_is_zero_at_the_truth():
    d = np.array([[1.0, 2.0], [3.0, 4.0]])
    angle = np.array([[0.0, 10.0], [20.0, 30.0]])
    e = np.moveaxis(model(d, np.cos(np.radians(angle))), 0, -1)
    step = kirlin_step(e, ATTENUATION, SCALE, d, angle)
    assert step.shape == (2, 2, 3) and np.allclose(step, 0.0, atol=1e-9)
    step = kirlin_step(e, ATTENUATION, SCALE, 2.5, 15.0)  # scalar seed for every pixel
    assert step.shape == (2, 2, 3) and np.all(np.isfinite(step))


def test_normals_of_a_tilted_plane_with_non_square_pixels():
    """A plane z = z0 + t·x seen through a camera with fx ≠ fy and an off-centre principal point:
    the normal is (t, 0, −1)/√(1+t²) everywhere (facing the camera)."""
    intr = Intrinsics(fx=500.0, fy=620.0, cx=70.3, cy=41.8)
    h, w, z0, t = 90, 140, 3.0, 0.4
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = (u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy
    z = z0 / (1 - t * x)  # on the ray (x z, y z, z): z = z0 + t·x·z
    rng = z * np.sqrt(x**2 + y**2 + 1)
    expected = np.array([t, 0.0, -1.0]) / np.sqrt(1 + t**2)
    for window in (1, 7):
        n = normals_from_range(rng, intr, window=window)
        k = max(window // 2, 1)
        assert np.allclose(n[k:-k, k:-k], expected, atol=2e-3 if window > 1 else 1e-6), window
        assert np.isnan(n[:, :k]).all() and np.isnan(n[:k]).all()  # the window reaches outside
    rng[40, 60] = np.nan
    n = normals_from_range(rng, intr)
    assert np.isnan(n[40, 60]).all() and np.isfinite(n[40, 61]).all() and np.isfinite(n[10, 10]).all()
    noisy = rng * (1 + 0.02 * np.random.default_rng(1).standard_normal(rng.shape))
    n = normals_from_range(noisy, intr, window=9)
    ok = np.isfinite(n).all(axis=-1)
    assert np.median(n[ok] @ expected) > 0.97  # 2 % range noise: the window averages it out
    with pytest.raises(ValueError, match="odd"):
        normals_from_range(rng, intr, window=4)


def test_normals_next_to_a_large_hole_are_finite_or_nan_never_infinite():
    """A masked block (no range) larger than the window: OpenCV's running box sums leave a
    residue of ~1e-16 where a window holds no pixel; it must not become an infinite point."""
    from uwcam.optics.geometry import Intrinsics
    from uwcam.optics.orientation import normals_from_range

    h, w = 60, 80
    r = np.full((h, w), 2.0) + np.linspace(0, 0.3, w)[None, :]
    r[10:40, 20:60] = np.nan
    with np.errstate(all="raise"):
        n = normals_from_range(r, Intrinsics(70.0, 70.0, w / 2, h / 2))
    assert not np.isinf(n).any()
    assert np.all(np.isnan(n[10:40, 20:60])) and np.isfinite(n[45:55, 10:70]).all()
