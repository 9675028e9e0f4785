"""A real Dask cluster on this machine: a scheduler and worker processes joining it by address, as on two machines.
A run on it gives the single-process answer; a worker killed in the middle of a task is replaced and the task run
again; a task that kills every worker it gets ends the run in one line, and the cache continues it."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from dm2_backend.cli.main import cli
from dm2_backend.evaluation import consistency_profile as cp
from dm2_backend.evaluation import profile_cells, profile_stretches
from dm2_backend.evaluation.profile_cells import StoredCells
from dm2_backend.formats import open_scans, read_trajectory
from dm2_backend.kernel.prepared import Frames
from dm2_backend.runtime import cluster as cluster_module
from dm2_backend.runtime.cluster import ClusterSpec
from dm2_backend.runtime.errors import InputError
from dm2_backend.simulate.sequence import SimSettings, generate

FAULTS = Path(__file__).with_name("cluster_faults.py")
#: the environment the README's cluster recipe starts workers with
RECIPE = {"MALLOC_TRIM_THRESHOLD_": "1073741824", "MALLOC_MMAP_THRESHOLD_": "33554432"}


@pytest.fixture(scope="module")
def sim(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("cluster") / "sim"
    generate(SimSettings(frames=16, laps=1.0, planar=True), out, progress=False)
    return out


@contextlib.contextmanager
def cluster(tmp: Path, workers: int = 2, env: dict | None = None, allowed_failures: int = 3, recipe: bool = True):
    """A scheduler on a free port and ``workers`` single-threaded worker processes joining it by its address
    (``recipe``: with the README's glibc settings); yields the address."""
    file = tmp / "scheduler.json"
    scheduler_env = {**os.environ, "DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES": str(allowed_failures)}
    procs = [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                               "--port", "0", "--no-dashboard", "--scheduler-file", str(file)],
                              env=scheduler_env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                              start_new_session=True)]
    try:
        address = _scheduler_address(file, procs[0])
        worker_env = {**os.environ, "OMP_NUM_THREADS": "1", **(RECIPE if recipe else {}), **(env or {})}
        for _ in range(workers):
            procs.append(subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", address,
                                           "--nthreads", "1", "--no-dashboard", "--preload", str(FAULTS)],
                                          env=worker_env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                          start_new_session=True))
        from distributed import Client

        if workers:
            with Client(address, timeout=60) as client:
                client.wait_for_workers(workers, timeout=120)
        yield address
    finally:  # each process with the worker processes it started (a session of its own)
        for p in procs:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGKILL)
            p.wait(timeout=30)


def _scheduler_address(file: Path, scheduler: subprocess.Popen, wait_s: float = 60) -> str:
    """The address the scheduler writes to its file; the file appears before its text is complete."""
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        assert scheduler.poll() is None, f"the scheduler exited with {scheduler.returncode}"
        with contextlib.suppress(OSError, ValueError, KeyError):
            return json.loads(file.read_text())["address"]
        time.sleep(0.2)
    raise AssertionError(f"no scheduler address in {file} after {wait_s:.0f} s")


def baseline(sim: Path, out: Path, cache: Path, *extra: str, command: tuple[str, ...] = ("baseline", "gtsam")):
    return CliRunner().invoke(cli, [*command, "-s", str(sim / "velodyne"), "-p", str(sim / "warm_start.txt"),
                                    "-o", str(out), "--cache-dir", str(cache), "-q", *extra], obj={})


def pairwise(cache: Path) -> dict[str, np.ndarray]:
    (entry,) = cache.glob("pairwise-*")
    return {name: np.load(entry / f"{name}.npy") for name in ("relative", "valid", "fitness")}


@pytest.fixture(scope="module")
def single(sim, tmp_path_factory) -> Path:
    """The single-process baseline run."""
    root = tmp_path_factory.mktemp("single")
    result = baseline(sim, root / "run", root / "cache")
    assert result.exit_code == 0, result.output
    return root


@pytest.fixture(scope="module")
def single_refine(sim, tmp_path_factory) -> Path:
    """The single-process refine."""
    root = tmp_path_factory.mktemp("single-refine")
    result = baseline(sim, root / "run", root / "cache", command=("refine",))
    assert result.exit_code == 0, result.output
    return root


def same_answer(single: Path, root: Path) -> None:
    mine, theirs = pairwise(root / "cache"), pairwise(single / "cache")
    assert set(np.unique(theirs["valid"])) == {False, True}  # some pairs pass the gates and some fail
    np.testing.assert_array_equal(mine["valid"], theirs["valid"])
    np.testing.assert_allclose(mine["relative"], theirs["relative"], atol=1e-9)
    np.testing.assert_allclose(mine["fitness"], theirs["fitness"], atol=1e-9)
    np.testing.assert_allclose(np.load(root / "run" / "poses.npy"), np.load(single / "run" / "poses.npy"),
                               atol=1e-7)


