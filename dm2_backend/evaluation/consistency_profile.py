"""Where a trajectory went wrong, without ground truth: each frame judged by the map the *other* frames make.

Every scan is summed into cells once (``kernel.planes``); planes come from many frames in adaptive voxels. A
frame's score (m) is the largest of three views of "the others":

- **past** and **future**: the planes of the neighbouring stretch before / after it (blocks of ``window``
  frames). Each cell of the frame is measured to the nearest of those planes that reaches it (so a point a jump
  moved out of its plane's voxel still finds it) and, for a flat cell, faces its way (``SAME_SURFACE_DEG``),
  capped at ``CAP`` noise sigmas, and the frame's worst ``TRIM`` of points is left out (what the stretch could
  not see). A front-end jump makes the frames after it disagree with the sharp map of the stretch before;
- **all**: every other frame (leave-one-out, robust weights), which sees a revisit that does not line up (a
  wrong loop closure, a drift that shows where the path comes back).

A frame needs its cells at full density (``CELLS_PER_FRAME``) for its score to mean anything (fewer cells a
frame make a true frame's score noise): the scans are summed into cells once (``profile_cells``: in memory, or for a
long sequence in temporary files), and a sequence longer than ``MAX_CELLS`` cells is judged a stretch of frames at a
time (:func:`_stretched_views`) against a sparser map of the other frames, so memory stays bounded and every frame
is judged as in a short sequence. The sets of poses (the warm start and the result) are
judged side by side (``SIDE_BY_SIDE``), on threads where there are processors, sharing that budget.

Segments scoring above the flag threshold are flagged with their frame and time ranges: ``RATIO`` times the
level of the sequence's agreeing frames (its lower quartile), and at least ``FLOOR`` times the noise the planes
measure (a frame placed within the sensor's own noise is not misplaced, however sharp the rest). Cases and their
results: ``benchmarks/consistency_cases.py`` and the tests (true, refined-to-floor and broken poses of 3D and 2D
simulations, real LiDAR keyframes, a ray-cast through their map, a simulated depth camera, the noise-free
DeepMapping set); why these thresholds: docs/decisions/0013-consistency-profile-thresholds.md.
"""

from __future__ import annotations

import csv
import json
import os
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from dm2_backend.evaluation import plots
from dm2_backend.evaluation.profile_cells import CELLS_PER_FRAME, StoredCells, full_cells
from dm2_backend.evaluation.report_writers import safe_name
from dm2_backend.kernel.geometry.symmetric3 import smallest_eigen
from dm2_backend.kernel.geometry.voxels import group_rows
from dm2_backend.kernel.planes import (
    FLATNESS,
    MIN_WIDTH,
    Assignment,
    Cells,
    Planes,
    assign,
    chunks,
    disagreement,
    fit,
    placed_means,
    rotated,
)
from dm2_backend.kernel.prepared import ScanScale
from dm2_backend.kernel.scan_scale import derive_scale
from dm2_backend.kernel.scans import ScanSequence
from dm2_backend.runtime import cluster
from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.runtime.memory import release_freed_memory, release_mapped
from dm2_backend.runtime.progress import progress as progress_of
from dm2_backend.runtime.threads import ordered_map

