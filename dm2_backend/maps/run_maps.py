"""The maps of a run folder, from the scans at the run's final poses (``refine``, ``baseline``, ``dm2 map``).

Planar data: ``map.pgm``/``map.yaml`` (ray-cast occupancy grid) and, after ``refine``, ``mnet_map.pgm``/``.yaml``
(the trained M-Net's occupancy probability at the same cells; unknown (205) where no beam reached, as the field is
untrained there). 3D data: ``octomap.bt`` (with ``pyoctomap``) and,
after ``refine``, ``mnet_mesh.ply`` (the M-Net's decision surface, with scikit-image). ``maps.json`` records
what was made, how (resolution and where it came from, frames and points used, seconds per stage), what was
skipped and why, and the scan source (so ``dm2 map RUN`` can find the scans again).

Resolution, from the data (:func:`resolution`): in 2D the median point spacing of the raw scans (the median
distance between neighbouring beam end points: one cell per beam at the median range); in 3D the larger of that
spacing and ``range_median / 40`` (the voxel dm2 down-samples 3D scans to), as a 3D map at the raw spacing of a
spinning LiDAR would be mostly empty cells. A grid is coarsened by 1.25x steps until it has at most
``MAX_GRID_CELLS`` cells.

Bounded time and memory: at most ``MAX_FRAMES`` frames (evenly spaced) and ``MAX_POINTS_2D`` beams /
``MAX_POINTS_3D`` points in all (every k-th point of each frame) are used.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dm2_backend.kernel.prepared import ScanScale
from dm2_backend.kernel.scans import ScanSequence
from dm2_backend.maps import mnet_export, occupancy_grid
from dm2_backend.maps.octomap_export import MissingExtra, write_octomap
from dm2_backend.optim import mnet_file
from dm2_backend.runtime.atomic import atomic_write

log = logging.getLogger(__name__)

MAPS_JSON = "maps.json"
MAX_FRAMES = 2000
MAX_POINTS_2D = 2_000_000
MAX_POINTS_3D = 1_000_000
MAX_GRID_CELLS = 1 << 22
MESH_HINT = "pip install 'dm2[maps]' (or: pip install scikit-image)"


@dataclass
class MapData:
    """Frames ``index`` of a run at their poses: sensor positions (K, 3) and world points (float32) per frame."""

    index: np.ndarray
    sensors: np.ndarray
    points: list[np.ndarray]
    planar: bool
    scale: ScanScale

    def all_points(self, limit: int | None = None) -> np.ndarray:
        pts = np.concatenate(self.points) if self.points else np.zeros((0, 3), np.float32)
        return pts if limit is None or len(pts) <= limit else pts[:: int(np.ceil(len(pts) / limit))]

    def frame_of_points(self) -> np.ndarray:
        return np.repeat(self.index, [len(p) for p in self.points])


def resolution(scale: ScanScale, planar: bool) -> tuple[float, str]:
    """The map resolution (m, 3 significant digits) from the scans' scale, and a sentence saying why."""
    spacing = max(float(scale.spacing_raw or 0.0), 1e-3)
    if planar:
        res, why = spacing, "median point spacing of the raw scans"
    else:
        coarse = float(scale.range_median or 0.0) / 40.0
        res, why = (spacing, "median point spacing of the raw scans") if spacing >= coarse else (
            coarse, "median range / 40 (dm2's 3D voxel), coarser than the raw point spacing")
    return float(f"{res:.3g}"), why


