"""A Rerun recording (``.rrd``) of a run folder, for a look without writing code (``rerun FILE.rrd``); needs the
optional ``rerun-sdk`` (the ``view`` extra).

Entities (world frame of the run's poses, z up):

- ``world/warm_start/path``, ``world/refined/path`` (and ``world/ground_truth/path``, aligned onto the refined
  trajectory, with ground truth): the trajectories, static;
- ``world/map``: the scans at the refined poses (a bounded sample), coloured by their frame's translation error
  against the ground truth when there is one (turbo colour map, blue 0 to red at the largest error), else the
  run's ``map.ply``;
- ``world/loop_closures/accepted``, ``.../rejected`` (and ``dropped``, ``verified``): the place recognition's
  candidates from ``topology.json``, as segments between the refined positions;
- ``maps/grid``, ``maps/mnet`` (planar runs): ``map.pgm`` and ``mnet_map.pgm`` as images; ``world/mnet_map``
  the cells the M-Net calls occupied, in the world; ``world/mnet_mesh`` (3D runs): ``mnet_mesh.ply``;
- on the ``frame`` timeline: ``world/refined/pose``, ``world/warm_start/pose``, ``world/scan`` (that frame's
  points) and ``metrics/translation_error`` (with ground truth).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dm2_backend.formats.poses_npy import read_poses_npy
from dm2_backend.kernel.scans import ScanSequence
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.maps import occupancy_grid, run_maps
from dm2_backend.maps.octomap_export import MissingExtra
from dm2_backend.runtime.atomic import atomic_path
from dm2_backend.runtime.errors import InputError

VIEW_HINT = "pip install 'dm2[view]' (or: pip install rerun-sdk)"
MAX_LOGGED_FRAMES = 1000
MAX_MAP_POINTS = 500_000
SCAN_POINTS = 4000
COLOURS = {"warm_start": (230, 140, 30), "refined": (40, 120, 230), "ground_truth": (60, 180, 75),
           "accepted": (40, 200, 60), "dropped": (240, 160, 0), "verified": (150, 150, 150),
           "rejected": (220, 40, 40), "across": (40, 190, 210)}


def require_rerun():
    try:
        import rerun
    except ImportError as exc:
        raise MissingExtra(f"the Rerun recording needs rerun-sdk: {VIEW_HINT}") from exc
    return rerun


def error_colours(errors: np.ndarray) -> np.ndarray:
    """uint8 RGB per value: turbo from 0 (blue) to the largest value (red)."""
    from matplotlib import colormaps

    top = float(np.max(errors)) if len(errors) and np.max(errors) > 0 else 1.0
    return (colormaps["turbo"](np.clip(errors / top, 0, 1))[:, :3] * 255).astype(np.uint8)


def write_recording(run: Path, rrd: Path, scans: ScanSequence | None = None, gt: Trajectory | None = None) -> dict:
    """Write ``rrd`` from the run folder ``run`` (``poses.npy``, ``warm_start.npy``, ``topology.json``, the map
    files); ``scans`` (matched to the run's poses) gives the map points and per-frame scans, ``gt`` (one pose
    per frame) the errors. Returns the entity paths logged."""
    rr = require_rerun()
    from dm2_backend.evaluation.paper_ate import paper_ate
    from dm2_backend.evaluation.topology_log import pairs_by_status

    run = Path(run)
    if not (run / "poses.npy").exists():
        raise InputError(run, "not a dm2 run folder (no poses.npy)")
    final = read_poses_npy(run / "poses.npy").poses  # input like any other: bounded, rigid, finite
    warm = read_poses_npy(run / "warm_start.npy").poses if (run / "warm_start.npy").exists() else None
    report = _json(run / "report.json")
    planar = bool(report.get("planar", scans.planar if scans is not None else False))
    errors = None
    paths = {"refined": final[:, :3, 3]}
    if warm is not None:
        paths["warm_start"] = warm[:, :3, 3]
    if gt is not None:
        if len(gt) != len(final):
            raise InputError(None, f"ground truth has {len(gt)} poses for the run's {len(final)}")
        ate = paper_ate(gt.poses, final)
        errors = ate.trans_errors
        paths["ground_truth"] = (gt.positions - ate.translation) @ ate.rotation  # R^T (g - t): onto the estimate
    logged: list[str] = []
    with atomic_path(rrd) as tmp:
        rec = rr.RecordingStream("dm2", recording_id=f"dm2-{run.resolve().name}")
        rec.save(str(tmp))

        def log(path: str, value, static: bool = False) -> None:
            rec.log(path, value, static=static)
            if path not in logged:
                logged.append(path)

        log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        for name, xyz in paths.items():
            log(f"world/{name}/path", rr.LineStrips3D([xyz], colors=[COLOURS[name]]), static=True)
        data = None
        if scans is not None:
            if len(scans) != len(final):
                raise InputError(scans.source, f"{len(scans)} scans for the run's {len(final)} poses")
            data = run_maps.gather(scans, final, planar, max_frames=MAX_LOGGED_FRAMES, max_points=MAX_MAP_POINTS)
            colours = error_colours(errors[data.frame_of_points()]) if errors is not None else None
            log("world/map", rr.Points3D(data.all_points(), colors=colours, radii=rr.Radius.ui_points(1.5)),
                static=True)
        elif (run / "map.ply").exists():
            import open3d as o3d

            pts = np.asarray(o3d.io.read_point_cloud(str(run / "map.ply")).points)
            log("world/map", rr.Points3D(pts[:: max(1, len(pts) // MAX_MAP_POINTS)],
                                         radii=rr.Radius.ui_points(1.5)), static=True)
        topo = _json(run / "topology.json")
        if topo:
            for status, pairs in pairs_by_status(topo).items():
                if status in ("accepted", "rejected") or len(pairs):
                    pos = final[:, :3, 3]
                    segs = [pos[[i, j]] for i, j in pairs if i < len(pos) and j < len(pos)]
                    log(f"world/loop_closures/{status}", rr.LineStrips3D(segs, colors=[COLOURS[status]]),
                        static=True)
        _log_maps(rr, run, log)
        index = data.index if data is not None else np.unique(
            np.linspace(0, len(final) - 1, min(MAX_LOGGED_FRAMES, len(final))).astype(int))
        for k, i in enumerate(index):
            rec.set_time("frame", sequence=int(i))
            log("world/refined/pose", rr.Points3D([final[i, :3, 3]], colors=[COLOURS["refined"]],
                                                  radii=rr.Radius.ui_points(6.0)))
            if warm is not None:
                log("world/warm_start/pose", rr.Points3D([warm[i, :3, 3]], colors=[COLOURS["warm_start"]],
                                                         radii=rr.Radius.ui_points(6.0)))
            if data is not None:
                pts = data.points[k][:: max(1, len(data.points[k]) // SCAN_POINTS)]
                log("world/scan", rr.Points3D(pts, colors=[(255, 255, 255)], radii=rr.Radius.ui_points(2.0)))
            if errors is not None:
                log("metrics/translation_error", rr.Scalars(float(errors[i])))
        rec.flush()
        rec.disconnect()
    return {"entities": logged, "frames": int(len(index))}


def _log_maps(rr, run: Path, log) -> None:
    for name, stem in (("grid", "map"), ("mnet", "mnet_map")):
        if (run / f"{stem}.yaml").exists():
            m = occupancy_grid.read_map_server(run / f"{stem}.yaml")
            log(f"maps/{name}", rr.Image(m.image), static=True)
            if name == "mnet":
                rows, cols = np.nonzero(m.occupancy() > m.occupied_thresh)
                h = m.image.shape[0]
                xy = np.column_stack([m.origin[0] + (cols + 0.5) * m.resolution,
                                      m.origin[1] + (h - rows - 0.5) * m.resolution])
                log("world/mnet_map", rr.Points3D(np.column_stack([xy, np.zeros(len(xy))]),
                                                  colors=[(200, 60, 200)], radii=0.5 * m.resolution), static=True)
    if (run / "mnet_mesh.ply").exists():
        import open3d as o3d

        mesh = o3d.io.read_triangle_mesh(str(run / "mnet_mesh.ply"))
        normals = np.asarray(mesh.vertex_normals) if mesh.has_vertex_normals() else None
        log("world/mnet_mesh", rr.Mesh3D(vertex_positions=np.asarray(mesh.vertices),
                                         triangle_indices=np.asarray(mesh.triangles), vertex_normals=normals),
            static=True)


def _json(path: Path) -> dict:
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return {}