def test_a_refine_across_a_scheduler_and_its_workers_gives_the_single_process_answer(sim, single_refine, tmp_path):
    with cluster(tmp_path) as address:
        result = baseline(sim, tmp_path / "run", tmp_path / "cache", "--scheduler", address, command=("refine",))
    assert result.exit_code == 0, result.output
    same_answer(single_refine, tmp_path)


def test_a_worker_killed_in_the_middle_of_a_task_is_replaced(sim, single, tmp_path):
    died = tmp_path / "died"
    with cluster(tmp_path, env={"DM2_TEST_DIE_ONCE": str(died)}) as address:
        result = baseline(sim, tmp_path / "run", tmp_path / "cache", "--scheduler", address)
    assert result.exit_code == 0, result.output
    assert died.exists()  # a worker did die running a registration task
    same_answer(single, tmp_path)


def test_a_task_that_kills_every_worker_ends_the_run_in_one_line_and_the_cache_continues(sim, single, tmp_path):
    with cluster(tmp_path, workers=1, env={"DM2_TEST_DIE_ALWAYS": "1"}, allowed_failures=1) as address:
        failed = baseline(sim, tmp_path / "run", tmp_path / "cache", "--scheduler", address)
    errors = [line for line in failed.output.splitlines() if line.startswith("dm2: error:")]
    assert failed.exit_code == 2 and "Traceback" not in failed.output and len(errors) == 1
    assert "2 workers died running its task" in errors[0] and "run the command again" in errors[0]
    again = baseline(sim, tmp_path / "run", tmp_path / "cache", "--force")
    assert again.exit_code == 0, again.output
    cached = json.loads((tmp_path / "run" / "report.json").read_text())["prepare"]["cached"]
    assert cached["frames"] and cached["place_recognition"] and not cached["registration"]
    same_answer(single, tmp_path)


def test_a_local_cluster_of_two_workers_gives_the_single_process_answer(sim, single, tmp_path):
    result = baseline(sim, tmp_path / "run", tmp_path / "cache", "--workers", "2")
    assert result.exit_code == 0, result.output
    same_answer(single, tmp_path)


def test_frames_travel_by_their_cache_entry_or_with_the_task(tmp_path):
    from dm2_backend.prepare import store

    points = [np.random.default_rng(i).normal(size=(5 + i, 3)).astype(np.float32) for i in range(4)]
    frames = Frames(points, None, False)
    store.put_frames(tmp_path, "frames-x", frames)
    stored = store.frames_from(*store.get(tmp_path, "frames-x"), tmp_path / "frames-x")
    for source in (frames, stored):
        back = source.part(np.array([3, 1, 3])).frames()
        assert len(back) == 4 and len(back.points[0]) == len(back.points[2]) == 0
        np.testing.assert_array_equal(back.points[1], points[1])
        np.testing.assert_array_equal(back.points[3], points[3])
    assert stored.part(np.array([1])).carried == ()  # read where it is stored, not sent


def test_workers_and_a_scheduler_at_once_are_refused(monkeypatch):
    with pytest.raises(InputError, match="give one"):
        ClusterSpec.of(2, "tcp://127.0.0.1:1")
    monkeypatch.setenv("DASK_SCHEDULER_ADDRESS", "tcp://10.0.0.1:8786")
    assert ClusterSpec.of(None, None).address == "tcp://10.0.0.1:8786"
    assert ClusterSpec.of(2, None) == ClusterSpec(2, None)
    assert not ClusterSpec.of(0, None).distributed  # --workers 0: in this process, whatever the environment says


def refuse(path: str) -> None:
    raise InputError(path, "not a scan")


def test_a_task_s_input_error_reaches_the_user_as_it_was_raised(tmp_path):
    with cluster_module.engine(ClusterSpec(workers=1)) as engine:
        assert engine.slots == 1
        with pytest.raises(InputError) as info:
            engine.map(refuse, [str(tmp_path / "a.pcd")], "reading", enabled=False)
    assert info.value.message == f"{tmp_path / 'a.pcd'}: not a scan"


def test_frames_stored_where_a_worker_cannot_read_them_are_one_line(tmp_path):
    part = Frames([np.zeros((2, 3), np.float32)], None, False, stored=tmp_path / "gone").part(np.array([0]))
    with pytest.raises(InputError, match="cannot read the cached frames"):
        part.frames()


def test_a_scheduler_without_workers_is_one_line_not_a_wait(tmp_path, monkeypatch):
    monkeypatch.setattr(cluster_module, "CONNECT_TIMEOUT", 5)
    with cluster(tmp_path, workers=0) as address, cluster_module.engine(ClusterSpec(address=address)) as engine:
        with pytest.raises(cluster_module.ClusterError, match="no Dask scheduler with a worker"):
            engine.map(refuse, ["x"], "reading", enabled=False)


