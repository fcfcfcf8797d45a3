"""One-pass fusion for the frame loop: compiled with numba when it is installed, numpy otherwise.

Same mathematics as :func:`uwcam.optics.fusion.fused_path_length` followed by
:func:`uwcam.optics.geometry.camera_range_from_path_length` and
:func:`uwcam.optics.validity.pixel_reasons`, in one pass over the frame.

Per pixel, with y_k = ln E_k − b_k and weights w_k = E_k²/σ_k², the weighted least-squares fit
of :mod:`uwcam.optics.fusion` is written over channel pairs (Lagrange's identity):

    D = Σ_{k<l} w_k w_l (c_k − c_l)²,   M = Σ_{k<l} w_k w_l (c_k − c_l)(y_k − y_l)
    d_T = −M / D,   Var(d_T) = Σ w_k / D

Every term of D is ≥ 0 and, for a pixel that fits the model, every term of M has the sign of
−d_T (y_k − y_l ≈ −(c_k − c_l)·d_T), so neither sum cancels digits: unlike the moment form Σw·Σwc² − (Σwc)², float32 is accurate to
a few 1e-7 relative here, which lets the arithmetic run 16 pixels per AVX-512 instruction. D is
exactly 0 when no two usable channels differ in attenuation (a product with c_k − c_l = 0 is
exactly 0), so that test needs no bookkeeping of its own. Beside D the kernels sum what the
calibration's uncertainty alone would give it, Σ_{k<l} w_k w_l Var(c_k − c_l); a range needs D
above :data:`ATTENUATION_SIGMAS`² times that (zero for a calibration without uncertainties).

How a frame flows:
* Integer frames: everything that depends on one channel's code alone (ln E − offset, the
  weight, the channel state) is tabulated per channel and code once per calibration. Float
  frames (ambient subtraction) get the same pairs from numpy, one per pixel and channel.
* A pair is two float32 [y, w] packed in 8 bytes. An unusable channel has w = 0 and carries in
  y, instead of ln E, its state as a count to add up (``FLAG_*``): one sum per pixel then counts
  usable, saturated and backscatter-only channels, and the reason for a missing range follows
  without branches.
* The compiled kernels (:mod:`uwcam.optics.kernels_numba`) look pairs up for one image row into
  a small buffer (scalar loads: LLVM will not emit AVX-512 gathers for AMD CPUs), then fuse the
  row in a branch-free loop that LLVM vectorises. They release the GIL (the camera, the loop and
  the API share one process) and are cached on disk (``cache=True``) so that a restart loads
  them instead of compiling; :meth:`uwcam.ranging.estimator.RangeEstimator.warm_up` does that before the
  frame loop starts.
* Without numba (e.g. 32-bit ARM, where no wheels exist) the numpy functions below compute the
  same float32 operations in the same order, a block of rows at a time so that temporaries stay
  a few MB; :data:`BACKEND` says which is in use.
"""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import NDArray

# Geometry modes for path length → camera range; the kernels use one formula for all three
# (see lamp_geometry), the mode only says how S·u is found.
EQUIDISTANT = 0
LAMP_ON_AXIS_RAY = 1  # exact lamp geometry, every pixel treated as on the optical axis
LAMP_PIXEL_RAYS = 2  # exact lamp geometry with each pixel's own ray from intrinsics

# Reasons as plain ints (mirrors of uwcam.optics.validity.Reason).
_VALID, _R_BELOW, _R_SATURATED, _R_BACKSCATTER, _R_TOO_FEW, _R_BOUNDS = 0, 1, 2, 3, 4, 5

# Counts carried by a channel in a pair: a usable channel counts 1 (added by the kernel, since
# its y holds ln E), an unusable one its flag. Sums stay exact in float32 for up to 255 channels.
FLAG_USABLE, FLAG_BACKSCATTER, FLAG_SATURATED = 1.0, 256.0, 65536.0
MAX_CHANNELS = 255

# A channel whose signal, once a known background is subtracted, is not this many standard
# deviations of the total light's noise above zero carries no usable surface signal.
BACKGROUND_SIGMAS = 3.0

ATTENUATION_SIGMAS = 3.0
"""A pixel's usable channels must differ in attenuation by more than this many of the
calibration's standard uncertainties of those differences, weighted as the fit weighs them:
D > ATTENUATION_SIGMAS² · Σ_{k<l} w_k w_l Var(c_k − c_l) (for two channels, |c_k − c_l| > 3σ).
Otherwise the difference the range divides by may be the calibration's error, the range anything
(e.g. green and blue where they attenuate alike): no range, and the reason names the missing
channel as for too few usable ones (2 clipped, 3 lost in the water's light, else 4). A calibration
without uncertainties tests D > 0 as before."""


