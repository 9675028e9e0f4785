"""Preloaded into a Dask worker by ``tests/test_cluster.py`` (``dask worker --preload``): the worker's process
dies as it starts a task of dm2's pairwise registration. ``DM2_TEST_DIE_ONCE``: a file; the first such task on any
worker creates it and dies, later tasks run. ``DM2_TEST_DIE_ALWAYS=1``: every such task dies."""

from __future__ import annotations

import os
from pathlib import Path

import dm2_backend.algorithms.pairwise as pairwise

#: the registration's own task (Dask imports a preload file twice: the second import must not wrap the first's)
_register = getattr(pairwise, "_unwrapped_register_pairs", pairwise.register_pairs)
pairwise._unwrapped_register_pairs = _register


def _dying(task):
    once = os.environ.get("DM2_TEST_DIE_ONCE")
    if os.environ.get("DM2_TEST_DIE_ALWAYS") == "1":
        os._exit(17)
    if once:
        try:
            with open(Path(once), "x"):
                pass
        except FileExistsError:
            return _register(task)
        os._exit(17)
    return _register(task)


pairwise.register_pairs = _dying  # a task's function is pickled by name: the worker resolves it to this one