def gather(scans: ScanSequence, poses: np.ndarray, planar: bool, max_frames: int = MAX_FRAMES,
           max_points: int | None = None) -> MapData:
    """Load the scans (a subset for huge runs) and put them at ``poses`` (the sensor's poses)."""
    from dm2_backend.kernel.scan_scale import derive_scale

    if len(scans) != len(poses):
        raise ValueError(f"{len(scans)} scans for {len(poses)} poses")
    max_points = max_points or (MAX_POINTS_2D if planar else MAX_POINTS_3D)
    index = np.unique(np.linspace(0, len(scans) - 1, min(max_frames, len(scans))).astype(int))
    per_frame = max(1, max_points // len(index))
    points = []
    for i in index:
        p = scans[int(i)].points
        p = p[:: int(np.ceil(len(p) / per_frame))]
        T = poses[i]
        points.append((p.astype(np.float64) @ T[:3, :3].T + T[:3, 3]).astype(np.float32))
    return MapData(index, poses[index, :3, 3].copy(), points, planar, derive_scale(scans))


def write_run_maps(out: Path, scans: ScanSequence, poses: np.ndarray, planar: bool | None = None,
                   progress: bool = True, strict: bool = False, echo: Callable[[str], None] | None = None
                   ) -> list[str]:
    """Write the maps of the run folder ``out`` (see the module docstring); returns the files written. Not
    ``strict`` (a run's last step): a stage that fails is logged and recorded in ``maps.json``, not raised."""
    out = Path(out)
    planar = scans.planar if planar is None else planar
    say = echo or (log.info if progress else (lambda _msg: None))
    summary: dict = {"planar": planar, "scans": {"source": _source(scans.source), "format": scans.meta.get("format"),
                                                 "count": len(scans), "smoothed": bool(scans.meta.get("smoothed"))},
                     "files": [], "skipped": {}, "seconds": {}}
    t0 = time.perf_counter()
    data = gather(scans, np.asarray(poses, np.float64), planar)
    res, why = resolution(data.scale, planar)
    summary.update(frames_used=int(len(data.index)), points_used=int(sum(len(p) for p in data.points)),
                   resolution=res, resolution_from=why, scale=data.scale.to_dict())
    summary["seconds"]["load"] = round(time.perf_counter() - t0, 3)
    say(f"maps: {len(data.index)} of {len(scans)} frames, {summary['points_used']} points, "
        f"resolution {res:g} m ({why}) [{summary['seconds']['load']:.1f} s]")
    mnet = _load_mnet(out, summary)
    stages = [("grid", _grid_stage), ("mnet_map", _mnet_map_stage)] if planar else [
        ("octomap", _octomap_stage), ("mnet_mesh", _mnet_mesh_stage)]
    context: dict = {"data": data, "resolution": res, "mnet": mnet}
    for name, stage in stages:
        t = time.perf_counter()
        try:
            written, note = stage(out, context)
        except MissingExtra as exc:
            written, note = [], None
            summary["skipped"][name] = str(exc)
        except Exception as exc:  # noqa: BLE001 (a map must not cost a finished run its folder)
            if strict:
                raise
            log.warning("map %s failed: %s", name, exc)
            written, note = [], None
            summary["skipped"][name] = f"failed: {exc}"
        summary["seconds"][name] = round(time.perf_counter() - t, 3)
        summary["files"] += written
        if written:
            say(f"maps: {', '.join(written)}{f' ({note})' if note else ''} [{summary['seconds'][name]:.1f} s]")
        elif name in summary["skipped"]:
            say(f"maps: no {name}: {summary['skipped'][name]}")
    with atomic_write(out / MAPS_JSON) as fh:
        json.dump(summary, fh, indent=2, default=_json_default)
    return summary["files"] + [MAPS_JSON]


def _source(source: str) -> str:
    """The scan source as an absolute path when it is one (``dm2 map`` may run from another folder)."""
    try:
        return str(Path(source).resolve()) if source and Path(source).exists() else str(source)
    except OSError:
        return str(source)


def _json_default(v):
    if isinstance(v, np.generic):
        return v.item()
    return str(v)


def _load_mnet(out: Path, summary: dict) -> mnet_file.MNet | None:
    path = out / mnet_file.MNET
    if not path.exists():
        summary["skipped"]["mnet"] = f"no {mnet_file.MNET} in the run folder (only dm2 refine trains an M-Net)"
        return None
    mnet = mnet_file.load_mnet(path)
    if not mnet.trained:
        summary["skipped"]["mnet"] = "the run did not train the M-Net (no first-order epoch, or use_bce off)"
        return None
    return mnet


def occupancy(data: MapData, res: float) -> occupancy_grid.OccupancyGrid:
    """The ray-cast grid of planar map data."""
    pts = data.all_points()
    lo = np.minimum(pts[:, :2].min(0), data.sensors[:, :2].min(0))
    hi = np.maximum(pts[:, :2].max(0), data.sensors[:, :2].max(0))
    r, origin, shape = occupancy_grid.grid_frame(lo, hi, res, MAX_GRID_CELLS)
    pairs = ((s[:2], p[:, :2]) for s, p in zip(data.sensors, data.points))
    return occupancy_grid.ray_cast(pairs, r, origin, shape)


def _grid_stage(out: Path, ctx: dict) -> tuple[list[str], str]:
    grid = occupancy(ctx["data"], ctx["resolution"])
    ctx["grid"] = grid
    files = occupancy_grid.write_map_server(out / "map.yaml", occupancy_grid.trinary_pixels(grid.probability()),
                                            grid.resolution, grid.origin)
    h, w = grid.shape
    return files, f"{w} x {h} cells of {grid.resolution:g} m"


def _mnet_map_stage(out: Path, ctx: dict) -> tuple[list[str], str | None]:
    if ctx["mnet"] is None or "grid" not in ctx:
        return [], None
    grid = ctx["grid"]
    prob = np.where(grid.observed, mnet_export.sample_grid(ctx["mnet"], grid.centers()), np.nan)
    files = occupancy_grid.write_map_server(out / "mnet_map.yaml", occupancy_grid.scale_pixels(prob),
                                            grid.resolution, grid.origin, mode="scale")
    return files, "M-Net occupancy probability on the observed cells of the same grid"


def _octomap_stage(out: Path, ctx: dict) -> tuple[list[str], str]:
    data = ctx["data"]
    info = write_octomap(out / "octomap.bt", zip(data.sensors, data.points), ctx["resolution"])
    return ["octomap.bt"], f"{info['leaf_nodes']} leaves at {info['resolution']:g} m"


def _mnet_mesh_stage(out: Path, ctx: dict) -> tuple[list[str], str | None]:
    if ctx["mnet"] is None:
        return [], None
    try:
        import skimage  # noqa: F401
    except ImportError as exc:
        raise MissingExtra(f"the M-Net mesh needs scikit-image: {MESH_HINT}") from exc
    verts, faces, normals, step = mnet_export.mesh(ctx["mnet"], ctx["data"].all_points(limit=MAX_POINTS_3D))
    mnet_export.write_ply(out / "mnet_mesh.ply", verts, faces, normals)
    return ["mnet_mesh.ply"], f"{len(faces)} triangles, marching cubes at {step:.3g} m"


def read_summary(run: Path) -> dict:
    """``maps.json`` of a run folder ({} when absent)."""
    try:
        return json.loads((Path(run) / MAPS_JSON).read_text())
    except (OSError, ValueError):
        return {}
