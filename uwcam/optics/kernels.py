"""Compiled one-pass fusion for the frame loop.

Same mathematics as :func:`uwcam.optics.fusion.fused_path_length` followed by
:func:`uwcam.optics.geometry.camera_range_from_path_length` and
:func:`uwcam.optics.validity.pixel_reasons`, fused into a single pass over the frame
so that no (H, W, N) float temporaries are made.

Integer sensors have few codes, so everything that depends on one channel's value
alone (ln E − b, the weight E²/σ², the channel state) is tabulated per channel once
per calibration: the pixel loop is then table look-ups and a handful of multiply-adds,
with no logarithm. Float frames go through a twin loop reading y, w and state from arrays
computed with numpy; both share everything after the channel loop.

Why it is shaped like this:
* Attenuations arrive as a tuple, so the channel count is a compile-time constant and
  the channel loop unrolls (twice as fast as a loop over a runtime count).
* An unusable channel has weight 0 and simply adds nothing, so the hot loop has no
  branches; channel states are read only for pixels left without a range, to name
  the reason.
* Kernels release the GIL (nogil): the camera, the frame loop and the API server run in
  threads of one process and must not stall each other.
* Two module-level kernels rather than one taking fetch functions as arguments: numba's
  on-disk cache cannot reload kernels specialised on other compiled functions.
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


@njit(cache=True, inline="always")
def _finish(i, j, sw, swc, swy, swcc, swcy, n_usable, groups, geo, bounds, out_range, out_var, out_reason):
    """Path length, camera range, variance and reason of pixel (i, j) from its weighted sums.
    Returns False when the pixel has too few usable channels and the caller must name why."""
    if n_usable < 2:
        return False
    if groups & (groups - 1) == 0:  # usable channels share one attenuation
        out_range[i, j] = np.nan
        out_var[i, j] = np.nan
        out_reason[i, j] = _R_TOO_FEW
        return True
    inv_sw = 1.0 / sw
    spread = swcc - swc * swc * inv_sw
    inv_spread = 1.0 / spread
    d = -(swcy - swc * swy * inv_sw) * inv_spread
    if not (d >= bounds[0] and d <= bounds[1] and d > geo[4] and spread > 0):
        out_range[i, j] = np.nan
        out_var[i, j] = np.nan
        out_reason[i, j] = _R_BOUNDS
        return True
    mode = int(geo[0])
    if mode == EQUIDISTANT:
        dc = 0.5 * d
        deriv = 0.5
    else:
        s2 = geo[4] * geo[4]
        if mode == LAMP_PIXEL_RAYS:
            ux = (j - geo[7]) * geo[5]
            uy = (i - geo[8]) * geo[6]
            p = (geo[1] * ux + geo[2] * uy + geo[3]) / math.sqrt(ux * ux + uy * uy + 1.0)
        else:
            p = geo[3]
        inv_den = 1.0 / (d - p)
        dc = 0.5 * (d * d - s2) * inv_den
        deriv = 0.5 * (d * d - 2.0 * d * p + s2) * inv_den * inv_den
    out_range[i, j] = dc
    out_var[i, j] = deriv * deriv * inv_spread
    out_reason[i, j] = _VALID
    return True


@njit(cache=True, inline="always")
def _invalid(i, j, reason, out_range, out_var, out_reason):
    out_range[i, j] = np.nan
    out_var[i, j] = np.nan
    out_reason[i, j] = reason


@njit(parallel=True, cache=True, nogil=True)
def fuse_lookup(raw, table, states, c, b, bits, geo, bounds, out_range, out_var, out_reason):
    """Range, variance and reason of every pixel of an integer frame.

    raw: (H, W, N) codes; table: (N, L, 2) float32 [ln E − offset, E²/σ²] per code, weight 0
    where unusable; states: (N, L) uint8 ChannelState per code; c: tuple of N centred
    attenuations (1/m); b: tuple of N log constants minus the table's offset (y = table − b, so
    log constants change without rebuilding tables); bits: tuple of N ints, one bit per distinct attenuation; geo: [mode, Sx, Sy, Sz, |S|,
    1/fx, 1/fy, cx, cy]; bounds: [min, max] path length (m). Outputs (H, W) float32, float32, uint8.
    """
    h, w = out_range.shape
    n = len(c)
    for i in prange(h):
        for j in range(w):
            sw = swc = swy = swcc = swcy = 0.0
            n_usable = groups = 0
            for k in range(n):
                code = raw[i, j, k]
                wk = np.float64(table[k, code, 1])
                yk = np.float64(table[k, code, 0]) - b[k]
                wc = wk * c[k]
                sw += wk
                swc += wc
                swy += wk * yk
                swcc += wc * c[k]
                swcy += wc * yk
                if wk > 0:
                    n_usable += 1
                    groups |= bits[k]
            if not _finish(i, j, sw, swc, swy, swcc, swcy, n_usable, groups, geo, bounds, out_range, out_var, out_reason):
                n_sat = n_back = 0
                for k in range(n):
                    st = states[k, raw[i, j, k]]
                    n_sat += st == _SATURATED
                    n_back += st == _BACKSCATTER
                _invalid(i, j, _no_range(n_usable, n_sat, n_back), out_range, out_var, out_reason)


@njit(parallel=True, cache=True, nogil=True)
def fuse_arrays(y, weight, state, c, b, bits, geo, bounds, out_range, out_var, out_reason):
    """As :func:`fuse_lookup`, with y = ln E (minus b in the kernel), weight = E²/σ² (0 where unusable) and the
    ChannelState given per pixel and channel, each (H, W, N): for float frames."""
    h, w = out_range.shape
    n = len(c)
    for i in prange(h):
        for j in range(w):
            sw = swc = swy = swcc = swcy = 0.0
            n_usable = groups = 0
            for k in range(n):
                wk = np.float64(weight[i, j, k])
                yk = np.float64(y[i, j, k]) - b[k]
                wc = wk * c[k]
                sw += wk
                swc += wc
                swy += wk * yk
                swcc += wc * c[k]
                swcy += wc * yk
                if wk > 0:
                    n_usable += 1
                    groups |= bits[k]
            if not _finish(i, j, sw, swc, swy, swcc, swcy, n_usable, groups, geo, bounds, out_range, out_var, out_reason):
                n_sat = n_back = 0
                for k in range(n):
                    n_sat += state[i, j, k] == _SATURATED
                    n_back += state[i, j, k] == _BACKSCATTER
                _invalid(i, j, _no_range(n_usable, n_sat, n_back), out_range, out_var, out_reason)
