"""Write a run folder: trajectories in several formats, the map, plots, priors and report.json."""

from __future__ import annotations

import json
import logging
import resource
from pathlib import Path

import numpy as np
import open3d as o3d

from dm2_backend.atomic import atomic_path, atomic_write
from dm2_backend.errors import InputError
from dm2_backend.evaluation import plots, topology_log
from dm2_backend.formats import TRAJECTORY_FORMATS, ReadOptions, write_trajectory
from dm2_backend.formats.dm2_priors import write_priors
from dm2_backend.formats.kitti import lidar_to_camera, read_calib_tr
from dm2_backend.prepare.types import Frames, Pairwise, Topology
from dm2_backend.trajectory import Trajectory

log = logging.getLogger(__name__)


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MiB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def write_trajectories(out: Path, traj: Trajectory, given_path: Path | None, given_format: str | None,
                       stem: str = "poses") -> list[str]:
    """``poses_tum.txt``, ``poses_kitti.txt``, ``poses.npy`` and, when the input format is writable, the
    trajectory in that format (same file suffix as the input). Returns the files written.

    When KITTI camera-frame poses came in through a calibration (``traj.meta["calib"]``), these files are in
    the camera frame, as the input was, and ``{stem}_lidar_tum.txt`` / ``{stem}_lidar_kitti.txt`` hold the
    LiDAR-frame poses the map is built from."""
    written = []
    if traj.meta.get("calib"):
        for fmt, name in (("tum", f"{stem}_lidar_tum.txt"), ("kitti", f"{stem}_lidar_kitti.txt")):
            write_trajectory(traj, out / name, fmt)
            written.append(name)
        traj = traj.with_poses(lidar_to_camera(traj.poses, read_calib_tr(traj.meta["calib"])))
    for fmt, name in (("tum", f"{stem}_tum.txt"), ("kitti", f"{stem}_kitti.txt")):
        try:
            write_trajectory(traj, out / name, fmt)
            written.append(name)
        except InputError as exc:  # e.g. TUM with unsorted stamps from a CARMEN log
            log.warning("skipped %s: %s", name, exc.message)
    with atomic_write(out / f"{stem}.npy", "wb") as fh:
        np.save(fh, traj.poses)
    written.append(f"{stem}.npy")
    spec = TRAJECTORY_FORMATS.get(given_format or "")
    if spec is not None and spec.write is not None and given_format not in ("tum", "kitti"):
        suffix = "".join(given_path.suffixes) if given_path is not None and given_path.is_file() else ""
        name = f"{stem}_{given_format}{suffix or spec.suffixes[0]}"
        options = ReadOptions(extra={"template": traj.meta.get("template")} if traj.meta.get("template") else {})
        try:
            write_trajectory(traj, out / name, given_format, options)
            written.append(name)
        except InputError as exc:
            log.warning("skipped %s: %s", name, exc.message)
    return written


def write_map(path: Path, frames: Frames, poses: np.ndarray, voxel: float) -> None:
    """All frames in the refined frame, voxel-down-sampled, as a PLY point cloud."""
    world = np.concatenate([p @ T[:3, :3].T + T[:3, 3] for p, T in zip(frames.points, poses)])
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(world.astype(np.float64)))
    if voxel > 0:
        pcd = pcd.voxel_down_sample(voxel)
    with atomic_path(path) as tmp:
        if not o3d.io.write_point_cloud(str(tmp), pcd):
            raise OSError(f"open3d could not write {path}")


def write_prior_files(folder: Path, warm: np.ndarray, topology: Topology, pairwise: Pairwise) -> None:
    """The official DeepMapping2 ``init_pose.npy``, ``group_matrix.npy``, ``pairwise_pose.npy``."""
    folder.mkdir(parents=True, exist_ok=True)
    write_priors(folder, warm, topology.groups, pairwise.relative, pairwise.valid)


def write_plots(out: Path, estimates: dict[str, np.ndarray], gt: Trajectory | None,
                per_frame: dict[str, tuple[np.ndarray, str]] | None, epochs: list[dict] | None) -> None:
    gt_pos = gt.positions if gt is not None else None
    plots.plot_trajectories(out / "trajectory.png", gt_pos, {k: v[:, :3, 3] for k, v in estimates.items()})
    if per_frame:
        last = list(estimates)[-1]
        plots.plot_error_map(out / "errors.png", last, estimates[last][:, :3, 3], per_frame, gt_pos)
    if epochs:
        plots.plot_error_vs_epoch(out / "epochs.png", epochs)


def write_topology(out: Path, topology: Topology, poses: np.ndarray) -> list[str]:
    """``topology.json`` (the place recognition's log: summary, counts, reasons, every candidate) and
    ``topology.png`` (closures and loop edges over the top view of ``poses``). Returns the files written."""
    doc = topology_log.document(topology)
    write_report(out / "topology.json", doc)
    edges, kinds = np.asarray(topology.edges, dtype=int).reshape(-1, 2), list(topology.edge_kind)
    loops = edges[np.array([k == "loop" for k in kinds], bool)] if len(kinds) == len(edges) else edges[:0]
    c = doc["counts"]
    title = (f"place recognition {doc['plugin'] or ''}: {c['accepted']} accepted, {c['dropped']} dropped, "
             f"{c['candidates']} candidates")
    plots.plot_topology(out / "topology.png", poses[:, :3, 3], topology_log.pairs_by_status(doc), loops, title)
    return ["topology.json", "topology.png"]


def write_report(path: Path, report: dict) -> None:
    with atomic_write(path) as fh:
        json.dump(report, fh, indent=2, default=_json_default)


def _json_default(v):
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return str(v)
