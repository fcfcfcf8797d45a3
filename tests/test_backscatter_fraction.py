"""The backscatter model's share F at surface depths, against a per-pixel loop written here."""

from __future__ import annotations

import math

import numpy as np
import pytest

from uwcam.water import backscatter
from uwcam.water.backscatter import BackscatterModel


def model(shares: np.ndarray, depths: np.ndarray, grid_step: int) -> BackscatterModel:
    m = object.__new__(BackscatterModel)  # only the tables matter here
    for key, value in {"shares": shares, "depths": depths, "grid_step": grid_step, "pattern": np.ones(shares.shape[-1])}.items():
        object.__setattr__(m, key, value)
    return m


def naive(shares, depths, grid_step, z, row, col):
    """F at one pixel: linear in log depth between tabulated depths (NaN: the deepest, open water;
    clipped to the table), bilinear between the four grid nodes around the pixel."""
    gh, gw = shares.shape[:2]
    z = depths[-1] if math.isnan(z) else min(max(z, depths[0]), depths[-1])
    pos = np.interp(math.log(z), np.log(depths), np.arange(len(depths)))
    i0 = min(int(pos), len(depths) - 2)
    f = pos - i0
    gy, gx = row / grid_step, col / grid_step
    y0, x0 = min(int(gy), gh - 2), min(int(gx), gw - 2)
    fy, fx = gy - y0, gx - x0
    total = np.zeros(shares.shape[-1])
    for dy, wy in ((0, 1 - fy), (1, fy)):
        for dx, wx in ((0, 1 - fx), (1, fx)):
            node = shares[y0 + dy, x0 + dx]
            total += wy * wx * ((1 - f) * node[i0] + f * node[i0 + 1])
    return total


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "numpy"])
def test_fraction_interpolates_in_log_depth_and_across_the_grid(compiled, monkeypatch):
    if compiled and backscatter._interpolate_table is None:
        pytest.skip("numba is not installed")  # the numpy case still runs
    if not compiled:
        monkeypatch.setattr(backscatter, "_interpolate_table", None)
    rng = np.random.default_rng(2)
    shares = rng.random((6, 9, 14, 3))
    depths = np.geomspace(0.05, 40.0, 14)
    h, w = 17, 23
    z = rng.uniform(0.01, 60.0, (h, w))
    z[rng.random((h, w)) < 0.2] = np.nan
    rows = rng.uniform(0, 5 * 16, (h, w))
    cols = rng.uniform(0, 8 * 16, (h, w))
    m = model(shares, depths, 16)
    got = m.fraction(z, rows, cols)
    want = np.array([[naive(shares, depths, 16, z[i, j], rows[i, j], cols[i, j]) for j in range(w)] for i in range(h)])
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)
    # The grid's corners computed once and given again (as the frame loop does) change nothing.
    corners = m.corners(rows, cols)
    np.testing.assert_allclose(m.fraction(z, corners=corners), want, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(m.fraction(z[::-1], corners=corners), np.array(
        [[naive(shares, depths, 16, z[::-1][i, j], rows[i, j], cols[i, j]) for j in range(w)] for i in range(h)]), rtol=1e-12, atol=1e-14)
