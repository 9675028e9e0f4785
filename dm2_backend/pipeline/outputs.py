"""Write a run folder: trajectories in several formats, the map, plots, priors and report.json."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import open3d as o3d
from evo.core.geometry import umeyama_alignment
from matplotlib.figure import Figure

from dm2_backend.evaluation import drawn_alignment, plots, topology_log
from dm2_backend.formats import TRAJECTORY_FORMATS, write_trajectory
from dm2_backend.formats.dm2_priors import write_priors
from dm2_backend.formats.hba import write_hba_folder
from dm2_backend.formats.kitti import lidar_to_camera, read_calib_tr
from dm2_backend.kernel.prepared import Frames, Pairwise, Topology
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.runtime.atomic import atomic_path, atomic_write
from dm2_backend.runtime.errors import InputError

log = logging.getLogger(__name__)


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
        try:
            write_trajectory(traj, out / name, given_format)
            written.append(name)
        except InputError as exc:
            log.warning("skipped %s: %s", name, exc.message)
    return written


def write_layout(out: Path, traj: Trajectory, scans) -> list[str]:
    """The result in the layout of a scan source that carries its poses file, for that layout's own tools: an
    HBA folder's as ``hba/pose.json`` (HBA's ``data_path`` is that folder with the input's ``pcd/`` in it;
    the input's own ``pose.json`` is never written). Returns the files written (none for other sources)."""
    if scans.meta.get("layout") != "hba":
        return []
    return write_hba_folder(out / "hba", traj)


#: frames placed and down-sampled at a time by :func:`write_map` (its memory is that of one chunk and the map)
MAP_CHUNK = 1000


def write_map(path: Path, frames: Frames, poses: np.ndarray, voxel: float) -> None:
    """All frames in the refined frame, voxel-down-sampled, as a PLY point cloud. Placed and down-sampled
    ``MAP_CHUNK`` frames at a time, then once more over the chunks (a voxel's point is then a mean of its chunks'
    means): all points at once took about 100 KB per 3D frame, 2 GB at 20,000 frames."""
    parts = []
    for c0 in range(0, len(frames), MAP_CHUNK):
        chunk = zip(frames.points[c0 : c0 + MAP_CHUNK], poses[c0 : c0 + MAP_CHUNK], strict=True)
        world = np.concatenate([p @ T[:3, :3].T + T[:3, 3] for p, T in chunk] or [np.zeros((0, 3))])
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(world.astype(np.float64, copy=False)))
        parts.append(np.asarray(pcd.voxel_down_sample(voxel).points) if voxel > 0 else world)
    world = np.concatenate(parts) if parts else np.zeros((0, 3))
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(world))
    if voxel > 0 and len(parts) > 1:
        pcd = pcd.voxel_down_sample(voxel)
    with atomic_path(path) as tmp:
        if not o3d.io.write_point_cloud(str(tmp), pcd):
            raise OSError(f"open3d could not write {path}")


def write_prior_files(folder: Path, warm: np.ndarray, topology: Topology, pairwise: Pairwise) -> None:
    """The official DeepMapping2 ``init_pose.npy``, ``group_matrix.npy``, ``pairwise_pose.npy`` (each write makes
    the folder, so a run that fails before leaves none)."""
    write_priors(folder, warm, topology.groups, pairwise.relative, pairwise.valid)


def aligned_to(gt: np.ndarray, est: np.ndarray) -> np.ndarray:
    """Positions ``est`` (N,3) after the rigid (SE(3), no scale) alignment onto ``gt`` (N,3) that ``dm2 eval``
    applies by default and the per-frame errors of a run are measured after."""
    R, t, _ = umeyama_alignment(np.asarray(est, np.float64).T, np.asarray(gt, np.float64).T, with_scale=False)
    return est @ R.T + t


def write_plots(out: Path, estimates: dict[str, np.ndarray], gt: Trajectory | None,
                per_frame: dict[str, tuple[np.ndarray, str]] | None, epochs: list[dict] | None,
                start: float | dict[str, float] | None = None) -> dict[str, Figure]:
    """``trajectory.png``, ``errors.png`` (with ``per_frame`` errors of the last estimate) and ``epochs.png``
    (``start``: the per-epoch metric at the optimiser's start, drawn at epoch 0; see
    :func:`plots.run_start`). Returns the figures by file name.

    With ground truth of one pose per estimated pose, every estimate is drawn after its SE(3) alignment onto
    the ground truth, so the ground-truth line and the estimates (and the per-frame errors, measured after
    the same alignment) share one frame; with ground truth of another length it is left out rather than
    drawn in a frame the estimates are not in. Where the console cautions that the SE(3) alignment is not
    meaningful (a path nearly a point or a line, :mod:`~dm2_backend.evaluation.drawn_alignment`), that estimate
    is aligned at its first pose instead, ``per_frame`` is replaced by its translation error after that
    alignment, and the title says so."""
    figures: dict[str, Figure] = {}
    pos = {k: np.asarray(v)[:, :3, 3] for k, v in estimates.items()}
    gt_pos, title, drawn = (gt.positions if gt is not None else None), "", {}
    if gt_pos is not None:
        if len(gt_pos) >= 3 and all(len(p) == len(gt_pos) for p in pos.values()):
            drawn = {k: drawn_alignment.from_poses(gt.poses, v) for k, v in estimates.items()}
            pos = {k: d.positions for k, d in drawn.items()}
            title = drawn_alignment.title(drawn)
        else:
            title = f"ground truth ({len(gt_pos)} poses) not drawn: not one pose per estimated pose"
            gt_pos = None
    figures["trajectory.png"] = plots.trajectory_figure(gt_pos, pos, title)
    if per_frame:
        last = list(estimates)[-1]
        if last in drawn:
            title = drawn_alignment.title({last: drawn[last]})
            if drawn[last].instead_of is not None:
                per_frame = {"translation error": (drawn[last].trans_errors, "m")}
        figures["errors.png"] = plots.error_map_figure(last, pos[last], per_frame, gt_pos, title)
    if epochs:
        fig = plots.epochs_figure(epochs, start)
        if fig is not None:
            figures["epochs.png"] = fig
    for name, fig in figures.items():
        plots.save(fig, out / name)
    return figures


def topology_plot(topology: Topology, poses: np.ndarray, doc: dict | None = None) -> Figure:
    """The figure of ``topology.png``: closures and loop edges over the top view of ``poses``."""
    doc = doc if doc is not None else topology_log.document(topology)
    edges, kinds = np.asarray(topology.edges, dtype=int).reshape(-1, 2), list(topology.edge_kind)
    loops = edges[np.array([k == "loop" for k in kinds], bool)] if len(kinds) == len(edges) else edges[:0]
    c = doc["counts"]
    title = (f"place recognition {doc['plugin'] or ''}: {c['accepted']} accepted, {c['dropped']} dropped, "
             f"{c['candidates']} candidates")
    return plots.topology_figure(poses[:, :3, 3], topology_log.pairs_by_status(doc), loops, title)


def write_topology(out: Path, topology: Topology, poses: np.ndarray) -> list[str]:
    """``topology.json`` (the place recognition's log: summary, counts, reasons, every candidate) and
    ``topology.png`` (:func:`topology_plot`). Returns the files written."""
    doc = topology_log.document(topology)
    write_report(out / "topology.json", doc)
    plots.save(topology_plot(topology, poses, doc), out / "topology.png")
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
