"""Intrinsics, reflectance ratios and the forward lamp geometry against values written out here: fx = (W/2)/tan(FOV/2),
positive focal lengths only, and d_T = d_c + |d_c·u − S| for several points at once."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from uwcam.optics.geometry import Intrinsics, path_length_from_camera_range


def test_intrinsics_from_a_field_of_view_and_their_checks():
    intr = Intrinsics.from_fov(640, 480, 60.0)
    assert intr.fx == pytest.approx(320.0 / np.tan(np.pi / 6), rel=1e-12) == pytest.approx(554.2562584, rel=1e-9)
    assert intr.fy == intr.fx and (intr.cx, intr.cy) == (319.5, 239.5)
    for fx, fy in [(500.0, 0.0), (0.0, 500.0), (500.0, -1.0)]:
        with pytest.raises(ValueError, match="focal lengths must be positive"):
            Intrinsics(fx, fy, 10.0, 10.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        intr.fx = 1.0  # type: ignore[misc]


def test_forward_geometry_of_several_points_along_several_rays():
    s = np.array([0.3, -0.1, 0.05])
    rays = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, -0.28, 0.96], [0.36, 0.48, 0.8]])
    dc = np.array([1.0, 2.5, 4.0, 0.7])
    expected = [d + np.sqrt(((d * u - s) ** 2).sum()) for d, u in zip(dc, rays)]
    np.testing.assert_allclose(path_length_from_camera_range(dc, s, rays), expected, rtol=1e-12)
    np.testing.assert_allclose(path_length_from_camera_range(dc, s), [d + np.sqrt(((d * rays[0] - s) ** 2).sum()) for d in dc],
                               rtol=1e-12)


def test_reflectance_ratios_are_relative_to_the_first_channel_by_default():
    """Signals of a surface whose reflectance ratios are (1, 2, 0.5) times the target's, at a known
    path: the ratios come back relative to channel 0, which is 1."""
    from uwcam.optics.reflectance import reflectance_ratio_from_range

    c = np.array([0.46, 0.11, 0.06])
    b_target = np.array([9.0, 9.6, 9.3])
    d = 3.0
    signal = np.exp(b_target + np.log([1.0, 2.0, 0.5]) + 0.7 - c * d)  # 0.7: overall brightness, cancels
    np.testing.assert_allclose(reflectance_ratio_from_range(signal[None], [d], c, b_target), [1.0, 2.0, 0.5], rtol=1e-12)


@pytest.mark.skipif(__import__("uwcam.optics.kernels", fromlist=["BACKEND"]).BACKEND != "numba", reason="numba is not installed here")
@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_numpy_path_with_non_square_pixels_and_an_off_centre_principal_point(dtype, monkeypatch):
    """The numpy path (machines without numba) against the compiled kernels, with fx ≠ fy and the
    principal point off centre, a lamp beside the camera: every pixel's own ray must be used."""
    from tests.synthetic import make_profile
    from uwcam.optics import kernels
    from uwcam.ranging.estimator import RangeEstimator

    intr = Intrinsics(60.0, 41.0, 30.3, 14.2)
    profile = make_profile([0.46, 0.11, 0.06], [9.0, 9.6, 9.3], read_noise=2.0, shot_gain=0.3,
                           lamp=(0.3, -0.2, 0.05), intrinsics=intr)
    est = RangeEstimator(profile, calibration_variance=False)
    yy, xx = np.mgrid[0:24, 0:40]
    path = 2.0 + 0.05 * xx + 0.08 * yy
    frame = np.exp(np.array([9.0, 9.6, 9.3]) - np.array([0.46, 0.11, 0.06]) * path[..., None])
    frame = np.rint(frame) if dtype == np.uint16 else frame
    compiled = est(frame.astype(dtype))
    monkeypatch.setattr(kernels, "fuse_lookup", kernels.fuse_lookup_numpy)
    monkeypatch.setattr(kernels, "fuse_arrays", kernels.fuse_arrays_numpy)
    numpy_path = RangeEstimator(profile, calibration_variance=False)(frame.astype(dtype))
    assert np.isfinite(compiled.range).all()
    np.testing.assert_allclose(numpy_path.range, compiled.range, rtol=2e-5)
    np.testing.assert_allclose(numpy_path.variance, compiled.variance, rtol=2e-4)
