"""The dense stage and the consistency profiles alone on a simulated sequence: CPU, wall time and peak RSS per stage.

    python benchmarks/dense_scale.py SIM OUT.json [ROUNDS]

SIM is a ``dm2 simulate`` folder (velodyne/, warm_start.txt, poses.txt). The stages as ``dm2 refine`` runs them
(cells of a quarter of the profile voxel, 2048 a frame and 1.5 M in all, the thin ones with their scatter, the
same voxel for the planes), but the graph is the warm start's odometry chain (1 cm, 1 mrad), not the pipeline's
registrations, so no preparation is needed; ROUNDS caps the dense rounds (default 30). RSS is sampled every
0.1 s; ``peak_mib`` of a stage is the highest RSS from its start to its end. Used for
``benchmarks/results/2026-12-03-dense-scale.md``.
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time

import numpy as np
import psutil

from dm2_backend.config.optimiser import OptimConfig
from dm2_backend.evaluation.consistency_profile import consistency_profiles, profile_voxel
from dm2_backend.formats import open_scans
from dm2_backend.kernel import planes
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.pose_graph import PoseGraph
from dm2_backend.optim.dense import refine_dense


class Stages:
    """Per stage: wall and CPU seconds, peak and final RSS (MiB)."""

    def __init__(self) -> None:
        self.proc = psutil.Process()
        self.peak = 0.0
        self.wall, self.cpu = time.perf_counter(), time.process_time()
        self.rows: dict[str, dict] = {}
        threading.Thread(target=self._sample, daemon=True).start()

    def _sample(self) -> None:
        while True:
            self.peak = max(self.peak, self.proc.memory_info().rss / 2**20)
            time.sleep(0.1)

    def end(self, name: str) -> None:
        wall, cpu, rss = time.perf_counter(), time.process_time(), self.proc.memory_info().rss / 2**20
        self.rows[name] = {"s": round(wall - self.wall, 1), "cpu_s": round(cpu - self.cpu, 1),
                           "peak_mib": round(max(self.peak, rss)), "end_mib": round(rss), "load": os.getloadavg()}
        print(name, self.rows[name], flush=True)
        self.peak, self.wall, self.cpu = rss, wall, cpu


def kitti(path: str) -> np.ndarray:
    rows = np.loadtxt(path).reshape(-1, 3, 4)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3] = rows
    return poses


def main(sim: str, out: str, rounds: int = 30) -> None:
    stages = Stages()
    scans = open_scans(sim + "/velodyne")
    warm = kitti(sim + "/warm_start.txt")
    voxel = profile_voxel(scans)
    stages.end("setup")
    cells = planes.cells_from_scans(scans, voxel / 4, 2048, 1_500_000, 0, keep_scatter=OptimConfig().dense_cell_scatter)
    stages.end("dense_cells")
    n = len(warm)
    info = np.diag([1e4] * 3 + [1e6] * 3)
    graph = PoseGraph(ids=np.arange(n), poses=warm.copy(), edges=np.stack([np.arange(n - 1), np.arange(1, n)], 1),
                      relative=se3.relative(warm[:-1], warm[1:]), information=np.repeat(info[None], n - 1, 0),
                      planar=False)
    result = refine_dense(cells, graph, warm, voxel, rounds)
    stages.end("dense_rounds")
    agreement = planes.agreement_score(cells, {"warm": warm, "dense": result.poses}, voxel)
    stages.end("agreement")
    del cells
    stages.end("free")
    profiles = consistency_profiles(scans, {"warm": warm, "dense": result.poses})
    stages.end("profiles")
    report = {"frames": n, "cells_cap": 1_500_000, "voxel": voxel, "rounds": len(result.history),
              "stopped": result.stopped.detail, "stages": stages.rows, "agreement": agreement,
              "poses_sum": float(result.poses.sum()),
              "profiles": {k: {"levels_m": p.levels_m, "flagged": int(p.flagged.sum()),
                               "score_sum": float(np.nansum(p.score))} for k, p in profiles.items()}}
    with open(out, "w") as fh:
        json.dump(report, fh, indent=1)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], int(sys.argv[3]) if len(sys.argv) > 3 else 30)
