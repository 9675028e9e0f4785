"""Run the dm2 benchmarks: dataset x method cases, each in a fresh subprocess.

    python benchmarks/run.py [--quick | --set quick|freiburg|full] [--only NAME ...] [--out DIR] [--epochs N]

Writes ``<out>/YYYY-MM-DD-<set>.json`` (every number and setting), ``<out>/latest-<set>.md`` (the table the
README includes) and ``<out>/scaling-<set>.png`` (time and memory against frames). Run folders and logs
go to ``$DM2_BENCH_CACHE`` (default ``~/.cache/dm2/bench``), never into the repository. Not part of the
test suite.
"""

from __future__ import annotations

import argparse
import copy
import datetime
import fnmatch
import importlib.metadata
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_cases import METHODS, command_available, run_case  # noqa: E402
from bench_datasets import DATASETS, PUBLISHED, REPO, Env, Skip  # noqa: E402
from bench_report import add_derived, loop_closed_case, markdown, scaling_plot, warm_start_case  # noqa: E402

ABLATIONS = ["no consistency", "temporal batches", "L-Net poses"]
#: the loss switches from the pose-graph start (3D data only: on planar data refine starts from the prepared poses)
ABLATIONS_3D = ["graph start", "no dense", "dense + first-order", "dense + BCE", "dense + consistency",
                "prepared start"]
ALL = [m for m in METHODS if m not in ABLATIONS_3D and m not in ("+ BCE", "+ consistency", "point Chamfer",
                                                                "paper losses", "hessian refine",
                                                                "hessian gtsam")]
BASELINES = ["gtsam", "g2o", "multiway"]

#: set -> (dataset -> methods), epochs (None: the default config), per-case timeout (s)
SETS: dict[str, dict] = {
    "quick": {
        "cases": {
            "sim-2d-500": ["dm2 refine", *ABLATIONS, *BASELINES],
            "sim-3d-200": ["dm2 refine"],
            "sim-3d-500": ["dm2 refine", "gtsam"],
            "kitti00-6": ["dm2 refine", "gtsam", "multiway"],
            "deepmapping2d": ["dm2 refine", "gtsam"],
            "redkitchen": ["dm2 refine", "gtsam"],
        },
        "epochs": 3,
        "timeout": 600,
    },
    "freiburg": {
        "cases": {"aces": ["dm2 refine", *BASELINES], "intel": ["dm2 refine", *BASELINES],
                  "fr-clinic": ["dm2 refine", "gtsam"]},
        "epochs": None,
        "timeout": 3600,
    },
    # where 2D scan matching and loop closure break: corridors, degraded odometry (issue: 2D laser logs that break)
    "corridors": {
        "cases": {"corridors-560": ["dm2 refine", "gtsam"], "aces-degraded": ["dm2 refine", "gtsam"],
                  "intel-degraded": ["dm2 refine", "gtsam"], "hospital-1000": ["dm2 refine", "gtsam"]},
        "epochs": None,
        "timeout": 3600,
    },
    "freiburg-ablations": {
        "cases": {"aces": ["L-Net poses", "no consistency"]},
        "epochs": None,
        "timeout": 3600,
    },
    "3d": {
        "cases": {name: ["dm2 refine", "from truth", "gtsam", "g2o"]
                  for name in ("sim-3d-500", "sim-3d-2000", "sim-realmap", "sim-room-walk", "sim-room-across",
                               "sim-room-rpy", "redkitchen", "kitti00-6", "balm")},
        "epochs": None,
        "timeout": 3600,
    },
    # real depth frames: the icp warm start of both halves of RedKitchen, and its reference poses plus a smooth
    # drift as the input (refine must lower APE and keep RPE per frame within 1.5 mm of the input's), refined from
    # the undrifted reference too ("from truth": whether the frames leave the reference where it is); the same
    # drift on a simulated Kinect-like camera, whose truth is exact
    "depth": {
        "cases": {"redkitchen": ["dm2 refine", "gtsam"], "redkitchen-500": ["dm2 refine", "gtsam"],
                  "redkitchen-drift": ["dm2 refine", "from truth"], "redkitchen-drift-100hz": ["dm2 refine"],
                  "redkitchen-0-drift": ["dm2 refine", "from truth"], "sim-room-walk-drift": ["dm2 refine"],
                  "sim-room-hall": ["dm2 refine", "gtsam"]},
        "epochs": None,
        "timeout": 3600,
    },
    "3d-ablations": {
        "cases": {name: ["dm2 refine", *ABLATIONS_3D, "gtsam"]
                  for name in ("sim-3d-500", "balm")},
        "epochs": None,
        "timeout": 3600,
    },
    # the registrations' information for the pose graph: isotropic (default) against their own Hessian
    "3d-information": {
        "cases": {name: ["dm2 refine", "hessian refine", "gtsam", "hessian gtsam"]
                  for name in ("sim-3d-500", "sim-realmap", "redkitchen", "kitti00-6", "balm")},
        "epochs": None,
        "timeout": 3600,
    },
    "scale": {
        "cases": {"sim-3d-500": ["dm2 refine"], "sim-3d-2000": ["dm2 refine"], "sim-3d-5000": ["dm2 refine"]},
        "epochs": None,
        "timeout": 3600,
    },
    # the paper's largest scale (NeBula, about 38,000 scans) on one machine: dm2 simulate --frames N --seed 11
    # (3D LiDAR and planar laser), refine and gtsam on the same preparation; 3D 40,000 last (the longest)
    "huge": {
        "cases": {name: ["dm2 refine", "gtsam"]
                  for name in ("huge-2d-10000", "huge-3d-10000", "huge-2d-20000", "huge-3d-20000", "huge-2d-40000",
                               "huge-3d-40000")},
        "epochs": None,
        "timeout": 3 * 3600,
        "targets": {"s_per_frame": 0.05, "peak_rss_mb": 2048, "at_frames": 20000},
    },
    # the same at 2,000 frames (the size the huge set's defaults were measured at; minutes)
    "huge-small": {
        "cases": {"huge-2d-2000": ["dm2 refine", "gtsam"], "huge-3d-2000": ["dm2 refine", "gtsam"]},
        "epochs": None,
        "timeout": 3600,
        "targets": {"s_per_frame": 0.05, "peak_rss_mb": 2048, "at_frames": 20000},
    },
    "full": {
        "cases": {name: ALL[1:] for name in DATASETS},
        "epochs": None,
        "timeout": 6 * 3600,
    },
}


