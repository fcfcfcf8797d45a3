"""Compiled fusion kernels (numba); see :mod:`uwcam.optics.kernels` for the mathematics and the
layout of pairs. Importing this module imports numba: :mod:`uwcam.optics.kernels` does it only
when numba is installed.

Why it is shaped like this:
* Two kernels, one per source of pairs (a lookup table per code, or pairs per pixel), each with
  its own inlined row filler, that hand a row buffer to one shared row function: the row
  function is where the arithmetic is, and it sees only contiguous float32, so LLVM vectorises
  it (the lookup itself stays scalar). Kernels do not take functions as arguments because
  numba's on-disk cache cannot reload kernels specialised on other compiled functions: hence
  two kernels, not one that takes its filler.
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
from uwcam.compute.parallel import parallel


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
def _fuse_row(pair, p_row, c, b, cv, lo, hi, s_norm, out_range, out_var, out_reason):
    """Fuse one row: pair (N, 2W) float32 [y, w] per channel and pixel; p_row (W,) S·u; cv (N, N)
    the significance constants of :func:`uwcam.optics.kernels.pair_noise`; outputs (W,)."""
    n = len(c)
    half, two, zero = np.float32(0.5), np.float32(2.0), np.float32(0.0)
    s2 = np.float32(s_norm * s_norm)
    s_norm32, lo32, hi32 = np.float32(s_norm), np.float32(lo), np.float32(hi)
    for j in range(out_range.shape[0]):
        sw = det = noise = num = flags = zero
        for k in range(n):
            yk = pair[k, 2 * j]
            wk = pair[k, 2 * j + 1]
            sw += wk
            flags += np.float32(FLAG_USABLE) if wk > zero else yk
            for m in range(k + 1, n):
                dc = np.float32(c[k] - c[m])
                ww = wk * pair[m, 2 * j + 1]
                det += ww * (dc * dc)
                noise += ww * np.float32(cv[k, m])
                num += (ww * dc) * (yk - pair[m, 2 * j] - np.float32(b[k] - b[m]))
        p = p_row[j]
        inv = np.float32(1.0) / det
        d = -num * inv
        den = np.float32(1.0) / (d - p)
        rng = half * (d * d - s2) * den
        deriv = half * (d * d - two * d * p + s2) * den * den
        var = deriv * deriv * sw * inv
        distinct = det > noise
        ok = distinct & (d >= lo32) & (d <= hi32) & (d > s_norm32)
        counts = np.int32(flags)
        n_usable = counts & 255
        n_back = (counts >> 8) & 255
        n_sat = counts >> 16
        # The most telling reason wins (as in validity.pixel_reasons), chosen without branches: a
        # pixel short of channels that differ says why the others are missing, if it can.
        reason = _R_BELOW
        reason = _R_TOO_FEW if n_usable >= 1 else reason
        reason = _R_BACKSCATTER if (n_usable + n_back >= 2) & (n_back > 0) else reason
        reason = _R_SATURATED if n_sat > 0 else reason
        reason = _R_BOUNDS if distinct else reason
        reason = _VALID if ok else reason
        out_range[j] = rng if ok else np.nan
        out_var[j] = var if ok else np.nan
        out_reason[j] = reason


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def _fuse_filled_row(i, buf, geo, c, b, cv, bounds, out_range, out_var, out_reason):
    """Row ``i`` of the outputs from its (N, W) buffer of packed (log signal, variance) pairs."""
    p_row = np.empty(buf.shape[1], np.float32)
    _lamp_dot_row(i, geo, p_row)
    _fuse_row(buf.view(np.float32), p_row, c, b, cv, bounds[0], bounds[1], geo[4], out_range[i], out_var[i], out_reason[i])


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def _looked_up_row(i, raw, table, c):
    """(N, W) pairs of row ``i`` of an integer frame: each channel's code looked up in its table
    (N from the attenuation tuple ``c``, known when compiling, so the channel loop unrolls)."""
    w, n = raw.shape[1], len(c)
    buf = np.empty((n, w), np.uint64)
    for j in range(w):
        for k in range(n):
            buf[k, j] = table[k, raw[i, j, k]]
    return buf


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def _given_row(i, pairs, c):
    """(N, W) pairs of row ``i`` from pairs given per pixel, (H, W, N) (a loop: 5-10 % faster
    than copying the transposed row)."""
    w, n = pairs.shape[1], len(c)
    buf = np.empty((n, w), np.uint64)
    for j in range(w):
        for k in range(n):
            buf[k, j] = pairs[i, j, k]
    return buf


@parallel
@njit(parallel=True, cache=True, nogil=True, error_model="numpy")
def fuse_lookup(raw, table, c, b, cv, geo, bounds, out_range, out_var, out_reason):
    """Range, variance and reason of every pixel of an integer frame; arguments as
    :func:`uwcam.optics.kernels.fuse_lookup_numpy`."""
    for i in prange(out_range.shape[0]):
        _fuse_filled_row(i, _looked_up_row(i, raw, table, c), geo, c, b, cv, bounds, out_range, out_var, out_reason)


@parallel
@njit(parallel=True, cache=True, nogil=True, error_model="numpy")
def fuse_arrays(pairs, c, b, cv, geo, bounds, out_range, out_var, out_reason):
    """As :func:`fuse_lookup` with pairs (H, W, N) given per pixel and channel: for float frames."""
    for i in prange(out_range.shape[0]):
        _fuse_filled_row(i, _given_row(i, pairs, c), geo, c, b, cv, bounds, out_range, out_var, out_reason)


LN2 = np.float32(0.6931471805599453)
SQRT2_MANTISSA = 0x3FB504F3  # the bits of √2 (float32) with exponent 0: larger mantissas are halved
MANTISSA_MASK = 0x007FFFFF
EXPONENT_ONE = 0x3F800000


@njit(cache=True, nogil=True, error_model="numpy")
def _ln_row(x, out, bits):
    """ln x of every x of a row (float32, positive and normal) into out (float32); bits: an int32
    row for scratch. Branch-free, so that the loop vectorises (libm's log is a call per value):
    x = m·2^k with m in [√½, √2), ln x = k·ln 2 + 2·atanh(s), s = (m − 1)/(m + 1), |s| ≤ 0.172,
    from the series to s⁷ (the next term, 2s⁹/9 ≤ 3e-8, is below float32's resolution: within
    about 3 units in the last place of the result). float32 throughout: twice the values per
    vector instruction of float64, and the terms are stored as float32."""
    xi = x.view(np.int32)
    one, two = np.float32(1.0), np.float32(2.0)
    for j in range(x.shape[0]):
        b = xi[j]
        m = (b & MANTISSA_MASK) | EXPONENT_ONE
        high = np.int32(m > SQRT2_MANTISSA)
        bits[j] = m - (high << 23)
        out[j] = np.float32(((b >> 23) & 0xFF) - 127 + high) * LN2
    mantissa = bits.view(np.float32)
    for j in range(x.shape[0]):
        s = (mantissa[j] - one) / (mantissa[j] + one)
        s2 = s * s
        series = one + s2 * (np.float32(1.0 / 3.0) + s2 * (np.float32(0.2) + s2 * np.float32(1.0 / 7.0)))
        out[j] += two * s * series


@njit(cache=True, nogil=True, error_model="numpy")
def _background_terms(raw, bg, doubt_rows, n_rows, t, level, sat, e, var, ln, bits, y_out, w_out):
    """[y, w] of every value of one row, channels interleaved as in the frame ((W·N,) each): the
    arithmetic of RangeEstimator.channel_terms with a background ``bg`` (DN) known not to come from
    the surface, in float32 (a 16-bit code and the noise terms need no more: the values differ
    from float64's by float32 rounding, ~1e-7 relative, the precision they are stored in anyway).
    t: (10, W·N) float32, each channel's constants repeated along the row (dark, read², shot gain,
    fixed pattern f, q²/12, floor, b, active, relative background uncertainty u, adding (u·bg)², and
    the fixed pattern r the background leaves: r²·total² + (f² − r²)·e² instead of f²·total²);
    doubt_rows: (W·N,) float32, the background's own variance (DN²) added to each value's, or an
    empty row: none;
    level: (W·N,) float32, the open-water level (−inf: none); sat: float32; e, var, ln: float32
    rows and bits an int32 row, for scratch. n_rows: (W·N,) float32, how many single-pixel noises
    each value's noise is (frames fused over time; the variance is divided by it, at least 1), or
    an empty row: one.

    Three passes, each over contiguous memory with no call and no branch, so that each vectorises
    (per pixel and channel, the terms cost about what the table lookup of integer frames does):
    signal and noise; ln of the signal; each value's state, whose tests are written as selections."""
    zero, one = np.float32(0.0), np.float32(1.0)
    for x in range(raw.shape[0]):
        b = bg[x]
        v = np.float32(raw[x]) - t[0, x] - b
        total = max(v + b, zero)
        surface = max(v, zero)
        s2 = (t[1, x] + t[2, x] * total + t[4, x] + (t[9, x] * total) * (t[9, x] * total)
              + (t[3, x] * t[3, x] - t[9, x] * t[9, x]) * (surface * surface))
        s2 = s2 if s2 > zero else one
        if n_rows.shape[0] > 0:
            s2 = s2 / max(n_rows[x], one)
        u = t[8, x]
        s2 = s2 + (u * b) * (u * b) if u > zero else s2
        var[x] = s2 + doubt_rows[x] if doubt_rows.shape[0] > 0 else s2
        e[x] = v
        ln[x] = max(v, np.float32(1e-30))  # a valid argument everywhere; only usable values (e > 3σ > 0) are kept
    _ln_row(ln, ln, bits)
    sigmas = np.float32(BACKGROUND_SIGMAS)
    for x in range(raw.shape[0]):
        v = e[x]
        s2 = var[x]
        on = t[7, x] != zero
        saturated = np.float32(raw[x]) >= sat
        dark = (not (v > t[5, x])) | (not math.isfinite(v))
        water = (v <= level[x]) | (v <= sigmas * math.sqrt(s2))
        usable = on & (not saturated) & (not dark) & (not water)
        # The first state that applies wins, as in channel_terms.
        flag = np.float32(FLAG_SATURATED) if saturated else (zero if dark else (np.float32(FLAG_BACKSCATTER) if water else zero))
        flag = flag if on else zero
        y_out[x] = ln[x] - t[6, x] if usable else flag
        w_out[x] = v * v / s2 if usable else zero


@parallel
@njit(parallel=True, cache=True, nogil=True, error_model="numpy")
def fuse_background(frame, background, doubt, samples, noise, levels, sat, c, cv, geo, bounds, out_range, out_var,
                    out_reason):
    """As :func:`fuse_arrays` for a C-contiguous frame (H, W, N) of any pixel type with a
    C-contiguous background (H, W, N) float32 subtracted: the per-channel terms are computed here,
    row by row (:func:`_background_terms`), instead of in numpy. doubt: C-contiguous (H, W, N)
    float32, the background's own variance (DN²), or an empty (0, 0, 0) array: none. samples:
    C-contiguous (H, W, N) float32, how many single-pixel noises each value's noise is (see
    RangeEstimator.channel_terms), or an empty (0, 0, 0) array: one. noise: (N, 10) per channel
    (RangeEstimator._noise_terms)."""
    h, w = out_range.shape
    n = len(c)
    m = w * n
    raw_rows = frame.reshape(h, m)
    bg_rows = background.reshape(h, m)
    counted = samples.size > 0
    n_rows = samples.reshape(h, m) if counted else np.empty((h, 0), np.float32)
    doubted = doubt.size > 0
    doubt_rows = doubt.reshape(h, m) if doubted else np.empty((h, 0), np.float32)
    t = np.empty((10, m), np.float32)
    level = np.empty(m, np.float32)
    for j in range(w):
        for k in range(n):
            for q in range(10):
                t[q, j * n + k] = noise[k, q]
            level[j * n + k] = levels[k]
    sat32 = np.float32(sat)
    zeros = np.zeros(n)
    for i in prange(h):
        e = np.empty(m, np.float32)
        var = np.empty(m, np.float32)
        ln = np.empty(m, np.float32)
        bits = np.empty(m, np.int32)
        y = np.empty(m, np.float32)
        wt = np.empty(m, np.float32)
        _background_terms(raw_rows[i], bg_rows[i], doubt_rows[i], n_rows[i], t, level, sat32, e, var, ln, bits, y, wt)
        buf = np.empty((n, 2 * w), np.float32)
        for j in range(w):
            for k in range(n):
                buf[k, 2 * j] = y[j * n + k]
                buf[k, 2 * j + 1] = wt[j * n + k]
        p_row = np.empty(w, np.float32)
        _lamp_dot_row(i, geo, p_row)
        _fuse_row(buf, p_row, c, zeros, cv, bounds[0], bounds[1], geo[4], out_range[i], out_var[i], out_reason[i])
