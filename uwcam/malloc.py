"""Large buffers go back to the operating system when freed.

The daemon allocates and frees many multi-megabyte buffers (frames, range maps, snapshot
encodings) from many threads. glibc serves a block above its mmap threshold with its own
mapping, returned to the system on free; but the threshold *rises* each time such a block is
freed (up to 32 MiB), after which frame-sized blocks come from per-thread heaps that fragment and
stay resident: snapshot hammering left the daemon ~110 MB above its baseline for good
(bench/bench_snapshots.py). Fixing the threshold stops that drift.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging

log = logging.getLogger(__name__)
M_MMAP_THRESHOLD = -3  # from glibc's malloc.h
MMAP_THRESHOLD_BYTES = 256 * 1024


def return_large_blocks_to_the_system(threshold: int = MMAP_THRESHOLD_BYTES) -> bool:
    """Fix glibc's mmap threshold at ``threshold`` bytes; False where libc is not glibc."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl, macOS: no mallopt, nothing to tune
        return False
    ok = bool(mallopt(M_MMAP_THRESHOLD, threshold))
    if not ok:
        log.debug("mallopt(M_MMAP_THRESHOLD) refused")
    return ok
