"""Correlative scan matching in 2D (Olson 2009) with a two-level branch and bound: a global search over
translation and rotation for the pose that puts the most source points on target structure, and the
best clearly different alignment (the runner-up), which exposes ambiguous matches such as corridors, and
whether the ambiguity runs along one direction only (``Correlation.axis``: every alignment scoring near the
best lies on one line through it at the same heading, as in a featureless corridor), so that the match
still fixes the pose across that line and in yaw.

The target becomes a likelihood grid ``exp(-d^2 / 2 sigma^2)`` (d: distance to the nearest target point,
an exact Euclidean distance transform). For every rotation, blocks of ``block x block`` translations are
bounded from above with a max-filtered grid; blocks are opened best bound first, and the search stops once
no unopened block can beat ``ratio`` times the best score, so every alignment scoring above that is found:
the best is exact and the runner-up test is sound.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import distance_transform_edt, maximum_filter

from dm2_backend.kernel.geometry import se3


@dataclass
class Correlation:
    x: float
    y: float
    yaw: float
    #: mean likelihood of the source points at the best pose (1 = every point on a target point)
    score: float
    #: best score of an alignment at least ``distinct_t`` / ``distinct_yaw`` away from the best; 0 when
    #: none reaches ``ratio * score`` (the search does not look further)
    runner_up: float
    runner_up_pose: tuple[float, float, float] | None = None
    #: unit direction (target frame) along which every alignment scoring at least ``ratio`` of the best lies,
    #: when they all do (a line through the best, within ``distinct_t / 2`` across it and ``distinct_yaw`` of
    #: its heading) and one of them is distinct; None otherwise
    axis: tuple[float, float] | None = None


class LikelihoodGrid:
    """Likelihood of the target points on a grid of cell ``res`` (m), with a zero border."""

    def __init__(self, target_xy: np.ndarray, res: float, sigma: float | None = None) -> None:
        sigma = sigma or res
        pad = int(np.ceil(3 * sigma / res)) + 2
        self.res = res
        self.origin = target_xy.min(axis=0) - pad * res
        shape = np.ceil((target_xy.max(axis=0) + pad * res - self.origin) / res).astype(int) + 1
        occ = np.zeros(shape, dtype=bool)
        idx = ((target_xy - self.origin) / res).astype(int)
        occ[idx[:, 0], idx[:, 1]] = True
        d = distance_transform_edt(~occ) * res
        grid = np.exp(-0.5 * (d / sigma) ** 2).astype(np.float32)
        grid[[0, -1], :] = 0.0
        grid[:, [0, -1]] = 0.0
        self.grid = grid

    def cells(self, xy: np.ndarray) -> np.ndarray:
        return np.floor((xy - self.origin) / self.res).astype(np.int64)


def _bounds(flat: np.ndarray, cells: np.ndarray, offsets: np.ndarray, count: int) -> np.ndarray:
    """Sum of ``flat`` (a raveled, zero-padded grid plus one trailing zero) at ``cells`` (A, M) flat indices
    shifted by each of ``offsets`` (O,) flat offsets, over ``count`` points: (A, O). Cells of -1 (points
    that never reach the target) read the trailing zero whatever the offset. Chunked over A."""
    out = np.empty((cells.shape[0], len(offsets)), dtype=np.float32)
    chunk = max(1, 2**22 // max(1, cells.shape[1] * len(offsets)))
    last = len(flat) - 1
    for a in range(0, cells.shape[0], chunk):
        c = cells[a : a + chunk, None, :]
        idx = np.where(c >= 0, c + offsets[None, :, None], last)
        out[a : a + chunk] = flat[idx].sum(axis=-1) / count
    return out


def match(
    source_xy: np.ndarray,
    target: LikelihoodGrid,
    init: tuple[float, float, float],
    window_t: float,
    window_yaw: float,
    *,
    block: int = 8,
    ratio: float = 0.9,
    distinct_t: float | None = None,
    distinct_yaw: float | None = None,
    floor: float = 0.0,
) -> Correlation:
    """Best pose (x, y, yaw) of the source points in the target's frame within ``window_t`` (m) and
    ``window_yaw`` (rad) of ``init``, and the runner-up score of a distinct alignment. Blocks that cannot
    reach ``floor`` are not opened (a score of 0 comes back when none can)."""
    res = target.res
    reach = max(float(np.percentile(np.hypot(source_xy[:, 0], source_xy[:, 1]), 90)), res)
    step = res / reach  # a rotation step moves the far points by about one cell
    n_yaw = int(np.ceil(min(window_yaw, np.pi) / step))
    yaws = init[2] + step * np.arange(-n_yaw, n_yaw + 1)
    if window_yaw >= np.pi:
        yaws = init[2] + np.linspace(-np.pi, np.pi, 2 * n_yaw + 1, endpoint=False)
    c, s = np.cos(yaws), np.sin(yaws)
    rotated = np.stack([c[:, None] * source_xy[:, 0] - s[:, None] * source_xy[:, 1],
                        s[:, None] * source_xy[:, 0] + c[:, None] * source_xy[:, 1]], axis=-1)
    w = int(np.ceil(window_t / res))
    nb = int(np.ceil((2 * w + 1) / block))
    # zero-pad so that every shift of a point near the grid stays inside it; points farther out than the
    # largest shift never reach the target and only count in the mean
    reach_cells = w + block
    pad = 2 * reach_cells
    grid = np.pad(target.grid, pad)
    upper = maximum_filter(grid, size=block, origin=-(block // 2), mode="constant")
    width = grid.shape[1]
    cells = target.cells(rotated + np.array(init[:2])) + pad  # (A, M, 2)
    inside = ((cells >= reach_cells) & (cells < np.array(grid.shape) - reach_cells)).all(axis=-1)
    cells = np.where(inside[..., None], cells, 0)
    flat_cells = cells[..., 0] * width + cells[..., 1]
    count = source_xy.shape[0]
    zero = np.zeros(1, dtype=np.float32)
    grid_flat = np.concatenate([grid.ravel(), zero])
    upper_flat = np.concatenate([upper.ravel(), zero])
    flat_cells = np.where(inside, flat_cells, -1)
    corner = np.stack(np.meshgrid(np.arange(nb), np.arange(nb), indexing="ij"), -1).reshape(-1, 2) * block - w
    fine = np.stack(np.meshgrid(np.arange(block), np.arange(block), indexing="ij"), -1).reshape(-1, 2)
    bounds = _bounds(upper_flat, flat_cells, corner[:, 0] * width + corner[:, 1], count)
    order = np.argsort(bounds, axis=None)[::-1]
    best, opened = -1.0, []
    for start in range(0, len(order), 32):  # open blocks 32 at a time, best bound first
        batch = order[start : start + 32]
        batch = batch[bounds.flat[batch] >= max(ratio * best, floor)]
        if len(batch) == 0:
            break
        angle, blk = np.divmod(batch, bounds.shape[1])
        offs = corner[blk][:, None, :] + fine[None]  # (K, block^2, 2)
        c = flat_cells[angle][:, None, :]  # (K, 1, M)
        idx = np.where(c >= 0, c + (offs[..., 0] * width + offs[..., 1])[..., None], len(grid_flat) - 1)
        sc = grid_flat[idx].sum(axis=-1) / count
        sc[(np.abs(offs) > w).any(axis=-1)] = -1.0
        k = np.argmax(sc, axis=1)
        opened.append((sc, angle, offs))
        best = max(best, float(sc[np.arange(len(batch)), k].max()))
    if not opened:
        return Correlation(*init, score=0.0, runner_up=0.0)
    scores = np.concatenate([o[0] for o in opened])  # (K, block^2): every cell of every opened block
    angles = np.concatenate([o[1] for o in opened])
    offsets = np.concatenate([o[2] for o in opened])
    blk, cell = np.unravel_index(int(np.argmax(scores)), scores.shape)
    score, a, off = float(scores[blk, cell]), int(angles[blk]), offsets[blk, cell]
    pose = (init[0] + off[0] * res, init[1] + off[1] * res, float(yaws[a]))
    dt, dy = distinct_t or 5 * res, distinct_yaw or 5 * step
    far = (np.hypot(*(offsets - off).transpose(2, 0, 1)) * res > dt) | (
        np.abs(se3.wrap_angle(yaws[angles] - yaws[a]))[:, None] > dy)
    runner, runner_pose = 0.0, None
    if far.any():
        masked = np.where(far, scores, -1.0)
        rb, rc = np.unravel_index(int(np.argmax(masked)), masked.shape)
        if masked[rb, rc] > 0:
            runner = float(masked[rb, rc])
            o2 = offsets[rb, rc]
            runner_pose = (init[0] + o2[0] * res, init[1] + o2[1] * res, float(yaws[angles[rb]]))
    axis = None
    if runner > 0 and runner >= ratio * score:  # ambiguous: does the ambiguity run along one line?
        axis = _ridge_axis(scores, offsets - off, se3.wrap_angle(yaws[angles] - yaws[a]), ratio * score, res, dt, dy)
    return Correlation(*pose, score=score, runner_up=runner, runner_up_pose=runner_pose, axis=axis)


def _ridge_axis(scores: np.ndarray, offsets: np.ndarray, dyaw: np.ndarray, level: float, res: float,
                distinct_t: float, distinct_yaw: float) -> tuple[float, float] | None:
    """Direction of the line on which every alignment scoring at least ``level`` lies (``offsets`` in cells
    and ``dyaw`` relative to the best), or None when they spread across it or in heading."""
    near = scores >= level
    if not near.any() or np.abs(dyaw[np.any(near, axis=1)]).max() > distinct_yaw:
        return None
    d = offsets[near].astype(np.float64) * res  # (n, 2) metres from the best
    _, vec = np.linalg.eigh(d.T @ d)
    if np.abs(d @ vec[:, 0]).max() > distinct_t / 2:
        return None
    return float(vec[0, 1]), float(vec[1, 1])