def pair_noise(covariance: NDArray, sigmas: float = ATTENUATION_SIGMAS) -> NDArray[np.float64]:
    """The kernels' significance constants: (N, N) sigmas² · Var(c_k − c_l), C-contiguous float64,
    from the (N, N) covariance of the attenuation differences (1/m)². An array, not a tuple as the
    attenuations are: numba refuses tuples of 1000 values and more, i.e. 32 channels and more."""
    cvv = np.asarray(covariance, dtype=np.float64)
    var = np.diag(cvv)[:, None] + np.diag(cvv)[None, :] - cvv - cvv.T
    return np.ascontiguousarray(sigmas * sigmas * np.maximum(var, 0.0))

# Rows per block in the numpy path: bounds its temporaries (~20 float32 rows of the block).
_NUMPY_BLOCK_ROWS = 32


def pack_pairs(y: NDArray, weight: NDArray, state: NDArray, saturated: int, backscatter: int) -> NDArray[np.uint64]:
    """Pairs [y, w] as float32, packed in uint64, from per-channel terms of any shape (..., N).

    y: ln E − b (any finite value where the channel is unusable); weight: E²/σ², > 0 exactly
    where the channel is usable; state: channel state codes, of which ``saturated`` and
    ``backscatter`` are counted for reasons. Returns shape (..., N).
    """
    usable = weight > 0
    flag = np.where(state == saturated, FLAG_SATURATED, np.where(state == backscatter, FLAG_BACKSCATTER, 0.0))
    pairs = np.empty((*np.shape(weight), 2), dtype=np.float32)
    pairs[..., 0] = np.where(usable, y, flag)
    pairs[..., 1] = np.where(usable, weight, 0.0)
    return pairs.view(np.uint64)[..., 0]


def lamp_geometry(geo: NDArray) -> tuple[float, float, float, float, float, float, float, float]:
    """(Sx, Sy, Sz, 1/fx, 1/fy, cx, cy, |S|) from the estimator's geometry vector, with the ray
    terms zeroed unless each pixel has its own ray, so that S·u = Sz on the axis and 0 without a lamp."""
    mode = int(geo[0])
    sx, sy, sz, s_norm = float(geo[1]), float(geo[2]), float(geo[3]), float(geo[4])
    if mode == LAMP_PIXEL_RAYS:
        return sx, sy, sz, float(geo[5]), float(geo[6]), float(geo[7]), float(geo[8]), s_norm
    return 0.0, 0.0, sz if mode == LAMP_ON_AXIS_RAY else 0.0, 0.0, 0.0, 0.0, 0.0, s_norm


# --------------------------------------------------------------------------------------------
# numpy path: the same float32 operations in the same order as kernels_numba._fuse_row.

def _fuse_block(y: NDArray, w: NDArray, c: tuple, b: tuple, cv: NDArray, p: NDArray, bounds: NDArray, s_norm: float,
                out_range: NDArray, out_var: NDArray, out_reason: NDArray) -> None:
    """Fuse a block: y, w (N, R, W) float32 pairs; p (R, W) float32 S·u; outputs (R, W)."""
    f32 = np.float32
    n = len(c)
    sw = np.zeros(p.shape, f32)
    flags = np.zeros(p.shape, f32)
    det = np.zeros(p.shape, f32)
    noise = np.zeros(p.shape, f32)
    num = np.zeros(p.shape, f32)
    for k in range(n):
        sw += w[k]
        flags += np.where(w[k] > 0, f32(FLAG_USABLE), y[k])
        for m in range(k + 1, n):
            dc = f32(c[k] - c[m])
            ww = w[k] * w[m]
            det += ww * (dc * dc)
            noise += ww * f32(cv[k, m])
            num += (ww * dc) * (y[k] - y[m] - f32(b[k] - b[m]))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        inv = f32(1.0) / det
        d = -num * inv
        den = f32(1.0) / (d - p)
        s2 = f32(s_norm * s_norm)
        rng = f32(0.5) * (d * d - s2) * den
        deriv = f32(0.5) * (d * d - f32(2.0) * d * p + s2) * den * den
        var = deriv * deriv * sw * inv
        distinct = det > noise
        ok = distinct & (d >= f32(bounds[0])) & (d <= f32(bounds[1])) & (d > f32(s_norm))
    counts = flags.astype(np.int32)
    n_usable, n_back, n_sat = counts & 255, (counts >> 8) & 255, counts >> 16
    reason = np.full(p.shape, _R_BELOW, np.uint8)
    reason[n_usable >= 1] = _R_TOO_FEW
    reason[(n_usable + n_back >= 2) & (n_back > 0)] = _R_BACKSCATTER
    reason[n_sat > 0] = _R_SATURATED
    reason[distinct] = _R_BOUNDS
    reason[ok] = _VALID
    out_range[...] = np.where(ok, rng, np.nan)
    out_var[...] = np.where(ok, var, np.nan)
    out_reason[...] = reason


