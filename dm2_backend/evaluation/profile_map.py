"""The consistency profile's "all" view of a long sequence: each frame's cells at full density judged against the
map that every *other* frame makes, that map made once for the whole sequence from every frame's sampled cells.

The map (:class:`SparseMap`) is one plane assignment (``kernel.planes``) of every frame's sampled cells at a set of
poses. A judged cell lies where the assignment would put it: on the plane of the largest voxel its mean falls in
whose plane faces the cell's sensor (a panel seen from both sides has a plane a face), weighted by the assignment's
kernel on its distance to that plane. A frame's points on a plane are measured against the plane the map's points
make without the frame's own sampled ones (leave-one-out; ``kernel.planes.left_out_squares``), as
``kernel.planes.disagreement`` measures a frame of the map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dm2_backend.kernel.geometry.voxels import group_rows
from dm2_backend.kernel.planes import (
    Assignment,
    Cells,
    assign,
    cell_weight,
    chunks,
    expand_moments,
    left_out_squares,
    moment_sums,
    moments_about,
    pair_ids,
    placed_means,
    placed_sum,
    plane_of,
    standard_distance,
)

#: bits of a packed voxel key per axis (a map spanning more voxels than this is matched by grouping keys)
BITS = 21


@dataclass(frozen=True)
class SparseMap:
    """One set of poses' map of every frame's sampled cells: its assignment, each plane's world moment about its
    voxel's centre (V,4,4) and its plane ``normal . x = offset`` with the normal towards the sensors that see it,
    the planes of each voxel size (largest first) and each (frame, plane) pair's key (sorted: the assignment
    numbers its pairs so)."""

    assignment: Assignment
    total: np.ndarray
    normal: np.ndarray
    offset: np.ndarray
    levels: tuple[_Level, ...]
    pair_key: np.ndarray

    @classmethod
    def of(cls, cells: Cells, poses: np.ndarray, voxel: float) -> SparseMap:
        """The map of ``cells`` at ``poses``: one :func:`~dm2_backend.kernel.planes.assign` with ``voxel``."""
        a = assign(cells, poses, voxel)
        total = placed_sum(a, poses)
        _, mu, _, normal = plane_of(np.where(total[:, 3:, 3:] > 0, total, np.eye(4)))
        sensor = np.take(poses[:, :3, 3], a.frame, axis=0) - np.take(a.centre, a.voxel, axis=0)
        facing = np.bincount(a.voxel, (np.take(normal, a.voxel, axis=0) * sensor).sum(1) * a.points,
                             minlength=a.voxels)
        normal = np.where(facing[:, None] < 0, -normal, normal)
        levels = tuple(_Level.of(float(size), a.centre, np.flatnonzero(a.size == size))
                       for size in np.unique(a.size)[::-1])
        return cls(a, total, normal, (normal * (mu + a.centre)).sum(1), levels,
                   a.frame.astype(np.int64) * max(a.voxels, 1) + a.voxel)

    def plane_of_cells(self, world: np.ndarray, sensor: np.ndarray) -> np.ndarray:
        """The plane (index) of each point ``world`` (k,3) seen from ``sensor`` (k,3), -1 where none: in the
        largest voxel with a plane that faces the sensor (of two such, the nearer)."""
        out = np.full(len(world), -1)
        best = np.full(len(world), np.inf)
        todo = np.flatnonzero(np.isfinite(world).all(1))
        for level in self.levels:
            if not len(todo):
                break
            first, count = level.find(np.floor(world[todo] / level.size).astype(np.int64))
            for k in range(int(count.max())):  # (at most two faces a voxel)
                has = np.flatnonzero(count > k)
                at, plane = todo[has], np.take(level.ids, first[has] + k)
                n = np.take(self.normal, plane, axis=0)
                dist = (n * world[at]).sum(1) - np.take(self.offset, plane)
                faces = (n * sensor[at]).sum(1) - np.take(self.offset, plane) >= 0.0
                nearer = faces & (np.abs(dist) < best[at])
                out[at[nearer]], best[at[nearer]] = plane[nearer], np.abs(dist[nearer])
            todo = todo[out[todo] < 0]
        return out

    def own_pair(self, frame: np.ndarray, plane: np.ndarray) -> np.ndarray:
        """The map's pair (index) of each (frame, plane), -1 where the frame has no sampled cell on the plane."""
        if not len(self.pair_key):
            return np.full(len(frame), -1)
        key = frame.astype(np.int64) * max(self.assignment.voxels, 1) + plane
        at = np.minimum(np.searchsorted(self.pair_key, key), len(self.pair_key) - 1)
        return np.where(self.pair_key[at] == key, at, -1)


