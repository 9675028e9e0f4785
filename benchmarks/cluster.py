"""The preparation's registration in this process and as tasks on a local Dask cluster of 1 and N workers.

    python benchmarks/cluster.py [--frames 300] [--workers 1 2] [--planar] [--refine | --profile]
                                 [--out benchmarks/results]

A ``dm2 simulate`` sequence is prepared once (frames, warm start, place recognition) into a cache; then the
registration runs on the same frames in-process and on each cluster (started before the clock, its start-up timed
apart), and every answer is compared with the in-process one. The per-task overhead is the mean time of 200 empty
tasks sent at once. With ``--refine``: the whole ``dm2 refine`` instead, in a fresh process and cache for each
(``--workers 0`` and each N), with its APE, map entropy, the preparation's stages and the peak RSS of every process
(sampled every 0.2 s). With ``--profile``: the consistency profile of the warm start and the truth (its stretches
as tasks; a sequence of more than 732 frames is judged in stretches), in-process (two sets of poses on two threads)
and on each cluster joined by address with the cells in a shared folder (as on several machines), every view
compared with the in-process one. Writes
``<out>/YYYY-MM-DD-cluster[-refine|-profile][-planar]-N.json`` (every number, the command, the
machine, the load). Not part of the test suite.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import dask
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_cases import run_process  # noqa: E402
from run import commit, machine  # noqa: E402

from dm2_backend.algorithms.common import repeatable_registration  # noqa: E402
from dm2_backend.config import load as load_config  # noqa: E402
from dm2_backend.evaluation.consistency_profile import consistency_profiles  # noqa: E402
from dm2_backend.formats import open_scans  # noqa: E402
from dm2_backend.formats.registry import read_trajectory  # noqa: E402
from dm2_backend.plugins.registry import load as load_plugin  # noqa: E402
from dm2_backend.prepare.steps import prepare, starting_poses  # noqa: E402
from dm2_backend.runtime import cluster  # noqa: E402
from dm2_backend.simulate.sequence import SimSettings, generate  # noqa: E402


def nothing(x: int) -> int:
    return x


def registration(prep, progress: bool = False):
    plugin = load_plugin("dm2.registration", prep.resolved["registration"].name)(progress=progress)
    t0 = time.perf_counter()
    with repeatable_registration():  # as the preparation runs it
        pair = plugin.run(prep.frames, starting_poses(prep.topology, prep.warm_start), prep.topology)
    return pair, time.perf_counter() - t0


def refine_row(sim: Path, root: Path, workers: int) -> dict:
    """``dm2 refine --workers N`` in a fresh process and cache: its report's accuracy and timings, and each
    process's peak RSS (MiB)."""
    out = root / f"run-{workers}"
    cmd = [sys.executable, "-m", "dm2_backend", "refine", "-s", str(sim / "velodyne"),
           "-p", str(sim / "warm_start.txt"), "--gt", str(sim / "poses.txt"), "-o", str(out),
           "--cache-dir", str(root / f"cache-{workers}"), "-q", "--workers", str(workers)]
    proc = run_process(cmd, root / f"log-{workers}.txt", timeout=3600)
    report = json.loads((out / "report.json").read_text())
    timings, peaks = report["timings"], proc["peak_rss_mb_per_process"]
    return {"mode": f"--workers {workers}", "returncode": proc["returncode"], "wall_s": proc["wall_s"],
            "preparation_s": sum(timings.get(k, 0.0) for k in ("frames", "warm_start", "place_recognition",
                                                                 "registration")),
            "timings": timings, "ape_trans_rmse_m": report["metrics"].get("ape_trans_rmse_m"),
            "map_entropy": report["metrics"].get("map_entropy"), "peak_rss_mb_per_process": peaks,
            "peak_rss_mb_dm2": peaks.get("dm2"),
            "peak_rss_mb_workers_max": max([mb for k, mb in peaks.items() if k != "dm2"], default=0.0)}


