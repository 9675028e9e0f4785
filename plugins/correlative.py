"""Correlative scan matching in 2D (Olson 2009) with a two-level branch and bound: a global search over
translation and rotation for the pose that puts the most source points on target structure, and the
best clearly different alignment (the runner-up), which exposes ambiguous matches such as corridors.

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


def _scores(grid: np.ndarray, cells: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Mean grid value of ``cells`` (A, M, 2) shifted by each of ``offsets`` (O, 2): (A, O)."""
    hi = np.array(grid.shape) - 1
    out = np.empty((cells.shape[0], len(offsets)), dtype=np.float32)
    for a in range(cells.shape[0]):
        c = np.clip(cells[a][None, :, :] + offsets[:, None, :], 0, hi)  # (O, M, 2)
        out[a] = grid[c[..., 0], c[..., 1]].mean(axis=1)
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
) -> Correlation:
    """Best pose (x, y, yaw) of the source points in the target's frame within ``window_t`` (m) and
    ``window_yaw`` (rad) of ``init``, and the runner-up score of a distinct alignment."""
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
    cells = target.cells(rotated + np.array(init[:2]))  # (A, M, 2)
    w = int(np.ceil(window_t / res))
    nb = int(np.ceil((2 * w + 1) / block))
    corner = np.stack(np.meshgrid(np.arange(nb), np.arange(nb), indexing="ij"), -1).reshape(-1, 2) * block - w
    upper = maximum_filter(target.grid, size=block, origin=-(block // 2), mode="constant")
    bounds = _scores(upper, cells, corner)  # (A, B)
    fine = np.stack(np.meshgrid(np.arange(block), np.arange(block), indexing="ij"), -1).reshape(-1, 2)
    order = np.argsort(bounds, axis=None)[::-1]
    best, opened = -1.0, []
    for flat in order:
        a, b = divmod(int(flat), bounds.shape[1])
        if bounds[a, b] < ratio * best:
            break
        offs = corner[b] + fine
        offs = offs[(np.abs(offs) <= w).all(axis=1)]
        sc = _scores(target.grid, cells[a : a + 1], offs)[0]
        k = int(np.argmax(sc))
        opened.append((float(sc[k]), a, offs[k]))
        best = max(best, float(sc[k]))
    score, a, off = max(opened, key=lambda t: t[0])
    pose = (init[0] + off[0] * res, init[1] + off[1] * res, float(yaws[a]))
    dt, dy = distinct_t or 5 * res, distinct_yaw or 5 * step
    runner, runner_pose = 0.0, None
    for sc, a2, off2 in opened:
        far_t = np.hypot(*(off2 - off)) * res > dt
        far_r = abs(np.angle(np.exp(1j * (yaws[a2] - yaws[a])))) > dy
        if (far_t or far_r) and sc > runner:
            runner = sc
            runner_pose = (init[0] + off2[0] * res, init[1] + off2[1] * res, float(yaws[a2]))
    return Correlation(*pose, score=score, runner_up=runner, runner_up_pose=runner_pose)
