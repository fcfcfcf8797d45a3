"""Geometry with non-square pixels and an off-centre principal point, against references written here.

Rays come from the pinhole model written out per pixel; camera range from path length is found
by bisection on the forward geometry d_T = d_c + |d_c·u − S| (no closed form involved); frames
are rendered by a naive forward model. A swap of 1/fx and 1/fy, or of cx and cy, moves ranges by
centimetres here, because fx ≠ fy, cx ≠ cy and the lamp sits off both axes.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.synthetic import make_profile
from uwcam.optics import Intrinsics, pixel_rays, plane_camera_range
from uwcam.optics import camera_range_derivative, camera_range_equidistant
from uwcam.optics import camera_range_from_path_length, path_length_from_camera_range
from uwcam.optics.validity import Reason
from uwcam.ranging.estimator import RangeEstimator

H, W = 30, 44
INTR = Intrinsics(fx=38.0, fy=26.0, cx=17.5, cy=11.0)  # wide, non-square, off-centre
LAMP = (0.35, -0.22, 0.08)
C = np.array([0.46, 0.11, 0.06])
B = np.array([9.5, 9.9, 9.6])


def ray(i: int, j: int, intr: Intrinsics = INTR) -> tuple[float, float, float]:
    """Unit ray of pixel (row i, column j): ((j − cx)/fx, (i − cy)/fy, 1), normalised."""
    x, y = (j - intr.cx) / intr.fx, (i - intr.cy) / intr.fy
    n = math.sqrt(x * x + y * y + 1.0)
    return x / n, y / n, 1.0 / n


def path_of(dc: float, u, s=LAMP) -> float:
    return dc + math.dist([dc * u[0], dc * u[1], dc * u[2]], s)


def camera_range_by_bisection(path: float, u, s=LAMP) -> float:
    lo, hi = 0.0, path
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if path_of(mid, u, s) < path else (lo, mid)
    return 0.5 * (lo + hi)


def test_pixel_rays_are_the_pinhole_model():
    rays = pixel_rays(INTR, H, W)
    assert rays.shape == (H, W, 3)
    for i, j in [(0, 0), (0, W - 1), (H - 1, 0), (H - 1, W - 1), (11, 17), (5, 30)]:
        np.testing.assert_allclose(rays[i, j], ray(i, j), rtol=1e-12, atol=1e-15)


def test_from_fov_gives_square_pixels_centred():
    intr = Intrinsics.from_fov(640, 480, 90.0)
    assert intr.fx == pytest.approx(320.0) and intr.fy == intr.fx
    assert (intr.cx, intr.cy) == (319.5, 239.5)
    assert Intrinsics(0.5, 0.25, 0.0, 0.0).fx == 0.5  # tiny, but positive
    with pytest.raises(ValueError, match="focal lengths must be positive"):
        Intrinsics(0.0, 1.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="focal lengths must be positive"):
        Intrinsics(1.0, -1.0, 0.0, 0.0)


@pytest.mark.parametrize("pixel", [(0, 0), (H - 1, W - 1), (0, W - 1), (11, 17), (25, 3)])
@pytest.mark.parametrize("camera_range", [0.6, 2.0, 7.5])
def test_camera_range_inverts_the_forward_geometry(pixel, camera_range):
    u = ray(*pixel)
    path = path_of(camera_range, u)
    assert path_length_from_camera_range(camera_range, LAMP, np.array(u)) == pytest.approx(path, rel=1e-12)
    got = camera_range_from_path_length(path, LAMP, np.array(u))
    assert got == pytest.approx(camera_range_by_bisection(path, u), abs=1e-9)
    assert got == pytest.approx(camera_range, abs=1e-9)
    h = 1e-6
    slope = (camera_range_by_bisection(path + h, u) - camera_range_by_bisection(path - h, u)) / (2 * h)
    assert camera_range_derivative(path, LAMP, np.array(u)) == pytest.approx(slope, rel=1e-5)


def test_lamp_on_the_optical_axis_and_beside_the_camera():
    # No rays given: the optical axis.
    for dc in (0.5, 3.0):
        path = path_of(dc, (0.0, 0.0, 1.0))
        assert camera_range_from_path_length(path, LAMP) == pytest.approx(dc, abs=1e-12)
        assert camera_range_from_path_length(path, LAMP, None) == pytest.approx(dc, abs=1e-12)
    # Lamp at the camera: half the path, derivative ½.
    assert camera_range_from_path_length(4.0) == pytest.approx(2.0)
    assert camera_range_derivative(4.0) == pytest.approx(0.5)
    assert path_length_from_camera_range(1.5) == pytest.approx(3.0)
    np.testing.assert_allclose(camera_range_equidistant([1.0, 3.0]), [0.5, 1.5])
    # A path no longer than |S| cannot reach any surface.
    s = math.sqrt(sum(v * v for v in LAMP))
    assert np.isnan(camera_range_from_path_length(s, LAMP)) and np.isnan(camera_range_from_path_length(0.9 * s, LAMP))
    assert np.isfinite(camera_range_from_path_length(1.01 * s, LAMP))
    with pytest.raises(ValueError, match=r"lamp_position must be \(x, y, z\)"):
        camera_range_from_path_length(3.0, (0.1, 0.2))
    # The forward direction refuses it too (numpy would broadcast a 2-vector against rays).
    with pytest.raises(ValueError, match=r"lamp_position must be \(x, y, z\)"):
        path_length_from_camera_range(1.5, (0.1, 0.2))


def test_plane_camera_range_is_distance_over_the_axial_component():
    rays = pixel_rays(INTR, H, W)
    r = plane_camera_range(1.7, rays)
    for i, j in [(0, 0), (H - 1, W - 1), (11, 17)]:
        assert r[i, j] == pytest.approx(1.7 / ray(i, j)[2], rel=1e-12)
    assert plane_camera_range(1.7) == pytest.approx(1.7)


def render_plate(distance: float, lamp=LAMP, intr: Intrinsics | None = INTR, tilt=(0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Naive forward model, pixel by pixel: a (possibly tilted) plane; returns (E (H, W, 3), d_c)."""
    frame = np.empty((H, W, 3))
    truth = np.empty((H, W))
    for i in range(H):
        for j in range(W):
            u = ray(i, j, intr) if intr is not None else ray(i, j)
            # Plane z = distance + tx·x + ty·y through the point on the ray.
            dc = distance / (u[2] - tilt[0] * u[0] - tilt[1] * u[1])
            dt = path_of(dc, u, lamp)
            g = 0.3 + 0.5 * (i + j) / (H + W)  # anything common to the channels
            frame[i, j] = g * np.exp(B - C * dt)
            truth[i, j] = dc
    return frame, truth


