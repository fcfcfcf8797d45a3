"""Give memory freed by the frame loop back to the operating system.

Frames and range maps are megabytes each and are allocated and freed every frame by several
threads. glibc's allocator keeps such freed blocks in its heaps (its mmap threshold rises to
the largest block freed, up to 32 MB) so that the next frame reuses them without page faults;
but whatever was free at the busiest moment then stays resident for good, tens of MB at
1080p. :func:`release_free_memory`, called about once a second by the frame loop, hands the
free pages back (``malloc_trim``); pages in use are untouched, and the few freed ones that are
needed again are simply faulted back in. Elsewhere than glibc it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys


def _malloc_trim():
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        trim = libc.malloc_trim
    except (OSError, AttributeError):  # not glibc (e.g. musl): nothing to do
        return None
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    return trim


_TRIM = _malloc_trim()


def release_free_memory() -> bool:
    """Return free heap pages to the OS; True if the allocator released any."""
    return bool(_TRIM(0)) if _TRIM is not None else False
