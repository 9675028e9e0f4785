"""Methods and running one dataset x method case in a fresh ``dm2`` subprocess (its own peak memory)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import yaml


@dataclass
class Method:
    name: str
    command: list[str]  # dm2 sub-command and its positional arguments; [] = the warm start itself
    config: dict | None = None  # YAML config overrides (the ablations)
    description: str = ""
    #: started from the ground truth (``--poses`` = the ``--gt`` file): the floor of the objective
    from_truth: bool = False


METHODS: dict[str, Method] = {m.name: m for m in [
    Method("warm start", [], description="the trajectory dm2 starts from (given, or the icp plugin)"),
    Method("dm2 refine", ["refine"], description="default config"),
    Method("no consistency", ["refine"], {"optimiser": {"use_consistency": "off"}},
           "ablation: optimiser.use_consistency=off"),
    Method("temporal batches", ["refine"], {"optimiser": {"batching": "temporal"}},
           "ablation: optimiser.batching=temporal (DeepMapping) instead of topology"),
    Method("L-Net poses", ["refine"], {"optimiser": {"pose_model": "lnet"}},
           "ablation: optimiser.pose_model=lnet instead of direct pose parameters"),
    Method("+ BCE", ["refine"], {"optimiser": {"use_bce": "on"}},
           "3D ablation: the occupancy BCE on from the pose-graph start (optimiser.use_bce=on)"),
    Method("+ consistency", ["refine"], {"optimiser": {"use_consistency": "on"}},
           "3D ablation: the consistency loss on from the pose-graph start (optimiser.use_consistency=on)"),
    Method("point Chamfer", ["refine"], {"optimiser": {"chamfer_metric": "point"}},
           "3D ablation: the paper's Euclidean Chamfer instead of point-to-plane"),
    Method("paper losses", ["refine"], {"optimiser": {"use_bce": "on", "use_consistency": "on",
                                                     "chamfer_metric": "point"}},
           "3D ablation: BCE + Euclidean Chamfer + consistency (the paper) from the pose-graph start"),
    Method("prepared start", ["refine"], {"optimiser": {"start": "prepared"}},
           "3D ablation: from the prepared (loop-closed) poses instead of the pose graph (optimiser.start=prepared)"),
    Method("from truth", ["refine"], description="dm2 refine started from the ground truth (--poses = --gt): "
           "where the objective leaves the truth, the noise floor", from_truth=True),
    Method("graph start", ["refine"], {"optimiser": {"dense": False, "first_order": "off"}},
           "3D ablation: the start alone (pose graph or loop-closed, the sharper map), no optimisation"),
    Method("dense + first-order", ["refine"], {"optimiser": {"first_order": "on"}},
           "3D ablation: the first-order epochs (point-to-plane Chamfer) after the dense stage"),
    Method("dense + BCE", ["refine"], {"optimiser": {"first_order": "on", "use_bce": "on"}},
           "3D ablation: the first-order epochs with the M-Net BCE after the dense stage"),
    Method("dense + consistency", ["refine"], {"optimiser": {"first_order": "on", "use_consistency": "on"}},
           "3D ablation: the first-order epochs with the consistency loss after the dense stage"),
    Method("no dense", ["refine"], {"optimiser": {"dense": False}},
           "3D ablation: the first-order epochs alone from the start (dm2 before the dense stage)"),
    Method("hessian refine", ["refine"], {"registration": {"options": {"information": "hessian"}}},
           "3D: the registrations' information from their point-to-plane Hessian (registration.options)"),
    Method("hessian gtsam", ["baseline", "gtsam"], {"registration": {"options": {"information": "hessian"}}},
           "3D: dm2 baseline gtsam with the registrations' information from their point-to-plane Hessian"),
    Method("gtsam", ["baseline", "gtsam"], description="dm2 baseline gtsam (same preparation)"),
    Method("g2o", ["baseline", "g2o"], description="dm2 baseline g2o (same preparation)"),
    Method("multiway", ["baseline", "multiway"], description="dm2 baseline multiway (Open3D)"),
]}

#: substrings of a failed run's output meaning that the method cannot run on this installation
UNAVAILABLE = ("needs g2opy", "install dm2[", "No such command", "No module named")


def command_available(sub: str) -> bool:
    """Whether ``dm2 <sub>`` exists in this checkout (``dm2 baseline`` may still be missing)."""
    result = subprocess.run([sys.executable, "-m", "dm2_backend", sub, "--help"], capture_output=True)
    return result.returncode == 0


def run_process(cmd: list[str], log: Path, timeout: float) -> dict:
    """Run ``cmd`` with its output in ``log``; wall time, exit code, the child's own peak RSS (wait4) and every
    process's of its tree (sampled every 0.1 s: ``dm2`` itself, and each process it started, ``child-PID``)."""
    t0 = time.perf_counter()
    peaks: dict[str, float] = {}
    with open(log, "w") as fh:
        proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)
        timed_out = False
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            if time.perf_counter() - t0 > timeout:
                os.killpg(proc.pid, signal.SIGKILL)
                pid, status, usage = os.wait4(proc.pid, 0)
                timed_out = True
                break
            _sample_tree(proc.pid, peaks)
            time.sleep(0.1)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return {"returncode": proc.returncode, "timed_out": timed_out, "wall_s": time.perf_counter() - t0,
            "peak_rss_mb": usage.ru_maxrss / 1024.0, "cpu_s": usage.ru_utime + usage.ru_stime,
            "peak_rss_mb_per_process": {k: round(v, 1) for k, v in peaks.items()}}


