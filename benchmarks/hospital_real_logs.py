"""ACES and Intel rewritten as the hospital's scanner would have written them (issue 27's hard cases): each trait
alone and all together, and the clean rewrite; the odometry's and the fused warm start's mean translational
relation error against the log's own ``.relations`` (the Freiburg metric, :mod:`dm2_backend.evaluation.relations`).

    .venv/bin/python benchmarks/hospital_real_logs.py --out /tmp/hospital-real

writes ``benchmarks/results/hospital-real-logs.{json,md}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from dm2_backend.evaluation.relations import load_relations, relations_error
from dm2_backend.formats.carmen import open_carmen_scans
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.plugins.warm_start_icp import IcpWarmStart
from dm2_backend.prepare.frames import load_frames
from dm2_backend.simulate.hospital import HospitalTraits
from dm2_backend.simulate.hospital_rewrite import write_rewritten

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "carmen"
RESULTS = Path(__file__).resolve().parent / "results"


def cases() -> dict[str, HospitalTraits]:
    """The clean rewrite, each trait alone and all together (the laser's mount stays 0: see the module;
    ``original``, not here, is the source log as it is)."""
    full = dataclasses.replace(HospitalTraits(), laser_offset=0.0)
    plain = full.plain()
    return {"clean": plain, "interlaced": dataclasses.replace(plain, interlaced=True),
            "max-range codes": dataclasses.replace(plain, code_share=full.code_share,
                                                   declared_max_range=full.declared_max_range),
            "long returns": dataclasses.replace(plain, long_share=full.long_share),
            "pauses": dataclasses.replace(plain, gaps=full.gaps), "all": full}


def warm_start_errors(seq, rel, windows: str = "auto", save: Path | None = None, weigh: str = "auto") -> dict:
    """The odometry's and the fused warm start's mean relation errors (m), the warm start's time and windows;
    ``save``: also write the warm start's poses there (``.npy``, for ``benchmarks/hospital_closures.py``); ``weigh``:
    the warm start's option of that name."""
    odometry = seq.trajectories["odometry"]
    t0 = time.perf_counter()
    ws = IcpWarmStart(progress=False, windows=windows, weigh=weigh)
    poses = ws.run(load_frames(seq, 1024, None, 0, False), odometry)
    seconds = time.perf_counter() - t0
    if save is not None:
        np.save(save, poses)

    def error(p) -> float:
        return relations_error(Trajectory(p, seq.timestamps, planar=True), rel).stats["trans_mean"]

    from_odometry = [v for v in ws.verdicts if v.source == "odometry"]
    return {"scans": len(seq), "relations": len(rel), "odometry": error(odometry.poses), "warm_start": error(poses),
            "weighed": ws.report["match_weights"]["weighed"],
            "seconds": round(seconds, 1), "windows": len(ws.verdicts), "windows_from_odometry": len(from_odometry)}


def measure(log: Path, relations: Path, out: Path, name: str, traits: HospitalTraits | None, count: int | None = None,
            windows: str = "auto", weigh: str = "auto") -> dict:
    """Rewrite (``traits``; None: the original log as it is), read, warm-start: :func:`warm_start_errors`."""
    if traits is None:
        seq = open_carmen_scans(log)
        if count is not None:
            raise ValueError("the original log is measured whole")
        out.mkdir(parents=True, exist_ok=True)
        return warm_start_errors(seq, load_relations(relations), windows, out / f"{name}.warm.npy", weigh)
    write_rewritten(out, log, relations, traits, name, count=count)
    return warm_start_errors(open_carmen_scans(out / f"{name}.clf"), load_relations(out / f"{name}.relations"),
                             windows, out / f"{name}.warm.npy", weigh)


def table(results: dict) -> str:
    rows = ["| log | case | scans | odometry (m) | warm start (m) | windows from odometry | warm start s |",
            "|---|---|---:|---:|---:|---:|---:|"]
    for log, by_case in results.items():
        for case, r in by_case.items():
            mark = "" if r["warm_start"] <= r["odometry"] else " (worse)"
            rows.append(f"| {log} | {case} | {r['scans']} | {r['odometry']:.4f} | {r['warm_start']:.4f}{mark} | "
                        f"{r['windows_from_odometry']} of {r['windows']} | {r['seconds']} |")
    return "\n".join(rows) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--logs", nargs="+", default=["aces", "intel"])
    parser.add_argument("--cases", nargs="+", default=["original", *cases()],
                        help="original (the FLASER log as it is) and the rewrites; measured rows replace the results "
                             "file's, the others stay")
    parser.add_argument("--count", type=int, default=None, help="only the first COUNT scans of each log")
    args = parser.parse_args()
    stem = "hospital-real-logs" + (f"-{args.count}" if args.count else "")
    path = RESULTS / f"{stem}.json"
    results: dict = json.loads(path.read_text()) if path.exists() else {}
    order = ["original", *cases()]
    for log in args.logs:
        for case in args.cases:
            r = measure(DATA / f"{log}.clf.bz2", DATA / f"{log}.relations", args.out / log, case.replace(" ", "-"),
                        cases().get(case), args.count)
            results.setdefault(log, {})[case] = r
            results[log] = {c: results[log][c] for c in order if c in results[log]}
            print(log, case, r, flush=True)
            RESULTS.mkdir(exist_ok=True)
            path.write_text(json.dumps(results, indent=2) + "\n")
    (RESULTS / f"{stem}.md").write_text(
        f"# ACES and Intel rewritten hospital-like (issue 27)\n\nGenerated by `python benchmarks/hospital_real_logs.py"
        f"{f' --count {args.count}' if args.count else ''}`: mean translational relation error against each log's "
        f".relations.\n\n" + table(results))


if __name__ == "__main__":
    main()
