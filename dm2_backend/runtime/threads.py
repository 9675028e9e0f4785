"""A function over a stream of items on a few threads, results in order, while the caller draws the next items.

For the per-scan passes over a whole sequence (down-sampling, voxelising, normals): the items are drawn in the
calling thread, so a scan reader need not be thread-safe, and reading the next file overlaps the work on the
ones before it (numpy's file reads, open3d and scipy's KD-tree release the GIL). The results are those of the
plain loop: anything random stays with the caller, drawn in order.
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")


def ordered_map(fn: Callable[[T], R], items: Iterable[T], workers: int | None = None, ahead: int = 16
                ) -> Iterator[R]:
    """``fn(item)`` for each item, in order, on ``workers`` threads (default: the CPU count, at most 4) with at
    most ``ahead`` items in flight."""
    workers = workers or min(4, os.cpu_count() or 1)
    if workers <= 1:
        yield from map(fn, items)
        return
    with ThreadPoolExecutor(workers) as pool:
        pending: deque = deque()
        for item in items:
            pending.append(pool.submit(fn, item))
            if len(pending) >= ahead:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