@pytest.mark.parametrize("distance, tilt", [(1.2, (0.0, 0.0)), (3.0, (0.3, -0.2))])
def test_estimator_ranges_every_pixel_with_its_own_ray(distance, tilt):
    frame, truth = render_plate(distance, tilt=tilt)
    est = RangeEstimator(make_profile(C, B, lamp=LAMP, intrinsics=INTR))
    out = est(frame)
    assert (out.reasons == Reason.VALID).all()
    np.testing.assert_allclose(out.range, truth, rtol=2e-6, atol=2e-6)
    # The same with swapped focal lengths or principal point is centimetres off: the
    # test above would see it.
    for wrong in (Intrinsics(INTR.fy, INTR.fx, INTR.cx, INTR.cy), Intrinsics(INTR.fx, INTR.fy, INTR.cy, INTR.cx)):
        bad = RangeEstimator(make_profile(C, B, lamp=LAMP, intrinsics=wrong))(frame)
        assert np.nanmax(np.abs(bad.range - truth)) > 0.01


@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_estimator_variance_carries_the_geometry_derivative(dtype):
    """Var d_c = (∂d_c/∂d_T)² · Var d_T, with the derivative by finite differences of the bisection."""
    frame, truth = render_plate(2.0)
    scale = 60000.0 / frame.max()
    raw = frame * scale
    raw = np.rint(raw).astype(dtype) if dtype == np.uint16 else raw.astype(dtype)
    profile = make_profile(C, B + np.log(scale), lamp=LAMP, intrinsics=INTR, read_noise=3.0, shot_gain=0.2)
    out = RangeEstimator(profile)(raw)
    for i, j in [(0, 0), (H - 1, W - 1), (0, W - 1), (17, 9)]:
        e = raw[i, j].astype(np.float64)
        var = 9.0 + 0.2 * e + 1.0 / 12.0
        w = e * e / var
        cbar = (w * C).sum() / w.sum()
        var_t = 1.0 / (w * (C - cbar) ** 2).sum()
        ybar = (w * (np.log(e) - B - np.log(scale))).sum() / w.sum()
        d_t = -(w * (C - cbar) * (np.log(e) - B - np.log(scale) - ybar)).sum() * var_t
        u = ray(i, j)
        h = 1e-6
        slope = (camera_range_by_bisection(d_t + h, u) - camera_range_by_bisection(d_t - h, u)) / (2 * h)
        assert out.range[i, j] == pytest.approx(camera_range_by_bisection(d_t, u), rel=1e-5)
        assert out.variance[i, j] == pytest.approx(slope**2 * var_t, rel=1e-4)


