"""Give memory the daemon no longer needs back to the operating system, without paying for it per frame.

Three kinds of memory stay resident for no use unless handed back:

* **Frame-sized blocks in many heaps.** glibc gives each thread that allocates concurrently a heap
  (an "arena") of its own, up to eight per core; frame-sized blocks freed in one and not reused
  fragment them all, and snapshot hammering left the daemon ~110 MB above its baseline for good
  (bench/bench_snapshots.py). :func:`limit_malloc_arenas` caps them at two, once, before any
  thread allocates. Frame-sized blocks then come from those heaps and are reused frame after
  frame. (An earlier cure, a fixed 256 kB mmap threshold so that every such block had a mapping of
  its own returned on free, made each of a frame's ~60 MB of temporaries a fresh mapping to fault
  in page by page and unmap again: ~17 ms of CPU per compensated 720p frame, and at 1080p60 a third
  of a core and the loop's stalls past 50 ms. Measured with bench/bench_daemon.py: 1080p60 replay
  24 → 14 ms of CPU per frame, p99 latency 68 → 32 ms; 720p with backscatter compensation
  27 → 30 fps.)
* **Free heap pages.** Whatever was free in the heaps at the busiest moment stays resident;
  :func:`release_free_memory`, called about once a second by the frame loop, hands free pages back
  (``malloc_trim``); pages in use are untouched. After a burst of snapshot requests resident
  memory comes back to within a few MB of its baseline.
* **The compiler's code.** numba compiles (or loads from its cache) the kernels with LLVM, whose
  library is ~100 MB of machine code; loading it alone makes ~95 MB of it resident (its static
  initialisers are spread over the whole library), yet none of it runs once the kernels are
  loaded: they are plain machine code in memory of their own. :func:`release_compiler_pages`
  asks the kernel to drop those pages from the process (``madvise(MADV_PAGEOUT)`` on the
  library's read-only mappings; Linux ≥ 5.4). They are clean pages of a file, so nothing is lost:
  should a kernel ever need compiling again, they are read back in as it runs.

Elsewhere than glibc and Linux these do nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import sys

log = logging.getLogger(__name__)

M_ARENA_MAX = -8  # from glibc's malloc.h
MALLOC_ARENAS = 2
MADV_PAGEOUT = 21  # from Linux's mman-common.h (since 5.4)
COMPILER_LIBRARIES = ("libllvmlite",)
"""Shared libraries whose code serves only to compile or load kernels (matched in the path)."""


def _libc() -> ctypes.CDLL | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    except OSError:
        return None


_LIBC = _libc()


def _function(name: str, restype, *argtypes):
    fn = getattr(_LIBC, name, None) if _LIBC is not None else None
    if fn is not None:
        fn.restype, fn.argtypes = restype, list(argtypes)
    return fn


_TRIM = _function("malloc_trim", ctypes.c_int, ctypes.c_size_t)  # glibc only (not musl)
_MALLOPT = _function("mallopt", ctypes.c_int, ctypes.c_int, ctypes.c_int)
_MADVISE = _function("madvise", ctypes.c_int, ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int)


def limit_malloc_arenas(arenas: int = MALLOC_ARENAS) -> bool:
    """Let glibc keep at most ``arenas`` heaps for all threads; False where libc is not glibc.
    Call it before threads allocate: arenas made already stay."""
    if _MALLOPT is None:  # musl, macOS: no mallopt, nothing to tune
        return False
    ok = bool(_MALLOPT(M_ARENA_MAX, arenas))
    if not ok:
        log.debug("mallopt(M_ARENA_MAX) refused")
    return ok


def release_free_memory() -> bool:
    """Return free heap pages to the OS; True if the allocator released any."""
    return bool(_TRIM(0)) if _TRIM is not None else False


def read_only_mappings(path_part: str, maps: str = "/proc/self/maps") -> list[tuple[int, int]]:
    """(start, end) addresses of this process's mappings of files whose path contains
    ``path_part`` and that are not writable (code and constants: clean pages of the file)."""
    spans = []
    try:
        with open(maps) as fh:
            for line in fh:
                fields = line.split(maxsplit=5)
                if len(fields) == 6 and path_part in fields[5] and "w" not in fields[1]:
                    start, end = (int(v, 16) for v in fields[0].split("-"))
                    spans.append((start, end))
    except OSError:
        return []
    return spans


def release_compiler_pages(libraries: tuple[str, ...] = COMPILER_LIBRARIES) -> int:
    """Drop the compiler library's resident code pages from this process (see the module's
    docstring); returns the bytes of mappings advised, 0 where unsupported. Call it once the
    kernels are compiled or loaded; calling it again later is cheap and harmless."""
    if _MADVISE is None:
        return 0
    advised = 0
    for library in libraries:
        for start, end in read_only_mappings(library):
            if _MADVISE(start, end - start, MADV_PAGEOUT) == 0:
                advised += end - start
            else:  # EINVAL before Linux 5.4: nothing to gain by trying the others
                log.debug("madvise(MADV_PAGEOUT) refused: errno %d", ctypes.get_errno())
                return advised
    return advised