#: a frame's points may lie this many noise sigmas from the others' planes before their distance is capped
#: (a wrong frame scores high, one stray object cannot dominate it)
CAP = 10.0
#: a frame is flagged when its score is this multiple of the level of the agreeing frames (the lower quartile)
RATIO = 1.75
#: ... and this multiple of the noise the planes measure (sigma of a point's distance to its plane)
FLOOR = 1.0
#: the noise is taken as at least this share of the scans' point spacing (a noise-free simulation's planes measure
#: the float rounding of its coordinates: no map shows a misplacement that fine)
RESOLUTION = 0.01
#: planes (nearest voxel centres) a cell of a judged frame is measured against
NEAREST_PLANES = 8
#: the worst share of a frame's points left out of its score (surfaces the reference could not see)
TRIM = 0.2
#: a flat cell is measured only against a plane within this angle of its own: a plane turned further is nearer
#: perpendicular to the cell's surface than parallel, another surface (the ground reaching into a wall's cell where
#: the stretch never saw the wall); a misplacement turns a surface far less
SAME_SURFACE_DEG = 45.0
#: flagged frames this close (frames) are one segment
GAP = 2
#: the cells of the stretches of frames judged at once, and of the other frames' map beside a stretch, which keeps
#: at least ``OTHERS_PER_FRAME`` of each frame
MAX_CELLS, OTHERS_PER_FRAME = 1_500_000, 64
#: sets of poses judged at once (the warm start and the result): a stretch holds ``MAX_CELLS / SIDE_BY_SIDE``
#: cells (a sequence of at most ``MAX_CELLS`` is judged whole, ``SIDE_BY_SIDE`` assignments of it at once) ...
SIDE_BY_SIDE = 2
#: ... each on a thread of its own, as many as there are processors
WORKERS = min(SIDE_BY_SIDE, os.cpu_count() or 1)



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
    #: the sensor's noise as the planes measure it (robust sigma of a point's distance to its plane, m; at the
    #: sharpest of the poses profiled together, at least ``RESOLUTION`` of the point spacing)
    noise_m: float = float("nan")

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
                "threshold_m": _number(self.threshold_m), "noise_m": _number(self.noise_m),
                "voxel_m": self.voxel_m, "window_frames": self.window,
                "flagged_frames": int(self.flagged.sum()), "segments": [vars(s) for s in self.segments]}


#: flagged stretches a console line names (the worst first); the rest are in ``consistency.csv``
NAMED = 3


def flag_text(summary: dict) -> str:
    """One line from a profile's :meth:`ConsistencyProfile.summary`: the level, how many stretches are flagged and
    the worst ``NAMED`` of them (by peak score)."""
    if summary["level_m"] is None:
        return "no frame scored"
    level = f"frames agree to {summary['level_m']:.3g} m, flagged above {summary['threshold_m']:.3g} m"
    segments = summary["segments"]
    if not segments:
        return f"{level}: no flagged frame"
    worst = sorted(segments, key=lambda s: -s["peak_m"])[:NAMED]
    named = ", ".join(f"{s['first']}-{s['last']}" + (f" ({s['start_s']:.3f}-{s['end_s']:.3f} s)"
                                                      if s["start_s"] is not None else "")
                      + f" peak {s['peak_m']:.3g} m at {s['peak_frame']}" for s in worst)
    rest = f"; the other {len(segments) - len(worst)} in consistency.csv" if len(segments) > len(worst) else ""
    return (f"{level}: {len(segments)} flagged stretch{'es' if len(segments) > 1 else ''} "
            f"({summary['flagged_frames']} frames), worst {named}{rest}")


def profile_voxel(scans: ScanSequence, scale: ScanScale | None = None) -> float:
    """The largest plane voxel, from the data as the dense stage takes it: a few per median range, its finest
    quarter at least a point spacing."""
    scale = scale or derive_scale(scans)
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


