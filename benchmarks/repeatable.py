"""Does a dm2 run give the same poses every time? The same command run N times, each in a fresh cache.

    python benchmarks/repeatable.py [--runs 2] [--method "baseline gtsam"] [--out benchmarks/results] -- ARGS...

``ARGS`` are the run's inputs (``-s FOLDER --warm-start icp``, say); without them the 7-Scenes RedKitchen frames
0-499 of ``../shared/data/depth3d`` from the ``icp`` warm start. Reports, for each run, the preparation's stages
(s) and the largest difference of its poses (``poses.npy``) and of its warm start (``warm_start.npy``) from the
first run's (0.0: the same bits). Writes ``<out>/YYYY-MM-DD-repeatable-NAME.json`` (commit, machine, load). Not
part of the test suite.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_cases import run_process  # noqa: E402
from run import commit, machine  # noqa: E402

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
PREPARATION = ("frames", "warm_start", "place_recognition", "registration")


def one_run(method: list[str], inputs: list[str], root: Path, index: int) -> dict:
    out = root / f"run-{index}"
    cmd = [sys.executable, "-m", "dm2_backend", *method, *inputs, "-o", str(out), "--cache-dir",
           str(root / f"cache-{index}"), "-q"]
    proc = run_process(cmd, root / f"log-{index}.txt", timeout=3600)
    if proc["returncode"] != 0:
        raise SystemExit(f"run {index} failed: {(root / f'log-{index}.txt').read_text()[-2000:]}")
    timings = json.loads((out / "report.json").read_text())["timings"]
    return {"wall_s": proc["wall_s"], "stages_s": {k: timings.get(k) for k in PREPARATION},
            "poses": np.load(out / "poses.npy"), "warm": np.load(out / "warm_start.npy")
            if (out / "warm_start.npy").exists() else None}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    inputs = argv[argv.index("--") + 1:] if "--" in argv else []
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--method", default="baseline gtsam")
    ap.add_argument("--name", default="redkitchen")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results")
    args = ap.parse_args(argv[:argv.index("--")] if "--" in argv else argv)
    if not inputs:
        folder = DATA / "depth3d" / "redkitchen_000-499"
        if not folder.is_dir():
            raise SystemExit(f"{folder}: not here (give the run's inputs after --)")
        inputs = ["-s", str(folder), "--warm-start", "icp"]
    load = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        runs = [one_run(args.method.split(), inputs, Path(tmp), i) for i in range(args.runs)]
    first = runs[0]
    rows = [{"run": i, "wall_s": r["wall_s"], "stages_s": r["stages_s"],
             "poses_max_difference": float(np.abs(r["poses"] - first["poses"]).max()),
             "warm_start_max_difference": None if r["warm"] is None else float(np.abs(r["warm"] - first["warm"]).max())}
            for i, r in enumerate(runs)]
    doc = {"command": "python benchmarks/repeatable.py " + " ".join(argv), "commit": commit(), "machine": machine(),
           "load_before": load, "load_after": os.getloadavg(), "method": args.method, "inputs": inputs, "rows": rows}
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / f"{datetime.date.today()}-repeatable-{args.name}.json"
    path.write_text(json.dumps(doc, indent=1))
    for r in rows:
        print(json.dumps(r))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
