"""ordered_map: the results of a plain loop, in order, with the items drawn in the calling thread."""

from __future__ import annotations

import threading
import time

import pytest

from dm2_backend.runtime.threads import ordered_map


@pytest.mark.parametrize("workers", [1, 2, 3])
def test_results_in_order_whatever_finishes_first(workers):
    def slow(i: int) -> int:
        time.sleep(0.002 * ((7 * i) % 5))  # later items often finish first
        return i * i

    assert list(ordered_map(slow, range(50), workers=workers, ahead=8)) == [i * i for i in range(50)]


def test_items_are_drawn_in_the_calling_thread():
    seen: list[int] = []

    def items():
        for i in range(20):
            seen.append(threading.get_ident())
            yield i

    workers_seen: set[int] = set()

    def work(i: int) -> int:
        workers_seen.add(threading.get_ident())
        return i

    assert list(ordered_map(work, items(), workers=2, ahead=4)) == list(range(20))
    assert set(seen) == {threading.get_ident()}  # a reader need not be thread-safe
    assert threading.get_ident() not in workers_seen


def test_an_error_in_the_work_reaches_the_caller():
    def fail(i: int) -> int:
        if i == 5:
            raise ValueError("scan 5")
        return i

    with pytest.raises(ValueError, match="scan 5"):
        list(ordered_map(fail, range(10), workers=2))