def registration_rows(sim: Path, root: Path, workers: list[int]) -> tuple[list[dict], int]:
    """The registration in-process and on each local cluster, on frames prepared once; the pairs."""
    prep = prepare(open_scans(sim / "velodyne"), read_trajectory(sim / "warm_start.txt"), load_config(None, {}),
                   root / "cache", progress=False)
    single, seconds = registration(prep)
    rows = [{"mode": "in-process", "seconds": seconds}]
    for n in workers:
        t0 = time.perf_counter()
        with cluster.engine(cluster.ClusterSpec(workers=n)) as engine:
            assert engine.slots == n  # started here, not in the clock below
            started = time.perf_counter() - t0
            t1 = time.perf_counter()
            engine.map(nothing, range(200), "overhead", enabled=False)
            overhead = (time.perf_counter() - t1) / 200
            pair, seconds = registration(prep)
        rows.append({"mode": f"{n} worker(s)", "seconds": seconds, "cluster_start_s": started,
                     "task_overhead_ms": 1000 * overhead,
                     "max_relative_difference": float(np.abs(pair.relative - single.relative).max()),
                     "same_valid": bool((pair.valid == single.valid).all())})
    one = next((r["seconds"] for r in rows if r["mode"] == "1 worker(s)"), None)
    for r in rows:
        r["speed_vs_1_worker"] = None if one is None else one / r["seconds"]
    return rows, int((prep.topology.groups >= 0).sum())


def profile_rows(sim: Path, root: Path, workers: list[int]) -> list[dict]:
    """The consistency profile in-process and as tasks on each cluster, joined by its address with the cells in a
    folder the workers share, as on several machines (a local ``--workers N`` on these cores keeps the profile in
    its process: ``profile_stretches.cluster_for``); the clusters started before the clock."""
    from distributed import LocalCluster

    scans = open_scans(sim / "velodyne")
    candidates = {name: read_trajectory(sim / f"{name}.txt").poses for name in ("warm_start", "poses")}
    t0 = time.perf_counter()
    single = consistency_profiles(scans, candidates, planar=scans.planar)
    rows = [{"mode": "in-process", "seconds": time.perf_counter() - t0}]
    for n in workers:
        with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}), \
                LocalCluster(n_workers=n, threads_per_worker=1, dashboard_address=None) as local, \
                cluster.engine(cluster.ClusterSpec(address=local.scheduler_address)) as engine:
            assert engine.slots == n
            t1 = time.perf_counter()
            profiles = consistency_profiles(scans, candidates, planar=scans.planar, folder=root / "cells")
            seconds = time.perf_counter() - t1
        rows.append({"mode": f"{n} worker(s)", "seconds": seconds,
                     "same_views": all(np.array_equal(profiles[k].views_m[v], single[k].views_m[v], equal_nan=True)
                                       for k in candidates for v in single[k].views_m)})
    one = next((r["seconds"] for r in rows if r["mode"] == "1 worker(s)"), None)
    for r in rows:
        r["speed_vs_1_worker"] = None if one is None else one / r["seconds"]
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--planar", action="store_true")
    ap.add_argument("--refine", action="store_true", help="the whole dm2 refine per worker count (0: in-process)")
    ap.add_argument("--profile", action="store_true", help="the consistency profile instead of the registration")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results")
    args = ap.parse_args(argv)
    load = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        sim = Path(tmp) / "sim"
        generate(SimSettings(frames=args.frames, planar=args.planar), sim, progress=False)
        if args.refine:
            rows, pairs = [refine_row(sim, Path(tmp), n) for n in [0, *args.workers]], None
        elif args.profile:
            rows, pairs = profile_rows(sim, Path(tmp), args.workers), None
        else:
            rows, pairs = registration_rows(sim, Path(tmp), args.workers)
    doc = {"command": "python benchmarks/cluster.py " + " ".join(argv if argv is not None else sys.argv[1:]),
           "commit": commit(), "machine": machine(), "load_before": load, "load_after": os.getloadavg(),
           "frames": args.frames, "planar": args.planar, "pairs": pairs, "rows": rows}
    args.out.mkdir(parents=True, exist_ok=True)
    kind = ("-refine" if args.refine else "-profile" if args.profile else "") + ("-planar" if args.planar else "")
    name = f"{datetime.date.today()}-cluster{kind}-{args.frames}.json"
    (args.out / name).write_text(json.dumps(doc, indent=1))
    for r in rows:
        print(json.dumps({k: v for k, v in r.items() if k not in ("timings", "peak_rss_mb_per_process")}))
    print(f"wrote {args.out / name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
