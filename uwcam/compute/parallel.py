"""numba's parallel kernels called from several threads, safely, on any machine.

The frame loop, the simulated camera and the API's workers each call ``parallel=True`` kernels
from their own threads. numba runs them on one of three threading layers: TBB and OpenMP accept
launches from several threads at once; its fallback, "workqueue", aborts the whole process when
two launches overlap ("Concurrent access has been detected"). numba picks workqueue where neither
libtbb nor libgomp is installed, as on minimal Debian and Raspberry Pi OS images.

So, before any kernel runs: where TBB or OpenMP can be loaded, numba is told to use one of them
("threadsafe"); where neither can, the kernels are wrapped by :func:`parallel` so that one runs
at a time (each still uses every core), and a warning says how to get concurrency back. A
``NUMBA_THREADING_LAYER`` set by the user is respected.

OpenMP's idle workers are told to sleep at once (``OMP_WAIT_POLICY=PASSIVE``, unless the user set
it) rather than spin: by default each spins for up to 300,000 pauses (milliseconds) after every
parallel region, waiting for the next one. A frame takes about ten regions with Python work in
between, so the spinning took the cores that the camera, the frame loop and the server threads
need: with another thread busy, backscatter compensation at 720p took 2.5× as long as with
PASSIVE. A sleeping worker wakes in tens of microseconds.
"""

from __future__ import annotations

import importlib
import logging
import os
import threading
from typing import Any, Callable

log = logging.getLogger(__name__)

_LOCK = threading.RLock()
_POOLS = {"tbb": "numba.np.ufunc.tbbpool", "omp": "numba.np.ufunc.omppool"}


def threadsafe_layers() -> list[str]:
    """The thread-safe numba threading layers whose libraries load on this machine."""
    found = []
    for name, module in _POOLS.items():
        try:
            importlib.import_module(module)
        except (ImportError, OSError):  # libtbb / libgomp missing
            continue
        found.append(name)
    return found


def _configure() -> bool:
    """Choose the threading layer; True if parallel kernels must then be serialised."""
    # Read by libgomp when it loads, which is below (threadsafe_layers) or at the first kernel.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    try:
        import numba
    except ImportError:  # the numpy twins run instead: nothing to choose
        return False
    chosen = os.environ.get("NUMBA_THREADING_LAYER", "").strip().lower()
    if chosen:
        return chosen == "workqueue"
    if threadsafe_layers():
        numba.config.THREADING_LAYER = "threadsafe"
        return False
    numba.config.THREADING_LAYER = "workqueue"
    log.warning("neither libgomp nor libtbb is installed: numba's parallel kernels run one at a time "
                "(install libgomp1, e.g. apt-get install libgomp1, to let them run concurrently)")
    return True


SERIALISED = _configure()
"""True where only numba's workqueue layer is available and kernels therefore take turns."""


class _Serialised:
    """A compiled kernel that waits for any other parallel kernel to finish before it runs."""

    def __init__(self, dispatcher: Callable) -> None:
        self._dispatcher = dispatcher
        self.__doc__ = getattr(dispatcher, "__doc__", None)
        self.__name__ = getattr(dispatcher, "__name__", "kernel")

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        with _LOCK:
            return self._dispatcher(*args, **kwargs)

    def __getattr__(self, name: str) -> Any:  # signatures, py_func, … of the numba dispatcher
        return getattr(self._dispatcher, name)


def parallel(dispatcher: Callable) -> Callable:
    """Wrap a ``parallel=True`` kernel so that concurrent calls are safe (unchanged where they are)."""
    return _Serialised(dispatcher) if SERIALISED else dispatcher
