"""``dm2 baseline`` as functions: a run folder from scans (same preparation as ``dm2 refine``), or an
existing g2o file optimised."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from dm2_backend.baselines.methods import METHODS
from dm2_backend.baselines.multiway import multiway
from dm2_backend.baselines.solvers import solve
from dm2_backend.config.schema import RunConfig
from dm2_backend.evaluation import plots
from dm2_backend.evaluation.evaluate import EvalOptions, evaluate
from dm2_backend.evaluation.report import estimate_cautions, run_metrics
from dm2_backend.formats import write_trajectory
from dm2_backend.formats.g2o import read_g2o, write_g2o
from dm2_backend.kernel.graph_edges import InformationModel, build_graph
from dm2_backend.kernel.solver_options import SolverOptions
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.pipeline import outputs
from dm2_backend.pipeline.inputs import RunInputs
from dm2_backend.pipeline.run_report import RunReport
from dm2_backend.pipeline.run_writer import write_run
from dm2_backend.prepare.steps import Prepared, prepare
from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.runtime.errors import InputError
from dm2_backend.runtime.memory import peak_rss_mb


def baseline(method: str, inputs: RunInputs, cfg: RunConfig, out: Path, cache_dir: Path | None,
             options: SolverOptions, progress: bool = True, started: float | None = None) -> RunReport:
    """Prepare (cached, shared with ``dm2 refine``), run the baseline, write the run folder. ``started``:
    when the command started (``time.perf_counter``): the report's total then counts it all."""
    if method not in METHODS:
        raise InputError(None, f"unknown baseline {method!r}; choices: {', '.join(METHODS)}")
    options.check()
    t_start = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    prep = prepare(inputs.scans, inputs.given, cfg, cache_dir, progress)
    stages = prep.stages.copy()
    extra: dict = {}
    with stages.stage("optimise"):
        final, extra["baseline"], files = _solve(method, prep, options, out)
    return write_run(out, cfg, inputs, prep, final, method, stages, extra, files=files,
                     started=t_start if started is None else started)


def _solve(method: str, prep: Prepared, options: SolverOptions, out: Path) -> tuple[np.ndarray, dict, list[str]]:
    """The baseline's poses, its summary for the report and the files it wrote."""
    if method == "icp":
        return prep.warm_start, {"solver": f"warm start ({prep.resolved['warm_start'].name})"}, []
    if method == "multiway":
        result = multiway(prep.frames, prep.initial, prep.topology, prep.pairwise, options)
        return result.poses, result.summary(), []
    model = InformationModel.from_resolved(prep.resolved)  # isotropic unless the registration asks
    graph = build_graph(prep.frames, prep.initial, prep.topology, prep.pairwise, model)
    write_g2o(graph, out / "graph.g2o")
    result = solve(method, graph, options)
    return result.poses, {**result.summary(), "graph": "graph.g2o", "nodes": len(graph), "edges": len(graph.edges),
                          **graph.summary()}, ["graph.g2o"]


def optimise_file(method: str, path: Path, out: Path, options: SolverOptions, gt: Trajectory | None = None,
                  started: float | None = None, information: str = "file") -> dict:
    """Optimise a g2o file; writes ``poses.g2o`` (optimised vertices, same edges), ``poses_kitti.txt``,
    ``poses.npy``, ``trajectory.png`` and ``report.json``. ``gt``: one pose per vertex (in id order); the
    report then holds the metrics of the file's vertices (``initial_metrics``) and of the result."""
    t_start = time.perf_counter()
    graph = read_g2o(path, information, warn=method != "gtsam")  # GTSAM's warning says how it weighs them
    t_read = time.perf_counter() - t_start
    if gt is not None and len(gt) != len(graph):
        raise InputError(gt.meta.get("source"), f"{len(gt)} ground-truth poses for the {len(graph)} vertices of "
                                                f"{path}: --gt with --graph needs one pose per vertex, in id order")
    result = solve(method, graph, options)
    out.mkdir(parents=True, exist_ok=True)
    write_g2o(replace(graph, poses=result.poses), out / "poses.g2o")
    traj = Trajectory(result.poses, planar=graph.planar)
    write_trajectory(traj, out / "poses_kitti.txt", "kitti")
    with atomic_write(out / "poses.npy", "wb") as fh:
        np.save(fh, result.poses)
    plots.plot_trajectories(out / "trajectory.png", None, {"initial": graph.poses[:, :3, 3],
                                                           method: result.poses[:, :3, 3]})
    report = {
        "method": method,
        "graph": str(path),
        "nodes": len(graph),
        "edges": int(len(graph.edges)),
        "planar": graph.planar,
        **result.summary(),
        "graph_meta": graph.summary(),
        "timings": {"read": t_read, "optimise": result.seconds,
                    "total": time.perf_counter() - (t_start if started is None else started)},
        "peak_rss_mb": peak_rss_mb(),
        "files": ["poses.g2o", "poses_kitti.txt", "poses.npy", "trajectory.png", "report.json"],
    }
    if gt is not None:
        report.update(graph_metrics(gt, graph.poses, result.poses, graph.planar))
    outputs.write_report(out / "report.json", report)
    return report


def graph_metrics(gt: Trajectory, initial: np.ndarray, final: np.ndarray, planar: bool) -> dict:
    """``initial_metrics``, ``metrics`` and ``cautions`` of a graph's vertices against ``gt`` (by index: the
    vertices carry no stamps)."""
    options = EvalOptions(by_index=True)
    before = evaluate(Trajectory(initial, planar=planar), gt=gt, options=options)
    after = evaluate(Trajectory(final, planar=planar), gt=gt, options=options)
    return {"initial_metrics": run_metrics(before), "metrics": run_metrics(after),
            "cautions": estimate_cautions(after)}
