"""Whether a depth camera's frames hold its steps: the simulated hall (``dm2 simulate --scene room --path hall``).

On a folder with its true poses (``truth.tum``), measured:

- each step (every ``--every``-th pair of consecutive frames) registered from the true step, on the frames as dm2
  prepares them (``load_frames``: ``frames.max_points`` points, the 3D voxel) with dm2's GICP, and on the full frames
  (``--voxel``, 2 cm by default) with open3d point-to-plane ICP: the median distance of the result from the true step;
- every consecutive pair of full frames registered from standing still and chained: the path's length and its APE;
- dm2's ``icp`` warm start on the prepared frames: the path's length and its APE;
- a trajectory that never moves (the APE it scores, as ``dm2 eval`` cautions);

each on the depth as recorded (dm2's default) and smoothed by the camera's measured noise (``--smooth-depth``,
``formats/depth_image_noise.py``).

APE: translation RMSE after the SE(3) alignment (evo, ``evaluate_poses``).

    python benchmarks/hall_steps.py [--scans FOLDER] [--frames 450]

simulates the hall into a temporary folder unless ``--scans`` is given; writes
``benchmarks/results/hall-steps.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import open3d as o3d

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from reference_check import registration_cloud  # noqa: E402

from dm2_backend.algorithms.common import Cloud, fine_distance, lengths, path_length  # noqa: E402
from dm2_backend.algorithms.icp import register  # noqa: E402
from dm2_backend.config.schema import FramesSection  # noqa: E402
from dm2_backend.evaluation.ape_rpe import evaluate_poses  # noqa: E402
from dm2_backend.evaluation.cautions import standing_still_rmse  # noqa: E402
from dm2_backend.formats import ReadOptions, open_scans, read_trajectory  # noqa: E402
from dm2_backend.kernel.geometry import se3  # noqa: E402
from dm2_backend.kernel.trajectory import Trajectory  # noqa: E402
from dm2_backend.plugins.warm_start_icp import IcpWarmStart  # noqa: E402
from dm2_backend.prepare.frames import load_frames  # noqa: E402
from dm2_backend.simulate.depth_room import write_depth_room  # noqa: E402


def step_error(truth: np.ndarray, steps: dict[int, np.ndarray]) -> float:
    """Median translation (m) of the registered steps from the true ones."""
    return float(np.median([np.linalg.norm(se3.relative(se3.relative(truth[i], truth[i + 1]), T)[:3, 3])
                            for i, T in steps.items()]))


def point_to_plane(source, target, start: np.ndarray, distance: float) -> np.ndarray:
    reg = o3d.pipelines.registration
    return reg.registration_icp(source, target, distance, start, reg.TransformationEstimationPointToPlane(),
                                reg.ICPConvergenceCriteria(max_iteration=50)).transformation


def path_and_ape(truth: Trajectory, poses: np.ndarray) -> dict:
    ape = evaluate_poses(truth, Trajectory(poses, truth.timestamps)).metrics["ape_trans"].stats["rmse"]
    return {"path_m": float(path_length(poses)[-1]), "ape_m": float(ape)}


def measure(folder: Path, every: int, voxel: float, smooth: bool) -> dict:
    scans, truth = open_scans(folder, options=ReadOptions(smooth_depth=smooth)), read_trajectory(folder / "truth.tum")
    gt = truth.poses
    frames = load_frames(scans, FramesSection().max_points, progress=False)
    fine = fine_distance(lengths(frames))
    pairs = range(0, len(gt) - 1, every)
    prepared = {i: register(Cloud(frames.points[i + 1], False, 2 * fine), Cloud(frames.points[i], False, 2 * fine),
                            se3.relative(gt[i], gt[i + 1]), (4 * fine, fine), "gicp").T for i in pairs}
    clouds = [registration_cloud(scans[i].points, voxel) for i in range(len(gt))]
    full = {i: point_to_plane(clouds[i + 1], clouds[i], se3.relative(gt[i], gt[i + 1]), 8 * voxel) for i in pairs}
    chained = [gt[0]]
    for i in range(len(gt) - 1):
        chained.append(chained[-1] @ point_to_plane(clouds[i + 1], clouds[i], np.eye(4), 8 * voxel))
    warm = IcpWarmStart(progress=False).run(frames, None)
    return {
        "scans": str(folder), "frames": len(gt), "true_path_m": float(path_length(gt)[-1]),
        "prepared": {"points": int(np.median([len(p) for p in frames.points])), "voxel_m": frames.scale.voxel,
                     "step_error_from_truth_m": step_error(gt, prepared)},
        "full_frames": {"voxel_m": voxel, "step_error_from_truth_m": step_error(gt, full)},
        "chained_full_frames": path_and_ape(truth, np.array(chained)),
        "icp_warm_start": path_and_ape(truth, warm),
        "standing_still_ape_m": float(standing_still_rmse(np.asarray(gt[:, :3, 3]), "se3", False)),
        "pairs_from_truth": len(pairs),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=Path, help="a folder with truth.tum [default: the hall, simulated]")
    parser.add_argument("--frames", type=int, default=450, help="frames to simulate [default: 450]")
    parser.add_argument("--every", type=int, default=10, help="every N-th step registered from the truth")
    parser.add_argument("--voxel", type=float, default=0.02, help="the full frames' voxel (m) [default: 0.02]")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    args = parser.parse_args()
    t = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.scans
        if folder is None:
            folder = Path(tmp) / "hall"
            write_depth_room(folder, args.frames, "hall", args.frames / 600, progress=False)
        result = {"as_recorded": measure(folder, args.every, args.voxel, False),
                  "smoothed": measure(folder, args.every, args.voxel, True)}
    result["seconds"] = round(time.perf_counter() - t, 1)
    result["command"] = "python benchmarks/hall_steps.py " + " ".join(sys.argv[1:])
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "hall-steps.json").write_text(json.dumps(result, indent=1))
    raw, smoothed = result["as_recorded"], result["smoothed"]

    def row(what: str, cell) -> str:
        return f"| {what} | {cell(raw)} | {cell(smoothed)} |"

    p = raw["prepared"]
    lines = [f"Hall steps ({raw['frames']} frames, true path {raw['true_path_m']:.2f} m; `{result['command']}`)",
             "", "| measured | depth as recorded (default) | smoothed by its noise (`--smooth-depth`) |",
             "|---|---:|---:|",
             row(f"step from the truth, prepared frames ({p['points']} points, {p['voxel_m']:.3f} m voxel), dm2 GICP",
                 lambda r: f"{1e3 * r['prepared']['step_error_from_truth_m']:.1f} mm"),
             row(f"step from the truth, full frames ({raw['full_frames']['voxel_m']:g} m voxel), point-to-plane",
                 lambda r: f"{1e3 * r['full_frames']['step_error_from_truth_m']:.1f} mm"),
             row("consecutive full-frame registrations chained: path / APE",
                 lambda r: f"{r['chained_full_frames']['path_m']:.1f} m / {r['chained_full_frames']['ape_m']:.3f} m"),
             row("dm2 icp warm start: path / APE",
                 lambda r: f"{r['icp_warm_start']['path_m']:.1f} m / {r['icp_warm_start']['ape_m']:.3f} m"),
             row("a camera that never moves: APE", lambda r: f"{r['standing_still_ape_m']:.3f} m")]
    (args.out / "hall-steps.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
