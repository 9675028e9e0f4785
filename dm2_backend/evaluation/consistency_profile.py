"""Where a trajectory went wrong, without ground truth: each frame judged by the map the *other* frames make.

Every scan is summed into cells once (``optim.planes``); planes come from many frames in adaptive voxels. A
frame's score (m) is the largest of three views of "the others":

- **past** and **future**: the planes of the neighbouring stretch before / after it (blocks of ``window``
  frames). Each cell of the frame is measured to the nearest of those planes that reaches it (so a point a jump
  moved out of its plane's voxel still finds it), capped at ``CAP`` noise sigmas, and the frame's worst ``TRIM``
  of points is left out (what the stretch could not see). A front-end jump makes the frames after it disagree
  with the sharp map of the stretch before;
- **all**: every other frame (leave-one-out, robust weights), which sees a revisit that does not line up (a
  wrong loop closure, a drift that shows where the path comes back).

A frame needs its cells at full density (``CELLS_PER_FRAME``) for its score to mean anything: a sequence longer
than ``MAX_CELLS`` holds at that density is read a second time, a stretch of frames at a time
(:func:`_stretched_views`), so memory stays bounded and every frame is judged as in a short sequence.

Segments scoring ``RATIO`` times the level of the sequence's agreeing frames (its lower quartile) are flagged
with their frame and time ranges. Validated in 3D (real LiDAR keyframes, a LiDAR ray-cast through their map, a
procedural street: no flag on the true or front-end poses, every jump, drifting stretch and wrong closure found);
on a sparse 2D simulation (260 points a scan, 3 m between frames) the truth itself gets flags.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from dm2_backend.atomic import atomic_write
from dm2_backend.evaluation import plots
from dm2_backend.evaluation.report_writers import safe_name
from dm2_backend.geometry.voxels import group_rows
from dm2_backend.memory import release_freed_memory
from dm2_backend.optim.planes import Cells, assign, cells_from_scans, chunks, disagreement, fit
from dm2_backend.progress import progress as progress_of
from dm2_backend.scan_scale import derive_scale
from dm2_backend.scans import ScanSequence

#: a frame's points may lie this many noise sigmas from the others' planes before their distance is capped
#: (a wrong frame scores high, one stray object cannot dominate it)
CAP = 10.0
#: a frame is flagged when its score is this multiple of the level of the agreeing frames (the lower quartile)
RATIO = 1.75
#: planes (nearest voxel centres) a cell of a judged frame is measured against
NEAREST_PLANES = 8
#: the worst share of a frame's points left out of its score (surfaces the reference could not see)
TRIM = 0.2
#: the cells of a frame measured against the neighbouring stretch's planes
JUDGED_CELLS = 1024
#: flagged frames this close (frames) are one segment
GAP = 2
#: the cells kept per frame (as the dense stage keeps them) and in all
CELLS_PER_FRAME, MAX_CELLS = 2048, 1_500_000


@dataclass(frozen=True)
class Segment:
    """Consecutive flagged frames ``first``..``last`` (inclusive), their stamps (s) when known, and the frame
    with the highest score."""

    first: int
    last: int
    start_s: float | None
    end_s: float | None
    peak_frame: int
    peak_m: float


@dataclass(frozen=True)
class ConsistencyProfile:
    """Per frame: ``score_m`` (the largest of the views, NaN where a frame has no point on a shared plane) and
    each view's RMS distance (m); the flag threshold and the flagged segments."""

    score_m: np.ndarray
    views_m: dict[str, np.ndarray]
    level_m: float
    threshold_m: float
    segments: list[Segment]
    voxel_m: float
    window: int
    stamps: np.ndarray | None

    @property
    def flagged(self) -> np.ndarray:
        out = np.zeros(len(self.score_m), bool)
        for s in self.segments:
            out[s.first:s.last + 1] = True
        return out

    def summary(self) -> dict:
        """The numbers a report shows (no per-frame arrays)."""
        finite = self.score_m[np.isfinite(self.score_m)]
        return {"frames": len(self.score_m), "frames_scored": len(finite), "level_m": _number(self.level_m),
                "median_m": float(np.median(finite)) if len(finite) else None,
                "p90_m": float(np.percentile(finite, 90)) if len(finite) else None,
                "threshold_m": _number(self.threshold_m), "voxel_m": self.voxel_m, "window_frames": self.window,
                "flagged_frames": int(self.flagged.sum()), "segments": [vars(s) for s in self.segments]}


