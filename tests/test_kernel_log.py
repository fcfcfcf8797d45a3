"""The compiled background kernel's branch-free natural logarithm, and frames in any layout."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from uwcam.optics import kernels

numba_kernels = pytest.importorskip("uwcam.optics.kernels_numba") if kernels.fuse_background is not None else None


def ln_row(values: list[float]) -> np.ndarray:
    x = np.array(values, dtype=np.float64)
    out = np.empty_like(x)
    numba_kernels._ln_row(x.copy(), out, np.empty(x.size, np.int64))
    return out


@pytest.mark.skipif(kernels.fuse_background is None, reason="numba is not installed: no compiled kernel to test")
@settings(max_examples=300, deadline=None)
@given(st.lists(st.floats(min_value=2.3e-308, max_value=1.7e308, allow_nan=False, allow_infinity=False), min_size=1, max_size=40))
def test_ln_matches_the_math_library_on_every_normal_number(values):
    got = ln_row(values)
    for v, g in zip(values, got):
        assert abs(g - math.log(v)) <= 1e-12 * max(1.0, abs(math.log(v)))


@pytest.mark.skipif(kernels.fuse_background is None, reason="numba is not installed: no compiled kernel to test")
def test_ln_at_the_seams_of_its_range_reduction():
    # Powers of two, √2 and its neighbours (where the mantissa is halved), sensor-sized values.
    seams = [1.0, 2.0, 0.5, 2.0**-1022, 2.0**1023, math.sqrt(2.0), np.nextafter(math.sqrt(2.0), 0), np.nextafter(math.sqrt(2.0), 2),
             math.sqrt(0.5), 3.0, 65535.0, 1e-5, 1e-300]
    np.testing.assert_allclose(ln_row(seams), [math.log(v) for v in seams], rtol=1e-12, atol=1e-12)


@pytest.mark.skipif(kernels.fuse_background is None, reason="numba is not installed: no compiled kernel to test")
def test_a_strided_frame_with_a_background_ranges_as_its_contiguous_copy():
    from tests.synthetic import make_profile
    from uwcam.ranging import RangeEstimator

    rng = np.random.default_rng(4)
    est = RangeEstimator(make_profile([0.46, 0.11, 0.06], [0.0, 0.3, 0.5], read_noise=3.0, shot_gain=0.2, noise_floor=5.0))
    wide = rng.uniform(200, 3000, (30, 80, 3)).round().astype(np.uint16)
    strided = wide[:, ::2, ::-1]  # every other column, channels reversed: no unit stride anywhere
    background = rng.uniform(0, 100, strided.shape).astype(np.float32)
    a = est(strided, background=background)
    b = est(np.ascontiguousarray(strided), background=background)
    np.testing.assert_array_equal(a.reasons, b.reasons)
    np.testing.assert_array_equal(a.range, b.range)
    assert np.isfinite(a.range).mean() > 0.2 and len(np.unique(a.reasons)) >= 2  # valid and invalid pixels compared