def test_the_consistency_profile_s_stretches_on_workers_score_as_in_this_process(sim, tmp_path, monkeypatch):
    """16 frames with a budget of 4 frames' cells (as 2,000 frames with 1.5 million): each stretch of each set of
    poses is a task on a worker, which maps the cells from the files in the folder given, and every view of every
    frame, the noise and the flags equal the in-process profile's."""
    scans = open_scans(sim / "velodyne")
    candidates = {name: read_trajectory(sim / f"{name}.txt", "kitti").poses for name in ("warm_start", "poses")}
    monkeypatch.setattr(profile_stretches, "MAX_CELLS", 4 * profile_cells.CELLS_PER_FRAME)
    here = cp.consistency_profiles(scans, candidates, planar=True)
    tasks = []
    sent = cluster_module.Engine.map
    monkeypatch.setattr(cluster_module.Engine, "map", lambda self, fn, items, *a, **k: tasks.extend(items)
                        or sent(self, fn, items, *a, **k))
    monkeypatch.setattr(profile_stretches, "_judged_here", None)  # nothing judged in this process
    with cluster(tmp_path) as address, cluster_module.engine(ClusterSpec(address=address)) as engine:
        there = cp.consistency_profiles(scans, candidates, planar=True, folder=tmp_path / "cells")
        held = engine.client.has_what()
        # without a folder the workers share, the stretches stay in this process
        assert profile_stretches.cluster_for(len(scans), 2, shared_folder=False) is None
    assert len(tasks) >= 4 and {name for name, _ in tasks} == set(candidates)  # two stretches or more, each set
    assert all(not keys for keys in held.values()), held  # what was sent to the workers is released
    (mine,) = (tmp_path / "cells").iterdir()  # this machine's folder in the shared one ...
    assert mine.name == socket.gethostname() and not list(mine.iterdir())  # ... and the cells removed from it
    for name in candidates:
        assert here[name].window > 0 and len(here[name].score) == 16
        for view in ("all", "past", "future"):
            np.testing.assert_array_equal(there[name].views_m[view], here[name].views_m[view])
        assert there[name].noise_m == here[name].noise_m and there[name].segments == here[name].segments


def test_a_local_cluster_no_larger_than_the_profile_s_threads_leaves_the_profile_here(sim, monkeypatch):
    """Tasks where the cluster runs more at once than this process would (2 sets of poses on 2 threads)."""
    scans = open_scans(sim / "velodyne")
    monkeypatch.setattr(profile_stretches, "MAX_CELLS", 4 * profile_cells.CELLS_PER_FRAME)
    monkeypatch.setattr(profile_stretches, "WORKERS", 2)
    with cluster_module.engine(ClusterSpec(workers=1)) as engine:
        assert profile_stretches.cluster_for(len(scans), 2, False) is None  # 1 worker, 2 threads here
        assert profile_stretches.cluster_for(len(scans), 1, False) is None  # 1 worker, 1 set of poses
        assert engine._client is None  # deciding started no cluster
    with cluster_module.engine(ClusterSpec(workers=3)):
        assert profile_stretches.cluster_for(len(scans), 2, False) is not None
        assert profile_stretches.cluster_for(2, 2, False) is None  # judged whole


@pytest.mark.parametrize("recipe", [True, False])
def test_workers_that_map_every_temporary_afresh_are_named(tmp_path, caplog, recipe):
    """Dask's nanny starts workers with MALLOC_TRIM_THRESHOLD_ set, which makes numpy's work 2-5 times slower; the
    run says so, unless the workers were started as the README says."""
    with cluster(tmp_path, workers=1, recipe=recipe) as address, \
            cluster_module.engine(ClusterSpec(address=address)) as engine:
        assert engine.slots == 1
    named = [r.getMessage() for r in caplog.records if "MALLOC_TRIM_THRESHOLD_" in r.getMessage()]
    assert len(named) == (0 if recipe else 1) and (recipe or "1 of 1 worker(s)" in named[0]), named


def test_a_local_cluster_s_workers_keep_glibc_s_adaptive_threshold(tmp_path):
    with cluster_module.engine(ClusterSpec(workers=1)) as engine:
        assert engine.client.run(cluster_module.fixed_mmap_threshold) == {
            address: False for address in engine.client.scheduler_info()["workers"]}


def test_cells_a_worker_cannot_read_are_one_line(tmp_path):
    with pytest.raises(InputError, match="cannot be read there.*storage every worker sees"):
        StoredCells(tmp_path / "elsewhere", 10, 0.1).open()
