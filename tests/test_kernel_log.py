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
    x = np.array(values, dtype=np.float32)
    out = np.empty_like(x)
    numba_kernels._ln_row(x.copy(), out, np.empty(x.size, np.int32))
    return out


def close_to_ln(got: float, v: float) -> bool:
    """Within float32's rounding of ln v: a few units in the last place of max(1, |ln v|)."""
    return abs(got - math.log(v)) <= 4 * 2.0**-23 * max(1.0, abs(math.log(v)))


FLOAT32_NORMAL = st.floats(min_value=float(np.finfo(np.float32).tiny), max_value=float(np.finfo(np.float32).max), allow_nan=False, allow_infinity=False, width=32)


@pytest.mark.skipif(kernels.fuse_background is None, reason="numba is not installed: no compiled kernel to test")
@settings(max_examples=300, deadline=None)
@given(st.lists(FLOAT32_NORMAL, min_size=1, max_size=40))
def test_ln_matches_the_math_library_on_every_normal_float32(values):
    got = ln_row(values)
    for v, g in zip(values, got):
        assert close_to_ln(float(g), v), (v, float(g), math.log(v))


@pytest.mark.skipif(kernels.fuse_background is None, reason="numba is not installed: no compiled kernel to test")
def test_ln_at_the_seams_of_its_range_reduction():
    # Powers of two, √2 and its neighbours (where the mantissa is halved), sensor-sized values.
    root2 = np.float32(math.sqrt(2.0))
    seams = [1.0, 2.0, 0.5, 2.0**-126, 2.0**127, root2, np.nextafter(root2, np.float32(0)), np.nextafter(root2, np.float32(2)),
             np.float32(math.sqrt(0.5)), 3.0, 65535.0, 1e-5, 1e-30]
    values = [float(np.float32(v)) for v in seams]  # the float32 values the kernel is given
    for v, g in zip(values, ln_row(values)):
        assert close_to_ln(float(g), v), (v, float(g), math.log(v))


@pytest.mark.skipif(kernels.fuse_background is None, reason="numba is not installed: no compiled kernel to test")
def test_a_strided_frame_with_a_background_ranges_as_its_contiguous_copy():
    from tests.synthetic import make_profile
    from uwcam.ranging.estimator import RangeEstimator

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


@pytest.mark.skipif(kernels.fuse_background is None, reason="numba is not installed: no compiled kernel to test")
def test_ln_within_three_and_a_half_units_in_the_last_place_around_one():
    """Over the binade around 1 (and √2·2^k), where ln x is the series alone (plus k·ln 2), the float32
    result is within 3.5 units in its last place of the exact value: each of the series' terms
    matters at that precision (a coefficient off by one in its denominator costs ~8 units)."""
    x = np.linspace(np.float32(0.70710677), np.float32(1.4142135), 200_001).astype(np.float32)
    x = np.unique(np.concatenate([x, np.float32(1.4142135) * np.float32(2.0) ** np.arange(-20, 21, dtype=np.float32)]))
    x = x[x != 1.0]  # ln 1 = 0 exactly: no unit in the last place to measure by
    got = ln_row(list(x.astype(np.float64)))
    exact = np.log(x.astype(np.float64))
    ulp = np.spacing(np.abs(exact).astype(np.float32)).astype(np.float64)
    assert np.max(np.abs(got.astype(np.float64) - exact) / ulp) <= 3.5
