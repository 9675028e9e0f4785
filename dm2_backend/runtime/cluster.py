"""Tasks on a Dask distributed cluster: a local one of N worker processes (``--workers N``) or an existing one
joined by its scheduler's address (``--scheduler tcp://host:8786``, or Dask's own ``DASK_SCHEDULER_ADDRESS``).
Without either, nothing here runs and every stage stays in its own process.

A stage that can split its work into independent tasks asks :func:`current` for the engine and, where there is
one, hands it a module-level function and the tasks (:meth:`Engine.map`); the results come back in the tasks'
order, so the stage's answer is the single-process one. A task whose worker dies is run again on another (Dask
reschedules it); one that kills more than :data:`ALLOWED_FAILURES` workers ends the run in one line, and the preparation
cache keeps every step that finished (``--resume`` or the same command continues from there).
"""

from __future__ import annotations

import contextlib
import contextvars
import logging
import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from dm2_backend.runtime.errors import InputError, one_line
from dm2_backend.runtime.progress import progress

log = logging.getLogger(__name__)

#: how many workers may die running one task and the task still be tried again (Dask's ``allowed-failures``)
ALLOWED_FAILURES = 3
#: seconds to reach a scheduler given by address before giving up
CONNECT_TIMEOUT = 30
#: the environment variable Dask reads a scheduler's address from (its ``scheduler-address`` setting)
ADDRESS_VARIABLE = "DASK_SCHEDULER_ADDRESS"


class ClusterError(InputError):
    """The cluster could not be reached, or lost a task's workers too often: one line, the run ends."""


@dataclass(frozen=True)
class ClusterSpec:
    """Where tasks run: ``workers`` local processes, or the scheduler at ``address``; neither: in-process."""

    workers: int | None = None
    address: str | None = None

    @classmethod
    def of(cls, workers: int | None, address: str | None) -> ClusterSpec:
        """The options as given, the address falling back on :data:`ADDRESS_VARIABLE` when no worker count is
        asked for; both at once is an error."""
        if workers is not None and address is not None:
            raise InputError(None, "--workers and --scheduler: give one (--workers starts a local cluster, "
                                   "--scheduler joins one)")
        if workers is None and address is None:
            address = os.environ.get(ADDRESS_VARIABLE) or None
        return cls(workers, address)

    @property
    def distributed(self) -> bool:
        return self.workers is not None or self.address is not None


class Engine:
    """A connected Dask client; :meth:`map` runs tasks on its workers."""

    def __init__(self, client: Any) -> None:
        self.client = client

    @property
    def workers(self) -> int:
        return len(self.client.scheduler_info(n_workers=-1)["workers"])

    def map(self, fn: Callable[[Any], Any], tasks: Sequence[Any], desc: str, *, unit: str = "task",
            enabled: bool = True) -> list:
        """``fn(task)`` for every task on the cluster's workers, the results in the tasks' order; the stage's
        progress counts finished tasks across all workers."""
        from distributed import as_completed
        from distributed.client import FutureCancelledError
        from distributed.scheduler import KilledWorker

        futures = self.client.map(fn, list(tasks), pure=False)
        try:
            for _ in progress(as_completed(futures), desc, total=len(futures), unit=unit, enabled=enabled):
                pass
            return self.client.gather(futures)
        except KilledWorker as exc:
            raise ClusterError(None, f"{desc}: {exc.allowed_failures + 1} workers died running its task {exc.task!r} "
                                     f"(the last: {exc.last_worker.address}; its log says why); the finished "
                                     "preparation steps are cached: run the command again to continue") from None
        except FutureCancelledError as exc:
            raise ClusterError(None, f"{desc}: the cluster cancelled a task ({one_line(str(exc))[:200]})") from None
        finally:
            self.client.cancel(futures)


_current: contextvars.ContextVar[Engine | None] = contextvars.ContextVar("dm2_cluster", default=None)


def current() -> Engine | None:
    """The engine of the :func:`engine` block around the caller, None outside one (run in-process)."""
    return _current.get()


@contextlib.contextmanager
def engine(spec: ClusterSpec) -> Iterator[Engine | None]:
    """Within the block, :func:`current` is the cluster ``spec`` names (started here for ``workers``, closed
    after); None when it names none."""
    if not spec.distributed:
        yield None
        return
    import dask
    from distributed import Client, LocalCluster

    with dask.config.set({"distributed.scheduler.allowed-failures": ALLOWED_FAILURES,
                          "distributed.worker.daemon": False, "distributed.admin.system-monitor.gil.enabled": False,
                          "logging.distributed": "error"}):
        with contextlib.ExitStack() as stack:
            if spec.workers is not None:
                # one thread each: the tasks are numpy, scipy and open3d work that use a core apiece
                cluster = stack.enter_context(LocalCluster(n_workers=spec.workers, threads_per_worker=1,
                                                           processes=True, dashboard_address=None,
                                                           env=_one_thread_env()))
                client = stack.enter_context(Client(cluster))
            else:
                client = stack.enter_context(_connect(spec.address))
            log.info("cluster: %d worker(s) at %s", len(client.scheduler_info(n_workers=-1)["workers"]),
                     client.scheduler.address)
            token = _current.set(Engine(client))
            try:
                yield _current.get()
            finally:
                _current.reset(token)


def _connect(address: str):
    from distributed import Client

    try:
        return Client(address, timeout=CONNECT_TIMEOUT)
    except (OSError, TimeoutError, ValueError) as exc:
        raise ClusterError(address, f"cannot reach the Dask scheduler ({one_line(str(exc))[:200]})") from None


def _one_thread_env() -> dict[str, str]:
    """Each worker process's thread caps: one task a core, not one task on every core."""
    return {name: "1" for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