def profile_voxel(scans: ScanSequence) -> float:
    """The largest plane voxel, from the data as the dense stage takes it: a few per median range, its finest
    quarter at least a point spacing."""
    scale = derive_scale(scans)
    return max(scale.range_median / 8.0, 4.0 * scale.spacing_raw, 1e-3)


def window_frames(poses: np.ndarray, voxel: float) -> int:
    """Frames in a neighbouring stretch: those within two voxels of path (a quarter of the median range: the
    stretch overlaps the judged frame's view), 2 to 10."""
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    step = float(np.median(steps)) if len(steps) else 0.0
    return int(np.clip(np.ceil(2.0 * voxel / max(step, 1e-9)), 2, 10))


def _rms(a: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return np.sqrt(a)


def _apart(poses: np.ndarray, group: np.ndarray, far: float) -> np.ndarray:
    """``poses`` with each group moved ``far`` from the others (on a grid), so that frames of different groups
    never share a voxel: one assignment then holds every group's planes side by side."""
    g = np.asarray(group, dtype=np.int64) + 1
    out = poses.copy()
    out[:, :3, 3] += np.stack([g % 64, (g // 64) % 64, g // 4096], 1) * far
    return out


def _against(cells: Cells, poses: np.ndarray, voxel: float, block: np.ndarray, step: int, far: float
             ) -> np.ndarray:
    """Per frame, the RMS distance (m) of its cells' means to the nearest plane that the frames of block
    ``block - step`` make and that reaches the cell (each distance capped at ``CAP`` noise sigmas, weighted by the
    cell's points, the worst ``TRIM`` left out); NaN for a frame without such a block. A point a jump moved out
    of its plane's voxel still finds that plane. Every block's planes come from one assignment (:func:`_apart`)."""
    reference = _apart(poses, block + step, far)
    judged = _apart(poses, block, far)
    a = assign(cells, reference, voxel)
    has_reference = np.isin(block - step, block)
    if a.voxels == 0:
        return np.full(len(poses), np.nan)
    planes = fit(a, reference)
    tree = cKDTree(a.centre)
    cells = _spread_subset(cells, JUDGED_CELLS)
    f = cells.frame.astype(np.int64)
    best = np.empty(len(cells))
    for c in chunks(len(cells)):  # bounded temporaries: (chunk, NEAREST_PLANES, 3)
        world = (judged[f[c], :3, :3] @ cells.mean[c].astype(np.float64)[:, :, None])[:, :, 0] + judged[f[c], :3, 3]
        _, idx = tree.query(world, k=min(NEAREST_PLANES, a.voxels), distance_upper_bound=voxel)
        idx = idx.reshape(len(world), -1)
        safe = np.where(idx < a.voxels, idx, 0)
        # a plane reaches half its voxel's edge beyond the voxel (a shifted point still finds it, a patch
        # elsewhere does not stand in for it)
        found = (idx < a.voxels) & (np.abs(world[:, None, :] - a.centre[safe]).max(2) <= a.size[safe])
        dist = np.abs((planes.normal[safe] * world[:, None, :]).sum(2) - planes.offset[safe])
        best[c] = np.where(found, dist, np.inf).min(1)
    on = np.isfinite(best)
    return _trimmed_rms(f[on], np.minimum(best[on], CAP * a.sigma), cells.count.astype(np.float64)[on],
                        has_reference)


def _spread_subset(cells: Cells, per_frame: int) -> Cells:
    """At most about ``per_frame`` cells of each frame, every k-th of its cells (a frame's score is a mean)."""
    n = int(cells.frame.max()) + 1 if len(cells) else 0
    count = np.bincount(cells.frame, minlength=n)
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    stride = np.maximum(1, np.ceil(count / per_frame)).astype(np.int64)
    rank = np.arange(len(cells)) - start[cells.frame]  # cells are in frame order
    keep = rank % stride[cells.frame] == 0
    return Cells(cells.frame[keep], cells.count[keep], cells.mean[keep], cells.scatter[keep], cells.size)


def _trimmed_rms(frame: np.ndarray, dist: np.ndarray, weight: np.ndarray, judged: np.ndarray) -> np.ndarray:
    """Per frame, the weighted RMS of ``dist`` over all but its worst ``TRIM`` share of weight (what the
    reference cannot have seen: an object it was occluded from); NaN for frames not judged or without cells."""
    order = np.lexsort((dist, frame))
    frame, dist, weight = frame[order], dist[order], weight[order]
    n = len(judged)
    total = np.bincount(frame, weight, minlength=n)
    before = np.cumsum(weight) - weight - np.concatenate([[0.0], np.cumsum(total)])[frame]
    keep = before < (1.0 - TRIM) * total[frame]
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.sqrt(np.bincount(frame[keep], weight[keep] * dist[keep] ** 2, minlength=n)
                      / np.bincount(frame[keep], weight[keep], minlength=n))
    out[~judged] = np.nan
    return out


def _neighbour_views(cells: Cells, poses: np.ndarray, voxel: float, window: int, first: int = 0
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Each frame against the block of ``window`` frames before it (past) and after it (future); ``first``: the
    sequence's number of frame 0 here (blocks are counted from the sequence's start)."""
    block = (np.arange(len(poses)) + first) // window
    reach = float(np.linalg.norm(cells.mean, axis=1).max()) if len(cells) else 0.0
    far = 2.0 * (float(np.ptp(poses[:, :3, 3], axis=0).max()) + 2.0 * reach) + 10.0 * voxel
    return _against(cells, poses, voxel, block, 1, far), _against(cells, poses, voxel, block, -1, far)


def _segments(score: np.ndarray, threshold: float, stamps: np.ndarray | None) -> list[Segment]:
    over = np.flatnonzero(np.nan_to_num(score, nan=0.0) > threshold)
    if len(over) == 0:
        return []
    breaks = np.flatnonzero(np.diff(over) > GAP + 1)
    out = []
    for run in np.split(over, breaks + 1):
        first, last = int(run[0]), int(run[-1])
        peak = first + int(np.nanargmax(score[first:last + 1]))
        out.append(Segment(first, last, None if stamps is None else float(stamps[first]),
                           None if stamps is None else float(stamps[last]), peak, float(score[peak])))
    return out


def threshold_of(score: np.ndarray) -> tuple[float, float]:
    """The level of the sequence's agreeing frames (the lower quartile of the scores: it holds while up to
    three quarters of the frames are broken) and the flag threshold, ``RATIO`` times that level."""
    finite = score[np.isfinite(score)]
    if len(finite) == 0:
        return float("nan"), float("inf")
    level = float(np.percentile(finite, 25))
    return level, RATIO * level


def consistency_profiles(scans: ScanSequence, candidates: dict[str, np.ndarray], stamps: np.ndarray | None = None,
                         planar: bool = False, voxel: float | None = None, seed: int = 0,
                         progress: bool = False) -> dict[str, ConsistencyProfile]:
    """The profile of each set of poses (one per scan), the scans summed into cells once (twice for a sequence
    longer than the cell budget holds at ``CELLS_PER_FRAME``: :func:`_stretched_views`). ``planar``: 2D scans,
    their lines seen as vertical walls."""
    voxel = voxel or profile_voxel(scans)
    release_freed_memory()
    candidates = {name: np.asarray(poses, dtype=np.float64) for name, poses in candidates.items()}
    cells = _cells(scans, voxel, MAX_CELLS, seed, planar, progress)
    if len(scans) * CELLS_PER_FRAME <= MAX_CELLS:
        views = {name: _views(cells, poses, voxel) for name, poses in candidates.items()}
    else:
        views = _stretched_views(scans, cells, candidates, voxel, seed, planar, progress)
    return {name: _profile(views[name], stamps, voxel, window_frames(poses, voxel))
            for name, poses in candidates.items()}


def consistency_profile(scans: ScanSequence, poses: np.ndarray, stamps: np.ndarray | None = None,
                        planar: bool = False, voxel: float | None = None, seed: int = 0) -> ConsistencyProfile:
    """The profile of one set of poses (:func:`consistency_profiles`)."""
    return consistency_profiles(scans, {"poses": poses}, stamps, planar, voxel, seed)["poses"]


def _cells(scans: ScanSequence, voxel: float, budget: int, seed: int, planar: bool, progress: bool) -> Cells:
    """The profiles' cells: a quarter voxel, every cell's scatter (a judge of the poses, not the dense stage's
    objective: its settings stay those its thresholds were measured with)."""
    # the cubes of a sensor-frame grid, on which the flags were validated: along the beams the real keyframes' last
    # frames score higher and a jump stands out less (its peak 2.8x the level, against 3.4x)
    cells = cells_from_scans(scans, voxel / 4.0, CELLS_PER_FRAME, budget, seed, progress, keep_scatter="all",
                             along_beams=False)
    return cells.extruded(voxel) if planar else cells


def _views(cells: Cells, poses: np.ndarray, voxel: float) -> dict[str, np.ndarray]:
    every = _rms(disagreement(assign(cells, poses, voxel), poses, CAP, bounded=True))
    past, future = _neighbour_views(cells, poses, voxel, window_frames(poses, voxel))
    return {"all": every, "past": past, "future": future}


def _stretched_views(scans: ScanSequence, sparse: Cells, candidates: dict[str, np.ndarray], voxel: float,
                     seed: int, planar: bool, progress: bool) -> dict[str, dict[str, np.ndarray]]:
    """The views of a sequence too long for ``CELLS_PER_FRAME`` cells a frame within ``MAX_CELLS``: with fewer
    cells a frame a score is noise (the true poses of a 10,000-frame street, 150 cells a frame, flagged half
    their frames). The scans are read again a stretch at a time at full density: each frame is judged by its
    own dense cells, against the dense neighbouring blocks (past, future) and against the map of the stretch's
    dense cells and every other frame's ``sparse`` cells in the voxels the stretch reaches (all)."""
    n = len(scans)
    margin = 2 * max(window_frames(poses, voxel) for poses in candidates.values())
    length = max(MAX_CELLS // (2 * CELLS_PER_FRAME) - 2 * margin, 2 * margin)  # with the sparse cells: one budget
    views = {name: {view: np.full(n, np.nan) for view in ("all", "past", "future")} for name in candidates}
    sparse_keys = {name: _voxel_keys(sparse, poses, voxel) for name, poses in candidates.items()}
    for s in progress_of(range(0, n, length), "profile stretches", total=-(-n // length), unit="stretch",
                         enabled=progress):
        release_freed_memory()  # the last stretch's blocks
        e = min(n, s + length)
        a, b = max(0, s - margin), min(n, e + margin)
        dense = _cells(scans.subset(np.arange(a, b)), voxel, (b - a) * CELLS_PER_FRAME, seed + s, planar, False)
        judged = slice(s - a, e - a)
        for name, poses in candidates.items():
            past, future = _neighbour_views(dense, poses[a:b], voxel, window_frames(poses, voxel), first=a)
            views[name]["past"][s:e], views[name]["future"][s:e] = past[judged], future[judged]
            mixed = _with_reach(replace(dense, frame=dense.frame + np.int32(a)), a, b, sparse, sparse_keys[name],
                                poses, voxel)
            views[name]["all"][s:e] = _rms(disagreement(assign(mixed, poses, voxel), poses, CAP, bounded=True))[s:e]
    return views


def _with_reach(dense: Cells, a: int, b: int, sparse: Cells, sparse_keys: np.ndarray, poses: np.ndarray,
                voxel: float) -> Cells:
    """The cells of frames ``a..b-1`` (``dense``) and the ``sparse`` cells of the other frames that fall in a
    voxel (``sparse_keys``: :func:`_voxel_keys`) one of them occupies at ``poses``: the others cannot share a plane
    with them."""
    other = (sparse.frame < a) | (sparse.frame >= b)
    inv, _ = group_rows(np.concatenate([_voxel_keys(dense, poses, voxel), sparse_keys[other]]))
    near = np.flatnonzero(other)[np.isin(inv[len(dense):], inv[:len(dense)])]
    return Cells(*(np.concatenate([getattr(dense, f), getattr(sparse, f)[near]])
                   for f in ("frame", "count", "mean", "scatter")), dense.size)


def _voxel_keys(cells: Cells, poses: np.ndarray, voxel: float) -> np.ndarray:
    """The voxel (edge ``voxel``) of each cell's mean at ``poses``, (K,3) integers."""
    keys = np.empty((len(cells), 3), np.int64)
    for c in chunks(len(cells)):
        keys[c] = np.floor(_placed(cells, poses, c) / voxel)
    return keys


def _placed(cells: Cells, poses: np.ndarray, part: slice) -> np.ndarray:
    f = cells.frame[part].astype(np.int64)
    return (poses[f, :3, :3] @ cells.mean[part].astype(np.float64)[:, :, None])[:, :, 0] + poses[f, :3, 3]


def _profile(views: dict[str, np.ndarray], stamps: np.ndarray | None, voxel: float, window: int
             ) -> ConsistencyProfile:
    stacked = np.stack(list(views.values()))
    score = np.where(np.isfinite(stacked).any(0), np.nanmax(np.where(np.isfinite(stacked), stacked, -np.inf), 0),
                     np.nan)
    level, threshold = threshold_of(score)
    return ConsistencyProfile(score, views, level, threshold, _segments(score, threshold, stamps), voxel, window,
                              stamps)


def write_profiles(folder: Path, profiles: dict[str, ConsistencyProfile], positions: np.ndarray,
                   stem: str = "consistency", steps: dict[str, list[int]] | None = None) -> list[str]:
    """``{stem}.json`` (each profile's summary and per-frame scores), ``{stem}.csv`` (one row per frame) and
    ``{stem}.png`` (:func:`plots.consistency_figure` over ``positions``). ``steps``: per-step marks (e.g. the step
    guard's ``held`` and ``contradicted`` steps: frame i marks its step to i+1), a column ``step_<name>`` each and
    a ``steps`` entry in the JSON. Returns the names written."""
    folder.mkdir(parents=True, exist_ok=True)
    first = next(iter(profiles.values()))
    steps = steps or {}
    doc = {label: {**p.summary(), "score_m": _floats(p.score_m), "views_m": {k: _floats(v) for k, v in
                                                                           p.views_m.items()}}
           for label, p in profiles.items()}
    if steps:
        doc["steps"] = {name: sorted(int(i) for i in marked) for name, marked in steps.items()}
    with atomic_write(folder / f"{stem}.json") as fh:
        json.dump(doc, fh, indent=1, allow_nan=False)
    columns = ["frame", "stamp_s"] + [f"{safe_name(label)}_{c}" for label in profiles for c in ("score_m", "flagged")]
    columns += [f"step_{name}" for name in steps]
    marks = {name: set(int(i) for i in marked) for name, marked in steps.items()}
    with atomic_write(folder / f"{stem}.csv", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(columns)
        flags = {label: p.flagged for label, p in profiles.items()}
        for i in range(len(first.score_m)):
            row = [i, "" if first.stamps is None else repr(float(first.stamps[i]))]
            for label, p in profiles.items():
                row += ["" if not np.isfinite(p.score_m[i]) else f"{p.score_m[i]:.6g}", int(flags[label][i])]
            w.writerow(row + [int(i in marked) for marked in marks.values()])
    plots.save(plots.consistency_figure(positions, profiles), folder / f"{stem}.png")
    return [f"{stem}.json", f"{stem}.csv", f"{stem}.png"]


def _number(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def _floats(a: np.ndarray) -> list[float | None]:
    return [float(v) if np.isfinite(v) else None for v in a]