def _offset(group: np.ndarray, far: float) -> np.ndarray:
    """Where each group is moved (:func:`_apart`): a grid of ``far`` steps."""
    g = np.asarray(group, dtype=np.int64) + 1
    return np.stack([g % 64, (g // 64) % 64, g // 4096], -1) * far


def _apart(poses: np.ndarray, group: np.ndarray, far: float) -> np.ndarray:
    """``poses`` with each group moved ``far`` from the others, so that frames of different groups never share a
    voxel: one assignment then holds every group's planes side by side (``far`` a whole number of voxels: each
    group's voxels are those it has in place)."""
    out = poses.copy()
    out[:, :3, 3] += _offset(group, far)
    return out


def _against(judged: Cells, placed: np.ndarray, a: Assignment, planes: Planes, tree: cKDTree, shift: np.ndarray,
             has_reference: np.ndarray, cap: float, surface: np.ndarray) -> np.ndarray:
    """Per frame, the RMS distance (m) of the ``judged`` cells' means (at ``placed`` moved by their frame's
    ``shift`` onto another group's planes) to the nearest plane that reaches the cell and, for a flat cell, lies
    within ``SAME_SURFACE_DEG`` of its normal (``surface`` (3,K), world, NaN where not flat), each distance
    capped at ``cap`` (m), weighted by the cell's points, the worst ``TRIM`` left out; NaN for a frame without
    ``has_reference``. A point a jump moved out of its plane's voxel still finds that plane."""
    f = judged.frame.astype(np.int64)
    best = np.empty(len(judged))
    centre, normal = np.ascontiguousarray(a.centre.T), np.ascontiguousarray(planes.normal.T)
    assert surface.shape == (3, len(judged))
    flat = np.isfinite(surface[0])
    surface = np.nan_to_num(surface)
    cos_limit = np.cos(np.radians(SAME_SURFACE_DEG))
    for c in chunks(len(judged)):  # bounded temporaries: a few (NEAREST_PLANES, chunk) arrays
        world = placed_means(judged, placed, c) + shift[f[c]]
        _, idx = tree.query(world, k=min(NEAREST_PLANES, a.voxels), distance_upper_bound=a.size.max())
        idx = idx.reshape(len(world), -1)
        x = np.ascontiguousarray(world.T)[:, None, :]  # (3,1,m) against (k,m) neighbours
        idx = np.ascontiguousarray(idx.T)
        found = idx < a.voxels
        i = np.where(found, idx, 0)
        size = a.size[i]
        # a plane reaches half its voxel's edge beyond the voxel (a shifted point still finds it, a patch
        # elsewhere does not stand in for it)
        for axis in range(3):
            found &= np.abs(x[axis] - centre[axis][i]) <= size
        nx, ny, nz = normal[0][i], normal[1][i], normal[2][i]
        n = surface[:, None, c]
        found &= ~flat[c] | (np.abs(nx * n[0] + ny * n[1] + nz * n[2]) >= cos_limit)
        dist = np.abs(nx * x[0] + ny * x[1] + nz * x[2] - planes.offset[i])
        nearest = np.where(found, dist, np.inf).min(0)
        best[c] = nearest
    on = np.isfinite(best)
    return _trimmed_rms(f[on], np.minimum(best[on], cap), judged.count.astype(np.float64)[on],
                        has_reference)


def _flat_normals(cells: Cells) -> np.ndarray:
    """The unit normal (sensor frame) of each flat cell (the voxels' test of ``kernel.planes`` on the cell's own points
    and size), NaN rows for the others (a line, a corner, too few points)."""
    out = np.full((len(cells), 3), np.nan)
    some = np.flatnonzero(cells.count >= 3)  # (most cells of a far surface hold a point or two)
    count = cells.count[some].astype(np.float64)
    lam, normal = smallest_eigen(*(cells.scatter[some, k] / count for k in range(6)))
    flat = (lam[:, 0] < FLATNESS * lam[:, 1]) & (lam[:, 1] >= (MIN_WIDTH * cells.size) ** 2)
    out[some[flat]] = normal[flat]
    return out


def _sampled(cells: Cells, per_frame: int, bounds: np.ndarray, seed: int) -> Cells:
    """About ``per_frame`` cells of each frame (frame i's are rows ``bounds[i]:bounds[i + 1]``), each kept with the
    same chance (seeded), copied into memory a thousand frames at a time (a file's pages dropped after each)."""
    rng = np.random.default_rng(seed)
    count = np.diff(bounds)
    chance = np.minimum(1.0, per_frame / np.maximum(count, 1))
    kept = []
    for a in range(0, len(count), 1000):
        b = min(len(count), a + 1000)
        draw = rng.random(int(bounds[b] - bounds[a])) < np.repeat(chance[a:b], count[a:b])
        at = bounds[a] + np.flatnonzero(draw)
        kept.append(Cells(cells.frame[at], cells.count[at], cells.mean[at], cells.scatter[at], cells.size))
        release_mapped([cells.frame, cells.count, cells.mean, cells.scatter])  # the pages read, if files
    return Cells(*(np.concatenate([getattr(k, f) for k in kept]) if kept else getattr(cells, f)[:0]
                   for f in ("frame", "count", "mean", "scatter")), cells.size)


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


def _neighbour_views(cells: Cells, poses: np.ndarray, voxel: float, window: int, first: int = 0,
                     scored: slice | None = None, surface: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Each frame (of ``scored``, default all; NaN for the others) against the planes of the block of ``window``
    frames before it (past) and after it (future), all blocks' planes from one assignment; ``first``: the
    sequence's number of frame 0 here (blocks are counted from the sequence's start); ``surface``: the
    :func:`_flat_normals` of the scored frames' cells, when known."""
    n = len(poses)
    block = (np.arange(n) + first) // window
    reach = float(np.linalg.norm(cells.mean, axis=1).max()) if len(cells) else 0.0
    far = voxel * np.ceil((2.0 * (float(np.ptp(poses[:, :3, 3], axis=0).max()) + 2.0 * reach)) / voxel + 10.0)
    placed = _apart(poses, block, far)
    a = assign(cells, placed, voxel)
    if a.voxels == 0:
        return np.full(n, np.nan), np.full(n, np.nan)
    planes = fit(a, placed)
    tree = cKDTree(a.centre)
    # every cell: where a stretch sees a fifth of a frame, fewer leave a score of a few cells
    judged = cells
    if scored is not None:
        keep = np.zeros(n, bool)
        keep[scored] = True
        judged = cells.of_frames(keep)
    surface = _flat_normals(judged) if surface is None else surface
    own = _offset(block, far)
    cap = CAP * a.sigma
    surface = rotated(np.ascontiguousarray(surface.T), placed, judged.frame)  # world (3,K), NaN rows stay NaN
    past = _against(judged, placed, a, planes, tree, _offset(block - 1, far) - own, np.isin(block - 1, block), cap,
                    surface)
    future = _against(judged, placed, a, planes, tree, _offset(block + 1, far) - own, np.isin(block + 1, block), cap,
                      surface)
    return past, future


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


def threshold_of(score: np.ndarray, noise: float = 0.0) -> tuple[float, float]:
    """The level of the sequence's agreeing frames (the lower quartile of the scores: it holds while up to
    three quarters of the frames are broken) and the flag threshold: ``RATIO`` times that level, and at least
    ``FLOOR`` times the sensor's ``noise`` (a frame placed within the sensor's own noise is not misplaced)."""
    finite = score[np.isfinite(score)]
    if len(finite) == 0:
        return float("nan"), float("inf")
    level = float(np.percentile(finite, 25))
    return level, max(RATIO * level, FLOOR * noise)


def consistency_profiles(scans: ScanSequence, candidates: dict[str, np.ndarray], stamps: np.ndarray | None = None,
                         planar: bool = False, voxel: float | None = None, seed: int = 0,
                         progress: bool = False, folder: Path | None = None) -> dict[str, ConsistencyProfile]:
    """The profile of each set of poses (one per scan). The scans are summed into cells once, at full density
    (:func:`~dm2_backend.evaluation.profile_cells.full_cells`: in memory, or for a long sequence temporary files in
    ``folder``), and judged a stretch at a time (:func:`_stretched_views`). ``planar``: 2D scans, their lines seen
    as vertical walls."""
    scale = derive_scale(scans)
    voxel = voxel or profile_voxel(scans, scale)
    release_freed_memory()
    candidates = {name: np.asarray(poses, dtype=np.float64) for name, poses in candidates.items()}
    # on a cluster the stretches are tasks, which map the cells from files (in ``folder``: storage they all see)
    stored = len(scans) * CELLS_PER_FRAME > MAX_CELLS and cluster.current() is not None
    with full_cells(scans, voxel, seed, planar, progress, folder, stored) as cells:
        views = _stretched_views(len(scans), cells, candidates, voxel, seed, progress)
    # the sensor's: as measured at the poses that make the sharpest planes, at least the scans' resolution
    noise = max(min(measured for _, measured in views.values()), RESOLUTION * scale.spacing_raw)
    return {name: _profile(views[name][0], noise, stamps, voxel, window_frames(poses, voxel))
            for name, poses in candidates.items()}


def consistency_profile(scans: ScanSequence, poses: np.ndarray, stamps: np.ndarray | None = None,
                        planar: bool = False, voxel: float | None = None, seed: int = 0) -> ConsistencyProfile:
    """The profile of one set of poses (:func:`consistency_profiles`)."""
    return consistency_profiles(scans, {"poses": poses}, stamps, planar, voxel, seed)["poses"]


def _stretched_views(n: int, cells: Cells, candidates: dict[str, np.ndarray], voxel: float, seed: int,
                     progress: bool) -> dict[str, tuple[dict[str, np.ndarray], float]]:
    """The views of every frame, and the noise the planes measure (m), a stretch of frames at a time: each frame
    is judged by its own cells at full density against the neighbouring blocks (past, future) and against the map
    of the stretch's cells and the other frames' cells (all: at the density ``MAX_CELLS`` gives them) in the voxels
    the stretch reaches. ``cells``: every frame's at full density, in memory or mapped from files; in memory
    besides: a stretch's (``MAX_CELLS``) and the other frames' map (``OTHERS_PER_FRAME`` a frame at least). On a
    cluster (:func:`cluster.current`) each stretch of each set of poses is a task (the cells stored in files)."""
    margin = 2 * max(window_frames(poses, voxel) for poses in candidates.values())
    whole = n * CELLS_PER_FRAME <= MAX_CELLS
    # the SIDE_BY_SIDE sets of poses judged at once share the budget (on any number of processors: the same
    # stretches, the same scores)
    length = n if whole else max(MAX_CELLS // SIDE_BY_SIDE // CELLS_PER_FRAME - 2 * margin, 2 * margin)
    bounds = np.searchsorted(cells.frame, np.arange(n + 1, dtype=cells.frame.dtype))  # cells are in frame order
    release_mapped([cells.frame])
    # the other frames' map: sparser (a revisit is many frames, each sampled)
    others = cells if whole else _sampled(cells, max(OTHERS_PER_FRAME, MAX_CELLS // n), bounds, seed)
    index = {} if whole else {name: _Reach.of(others, poses, voxel) for name, poses in candidates.items()}
    stretches = [_Stretch((max(0, s - margin), min(n, s + length + margin)), (s, min(n, s + length)),
                          (int(bounds[max(0, s - margin)]), int(bounds[min(n, s + length + margin)])))
                 for s in range(0, n, length)]
    engine = None if whole or StoredCells.of(cells) is None else cluster.current()
    if engine is not None:
        shared = _Shared(StoredCells.of(cells), candidates, others, index, voxel)
        tasks = [(name, stretch) for stretch in stretches for name in candidates]
        results = engine.map(judge_stretch_task, tasks, "profile stretches", unit="stretch", enabled=progress,
                             shared={"shared": shared})
    else:
        results = _judged_here(cells, candidates, stretches, others, whole, index, voxel, progress)
    views = {name: {view: np.full(n, np.nan) for view in ("all", "past", "future")} for name in candidates}
    noise: dict[str, list[float]] = {name: [] for name in candidates}
    for (name, stretch), (past, future, every, sigma) in zip(
            ((name, stretch) for stretch in stretches for name in candidates), results, strict=True):
        s, e = stretch.judged
        views[name]["past"][s:e], views[name]["future"][s:e], views[name]["all"][s:e] = past, future, every
        noise[name].append(sigma)
    return {name: (views[name], float(np.median(noise[name]))) for name in candidates}


def _judge_stretch(candidate: tuple[str, np.ndarray], dense: Cells, others: Cells, whole: bool,
                   index: dict[str, _Reach], frames: tuple[int, int], judged: tuple[int, int], voxel: float,
                   surface: np.ndarray) -> tuple[str, np.ndarray, np.ndarray, np.ndarray, float]:
    """One set of poses over one stretch (:func:`_stretched_views`): frames ``frames`` (a, b) in ``dense``,
    those of ``judged`` (s, e) scored against the map of ``others`` (every frame's cells when the stretch is the
    ``whole`` sequence, else the other frames' sparser ones, of which ``index`` finds those the stretch reaches),
    ``surface`` the judged cells' :func:`_flat_normals`. Its name, the past, future and all views of the judged
    frames, and the noise its planes measure."""
    name, poses = candidate
    (a, b), (s, e) = frames, judged
    local = slice(s - a, e - a)
    past, future = _neighbour_views(dense, poses[a:b], voxel, window_frames(poses, voxel), a, local, surface)
    mixed = others if whole else _with_reach(dense, a, b, others, index[name], poses, voxel)
    assigned = assign(mixed, poses, voxel)
    scored = np.zeros(len(poses), bool)
    scored[s:e] = True
    every = _rms(disagreement(assigned, poses, CAP, bounded=True, judged=scored))
    return name, past[local], future[local], every[s:e], assigned.sigma


@dataclass(frozen=True)
class _Stretch:
    """Frames ``frames`` (a, b) held to judge those of ``judged`` (s, e), their cells the rows ``rows``."""

    frames: tuple[int, int]
    judged: tuple[int, int]
    rows: tuple[int, int]

    def cells(self, cells: Cells) -> tuple[Cells, np.ndarray]:
        """The stretch's cells (frames numbered from its first) copied into memory, and the judged cells'
        :func:`_flat_normals`."""
        (a, b), (s, e), part = self.frames, self.judged, slice(*self.rows)
        dense = Cells(np.asarray(cells.frame[part]) - np.int32(a), np.asarray(cells.count[part]),
                      np.asarray(cells.mean[part]), np.asarray(cells.scatter[part]), cells.size)
        scored = np.zeros(b - a, bool)
        scored[s - a:e - a] = True
        return dense, _flat_normals(dense.of_frames(scored))


def _judged_here(cells: Cells, candidates: dict[str, np.ndarray], stretches: list[_Stretch], others: Cells,
                 whole: bool, index: dict[str, _Reach], voxel: float, progress: bool) -> list[tuple]:
    """:func:`_judge_stretch` of every stretch and set of poses in this process (the sets side by side on
    threads), in the order of the stretches, then the sets."""
    workers = min(len(candidates), SIDE_BY_SIDE, WORKERS)
    out = []
    for stretch in progress_of(stretches, "profile stretches", total=len(stretches), unit="stretch",
                               enabled=progress and not whole):
        release_freed_memory()  # the last stretch's blocks
        release_mapped([cells.frame, cells.count, cells.mean, cells.scatter])  # the last stretch's pages, if files
        dense, surface = stretch.cells(cells)  # the candidates' shared judged cells
        judge = partial(_judge_stretch, dense=dense, others=others, whole=whole, index=index,
                        frames=stretch.frames, judged=stretch.judged, voxel=voxel, surface=surface)
        # numpy's sorts, ufuncs and the KD-tree release the GIL
        out += [result[1:] for result in ordered_map(judge, candidates.items(), workers=workers)]
    return out


@dataclass(frozen=True)
class _Shared:
    """What every stretch task reads (sent to the cluster once): where the cells are stored, the sets of poses,
    the other frames' map and, per set, its index."""

    cells: StoredCells
    poses: dict[str, np.ndarray]
    others: Cells
    index: dict[str, _Reach]
    voxel: float


def judge_stretch_task(task: tuple[str, _Stretch], shared: _Shared) -> tuple:
    """One stretch of one set of poses on a cluster's worker (:func:`_judge_stretch`): its views and noise."""
    name, stretch = task
    dense, surface = stretch.cells(shared.cells.open())
    return _judge_stretch((name, shared.poses[name]), dense, shared.others, False, shared.index, stretch.frames,
                          stretch.judged, shared.voxel, surface)[1:]


@dataclass(frozen=True)
class _Reach:
    """Cells sorted by the voxel they fall in at some poses (one int64 key a voxel, ``BITS`` bits an axis from
    ``low``): the cells of any set of voxels by binary search, without sorting them all again. Cells spread over
    more voxels than the keys span keep their (K,3) voxels in ``key`` (``order`` None) and are matched by sorting."""

    low: np.ndarray | None
    key: np.ndarray
    order: np.ndarray | None

    BITS = 21

    @classmethod
    def of(cls, cells: Cells, poses: np.ndarray, voxel: float) -> _Reach:
        keys = _voxel_keys(cells, poses, voxel)
        if not len(keys):
            return cls(None, keys, None)
        low = keys.min(0)
        if int((keys.max(0) - low).max()) >= 1 << cls.BITS:
            return cls(None, keys, None)
        flat = cls._flat(keys, low)
        order = np.argsort(flat, kind="stable")
        return cls(low, flat[order], order)

    @classmethod
    def _flat(cls, keys: np.ndarray, low: np.ndarray) -> np.ndarray:
        """One key a row; -1 for a row outside the indexed cells' span (it meets none of them)."""
        k = keys - low
        inside = ((k >= 0) & (k < (1 << cls.BITS))).all(1)
        return np.where(inside, (k[:, 0] << (2 * cls.BITS)) | (k[:, 1] << cls.BITS) | k[:, 2], -1)

    def cells_in(self, keys: np.ndarray) -> np.ndarray:
        """The indexed cells in the voxels ``keys`` (K,3), ascending."""
        if self.order is None:
            inv, _ = group_rows(np.concatenate([keys, self.key]))
            return np.flatnonzero(np.isin(inv[len(keys):], inv[:len(keys)]))
        wanted = np.unique(self._flat(keys, self.low))
        wanted = wanted[wanted >= 0]
        first = np.searchsorted(self.key, wanted, "left")
        count = np.searchsorted(self.key, wanted, "right") - first
        at = np.repeat(first - np.cumsum(count) + count, count) + np.arange(int(count.sum()))
        return np.sort(self.order[at])


def _with_reach(dense: Cells, a: int, b: int, others: Cells, reach: _Reach, poses: np.ndarray,
                voxel: float) -> Cells:
    """The cells of frames ``a..b-1`` (``dense``, numbered from ``a``) and the cells of the other frames
    (``others``, indexed by ``reach``) that fall in a voxel one of them occupies at ``poses``: the others cannot
    share a plane with them."""
    dense = Cells(dense.frame + np.int32(a), dense.count, dense.mean, dense.scatter, dense.size)
    near = reach.cells_in(_voxel_keys(dense, poses, voxel))
    near = near[(others.frame[near] < a) | (others.frame[near] >= b)]
    return Cells(*(np.concatenate([getattr(dense, f), getattr(others, f)[near]])
                   for f in ("frame", "count", "mean", "scatter")), dense.size)


def _voxel_keys(cells: Cells, poses: np.ndarray, voxel: float) -> np.ndarray:
    """The voxel (edge ``voxel``) of each cell's mean at ``poses``, (K,3) integers."""
    keys = np.empty((len(cells), 3), np.int64)
    for c in chunks(len(cells)):
        keys[c] = np.floor(placed_means(cells, poses, c) / voxel)
    return keys


def _profile(views: dict[str, np.ndarray], noise: float, stamps: np.ndarray | None, voxel: float, window: int
             ) -> ConsistencyProfile:
    stacked = np.stack(list(views.values()))
    score = np.where(np.isfinite(stacked).any(0), np.nanmax(np.where(np.isfinite(stacked), stacked, -np.inf), 0),
                     np.nan)
    level, threshold = threshold_of(score, noise)
    return ConsistencyProfile(score, views, level, threshold, _segments(score, threshold, stamps), voxel, window,
                              stamps, noise)


#: what :func:`write_profiles` writes (stem "consistency")
PROFILE_FILES = ("consistency.json", "consistency.csv", "consistency.png")


def write_profiles(folder: Path, profiles: dict[str, ConsistencyProfile],
                   positions: np.ndarray | dict[str, np.ndarray],
                   stem: str = "consistency", steps: dict[str, list[int]] | None = None) -> list[str]:
    """``{stem}.json`` (each profile's summary and per-frame scores), ``{stem}.csv`` (one row per frame) and
    ``{stem}.png`` (:func:`plots.consistency_figure` over ``positions``, or each estimate's: label -> positions).
    ``steps``: per-step marks (e.g. the step guard's ``held`` and ``contradicted`` steps: frame i marks its step to
    i+1), a column ``step_<name>`` each and a ``steps`` entry in the JSON. Returns the names written."""
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