def selected(dataset: str, method: str, only: list[str]) -> bool:
    if not only:
        return True
    names = (dataset, method, f"{dataset}:{method}")
    return any(fnmatch.fnmatch(n, p) for p in only for n in names)


def machine() -> dict:
    def version(pkg: str) -> str | None:
        try:
            return importlib.metadata.version(pkg)
        except importlib.metadata.PackageNotFoundError:
            return None

    return {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(),
            "torch": version("torch"), "open3d": version("open3d"), "gtsam": version("gtsam"),
            "loadavg_start": os.getloadavg()}


def commit() -> str:
    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True).stdout.strip()

    sha = git("rev-parse", "--short", "HEAD") or "unknown"
    return sha + ("+dirty" if git("status", "--porcelain", "--untracked-files=no") else "")


def write_results(results: dict, out: Path, t_start: float, complete: bool) -> dict:
    """Derived numbers and warm-start rows on a copy; write the JSON, the Markdown table and the plot."""
    from dm2_backend.runtime.atomic import atomic_write

    r = copy.deepcopy(results)
    r["complete"] = complete
    cases = r["cases"]
    add_derived(cases)
    for name, ds in r["datasets"].items():
        if ds.get("skipped") or not any(c["dataset"] == name for c in cases):
            continue
        first = next(i for i, c in enumerate(cases) if c["dataset"] == name)
        stages = [warm_start_case(name, cases), loop_closed_case(name, cases)]
        cases[first:first] = [c for c in stages if c is not None]
    r["machine"]["loadavg_end"] = os.getloadavg()
    r["wall_s"] = time.perf_counter() - t_start
    out.mkdir(parents=True, exist_ok=True)
    json_path = out / f"{r['date']}-{r['set']}.json"
    r["json"] = str(json_path.relative_to(REPO) if json_path.is_relative_to(REPO) else json_path)
    plot = scaling_plot(r, out / f"scaling-{r['set']}.png")
    r["scaling_plot"] = plot.name if plot else None
    with atomic_write(json_path) as fh:
        json.dump(r, fh, indent=2, default=str)
    with atomic_write(out / f"latest-{r['set']}.md") as fh:
        fh.write(markdown(r))
    return r


