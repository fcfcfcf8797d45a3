"""Compiled fusion kernels (numba); see :mod:`uwcam.optics.kernels` for the mathematics and the
layout of pairs. Importing this module imports numba: :mod:`uwcam.optics.kernels` does it only
when numba is installed.

Why it is shaped like this:
* Two kernels, one per source of pairs (a lookup table per code, or pairs per pixel), that fill
  a row buffer and hand it to one shared row function: the row function is where the
  arithmetic is, and it sees only contiguous float32, so LLVM vectorises it (the lookup itself
  stays scalar). Kernels do not take functions as arguments because numba's on-disk cache
  cannot reload kernels specialised on other compiled functions.
* Attenuations and log constants arrive as tuples, so the channel count is a compile-time
  constant and the channel and pair loops unroll.
* Every constant in the row loop is a float32 (``np.float32(...)``): one Python float would turn
  the whole expression into float64 and halve the vector width.
* ``error_model="numpy"``: division by zero gives inf/NaN (masked afterwards) instead of a
  Python exception check in the loop, which would stop vectorisation.
* ``nogil=True`` and ``parallel=True`` over rows; ``cache=True`` so that start-up loads
  machine code instead of compiling it.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from uwcam.optics.kernels import (
    _R_BACKSCATTER,
    _R_BELOW,
    _R_BOUNDS,
    _R_SATURATED,
    _R_TOO_FEW,
    _VALID,
    BACKGROUND_SIGMAS,
    FLAG_BACKSCATTER,
    FLAG_SATURATED,
    FLAG_USABLE,
    LAMP_ON_AXIS_RAY,
    LAMP_PIXEL_RAYS,
)
from uwcam.parallel import parallel


@njit(cache=True, nogil=True, error_model="numpy")
def _lamp_dot_row(i, geo, p_row):
    """S·u for every pixel of row i into p_row (float32), computed in float64."""
    mode = int(geo[0])
    if mode == LAMP_PIXEL_RAYS:
        sx, ifx, cx = geo[1], geo[5], geo[7]
        uy = (i - geo[8]) * geo[6]
        a = geo[2] * uy + geo[3]
        q = uy * uy + 1.0
        for j in range(p_row.shape[0]):
            ux = (j - cx) * ifx
            p_row[j] = (sx * ux + a) / math.sqrt(ux * ux + q)
    else:
        p_row[:] = geo[3] if mode == LAMP_ON_AXIS_RAY else 0.0


@njit(cache=True, nogil=True, error_model="numpy")
def _fuse_row(pair, p_row, c, b, lo, hi, s_norm, out_range, out_var, out_reason):
    """Fuse one row: pair (N, 2W) float32 [y, w] per channel and pixel; p_row (W,) S·u; outputs (W,)."""
    n = len(c)
    half, two, zero = np.float32(0.5), np.float32(2.0), np.float32(0.0)
    s2 = np.float32(s_norm * s_norm)
    s_norm32, lo32, hi32 = np.float32(s_norm), np.float32(lo), np.float32(hi)
    for j in range(out_range.shape[0]):
        sw = det = num = flags = zero
        for k in range(n):
            yk = pair[k, 2 * j]
            wk = pair[k, 2 * j + 1]
            sw += wk
            flags += np.float32(FLAG_USABLE) if wk > zero else yk
            for m in range(k + 1, n):
                dc = np.float32(c[k] - c[m])
                ww = wk * pair[m, 2 * j + 1]
                det += ww * (dc * dc)
                num += (ww * dc) * (yk - pair[m, 2 * j] - np.float32(b[k] - b[m]))
        p = p_row[j]
        inv = np.float32(1.0) / det
        d = -num * inv
        den = np.float32(1.0) / (d - p)
        rng = half * (d * d - s2) * den
        deriv = half * (d * d - two * d * p + s2) * den * den
        var = deriv * deriv * sw * inv
        ok = (det > zero) & (d >= lo32) & (d <= hi32) & (d > s_norm32)
        counts = np.int32(flags)
        n_usable = counts & 255
        n_back = (counts >> 8) & 255
        n_sat = counts >> 16
        # The most telling reason wins (as in validity.pixel_reasons), chosen without branches.
        reason = _R_BELOW
        reason = _R_TOO_FEW if n_usable == 1 else reason
        reason = _R_BACKSCATTER if n_usable + n_back >= 2 else reason
        reason = _R_SATURATED if n_sat > 0 else reason
        reason = _R_TOO_FEW if n_usable >= 2 else reason
        reason = _R_BOUNDS if det > zero else reason
        reason = _VALID if ok else reason
        out_range[j] = rng if ok else np.nan
        out_var[j] = var if ok else np.nan
        out_reason[j] = reason


@parallel
@njit(parallel=True, cache=True, nogil=True, error_model="numpy")
def fuse_lookup(raw, table, c, b, geo, bounds, out_range, out_var, out_reason):
    """Range, variance and reason of every pixel of an integer frame; arguments as
    :func:`uwcam.optics.kernels.fuse_lookup_numpy`."""
    h, w = out_range.shape
    n = len(c)
    for i in prange(h):
        buf = np.empty((n, w), np.uint64)
        for j in range(w):
            for k in range(n):
                buf[k, j] = table[k, raw[i, j, k]]
        p_row = np.empty(w, np.float32)
        _lamp_dot_row(i, geo, p_row)
        _fuse_row(buf.view(np.float32), p_row, c, b, bounds[0], bounds[1], geo[4], out_range[i], out_var[i], out_reason[i])


@parallel
@njit(parallel=True, cache=True, nogil=True, error_model="numpy")
def fuse_arrays(pairs, c, b, geo, bounds, out_range, out_var, out_reason):
    """As :func:`fuse_lookup` with pairs (H, W, N) given per pixel and channel: for float frames."""
    h, w = out_range.shape
    n = len(c)
    for i in prange(h):
        buf = np.empty((n, w), np.uint64)
        for j in range(w):
            for k in range(n):
                buf[k, j] = pairs[i, j, k]
        p_row = np.empty(w, np.float32)
        _lamp_dot_row(i, geo, p_row)
        _fuse_row(buf.view(np.float32), p_row, c, b, bounds[0], bounds[1], geo[4], out_range[i], out_var[i], out_reason[i])


@njit(cache=True, nogil=True, error_model="numpy")
def _background_pair(raw, bg, k, noise, levels, sat):
    """One channel's [y, w] pair (as two float32 in a uint64's place) for a raw value with a
    background ``bg`` (DN) known not to come from the surface: the same arithmetic, in float64,
    as RangeEstimator.channel_terms. noise[k] = (dark, read², shot gain, fixed pattern, q²/12, floor,
    b, active, relative background uncertainty u, adding (u·bg)²); levels[k]: open-water level (−inf: none)."""
    dark, read2, gain, fpn, q12, floor, b, active, u = (noise[k, 0], noise[k, 1], noise[k, 2], noise[k, 3],
                                                          noise[k, 4], noise[k, 5], noise[k, 6], noise[k, 7], noise[k, 8])
    e = raw - dark - bg
    total = max(e + bg, 0.0)
    var = read2 + gain * total + q12 + (fpn * total) * (fpn * total)
    if not var > 0.0:
        var = 1.0
    if u > 0.0:
        var = var + (u * bg) * (u * bg)
    flag = 0.0
    usable = False
    if active == 0.0:
        flag = 0.0
    elif raw >= sat:
        flag = FLAG_SATURATED
    elif not (e > floor) or not math.isfinite(e):
        flag = 0.0
    elif e <= levels[k]:
        flag = FLAG_BACKSCATTER
    elif e <= BACKGROUND_SIGMAS * math.sqrt(var):
        flag = FLAG_BACKSCATTER
    else:
        usable = True
    if usable:
        return np.float32(math.log(e) - b), np.float32(e * e / var)
    return np.float32(flag), np.float32(0.0)


@parallel
@njit(parallel=True, cache=True, nogil=True, error_model="numpy")
def fuse_background(frame, background, noise, levels, sat, c, geo, bounds, out_range, out_var, out_reason):
    """As :func:`fuse_arrays` for a frame (H, W, N) of any pixel type with a background (H, W, N)
    float32 subtracted: the per-channel terms are computed here, row by row, instead of in numpy."""
    h, w = out_range.shape
    n = len(c)
    zeros = np.zeros(n)
    for i in prange(h):
        buf = np.empty((n, 2 * w), np.float32)
        for j in range(w):
            for k in range(n):
                y, wk = _background_pair(np.float64(frame[i, j, k]), np.float64(background[i, j, k]), k, noise, levels, sat)
                buf[k, 2 * j] = y
                buf[k, 2 * j + 1] = wk
        p_row = np.empty(w, np.float32)
        _lamp_dot_row(i, geo, p_row)
        _fuse_row(buf, p_row, c, zeros, bounds[0], bounds[1], geo[4], out_range[i], out_var[i], out_reason[i])
