"""The consistency profile a stretch of frames at a time: memory stays bounded and every frame is judged as in a
short sequence.

A sequence longer than ``MAX_CELLS`` cells is judged in stretches (:func:`stretched_views`): each frame by its own
cells at full density against its neighbouring blocks (``profile_views``) and against the map every other frame
makes (the "all" view: leave-one-out with robust weights, which sees a revisit that does not line up), that map
made once per set of poses from every frame's cells sampled sparser (``MAP_CELLS_PER_FRAME`` a frame at least;
``profile_map``). The sets of poses (the warm start and the result) are judged side by side
(``SIDE_BY_SIDE``) on threads; on a cluster each stretch of each set is a task (:func:`judge_stretch_task`) that
maps the cells from files.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import partial

import numpy as np

from dm2_backend.evaluation.profile_cells import CELLS_PER_FRAME, StoredCells
from dm2_backend.evaluation.profile_map import SparseMap, judged_against_map
from dm2_backend.evaluation.profile_views import CAP, flat_normals, neighbour_views, root, window_frames
from dm2_backend.kernel.planes import Cells, assign, disagreement
from dm2_backend.runtime import cluster
from dm2_backend.runtime.memory import release_freed_memory, release_mapped
from dm2_backend.runtime.progress import progress as progress_of
from dm2_backend.runtime.threads import ordered_map

#: the cells of the stretches of frames judged at once, and of the map every frame makes (``profile_map``), which
#: keeps at least ``MAP_CELLS_PER_FRAME`` of each frame
MAX_CELLS, MAP_CELLS_PER_FRAME = 1_500_000, 64
#: sets of poses judged at once (the warm start and the result): a stretch holds ``MAX_CELLS / SIDE_BY_SIDE``
#: cells (a sequence of at most ``MAX_CELLS`` is judged whole, ``SIDE_BY_SIDE`` assignments of it at once) ...
SIDE_BY_SIDE = 2
#: ... each on a thread of its own, as many as there are processors
WORKERS = min(SIDE_BY_SIDE, os.cpu_count() or 1)


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


def stretched_views(n: int, cells: Cells, candidates: dict[str, np.ndarray], voxel: float, seed: int,
                    progress: bool, engine: cluster.Engine | None = None
                    ) -> dict[str, tuple[dict[str, np.ndarray], float]]:
    """The views of every frame, and the noise the planes measure (m), a stretch of frames at a time: each frame
    is judged by its own cells at full density against the neighbouring blocks (past, future) and against the map
    every other frame makes (all: at the density ``MAX_CELLS`` gives them; :class:`SparseMap`). ``cells``: every
    frame's at full density, in memory or mapped from files; in memory besides: a stretch's (``MAX_CELLS``) and
    each set's map (``MAP_CELLS_PER_FRAME`` a frame at least). On
    ``engine`` (:func:`cluster_for`) each stretch of each set of poses is a task (the cells stored in files)."""
    margin = 2 * max(window_frames(poses, voxel) for poses in candidates.values())
    whole = n * CELLS_PER_FRAME <= MAX_CELLS
    # the SIDE_BY_SIDE sets of poses judged at once share the budget (on any number of processors: the same
    # stretches, the same scores)
    length = n if whole else max(MAX_CELLS // SIDE_BY_SIDE // CELLS_PER_FRAME - 2 * margin, 2 * margin)
    bounds = np.searchsorted(cells.frame, np.arange(n + 1, dtype=cells.frame.dtype))  # cells are in frame order
    release_mapped([cells.frame])
    # the map every frame makes: sparser (a revisit is many frames, each sampled)
    maps: dict[str, SparseMap] | None = None
    if not whole:
        sampled = _sampled(cells, max(MAP_CELLS_PER_FRAME, MAX_CELLS // n), bounds, seed)
        built = ordered_map(lambda poses: SparseMap.of(sampled, poses, voxel), candidates.values(),
                            workers=min(len(candidates), SIDE_BY_SIDE, WORKERS))
        maps = dict(zip(candidates, built, strict=True))
        del sampled
    stretches = [_Stretch((max(0, s - margin), min(n, s + length + margin)), (s, min(n, s + length)),
                          (int(bounds[max(0, s - margin)]), int(bounds[min(n, s + length + margin)])))
                 for s in range(0, n, length)]
    engine = None if whole or StoredCells.of(cells) is None else engine
    if engine is not None:
        shared = _Shared(StoredCells.of(cells), candidates, maps, voxel)
        tasks = [(name, stretch) for stretch in stretches for name in candidates]
        results = engine.map(judge_stretch_task, tasks, "profile stretches", unit="stretch", enabled=progress,
                             shared={"shared": shared})
    else:
        results = _judged_here(cells, candidates, stretches, maps, voxel, progress)
    views = {name: {view: np.full(n, np.nan) for view in ("all", "past", "future")} for name in candidates}
    noise: dict[str, list[float]] = {name: [] for name in candidates}
    for (name, stretch), (past, future, every, sigma) in zip(
            ((name, stretch) for stretch in stretches for name in candidates), results, strict=True):
        s, e = stretch.judged
        views[name]["past"][s:e], views[name]["future"][s:e], views[name]["all"][s:e] = past, future, every
        noise[name].append(sigma)
    return {name: (views[name], float(np.median(noise[name]))) for name in candidates}


def _judge_stretch(candidate: tuple[str, np.ndarray], dense: Cells, maps: dict[str, SparseMap] | None,
                   frames: tuple[int, int], judged: tuple[int, int], voxel: float,
                   surface: np.ndarray) -> tuple[str, np.ndarray, np.ndarray, np.ndarray, float]:
    """One set of poses over one stretch (:func:`stretched_views`): frames ``frames`` (a, b) in ``dense``,
    those of ``judged`` (s, e) scored against the map every other frame makes (the set's map in ``maps``; None:
    the stretch is the whole sequence, whose cells make it), ``surface`` the judged cells' :func:`flat_normals`.
    Its name, the past, future and all views of the judged frames, and the noise its planes measure."""
    name, poses = candidate
    (a, b), (s, e) = frames, judged
    local = slice(s - a, e - a)
    past, future = neighbour_views(dense, poses[a:b], voxel, window_frames(poses, voxel), a, local, surface)
    scored = np.zeros(len(poses), bool)
    scored[s:e] = True
    if maps is None:
        assert frames == (0, len(poses)), frames
        assigned = assign(dense, poses, voxel)
        every, sigma = disagreement(assigned, poses, CAP, bounded=True, judged=scored), assigned.sigma
    else:
        numbered = Cells(dense.frame + np.int32(a), dense.count, dense.mean, dense.scatter, dense.size)
        every, sigma = judged_against_map(numbered, poses, scored, maps[name], CAP), maps[name].assignment.sigma
    return name, past[local], future[local], root(every[s:e]), sigma


@dataclass(frozen=True)
class _Stretch:
    """Frames ``frames`` (a, b) held to judge those of ``judged`` (s, e), their cells the rows ``rows``."""

    frames: tuple[int, int]
    judged: tuple[int, int]
    rows: tuple[int, int]

    def cells(self, cells: Cells) -> tuple[Cells, np.ndarray]:
        """The stretch's cells (frames numbered from its first) copied into memory, and the judged cells'
        :func:`flat_normals`."""
        (a, b), (s, e), part = self.frames, self.judged, slice(*self.rows)
        dense = Cells(np.asarray(cells.frame[part]) - np.int32(a), np.asarray(cells.count[part]),
                      np.asarray(cells.mean[part]), np.asarray(cells.scatter[part]), cells.size)
        scored = np.zeros(b - a, bool)
        scored[s - a:e - a] = True
        return dense, flat_normals(dense.of_frames(scored))


def _judged_here(cells: Cells, candidates: dict[str, np.ndarray], stretches: list[_Stretch],
                 maps: dict[str, SparseMap] | None, voxel: float, progress: bool) -> list[tuple]:
    """:func:`_judge_stretch` of every stretch and set of poses in this process (the sets side by side on
    threads), in the order of the stretches, then the sets."""
    workers = min(len(candidates), SIDE_BY_SIDE, WORKERS)
    out = []
    for stretch in progress_of(stretches, "profile stretches", total=len(stretches), unit="stretch",
                               enabled=progress and len(stretches) > 1):
        release_freed_memory()  # the last stretch's blocks
        release_mapped([cells.frame, cells.count, cells.mean, cells.scatter])  # the last stretch's pages, if files
        dense, surface = stretch.cells(cells)  # the candidates' shared judged cells
        judge = partial(_judge_stretch, dense=dense, maps=maps, frames=stretch.frames, judged=stretch.judged,
                        voxel=voxel, surface=surface)
        # numpy's sorts, ufuncs and the KD-tree release the GIL
        out += [result[1:] for result in ordered_map(judge, candidates.items(), workers=workers)]
    return out


@dataclass(frozen=True)
class _Shared:
    """What every stretch task reads (sent to the cluster once): where the cells are stored, the sets of poses
    and each set's map."""

    cells: StoredCells
    poses: dict[str, np.ndarray]
    maps: dict[str, SparseMap]
    voxel: float


def judge_stretch_task(task: tuple[str, _Stretch], shared: _Shared) -> tuple:
    """One stretch of one set of poses on a cluster's worker (:func:`_judge_stretch`): its views and noise."""
    name, stretch = task
    dense, surface = stretch.cells(shared.cells.open())
    return _judge_stretch((name, shared.poses[name]), dense, shared.maps, stretch.frames, stretch.judged,
                          shared.voxel, surface)[1:]


def cluster_for(n: int, sets: int, shared_folder: bool) -> cluster.Engine | None:
    """The cluster that judges ``n`` frames' stretches of ``sets`` sets of poses (their cells then stored in
    files), None to judge them in this process: a sequence judged in stretches, a cluster whose workers see the
    files (a local one, or ``shared_folder``: a folder on their common storage), and more tasks at once than
    this process's threads (a local cluster on as many cores as the sets judged side by side gains nothing)."""
    engine = cluster.current()
    if engine is None or n * CELLS_PER_FRAME <= MAX_CELLS:
        return None
    local = engine.spec.workers  # a local cluster's workers run a task each (known before it starts)
    if local is None:
        return engine if shared_folder else None
    return engine if local > min(sets, SIDE_BY_SIDE, WORKERS) else None