def _sample_tree(pid: int, peaks: dict[str, float]) -> None:
    """Each process's RSS (MiB) in ``pid``'s tree into ``peaks`` (the highest seen), keyed ``dm2`` for ``pid``."""
    import psutil

    try:
        top = psutil.Process(pid)
        tree = [top, *top.children(recursive=True)]
    except psutil.Error:
        return
    for p in tree:
        try:
            mb = p.memory_info().rss / 2**20
        except psutil.Error:
            continue
        key = "dm2" if p.pid == pid else f"child-{p.pid}"
        peaks[key] = max(peaks.get(key, 0.0), mb)


def run_case(method: Method, input_args: list[str], run_dir: Path, cache_dir: Path, epochs: int | None,
             timeout: float) -> dict:
    """One case: returns status, metrics and timings from its report.json, wall time and peak RSS."""
    run_dir.mkdir(parents=True, exist_ok=True)
    if method.from_truth:
        if "--gt" not in input_args or "-p" not in input_args:
            return {"status": "not available", "reason": "needs a --gt trajectory file and --poses"}
        input_args = list(input_args)
        input_args[input_args.index("-p") + 1] = input_args[input_args.index("--gt") + 1]
        if "--gt-format" in input_args:
            input_args += ["--poses-format", input_args[input_args.index("--gt-format") + 1]]
    cmd = [sys.executable, "-m", "dm2_backend", *method.command, *input_args, "--out", str(run_dir / "run"),
           "--cache-dir", str(cache_dir), "-q", "--force"]
    if method.config:
        cfg = run_dir / "config.yaml"
        cfg.write_text(yaml.safe_dump(method.config))
        cmd += ["--config", str(cfg)]
    if epochs is not None and method.command[0] == "refine":
        cmd += ["--epochs", str(epochs)]
    proc = run_process(cmd, run_dir / "log.txt", timeout)
    case = {"command": " ".join(cmd[2:]), "log": str(run_dir / "log.txt"), **proc}
    output = (run_dir / "log.txt").read_text(errors="replace")
    report_path = run_dir / "run" / "report.json"
    if proc["timed_out"]:
        case.update(status="timeout", reason=f"killed after {timeout:.0f} s")
    elif proc["returncode"] != 0:
        last = [ln for ln in output.strip().splitlines() if ln.strip()][-1:] or ["no output"]
        unavailable = any(s in output for s in UNAVAILABLE)
        case.update(status="not available" if unavailable else "failed", reason=last[0][-300:])
    elif not report_path.is_file():
        case.update(status="failed", reason="no report.json")
    else:
        report = json.loads(report_path.read_text())
        case.update(status="ok", frames=report.get("frames"), metrics=report.get("metrics", {}),
                    warm_start_metrics=report.get("warm_start_metrics", {}),
                    loop_closed_metrics=report.get("loop_closed_metrics"),
                    start=report.get("start"), selection=report.get("selection"),
                    timings=report.get("timings", {}),
                    prepare_cached=report.get("prepare", {}).get("cached", {}),
                    report_peak_rss_mb=report.get("peak_rss_mb"), best_epoch=report.get("best_epoch"),
                    epochs_run=len(report.get("epochs", []) or []), device=report.get("device"),
                    convergence=convergence(report))
        if report.get("peak_rss_mb") is not None:  # the run's own peak (VmHWM): wait4's ru_maxrss keeps this
            case["wait_peak_rss_mb"] = case["peak_rss_mb"]  # process's peak across exec (1,651 MiB in every
            case["peak_rss_mb"] = report["peak_rss_mb"]  # case after the real-map simulation)
    return case


#: what each epoch row of a report contributes to the benchmark's convergence record
CONVERGENCE_KEYS = ("epoch", "steps", "loss", "ate", "map_entropy", "seconds", "rejected", "converged", "trace")


def convergence(report: dict) -> dict | None:
    """Loss, accuracy and map entropy against optimisation steps (per epoch, and the epochs' ``trace`` of a
    few points each); None for a baseline."""
    epochs = report.get("epochs")
    if epochs is None:
        return None
    derived = report.get("derived") or {}
    start = report.get("start") or {}
    return {"epochs_planned": derived.get("epochs"), "pose_warmup_steps": derived.get("pose_warmup_steps"),
            "start": start.get("name"), "start_ate": (report.get("start_metrics") or {}).get("ape_trans_rmse_m"),
            "epochs": [{k: e[k] for k in CONVERGENCE_KEYS if k in e} for e in epochs]}
