"""The process's memory between stages."""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import resource


@functools.cache
def _malloc_trim():
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):
        return None


def release_freed_memory() -> bool:
    """Hand the heap's freed pages back to the system (glibc ``malloc_trim``). Freed small blocks otherwise stay
    in the process: an OcTree's millions of nodes (1.1 GiB for 8 M leaves), the registrations' threads' arenas
    (250 MiB after the 80,000 registrations of 20,000 frames), each dense round's temporaries; the next stage's
    peak then sits on top of them. Call it between stages. False where the C library has no such call."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MiB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
