"""The preparation's registration in this process and as tasks on a local Dask cluster of 1 and N workers.

    python benchmarks/cluster.py [--frames 300] [--workers 1 2] [--planar] [--out benchmarks/results]

A ``dm2 simulate`` sequence is prepared once (frames, warm start, place recognition) into a cache; then the
registration runs on the same frames in-process and on each cluster (started before the clock, its start-up timed
apart), and every answer is compared with the in-process one. The per-task overhead is the round trip of 200 empty
tasks. Writes ``<out>/YYYY-MM-DD-cluster[-planar]-N.json`` (every number, the command, the machine, the load).
Not part of the test suite.
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

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from run import commit, machine  # noqa: E402

from dm2_backend.config import load as load_config  # noqa: E402
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
    pair = plugin.run(prep.frames, starting_poses(prep.topology, prep.warm_start), prep.topology)
    return pair, time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--planar", action="store_true")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        sim = Path(tmp) / "sim"
        generate(SimSettings(frames=args.frames, planar=args.planar), sim, progress=False)
        scans = open_scans(sim / "velodyne")
        given = read_trajectory(sim / "warm_start.txt")
        prep = prepare(scans, given, load_config(None, {}), Path(tmp) / "cache", progress=False)
        pairs = int((prep.topology.groups >= 0).sum())
        single, seconds = registration(prep)
        rows = [{"mode": "in-process", "seconds": seconds}]
        for n in args.workers:
            t0 = time.perf_counter()
            with cluster.engine(cluster.ClusterSpec(workers=n)) as engine:
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
    doc = {"command": "python benchmarks/cluster.py " + " ".join(argv if argv is not None else sys.argv[1:]),
           "commit": commit(), "machine": machine(), "load_before": os.getloadavg(),
           "frames": args.frames, "planar": args.planar, "pairs": pairs, "rows": rows}
    args.out.mkdir(parents=True, exist_ok=True)
    name = f"{datetime.date.today()}-cluster{'-planar' if args.planar else ''}-{args.frames}.json"
    (args.out / name).write_text(json.dumps(doc, indent=1))
    for r in rows:
        print(json.dumps(r))
    print(f"wrote {args.out / name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
