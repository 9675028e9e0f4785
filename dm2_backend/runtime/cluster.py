"""Tasks on a Dask distributed cluster: a local one of N worker processes (``--workers N``) or an existing one
joined by its scheduler's address (``--scheduler tcp://host:8786``, or Dask's own ``DASK_SCHEDULER_ADDRESS``;
``--workers 0`` ignores it). Without either, nothing here runs and every stage stays in its own process.

A stage that can split its work into independent tasks asks :func:`current` for the engine and, where there is
one, hands it a module-level function and the tasks (:meth:`Engine.map`); the results come back in the tasks'
order, so the stage's answer is the single-process one. The cluster is started (or joined) at the first such call,
so a run whose work is all cached starts none. A task whose worker dies is run again on another (Dask reschedules
it); one that kills more workers than the scheduler's ``allowed-failures`` (:data:`ALLOWED_FAILURES` on a local
cluster) ends the run in one line.
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

#: how many workers may die running one task and the task still be tried again (a local cluster's
#: ``allowed-failures``; a cluster started apart keeps its own setting)
ALLOWED_FAILURES = 3
#: seconds to reach a scheduler given by address, and for its first worker to join
CONNECT_TIMEOUT = 60
#: the environment variable Dask reads a scheduler's address from (its ``scheduler-address`` setting)
ADDRESS_VARIABLE = "DASK_SCHEDULER_ADDRESS"


class ClusterError(InputError):
    """The cluster could not be reached, has no worker, or lost a task's workers too often: one line."""


@dataclass(frozen=True)
class ClusterSpec:
    """Where tasks run: ``workers`` local processes, or the scheduler at ``address``; neither: in-process."""

    workers: int | None = None
    address: str | None = None

    @classmethod
    def of(cls, workers: int | None, address: str | None) -> ClusterSpec:
        """The options as given; without either the address in :data:`ADDRESS_VARIABLE`; ``workers`` 0: in
        this process whatever the environment says; both at once is an error."""
        if workers is not None and address is not None:
            raise InputError(None, "--workers and --scheduler: give one (--workers starts a local cluster, "
                                   "--scheduler joins one)")
        if workers == 0:
            return cls()
        if workers is None and address is None:
            address = os.environ.get(ADDRESS_VARIABLE) or None
        return cls(workers, address)

    @property
    def distributed(self) -> bool:
        return self.workers is not None or self.address is not None