def _lamp_dot_block(geo: NDArray, rows: slice, width: int) -> NDArray[np.float32]:
    """S·u for a block of rows, (R, W) float32, computed in float64 as the compiled kernel does."""
    sx, sy, sz, ifx, ify, cx, cy, _ = lamp_geometry(geo)
    i = np.arange(rows.start, rows.stop, dtype=np.float64)[:, None]
    j = np.arange(width, dtype=np.float64)[None, :]
    uy = (i - cy) * ify
    a = sy * uy + sz
    q = uy * uy + 1.0
    ux = (j - cx) * ifx
    return ((sx * ux + a) / np.sqrt(ux * ux + q)).astype(np.float32)


def _fuse_numpy(fetch, n: int, c: tuple, b: tuple, cv: NDArray, geo: NDArray, bounds: NDArray,
                out_range: NDArray, out_var: NDArray, out_reason: NDArray) -> None:
    h, w = out_range.shape
    for start in range(0, h, _NUMPY_BLOCK_ROWS):
        rows = slice(start, min(start + _NUMPY_BLOCK_ROWS, h))
        pairs = np.stack([fetch(rows, k) for k in range(n)]).view(np.float32)  # (N, R, 2W)
        _fuse_block(pairs[..., 0::2], pairs[..., 1::2], c, b, cv, _lamp_dot_block(geo, rows, w), bounds, float(geo[4]),
                    out_range[rows], out_var[rows], out_reason[rows])


def fuse_lookup_numpy(raw: NDArray, table: NDArray[np.uint64], c: tuple, b: tuple, cv: NDArray, geo: NDArray,
                      bounds: NDArray,
                      out_range: NDArray, out_var: NDArray, out_reason: NDArray) -> None:
    """Range, variance and reason of every pixel of an integer frame (numpy path).

    raw: (H, W, N) uint8/uint16 codes; table: (N, L) pairs (see :func:`pack_pairs`) per code,
    y = ln E − offset; c: N centred attenuations (1/m); b: N log constants minus the table's
    offset; cv: (N, N) significance constants (:func:`pair_noise`; zeros: any difference counts);
    geo: [mode, Sx, Sy, Sz, |S|, 1/fx, 1/fy, cx, cy]; bounds: [min, max] path length (m).
    Outputs (H, W) float32 range (m), float32 variance (m²), uint8 reason, written in place.
    """
    _fuse_numpy(lambda rows, k: np.take(table[k], raw[rows, :, k]), len(c), c, b, cv, geo, bounds,
                out_range, out_var, out_reason)


def fuse_arrays_numpy(pairs: NDArray[np.uint64], c: tuple, b: tuple, cv: NDArray, geo: NDArray, bounds: NDArray,
                      out_range: NDArray, out_var: NDArray, out_reason: NDArray) -> None:
    """As :func:`fuse_lookup_numpy` with the pairs given per pixel and channel, (H, W, N): for float frames."""
    _fuse_numpy(lambda rows, k: np.ascontiguousarray(pairs[rows, :, k]), len(c), c, b, cv, geo, bounds,
                out_range, out_var, out_reason)


try:
    from uwcam.optics import kernels_numba as _compiled
except ImportError as exc:
    if exc.name and exc.name.startswith("uwcam"):
        raise
    if exc.name not in ("numba", "llvmlite"):  # installed, but broken (e.g. built for another numpy)
        logging.getLogger(__name__).warning("numba cannot be imported (%s): ranging runs on numpy, ~20× slower", exc)
    _compiled = None

BACKEND: str = "numba" if _compiled is not None else "numpy"
"""Which implementation :func:`fuse_lookup` and :func:`fuse_arrays` use: "numba" or "numpy"."""

fuse_lookup = _compiled.fuse_lookup if _compiled is not None else fuse_lookup_numpy
fuse_arrays = _compiled.fuse_arrays if _compiled is not None else fuse_arrays_numpy
fuse_background = _compiled.fuse_background if _compiled is not None else None
"""Compiled per-channel terms and fusion for frames with a background; None on the numpy path."""