def test_estimator_without_intrinsics_treats_every_pixel_as_on_axis():
    frame, _ = render_plate(2.0)
    est = RangeEstimator(make_profile(C, B, lamp=LAMP))
    out = est(frame)
    for i, j in [(0, 0), (H - 1, W - 1), (11, 17)]:
        u = ray(i, j)
        d_t = path_of(2.0 / u[2], u)
        assert out.range[i, j] == pytest.approx(camera_range_by_bisection(d_t, (0.0, 0.0, 1.0)), rel=1e-6)


def test_estimator_with_the_lamp_at_the_camera_halves_the_path():
    frame, truth = render_plate(2.5, lamp=(0.0, 0.0, 0.0))
    out = RangeEstimator(make_profile(C, B, intrinsics=INTR))(frame)
    np.testing.assert_allclose(out.range, truth, rtol=2e-6)


def test_paths_shorter_than_the_lamp_offset_or_out_of_bounds_have_no_range():
    s = math.sqrt(sum(v * v for v in LAMP))
    e = np.stack([np.exp(B - C * d) for d in (0.5 * s, 2.0, 9.0)])[None]  # (1, 3, 3)
    est = RangeEstimator(make_profile(C, B, lamp=LAMP, intrinsics=INTR), path_length_bounds=(0.0, 8.0))
    out = est(e)
    assert list(out.reasons[0]) == [Reason.PATH_OUT_OF_BOUNDS, Reason.VALID, Reason.PATH_OUT_OF_BOUNDS]
    assert np.isnan(out.range[0, 0]) and np.isnan(out.variance[0, 2]) and np.isfinite(out.range[0, 1])
    low = RangeEstimator(make_profile(C, B), path_length_bounds=(2.5, 20.0))(e)
    assert list(low.reasons[0]) == [Reason.PATH_OUT_OF_BOUNDS, Reason.PATH_OUT_OF_BOUNDS, Reason.VALID]


def test_reduced_intrinsics_point_at_the_centres_of_the_blocks_they_average():
    """A 4×3-reduced image's pixel (i, j) averages full pixels 4j..4j+3 across and 3i..3i+2 down:
    its ray is the ray of the block's centre (4j + 1.5, 3i + 1), written out here."""
    from uwcam.optics.geometry import Intrinsics

    full = Intrinsics(800.0, 790.0, 639.5, 359.5)
    small = full.reduced(4, 3)
    for i, j in ((0, 0), (5, 7), (119, 159)):
        u, v = 4 * j + 1.5, 3 * i + 1.0
        assert (j - small.cx) / small.fx == pytest.approx((u - full.cx) / full.fx, rel=1e-12, abs=1e-15)
        assert (i - small.cy) / small.fy == pytest.approx((v - full.cy) / full.fy, rel=1e-12, abs=1e-15)