def render(path: Path) -> int:
    from dm2_backend.runtime.atomic import atomic_write

    r = json.loads(path.read_text())
    with atomic_write(path.parent / f"latest-{r['set']}.md") as fh:
        fh.write(markdown(r))
    scaling_plot(r, path.parent / f"scaling-{r['set']}.png")
    print(markdown(r))
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="The ~10-minute set (few epochs).")
    ap.add_argument("--set", dest="set_name", choices=list(SETS), default=None,
                    help="A named set (quick, freiburg: ACES + Intel against the baselines, full).")
    ap.add_argument("--only", nargs="+", default=[], metavar="NAME",
                    help="Only these datasets / methods / dataset:method (shell patterns).")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    ap.add_argument("--epochs", type=int, default=None, help="Override the set's optimisation epochs.")
    ap.add_argument("--timeout", type=float, default=None, help="Seconds per case (default per set).")
    ap.add_argument("--list", action="store_true", help="List the cases and exit.")
    ap.add_argument("--verbose", action="store_true", help="Show dm2 simulate output.")
    ap.add_argument("--render", type=Path, default=None, metavar="JSON",
                    help="Only rewrite the Markdown table and the plot of a results file.")
    args = ap.parse_args(argv)
    if args.render is not None:
        return render(args.render)

    set_name = args.set_name or ("quick" if args.quick else "full")
    spec = SETS[set_name]
    epochs = args.epochs if args.epochs is not None else spec["epochs"]
    timeout = args.timeout or spec["timeout"]
    plan = {d: [m for m in ms if selected(d, m, args.only)] for d, ms in spec["cases"].items()}
    plan = {d: ms for d, ms in plan.items() if ms}
    if args.list:
        for d, ms in plan.items():
            print(f"{d}: warm start, {', '.join(ms)}")
        return 0
    if not plan:
        print("no case matches --only", file=sys.stderr)
        return 2
    label = set_name + ("-partial" if args.only else "")
    date = datetime.date.today().isoformat()
    cache = Path(os.environ.get("DM2_BENCH_CACHE", Path.home() / ".cache" / "dm2" / "bench"))
    runs = cache / "runs" / f"{datetime.datetime.now():%Y%m%d-%H%M%S}-{label}"
    tmp = Path(tempfile.mkdtemp(prefix="dm2-bench-"))
    env = Env(cache=cache, tmp=tmp, quiet=not args.verbose)
    wants_baseline = any(m in BASELINES for ms in plan.values() for m in ms)
    has_baseline = command_available("baseline") if wants_baseline else True
    results: dict = {
        "set": label, "date": date, "commit": commit(), "dm2_version": importlib.metadata.version("dm2"),
        "machine": machine(), "settings": {"epochs": epochs, "timeout_s": timeout, "only": args.only,
                                           "config": "default (dm2_backend/config/__init__.py) + method overrides"},
        **({"targets": spec["targets"]} if "targets" in spec else {}),
        "methods": {m.name: {"command": m.command, "config": m.config, "description": m.description}
                    for m in METHODS.values()},
        "datasets": {}, "cases": [], "runs": str(runs),
    }
    t_start = time.perf_counter()
    try:
        for name, methods in plan.items():
            ds = DATASETS[name]
            entry = {"description": ds.description, "metric": ds.metric, "real": ds.real,
                     "published": PUBLISHED.get(name, []), "note": ds.note}
            results["datasets"][name] = entry
            try:
                t = time.perf_counter()
                inputs = ds.load(env)
                entry.update(frames=inputs.frames, inputs=inputs.info, load_s=time.perf_counter() - t)
            except Skip as exc:
                entry["skipped"] = str(exc)
                print(f"[{name}] skipped: {exc}", flush=True)
                continue
            except Exception as exc:  # a broken dataset must not stop the others
                entry["skipped"] = f"could not load: {exc!r}"[:300]
                print(f"[{name}] could not load: {exc!r}", flush=True)
                continue
            for method in methods:
                m = METHODS[method]
                if m.command and m.command[0] == "baseline" and not has_baseline:
                    case = {"status": "not available", "reason": "dm2 baseline is not in this checkout"}
                else:
                    folder = runs / name / method.replace(" ", "_")
                    case = run_case(m, inputs.args, folder, runs / name / "cache", epochs, timeout)
                case = {"dataset": name, "method": method, **case}
                results["cases"].append(case)
                detail = case.get("metrics", {}) if case["status"] == "ok" else case.get("reason", "")
                wall = case.get("wall_s", 0.0)
                print(f"[{name}] {method}: {case['status']} {wall:.1f} s {detail}", flush=True)
                write_results(results, args.out, t_start, complete=False)  # partial results survive a crash
            shutil.rmtree(runs / name / "cache", ignore_errors=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    final = write_results(results, args.out, t_start, complete=True)
    print(markdown(final))
    plot = f", {final['scaling_plot']}" if final["scaling_plot"] else ""
    print(f"wrote {final['json']}, latest-{label}.md{plot} in {final['wall_s']:.0f} s; run folders in {runs}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
