"""The consistency profile's "all" view of a long sequence: each frame's cells at full density judged against the
map that every *other* frame makes, that map made once for the whole sequence from every frame's sparser cells.

The map (:class:`SparseMap`) is one plane assignment (``kernel.planes``) of every frame's sampled cells at a set of
poses. A judged cell lies on the plane of the voxel its mean falls in, the largest voxel first (as the assignment
puts its own cells; of the two faces of a panel the nearer), weighted as the assignment weighs its cells. A frame's
points on a plane are measured against that plane fitted without the frame's own sampled cells (leave-one-out), where
the others' points spread across the voxel, as :func:`kernel.planes.disagreement` measures a frame of the map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dm2_backend.kernel.geometry.voxels import group_rows
from dm2_backend.kernel.planes import (
    KERNEL,
    Assignment,
    Cells,
    assign,
    chunks,
    expand_moments,
    left_out_squares,
    moment_sums,
    moments_about,
    pair_ids,
    placed_means,
    placed_sum,
    plane_of,
)

#: bits of a packed voxel key per axis (a map spanning more voxels than this is matched by grouping keys)
BITS = 21


@dataclass(frozen=True)
class SparseMap:
    """One set of poses' map of every frame's sampled cells: its assignment, each plane's world moment about its
    voxel's centre (V,4,4) and fitted plane, and the keys that find a plane and a frame's own pair in it."""

    assignment: Assignment
    total: np.ndarray
    normal: np.ndarray
    offset: np.ndarray
    levels: tuple[_Level, ...]
    pair_key: np.ndarray
    pair_order: np.ndarray

    @classmethod
    def of(cls, cells: Cells, poses: np.ndarray, voxel: float) -> SparseMap:
        a = assign(cells, poses, voxel)
        total = placed_sum(a, poses)
        _, mu, _, normal = plane_of(np.where(total[:, 3:, 3:] > 0, total, np.eye(4)))
        offset = (normal * (mu + a.centre)).sum(1)
        levels = []
        for size in np.unique(a.size)[::-1]:  # the largest voxels first
            ids = np.flatnonzero(a.size == size)
            levels.append(_Level.of(float(size), np.floor(a.centre[ids] / size).astype(np.int64), ids))
        pair_key = a.frame.astype(np.int64) * max(a.voxels, 1) + a.voxel
        pair_order = np.argsort(pair_key, kind="stable")
        return cls(a, total, normal, offset, tuple(levels), pair_key[pair_order], pair_order)

    def plane_of_cells(self, world: np.ndarray) -> np.ndarray:
        """The plane (index) of each point of ``world`` (k,3), -1 where none: the largest voxel with a plane
        first; of two planes in a voxel (a panel's two faces) the nearer."""
        out = np.full(len(world), -1)
        best = np.full(len(world), np.inf)
        for level in self.levels:
            todo = np.flatnonzero(out < 0)
            if not len(todo):
                break
            first, count = level.find(np.floor(world[todo] / level.size).astype(np.int64))
            for k in range(int(count.max()) if len(count) else 0):  # (at most two faces a voxel)
                has = np.flatnonzero(count > k)
                at, plane = todo[has], level.ids[first[has] + k]
                dist = np.abs((self.normal[plane] * world[at]).sum(1) - self.offset[plane])
                nearer = dist < best[at]
                out[at[nearer]], best[at[nearer]] = plane[nearer], dist[nearer]
        return out

    def own_pair(self, frame: np.ndarray, plane: np.ndarray) -> np.ndarray:
        """The map's pair (index) of each (frame, plane), -1 where the frame has no sampled cell on the plane."""
        if not len(self.pair_key):
            return np.full(len(frame), -1)
        key = frame.astype(np.int64) * max(self.assignment.voxels, 1) + plane
        at = np.minimum(np.searchsorted(self.pair_key, key), len(self.pair_key) - 1)
        return np.where(self.pair_key[at] == key, self.pair_order[at], -1)


@dataclass(frozen=True)
class _Level:
    """The planes of one voxel size: their voxel keys (P,3) in order, as one int64 each (``code``: ``BITS`` bits an
    axis from ``low``), and their indices ``ids``; ``low`` None where the keys span more than ``BITS`` bits (then
    the keys are in lexicographic order and matched by grouping)."""

    size: float
    keys: np.ndarray
    low: np.ndarray | None
    code: np.ndarray
    ids: np.ndarray

    @classmethod
    def of(cls, size: float, keys: np.ndarray, ids: np.ndarray) -> _Level:
        low = keys.min(0) - 1 if len(keys) else np.zeros(3, np.int64)
        code = _packed(keys, low)
        if (code < 0).any():
            order = np.lexsort(keys.T[::-1])
            return cls(size, keys[order], None, code[order], ids[order])
        order = np.argsort(code, kind="stable")
        return cls(size, keys[order], low, code[order], ids[order])

    def find(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For each voxel key (k,3): the first of its planes (a position in ``ids``) and how many there are."""
        planes = self.code
        if self.low is not None:
            code = _packed(keys, self.low)
        else:  # groups are numbered in the keys' order, as the planes are sorted
            inv, _ = group_rows(np.concatenate([self.keys, keys]))
            planes, code = inv[:len(self.keys)], inv[len(self.keys):]
        first = np.searchsorted(planes, code, "left")
        return first, np.searchsorted(planes, code, "right") - first


def _packed(key: np.ndarray, low: np.ndarray) -> np.ndarray:
    """One int64 a voxel key (K,3) from ``low``; -1 for a key outside the span (it meets no plane)."""
    k = key - low
    inside = ((k >= 0) & (k < (1 << BITS))).all(1)
    return np.where(inside, (k[:, 0] << (2 * BITS)) | (k[:, 1] << BITS) | k[:, 2], -1)


def judged_against_map(cells: Cells, poses: np.ndarray, judged: np.ndarray, world_map: SparseMap, cap: float
                       ) -> np.ndarray:
    """Per frame, the RMS distance (m) of the ``judged`` frames' ``cells`` (frames numbered as ``poses``) to the
    planes the other frames make in ``world_map``, each (frame, plane) pair capped at ``cap`` noise sigmas and the
    points of a frame weighed as :func:`kernel.planes.disagreement` (``bounded``) weighs them; NaN for the frames
    not judged or with no point on such a plane."""
    a = world_map.assignment
    n = len(poses)
    on = np.flatnonzero(judged[cells.frame])
    plane = np.full(len(on), -1)
    weight = np.zeros(len(on))
    for c in chunks(len(on)):
        part = Cells(cells.frame[on[c]], cells.count[on[c]], cells.mean[on[c]], cells.scatter[on[c]], cells.size)
        world = placed_means(part, poses, slice(None))
        plane[c] = world_map.plane_of_cells(world)
        hit = plane[c] >= 0
        r = (world_map.normal[plane[c][hit]] * world[hit]).sum(1) - world_map.offset[plane[c][hit]]
        z = np.sqrt(part.count[hit].astype(np.float64)) * np.abs(r)
        w = np.zeros(len(world))
        w[hit] = 1.0 / (1.0 + (z / (KERNEL * a.sigma)) ** 2)
        weight[c] = w
    keep = plane >= 0
    rows, plane, weight = on[keep], plane[keep], weight[keep]
    frame = cells.frame[rows].astype(np.int64)
    pair, first = pair_ids(frame, plane, a.voxels)
    moment = moment_sums(cells, rows, pair, len(first), weight)
    points = np.bincount(pair, cells.count[rows].astype(np.float64), minlength=len(first))
    frame, plane = frame[first], plane[first]
    own = world_map.own_pair(frame, plane)
    sq_sum, own_sum = np.zeros(n), np.zeros(n)
    for c in chunks(len(first)):
        M_pair = expand_moments(moments_about(poses, frame[c], a.centre[plane[c]], moment[c]))
        mine = own[c]
        rest = world_map.total[plane[c]].copy()
        has = mine >= 0
        rest[has] -= expand_moments(moments_about(poses, a.frame[mine[has]], a.centre[plane[c][has]],
                                                  a.moment[mine[has]]))
        sq, keep = left_out_squares(M_pair, rest, a.size[plane[c]], cap * a.sigma)
        sq_sum += np.bincount(frame[c], sq, minlength=n)
        own_sum += np.bincount(frame[c], points[c] * keep, minlength=n)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.sqrt(sq_sum / own_sum)
    out[~judged] = np.nan
    return out
