"""Seconds and memory per stage: what ``report.json``'s ``timings`` and ``peak_rss_mb_by_stage`` hold."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

from dm2_backend.runtime.memory import peak_rss_mb


@dataclass
class StageLog:
    """Each stage's seconds and the process's peak resident memory when it ended (MiB). The peak only grows: the
    first stage at the run's peak reached it (or the untimed work just before it did)."""

    seconds: dict[str, float] = field(default_factory=dict)
    peak_mb: dict[str, float] = field(default_factory=dict)

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        """Time the ``with`` block as stage ``name`` (recorded only when it completes)."""
        t = time.perf_counter()
        yield
        self.seconds[name] = time.perf_counter() - t
        self.peak_mb[name] = round(peak_rss_mb(), 1)

    def copy(self) -> StageLog:
        return StageLog(dict(self.seconds), dict(self.peak_mb))