@dataclass(frozen=True)
class _Level:
    """The planes of one voxel size, sorted by their voxel's key: their indices ``ids`` and the keys, each packed
    into one int64 (``BITS`` bits an axis from ``low``), or, where the keys span more than that (``low`` None),
    the (P,3) keys in lexicographic order, matched by grouping."""

    size: float
    ids: np.ndarray
    low: np.ndarray | None
    keys: np.ndarray

    @classmethod
    def of(cls, size: float, centre: np.ndarray, ids: np.ndarray) -> _Level:
        """The planes ``ids`` of edge ``size`` (their voxels' ``centre`` rows)."""
        keys = np.floor(centre[ids] / size).astype(np.int64)
        low = keys.min(0)
        packed = _packed(keys, low)
        if (packed < 0).any():
            order = np.lexsort(keys.T[::-1])
            return cls(size, ids[order], None, keys[order])
        order = np.argsort(packed, kind="stable")
        return cls(size, ids[order], low, packed[order])

    def find(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For each voxel key (k,3): the first of its planes (a position in ``ids``) and how many there are."""
        if self.low is not None:
            planes, code = self.keys, _packed(keys, self.low)
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
    """Per frame, the mean squared distance (m^2) of the ``judged`` frames' ``cells`` (frames numbered as
    ``poses``) to the planes the other frames make in ``world_map``, each (frame, plane) pair capped at ``cap``
    noise sigmas, over all the frame's points on such planes (as ``disagreement(..., bounded=True)``); NaN for
    the frames not judged or with no point on such a plane."""
    a = world_map.assignment
    n = len(poses)
    rows = np.flatnonzero(judged[cells.frame])
    plane = np.full(len(rows), -1)
    weight = np.zeros(len(rows))
    for c in chunks(len(rows)):
        part = Cells(*(np.take(getattr(cells, f), rows[c], axis=0) for f in ("frame", "count", "mean", "scatter")),
                     cells.size)
        world = placed_means(part, poses, slice(None))
        plane[c] = world_map.plane_of_cells(world, np.take(poses[:, :3, 3], part.frame, axis=0))
        on = plane[c] >= 0
        r = (np.take(world_map.normal, plane[c][on], axis=0) * world[on]).sum(1) - np.take(world_map.offset,
                                                                                          plane[c][on])
        weight[np.flatnonzero(on) + c.start] = cell_weight(standard_distance(part.count[on], r), a.sigma)
    on = plane >= 0
    rows, plane, weight = rows[on], plane[on], weight[on]
    frame = cells.frame[rows].astype(np.int64)
    pair, first = pair_ids(frame, plane, a.voxels)
    moment = moment_sums(cells, rows, pair, len(first), weight)
    points = np.bincount(pair, cells.count[rows].astype(np.float64), minlength=len(first))
    frame, plane = frame[first], plane[first]
    own = world_map.own_pair(frame, plane)
    sq_sum, own_sum = np.zeros(n), np.zeros(n)
    for c in chunks(len(first)):
        centre = np.take(a.centre, plane[c], axis=0)
        M_pair = expand_moments(moments_about(poses, frame[c], centre, moment[c]))
        rest = np.take(world_map.total, plane[c], axis=0)
        mine = np.flatnonzero(own[c] >= 0)
        pairs = own[c][mine]
        rest[mine] -= expand_moments(moments_about(poses, a.frame[pairs], centre[mine], a.moment[pairs]))
        sq, keep = left_out_squares(M_pair, rest, np.take(a.size, plane[c]), cap * a.sigma)
        sq_sum += np.bincount(frame[c], sq, minlength=n)
        own_sum += np.bincount(frame[c], points[c] * keep, minlength=n)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = sq_sum / own_sum
    out[~judged] = np.nan
    return out
