"""The fused warm start on a hospital-like log (issue 27) and on the same run without its traits: odometry, the warm
start as before (the codes read as points, no window check), with the window check alone, and now; ATE against the
simulator's truth and the mean translational relation error over its relations.

    .venv/bin/python benchmarks/hospital_warm_start.py --frames 1000 --out /tmp/hospital
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from dm2_backend.evaluation.relations import load_relations, relations_error
from dm2_backend.formats.carmen import open_carmen_scans
from dm2_backend.formats.registry import ReadOptions
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.plugins.warm_start_icp import IcpWarmStart
from dm2_backend.prepare.frames import load_frames
from dm2_backend.simulate.hospital import HospitalSettings, HospitalTraits, simulate_hospital, write_hospital


def ate(poses: np.ndarray, truth: np.ndarray) -> float:
    """Position RMSE without alignment (both start at the true first pose)."""
    return float(np.sqrt(np.mean(np.sum((poses[:, :2, 3] - truth[:, :2, 3]) ** 2, axis=1))))


def measure(out: Path, frames: int, traits: HospitalTraits) -> dict[str, tuple[float, float]]:
    settings = HospitalSettings(frames=frames, traits=traits)
    write_hospital(out, settings)
    truth = simulate_hospital(settings).truth
    relations = load_relations(out / "hospital.relations")
    as_points = ReadOptions(max_range=traits.declared_max_range)  # what the reader did before issue 27
    row = {}
    for label, options, windows in (("before", as_points, "off"), ("window check alone", as_points, "auto"),
                                    ("now", None, "auto")):
        seq = open_carmen_scans(out / "hospital.clf", options)
        odometry = seq.trajectories["odometry"]
        poses = IcpWarmStart(progress=False, windows=windows).run(load_frames(seq, 1024, None, 0, False), odometry)
        for name, p in (("odometry", odometry.poses), (label, poses)):
            rel = relations_error(Trajectory(p, seq.timestamps, planar=True), relations).stats["trans_mean"]
            row[name] = (ate(p, truth), rel)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    for name, traits in (("hospital-like", HospitalTraits()), ("without the traits", HospitalTraits().plain())):
        row = measure(args.out / name.replace(" ", "-"), args.frames, traits)
        print(f"{name} ({args.frames} scans): "
              + " | ".join(f"{k}: ATE {a:.3f} m, relations {r:.4f} m" for k, (a, r) in row.items()))


if __name__ == "__main__":
    main()
