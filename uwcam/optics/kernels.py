"""Compiled one-pass fusion for the frame loop.

Same mathematics as :func:`uwcam.optics.fusion.fused_path_length` followed by
:func:`uwcam.optics.geometry.camera_range_from_path_length` and
:func:`uwcam.optics.validity.pixel_reasons`, fused into a single pass over the frame
so that no (H, W, N) float temporaries are made. The weighted moments are updated
channel by channel with West's algorithm, which stays accurate when the common offset
of y is large or one channel's weight dwarfs the others.

Integer sensors have few codes, so everything that depends on one channel's value
alone (ln E − b, the weight E²/σ², the channel state) is tabulated per channel once
per calibration: the pixel loop is then table look-ups and a handful of
multiply-adds, with no logarithm. Float frames use the same loop on arrays of y, w
and state computed with numpy.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

# Geometry modes for path length → camera range.
EQUIDISTANT = 0
LAMP_ON_AXIS_RAY = 1  # exact lamp geometry, every pixel treated as on the optical axis
LAMP_PIXEL_RAYS = 2  # exact lamp geometry with each pixel's own ray from intrinsics

# Channel states and reasons as plain ints (numba-friendly mirrors of validity enums).
_USABLE, _BELOW, _SATURATED, _BACKSCATTER = 0, 1, 2, 3
_VALID, _R_BELOW, _R_SATURATED, _R_BACKSCATTER, _R_TOO_FEW, _R_BOUNDS = 0, 1, 2, 3, 4, 5


@njit(cache=True, inline="always")
def _add_channel(acc, st, wk, yk, ck):
    """One channel into the per-pixel accumulator (sw, c̄, ȳ, Σw(c−c̄)², Σw(c−c̄)(y−ȳ),
    c_min, c_max, n_usable, n_saturated, n_backscatter), by West's (1979) update."""
    sw, mc, my, spread, cov, cmin, cmax, n_usable, n_sat, n_back = acc
    if st == _USABLE:
        sw += wk
        f = wk / sw
        dc = ck - mc
        dy = yk - my
        mc += dc * f
        my += dy * f
        spread += wk * dc * (ck - mc)
        cov += wk * dc * (yk - my)
        cmin = min(cmin, ck)
        cmax = max(cmax, ck)
        n_usable += 1
    elif st == _SATURATED:
        n_sat += 1
    elif st == _BACKSCATTER:
        n_back += 1
    return sw, mc, my, spread, cov, cmin, cmax, n_usable, n_sat, n_back


@njit(cache=True, inline="always")
def _finish(acc, i, j, geo, bounds, out_range, out_var, out_reason):
    """Path length, camera range, variance and reason of pixel (i, j) from its accumulator."""
    spread, cov, cmin, cmax, n_usable, n_sat, n_back = acc[3], acc[4], acc[5], acc[6], acc[7], acc[8], acc[9]
    if n_usable < 2:
        reason = _R_BELOW
        if n_usable == 1:
            reason = _R_TOO_FEW
        if n_usable + n_back >= 2:
            reason = _R_BACKSCATTER
        if n_sat > 0:
            reason = _R_SATURATED
        out_range[i, j] = np.nan
        out_var[i, j] = np.nan
        out_reason[i, j] = reason
        return
    if not cmax > cmin or not spread > 0:
        out_range[i, j] = np.nan
        out_var[i, j] = np.nan
        out_reason[i, j] = _R_TOO_FEW
        return
    d = -cov / spread
    var = 1.0 / spread
    mode = int(geo[0])
    if d < bounds[0] or d > bounds[1] or not (d > geo[4]):
        out_range[i, j] = np.nan
        out_var[i, j] = np.nan
        out_reason[i, j] = _R_BOUNDS
        return
    if mode == EQUIDISTANT:
        dc = 0.5 * d
        deriv = 0.5
    else:
        sx, sy, sz, s2 = geo[1], geo[2], geo[3], geo[4] * geo[4]
        if mode == LAMP_PIXEL_RAYS:
            ux = (j - geo[7]) / geo[5]
            uy = (i - geo[8]) / geo[6]
            p = (sx * ux + sy * uy + sz) / math.sqrt(ux * ux + uy * uy + 1.0)
        else:
            p = sz
        den = d - p
        dc = (d * d - s2) / (2.0 * den)
        deriv = (d * d - 2.0 * d * p + s2) / (2.0 * den * den)
    out_range[i, j] = dc
    out_var[i, j] = deriv * deriv * var
    out_reason[i, j] = _VALID


@njit(parallel=True, cache=True)
def fuse_lookup(raw, table, states, c, geo, bounds, out_range, out_var, out_reason):
    """raw: (H, W, N) integer codes; table: (N, L, 2) float32 [ln E − b, E²/σ²];
    states: (N, L) uint8 channel state per code; c: (N,) centred attenuation (1/m);
    geo: [mode, Sx, Sy, Sz, |S|, fx, fy, cx, cy]; bounds: [min, max] path length (m)."""
    h, w, n = raw.shape
    for i in prange(h):
        for j in range(w):
            acc = (0.0, 0.0, 0.0, 0.0, 0.0, np.inf, -np.inf, 0, 0, 0)
            for k in range(n):
                code = raw[i, j, k]
                acc = _add_channel(acc, states[k, code], np.float64(table[k, code, 1]), np.float64(table[k, code, 0]), c[k])
            _finish(acc, i, j, geo, bounds, out_range, out_var, out_reason)


@njit(parallel=True, cache=True)
def fuse_arrays(y, weight, state, c, geo, bounds, out_range, out_var, out_reason):
    """As :func:`fuse_lookup` with y = ln E − b, weight = E²/σ² and state given per pixel (H, W, N)."""
    h, w, n = y.shape
    for i in prange(h):
        for j in range(w):
            acc = (0.0, 0.0, 0.0, 0.0, 0.0, np.inf, -np.inf, 0, 0, 0)
            for k in range(n):
                acc = _add_channel(acc, state[i, j, k], np.float64(weight[i, j, k]), np.float64(y[i, j, k]), c[k])
            _finish(acc, i, j, geo, bounds, out_range, out_var, out_reason)
