"""The process's memory between stages."""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import mmap
import resource

import numpy as np


@functools.cache
def _malloc_trim():
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):
        return None


def release_freed_memory() -> bool:
    """Hand the heap's freed pages back to the system (glibc ``malloc_trim``). Freed small blocks otherwise stay
    in the process: an OcTree's millions of nodes, the registrations' threads' arenas, each dense round's
    temporaries; the next stage's peak then sits on top of them. Call it between stages. False where the C
    library has no such call."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MiB: Linux's ``VmHWM`` (this program's own: ``ru_maxrss``
    keeps the peak of the process that forked it across ``exec``: a run started by the test suite would report the
    suite's peak),
    else ``ru_maxrss``."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def release_mapped(arrays: list[np.ndarray]) -> int:
    """Drop the resident pages of the read-only memory-mapped files behind ``arrays`` (views of a ``np.memmap``
    opened with mode "r", e.g. the cached frames' points): the data stays in the file and is read again where
    touched, but a stage that does not touch it does not count it in the process's memory. Returns the number of
    mappings released; arrays in memory, or copy-on-write maps, are left alone."""
    seen: dict[int, mmap.mmap] = {}
    for a in arrays:
        base = a
        while base is not None and not isinstance(base, np.memmap):
            base = getattr(base, "base", None)
        if base is not None and base.mode == "r" and isinstance(getattr(base, "_mmap", None), mmap.mmap):
            seen[id(base._mmap)] = base._mmap
    if not hasattr(mmap, "MADV_DONTNEED"):
        return 0
    for m in seen.values():
        m.madvise(mmap.MADV_DONTNEED)
    return len(seen)
