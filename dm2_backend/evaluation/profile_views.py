"""The consistency profile's views of a stretch of frames: each frame judged against the planes of its
neighbouring blocks of frames (past and future; :func:`neighbour_views`).

The blocks are moved apart (:func:`_apart`) so that one plane assignment (``kernel.planes``) holds every block's
planes side by side. Each flat cell of a judged frame (its own points make a plane: :func:`flat_normals`) is measured
to the nearest of the neighbouring block's planes that reaches it (so a point a jump moved out of its plane's voxel
still finds it) and faces its way (``SAME_SURFACE_DEG``), capped at ``CAP`` noise sigmas, and the frame's worst
``TRIM`` of points is left out (what the block could not see). A cell that is not flat (an edge, a corner, a point
or two) has no surface to be measured along: the nearest plane may be another surface's. A front-end jump makes the
frames after it disagree with the sharp map of the block before.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from dm2_backend.kernel.geometry.symmetric3 import smallest_eigen
from dm2_backend.kernel.planes import (
    FLATNESS,
    MIN_WIDTH,
    Assignment,
    Cells,
    Planes,
    assign,
    chunks,
    fit,
    placed_means,
    rotated,
)

#: a frame's points may lie this many noise sigmas from the others' planes before their distance is capped
#: (a wrong frame scores high, one stray object cannot dominate it)
CAP = 10.0
#: planes (nearest voxel centres) a cell of a judged frame is measured against
NEAREST_PLANES = 8
#: the worst share of a frame's points left out of its score (surfaces the reference could not see)
TRIM = 0.2
#: a flat cell is measured only against a plane within this angle of its own: a plane turned further is nearer
#: perpendicular to the cell's surface than parallel, another surface (the ground reaching into a wall's cell where
#: the stretch never saw the wall); a misplacement turns a surface far less
SAME_SURFACE_DEG = 45.0


def window_frames(poses: np.ndarray, voxel: float) -> int:
    """Frames in a neighbouring stretch: those within two voxels of path (a quarter of the median range: the
    stretch overlaps the judged frame's view), 2 to 10."""
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    step = float(np.median(steps)) if len(steps) else 0.0
    return int(np.clip(np.ceil(2.0 * voxel / max(step, 1e-9)), 2, 10))


def root(a: np.ndarray) -> np.ndarray:
    """The square root, NaN where ``a`` is (a frame with nothing to measure)."""
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
    """Per frame, the RMS distance (m) of the ``judged`` flat cells' means (at ``placed`` moved by their frame's
    ``shift`` onto another group's planes) to the nearest plane that reaches the cell and lies within
    ``SAME_SURFACE_DEG`` of its normal (``surface`` (3,K), world), each distance
    capped at ``cap`` (m), weighted by the cell's points, the worst ``TRIM`` left out; NaN for a frame without
    ``has_reference``. A point a jump moved out of its plane's voxel still finds that plane."""
    f = judged.frame.astype(np.int64)
    best = np.empty(len(judged))
    centre, normal = np.ascontiguousarray(a.centre.T), np.ascontiguousarray(planes.normal.T)
    assert surface.shape == (3, len(judged))
    cos_limit = np.cos(np.radians(SAME_SURFACE_DEG))
    for c in chunks(len(judged)):  # bounded temporaries: a few (NEAREST_PLANES, chunk) arrays
        world = placed_means(judged, placed, c) + np.take(shift, f[c], axis=0)
        _, idx = tree.query(world, k=min(NEAREST_PLANES, a.voxels), distance_upper_bound=a.size.max())
        idx = idx.reshape(len(world), -1)
        x = np.ascontiguousarray(world.T)[:, None, :]  # (3,1,m) against (k,m) neighbours
        idx = np.ascontiguousarray(idx.T)
        found = idx < a.voxels
        i = np.where(found, idx, 0)
        size = np.take(a.size, i)
        # a plane reaches half its voxel's edge beyond the voxel (a shifted point still finds it, a patch
        # elsewhere does not stand in for it)
        for axis in range(3):
            found &= np.abs(x[axis] - np.take(centre[axis], i)) <= size
        nx, ny, nz = (np.take(normal[axis], i) for axis in range(3))
        n = surface[:, None, c]
        found &= np.abs(nx * n[0] + ny * n[1] + nz * n[2]) >= cos_limit
        dist = np.abs(nx * x[0] + ny * x[1] + nz * x[2] - np.take(planes.offset, i))
        nearest = np.where(found, dist, np.inf).min(0)
        best[c] = nearest
    on = np.isfinite(best)
    return _trimmed_rms(f[on], np.minimum(best[on], cap), judged.count.astype(np.float64)[on],
                        has_reference)


def flat_normals(cells: Cells) -> np.ndarray:
    """The unit normal (sensor frame) of each flat cell (the voxels' test of ``kernel.planes`` on the cell's own points
    and size), NaN rows for the others (a line, a corner, too few points)."""
    out = np.full((len(cells), 3), np.nan)
    some = np.flatnonzero(cells.count >= 3)  # (most cells of a far surface hold a point or two)
    count = cells.count[some].astype(np.float64)
    lam, normal = smallest_eigen(*(cells.scatter[some, k] / count for k in range(6)))
    flat = (lam[:, 0] < FLATNESS * lam[:, 1]) & (lam[:, 1] >= (MIN_WIDTH * cells.size) ** 2)
    out[some[flat]] = normal[flat]
    return out


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


def neighbour_views(cells: Cells, poses: np.ndarray, voxel: float, window: int, first: int = 0,
                     scored: slice | None = None, surface: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Each frame (of ``scored``, default all; NaN for the others) against the planes of the block of ``window``
    frames before it (past) and after it (future), all blocks' planes from one assignment; ``first``: the
    sequence's number of frame 0 here (blocks are counted from the sequence's start); ``surface``: the
    :func:`flat_normals` of the scored frames' cells, when known."""
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
    # every flat cell: where a stretch sees a fifth of a frame, fewer leave a score of a few cells
    judged = cells
    if scored is not None:
        keep = np.zeros(n, bool)
        keep[scored] = True
        judged = cells.of_frames(keep)
    surface = flat_normals(judged) if surface is None else surface
    flat = np.isfinite(surface[:, 0])  # only flat cells are measured (:func:`_against`)
    judged = Cells(judged.frame[flat], judged.count[flat], judged.mean[flat], judged.scatter[flat], judged.size)
    surface = surface[flat]
    own = _offset(block, far)
    cap = CAP * a.sigma
    surface = rotated(np.ascontiguousarray(surface.T), placed, judged.frame)  # world (3,K)
    past = _against(judged, placed, a, planes, tree, _offset(block - 1, far) - own, np.isin(block - 1, block), cap,
                    surface)
    future = _against(judged, placed, a, planes, tree, _offset(block + 1, far) - own, np.isin(block + 1, block), cap,
                      surface)
    return past, future
