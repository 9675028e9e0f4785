"""The overlap gate of ``loops`` counts only what the other visit could see: two visits that meet at a junction
(one drives along the main corridor, the other comes out of a side corridor, turns and goes back) overlap fully where
both could see, though each submap holds a corridor the other never entered."""

from __future__ import annotations

import numpy as np

from dm2_backend.algorithms.common import Cloud
from dm2_backend.kernel.geometry import se3
from dm2_backend.plugins.topology_loops import LoopsTopology


def _walls(spacing: float = 0.05) -> np.ndarray:
    """A corridor along x (walls at y = +-1) with a side corridor leaving it at x = 0 towards +y (x = +-1)."""
    x = np.arange(-20, 20, spacing)
    y = np.arange(1, 20, spacing)
    main = [
        np.column_stack([x, np.full_like(x, -1.0)]),
        np.column_stack([x[np.abs(x) > 1], np.full(int((np.abs(x) > 1).sum()), 1.0)]),
    ]
    side = [np.column_stack([np.full_like(y, -1.0), y]), np.column_stack([np.full_like(y, 1.0), y])]
    return np.concatenate(main + side)


def _seen(walls: np.ndarray, origins: np.ndarray, reach: float) -> np.ndarray:
    d = np.linalg.norm(walls[:, None, :] - origins[None], axis=-1).min(axis=1)
    return walls[d < reach]


def _gate(reach: float = 5.0, res: float = 0.1):
    walls = _walls()
    s = np.arange(0, 8.01, 0.5)
    along = np.column_stack([np.concatenate([-s[::-1], s[1:]]), np.zeros(2 * len(s) - 1)])  # visit a: along x
    uturn = np.column_stack([np.zeros(2 * len(s) - 1), np.concatenate([s[::-1], s[1:]])])  # b: in and out of the side
    maps = [_seen(walls, along, reach), _seen(walls, uturn, reach)]  # both keyframes at the junction, yaw 0
    lt = LoopsTopology(progress=False)
    lt._lengths = {"resolution": res, "reach": reach}
    lt._origins = [along, uturn]
    cloud = lambda xy: Cloud(np.column_stack([xy, np.zeros(len(xy))]), True, 2 * res)  # noqa: E731
    lt._clouds = (cloud(maps[1]), cloud(maps[0]))  # (source: b, target: a)
    return lt


def test_overlap_counts_what_the_other_visit_could_see():
    lt = _gate()
    visible, whole = lt._overlap(0, 1, np.eye(4))
    assert whole < 0.5  # each submap holds a corridor the other never entered: the plain share fails the gate
    assert visible > 0.9
    # a wrong alignment (half a corridor across) still fails, whatever the visit saw
    off, _ = lt._overlap(0, 1, se3.from_xy_yaw(np.array([[0.0, 0.5, 0.0]]))[0])
    assert off < 0.4
    turned, _ = lt._overlap(0, 1, se3.from_xy_yaw(np.array([[0.0, 0.0, 0.3]]))[0])
    assert turned < 0.5
