"""numba when it is installed, numpy otherwise.

numba has no wheels for some platforms a vehicle runs (32-bit ARM). Every compiled kernel of
the simulator and of the backscatter model has a numpy twin computing the same values; :data:`HAVE_NUMBA` chooses between
them when a module is imported. Without numba, :func:`njit` leaves a function as plain Python
(its numpy twin is the one called) and :func:`set_threads` does nothing.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

try:
    import numba as _numba
except ImportError:  # pragma: no cover - exercised on platforms without numba wheels
    _numba = None

HAVE_NUMBA = _numba is not None

if _numba is not None:
    from uwcam.compute.parallel import parallel

    def njit(*args: Any, **kwargs: Any) -> Callable:
        """numba.njit; a ``parallel=True`` kernel is also made safe to call from several threads
        (see :mod:`uwcam.compute.parallel`)."""
        if kwargs.get("parallel"):
            return lambda f: parallel(_numba.njit(*args, **kwargs)(f))
        return _numba.njit(*args, **kwargs)

    prange = _numba.prange
else:  # pragma: no cover
    def njit(*args: Any, **kwargs: Any) -> Callable:
        """Without numba: the decorated function unchanged."""
        if args and callable(args[0]):
            return args[0]
        return lambda f: f

    prange = range


def kernel_array(values: Any, shape: tuple[int, ...], dtype: Any) -> "np.ndarray":
    """``values`` broadcast to ``shape`` as a C-contiguous, writable array of ``dtype`` for a
    compiled kernel: the array itself when it already is one, else a copy. numba compiles a kernel
    apart for read-only arrays (a broadcast view is one), so an argument that is a view one time
    and a copy the next would compile it twice, the second time in the frame loop."""
    a = np.asarray(values)
    if a.shape == shape and a.dtype == dtype and a.flags.c_contiguous and a.flags.writeable:
        return a
    return np.array(np.broadcast_to(a, shape), dtype=dtype, order="C")


def set_threads(n: int) -> None:
    """Limit numba's parallel kernels to ``n`` threads in the calling thread (no-op without numba)."""
    if _numba is not None:
        _numba.set_num_threads(max(1, min(n, _numba.config.NUMBA_NUM_THREADS)))


@njit(cache=True, nogil=True)
def repeat_per_pixel(values, row):  # pragma: no cover - compiled; called only from compiled kernels
    """Fill ``row`` (W·N,) with the N per-channel ``values`` once per pixel, in the order of a
    frame row's values (channels interleaved): a compiled kernel taking a row as W·N contiguous
    values reads each value's constant at the same index, a loop without branches that vectorises."""
    n = values.shape[0]
    for j in range(row.shape[0] // n):
        for k in range(n):
            row[j * n + k] = values[k]
