"""Compiled one-pass fusion for the frame loop.

Same mathematics as :func:`uwcam.optics.fusion.fused_path_length` followed by
:func:`uwcam.optics.geometry.camera_range_from_path_length` and
:func:`uwcam.optics.validity.pixel_reasons`, fused into a single pass over the frame
so that no (H, W, N) float temporaries are made.

Integer sensors have few codes, so everything that depends on one channel's value
alone (ln E − b, the weight E²/σ², the channel state) is tabulated per channel once
per calibration: the pixel loop is then table look-ups and a handful of multiply-adds,
with no logarithm. Float frames go through the same loop, reading y, w and state from
arrays computed with numpy.

Why it is shaped like this:
* Attenuations arrive as a tuple, so the channel count is a compile-time constant and
  the channel loop unrolls (twice as fast as a loop over a runtime count).
* An unusable channel has weight 0 and simply adds nothing, so the hot loop has no
  branches; channel states are read only for pixels left without a range, to name
  the reason.
* "Two usable channels of different attenuation" is a bit test: each distinct
  attenuation value has its own bit, and a pixel needs two different bits set.
* The sums are plain moments in float64 about a centred c and an offset y. Weights of
  real sensors span at most ~10⁷, well inside float64's 16 digits; the float64
  reference in fusion.py uses a more careful two-pass form for arbitrary inputs.
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
_SATURATED, _BACKSCATTER = 2, 3
_VALID, _R_BELOW, _R_SATURATED, _R_BACKSCATTER, _R_TOO_FEW, _R_BOUNDS = 0, 1, 2, 3, 4, 5


@njit(cache=True, inline="always")
def fetch_lookup(raw, table, i, j, k):
    """(weight, y) of channel k at pixel (i, j) from the per-code tables."""
    code = raw[i, j, k]
    return np.float64(table[k, code, 1]), np.float64(table[k, code, 0])


@njit(cache=True, inline="always")
def state_lookup(raw, states, i, j, k):
    return states[k, raw[i, j, k]]


@njit(cache=True, inline="always")
def fetch_arrays(y, weight, i, j, k):
    """(weight, y) of channel k at pixel (i, j) from per-pixel arrays."""
    return np.float64(weight[i, j, k]), np.float64(y[i, j, k])


@njit(cache=True, inline="always")
def state_arrays(unused, state, i, j, k):
    return state[i, j, k]


@njit(cache=True, inline="always")
def _no_range(n_usable, n_sat, n_back):
    """The most telling reason a pixel has no range (see validity.pixel_reasons)."""
    reason = _R_BELOW
    if n_usable == 1:
        reason = _R_TOO_FEW
    if n_usable + n_back >= 2:
        reason = _R_BACKSCATTER
    if n_sat > 0:
        reason = _R_SATURATED
    return reason


@njit(parallel=True, cache=True)
def fuse(fetch, state_of, src, aux, states, c, bits, geo, bounds, out_range, out_var, out_reason):
    """Range, variance and reason of every pixel.

    fetch(src, aux, i, j, k) → (weight, y); state_of(src, states, i, j, k) → ChannelState.
    c: tuple of N centred attenuations (1/m); bits: tuple of N ints, one bit per distinct
    attenuation; geo: [mode, Sx, Sy, Sz, |S|, 1/fx, 1/fy, cx, cy]; bounds: [min, max]
    path length (m). Outputs are (H, W) float32, float32 and uint8.
    """
    h, w = out_range.shape
    n = len(c)
    mode = int(geo[0])
    sx, sy, sz, s_norm = geo[1], geo[2], geo[3], geo[4]
    s2 = s_norm * s_norm
    lo, hi = bounds[0], bounds[1]
    for i in prange(h):
        uy = (i - geo[8]) * geo[6]
        for j in range(w):
            sw = swc = swy = swcc = swcy = 0.0
            n_usable = 0
            groups = 0
            for k in range(n):
                wk, yk = fetch(src, aux, i, j, k)
                wc = wk * c[k]
                sw += wk
                swc += wc
                swy += wk * yk
                swcc += wc * c[k]
                swcy += wc * yk
                if wk > 0:
                    n_usable += 1
                    groups |= bits[k]
            if n_usable < 2 or groups & (groups - 1) == 0:
                out_range[i, j] = np.nan
                out_var[i, j] = np.nan
                if n_usable >= 2:
                    out_reason[i, j] = _R_TOO_FEW  # usable channels share one attenuation
                else:
                    n_sat = n_back = 0
                    for k in range(n):
                        st = state_of(src, states, i, j, k)
                        n_sat += st == _SATURATED
                        n_back += st == _BACKSCATTER
                    out_reason[i, j] = _no_range(n_usable, n_sat, n_back)
                continue
            inv_sw = 1.0 / sw
            spread = swcc - swc * swc * inv_sw
            inv_spread = 1.0 / spread
            d = -(swcy - swc * swy * inv_sw) * inv_spread
            if not (d >= lo and d <= hi and d > s_norm and spread > 0):
                out_range[i, j] = np.nan
                out_var[i, j] = np.nan
                out_reason[i, j] = _R_BOUNDS
                continue
            if mode == EQUIDISTANT:
                dc = 0.5 * d
                deriv = 0.5
            else:
                if mode == LAMP_PIXEL_RAYS:
                    ux = (j - geo[7]) * geo[5]
                    p = (sx * ux + sy * uy + sz) / math.sqrt(ux * ux + uy * uy + 1.0)
                else:
                    p = sz
                inv_den = 1.0 / (d - p)
                dc = 0.5 * (d * d - s2) * inv_den
                deriv = 0.5 * (d * d - 2.0 * d * p + s2) * inv_den * inv_den
            out_range[i, j] = dc
            out_var[i, j] = deriv * deriv * inv_spread
            out_reason[i, j] = _VALID