class Engine:
    """The cluster ``spec`` names, started or joined at first use; :meth:`map` runs tasks on its workers."""

    def __init__(self, spec: ClusterSpec, stack: contextlib.ExitStack) -> None:
        self.spec, self._stack, self._client = spec, stack, None

    @property
    def client(self) -> Any:
        if self._client is None:
            self._client = self._stack.enter_context(_client(self.spec))
        return self._client

    @property
    def slots(self) -> int:
        """Tasks the cluster runs at once: its workers' threads together."""
        return sum(w["nthreads"] for w in self.client.scheduler_info(n_workers=-1)["workers"].values()) or 1

    def run_length(self, count: int, smallest: int = 1, largest: int | None = None) -> int:
        """How many of ``count`` items one task takes: at least four tasks a worker thread, within the bounds."""
        size = max(smallest, -(-count // (4 * self.slots)))
        return size if largest is None else max(smallest, min(largest, size))

    def map(self, fn: Callable[..., Any], tasks: Sequence[Any], desc: str, *, unit: str = "task",
            enabled: bool = True, shared: dict[str, Any] | None = None) -> list:
        """``fn(task, **shared)`` for every task on the cluster's workers, the results in the tasks' order; the
        stage's progress counts finished tasks across all workers. ``shared``: what every task reads, sent to the
        cluster once (each value whole), not with each task. A task's error is raised here as it was raised
        there."""
        from distributed import as_completed
        from distributed.client import FutureCancelledError
        from distributed.scheduler import KilledWorker

        client = self.client
        sent: dict[str, Any] = {}
        futures: list = []
        try:
            for name, value in (shared or {}).items():
                sent[name] = client.scatter([value], hash=False)[0]
            futures = client.map(fn, list(tasks), pure=False, **sent)
            for _ in progress(as_completed(futures), desc, total=len(futures), unit=unit, enabled=enabled):
                pass
            return client.gather(futures)
        except KilledWorker as exc:
            raise ClusterError(None, f"{desc}: {exc.allowed_failures + 1} workers died running its task {exc.task!r} "
                                     f"(the last: {exc.last_worker.address}); the preparation steps that finished "
                                     "are in the cache, if the run has one: run the command again to continue"
                               ) from None
        except FutureCancelledError as exc:
            raise ClusterError(None, f"{desc}: the cluster cancelled a task ({one_line(str(exc))[:200]})") from None
        finally:
            client.cancel([*futures, *sent.values()])


_current: contextvars.ContextVar[Engine | None] = contextvars.ContextVar("dm2_cluster", default=None)


def current() -> Engine | None:
    """The engine of the :func:`engine` block around the caller, None outside one (run in-process)."""
    return _current.get()


@contextlib.contextmanager
def engine(spec: ClusterSpec) -> Iterator[Engine | None]:
    """Within the block, :func:`current` is the cluster ``spec`` names (started or joined when first used, closed
    after the block); None when it names none."""
    if not spec.distributed:
        yield None
        return
    with contextlib.ExitStack() as stack:
        token = _current.set(Engine(spec, stack))
        try:
            yield _current.get()
        finally:
            _current.reset(token)


@contextlib.contextmanager
def _client(spec: ClusterSpec) -> Iterator[Any]:
    """A client of a local cluster of ``spec.workers`` processes, or of the scheduler at ``spec.address`` once a
    worker has joined it."""
    import dask
    from distributed import Client, LocalCluster

    settings = {"distributed.scheduler.allowed-failures": ALLOWED_FAILURES, "logging.distributed": "error",
                "distributed.admin.system-monitor.gil.enabled": False,
                # glibc's own memory thresholds (the one Dask sets maps and unmaps numpy's temporaries each time)
                "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}
    with dask.config.set(settings), contextlib.ExitStack() as stack:
        if spec.workers is not None:
            # one thread each: the tasks are numpy, scipy and open3d work that use a core apiece
            cluster = stack.enter_context(LocalCluster(n_workers=spec.workers, threads_per_worker=1, processes=True,
                                                       dashboard_address=None, env=_one_thread_env()))
            client = stack.enter_context(Client(cluster))
        else:
            try:
                client = stack.enter_context(Client(spec.address, timeout=CONNECT_TIMEOUT))
                client.wait_for_workers(1, timeout=CONNECT_TIMEOUT)
            except (OSError, TimeoutError, ValueError) as exc:
                raise ClusterError(spec.address, "no Dask scheduler with a worker answered within "
                                                 f"{CONNECT_TIMEOUT} s ({one_line(str(exc))[:200]})") from None
        workers = client.scheduler_info(n_workers=-1)["workers"]
        log.info("cluster: %d worker(s), %d thread(s) at %s", len(workers),
                 sum(w["nthreads"] for w in workers.values()), client.scheduler.address)
        slow = [address for address, fixed in client.run(fixed_mmap_threshold).items() if fixed]
        if slow:
            log.warning("cluster: %d of %d worker(s) (%s) run with Dask's MALLOC_TRIM_THRESHOLD_ alone: numpy's "
                        "temporaries are mapped and unmapped each time and tasks run 2-5 times slower; start the "
                        "workers with MALLOC_MMAP_THRESHOLD_ set too (the README's cluster recipe)", len(slow),
                        len(workers), ", ".join(sorted(slow)[:5]) + (", ..." if len(slow) > 5 else ""))
        yield client


def _one_thread_env() -> dict[str, str]:
    """Each worker process's thread caps: one task a core, not one task on every core."""
    return {name: "1" for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}


def fixed_mmap_threshold() -> bool:
    """Whether this process's glibc maps every allocation over 128 KiB afresh: ``MALLOC_TRIM_THRESHOLD_`` set
    (as Dask's nanny sets it) turns off the adaptive mmap threshold, unless ``MALLOC_MMAP_THRESHOLD_`` sets one."""
    return "MALLOC_TRIM_THRESHOLD_" in os.environ and "MALLOC_MMAP_THRESHOLD_" not in os.environ
