"""The dense multi-frame term of the objective: every scan point against planes shared by many frames.

Each scan is compressed once, in its sensor frame, into small cells holding the point count, mean and scatter (sum
of outer products about the mean) of their points (:class:`Cells`). The cells lie along the beams (a beam
direction's bin, a run of range bins: :func:`_beam_cells`), so a sensor's range noise, which lies along its beams,
does not split one surface into cells (3D scans; planar scans and the consistency profile keep cubes of a grid in the
sensor frame). These sums are all a point-to-plane cost needs: for a plane ``n . x = d`` and a frame at pose
(R, t), the squared distances of a cell's N points sum to ``N (n . (R mu + t) - d)^2 + m^T C m`` with ``m = R^T n``
(BALM2's point clusters, Liu et al. TRO 2023), so cost, gradient and Gauss-Newton Hessian are independent of the
number of points. The second term measures a cell's thickness; where that is mostly the sensor's range noise, which
lies along the beam (a depth camera's cells, a millimetre thick near it, centimetres across a room), it turns each
frame to lay its beams along the planes: from the truth, frames drift round after round. The dense stage therefore
takes a thick cell's points at its mean and keeps the scatter of thin cells only (:func:`kept_scatter`,
``optimiser.dense_cell_scatter``).

Planes come from many frames, never one scan (a 16-beam LiDAR's ground is a set of rings, lines, in one
scan): the cells are placed in the world by the current poses, grouped into voxels, and a voxel whose merged
points are flat (smallest eigenvalue of their covariance well below the middle one) and seen by at least two
frames gives a plane; a voxel that is not flat is split into eight, down to ``levels`` sizes (BALM's adaptive
voxelisation). A surface is seen from one side: the cells of a voxel whose sensors lie on either side of its plane
make a plane per side (the two faces of a thin panel). Each cell then pulls its frame towards its voxel's plane;
its weight is a Cauchy kernel of its mean's distance in units of the robust noise scale, so a moving object or a
corner that slipped into a flat voxel pulls with bounded force.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.sparse import bsr_matrix, csr_matrix

from dm2_backend.kernel.geometry.symmetric3 import smallest_eigen
from dm2_backend.kernel.geometry.voxels import flat_keys, group_rows
from dm2_backend.kernel.scans import ScanSequence
from dm2_backend.runtime.progress import progress as progress_of
from dm2_backend.runtime.threads import ordered_map

#: a voxel is flat when its smallest covariance eigenvalue is below this fraction of the middle one
#: (thickness under a quarter of its width) ...
FLATNESS = 1.0 / 16.0
#: ... and it spreads over at least this fraction of its size along the middle axis (not a pole or one ring)
MIN_WIDTH = 1.0 / 8.0
#: points a voxel needs to carry a plane
MIN_POINTS = 10
#: Cauchy kernel width on a cell mean's distance to its plane, in noise sigmas
KERNEL = 3.0
#: which cells keep their scatter (:func:`kept_scatter`)
CellScatter = Literal["all", "thin", "none"]


@dataclass
class Cells:
    """Every frame's points summed into cells along the beams, ``size`` wide at the scan's median range and deep
    (sensor frame; :func:`_beam_cells`; or cubes of edge ``size``): ``frame[k]`` the frame of cell k, ``count``
    its points, ``mean`` (K,3) their mean, ``scatter`` (K,6) the sum of (p - mean)(p - mean)^T (entries xx xy xz
    yy yz zz)."""

    frame: np.ndarray
    count: np.ndarray
    mean: np.ndarray
    scatter: np.ndarray
    size: float

    def __len__(self) -> int:
        return len(self.frame)

    def of_frames(self, keep: np.ndarray) -> Cells:
        """The cells of the frames where ``keep`` (bool per frame) is set; frame numbers unchanged."""
        on = keep[self.frame]
        return Cells(self.frame[on], self.count[on], self.mean[on], self.scatter[on], self.size)

    def extruded(self, height: float) -> Cells:
        """Planar scans (z = 0) seen as vertical walls ``height`` tall: each cell's points spread uniformly in z,
        so a line of a 2D scan is a plane here, with the line's normal (poses must keep z vertical)."""
        scatter = self.scatter.copy()
        scatter[:, 5] += self.count * np.float32(height**2 / 12.0)
        return Cells(self.frame, self.count, self.mean, scatter, self.size)


#: the entries (row, column) of a 3x3 scatter that :class:`Cells` keep, and the column of each
_SCATTER = np.triu_indices(3)
_SCATTER_AT = np.zeros((3, 3), dtype=np.int64)
_SCATTER_AT[_SCATTER] = np.arange(6)


def compress(points: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One scan's cells: count (K,), mean (K,3), scatter (K,6), float64."""
    pts, inv, k = _grouped(points, size, None)
    return _summed(pts, inv, k)


def _grouped(points: np.ndarray, size: float, share: int | None,
             along_beams: bool = True) -> tuple[np.ndarray, np.ndarray, int]:
    """A scan's finite points (float64) and the id of each one's cell of ``size``, or ``2 * size`` where ``size``
    gives more than ``share`` cells; and the number of cells. ``along_beams``: cells along the beams
    (:func:`_beam_cells`), else the cubes of a grid in the sensor frame."""
    pts = np.asarray(points, dtype=np.float64)[:, :3]
    if not np.isfinite(pts).all():  # (a scan sequence drops them already)
        pts = pts[np.isfinite(pts).all(1)]
    if len(pts) == 0:
        return pts, np.zeros(0, np.int64), 0
    if not along_beams:
        keys = np.floor(pts / size).astype(np.int64)
        inv, k = group_rows(keys)
        if share is not None and k > share:  # floor(p / 2s) = floor(floor(p / s) / 2): group the cells
            cell_keys = np.empty((k, 3), np.int64)
            cell_keys[inv] = keys
            coarse, k = group_rows(cell_keys // 2)
            inv = coarse[inv]
        return pts, inv, k
    distance = np.linalg.norm(pts, axis=1)
    reference = max(float(np.median(distance)), size)
    unit = pts / np.maximum(distance, 1e-12)[:, None]
    inv, k = _beam_cells(unit, distance, size, reference)
    if share is not None and k > share:
        inv, k = _beam_cells(unit, distance, 2.0 * size, reference)
    return pts, inv, k


def _beam_cells(unit: np.ndarray, distance: np.ndarray, size: float, reference: float) -> tuple[np.ndarray, int]:
    """Each point's cell (its beam's ``unit`` direction, of length one, and its ``distance``) and the number of cells:
    its beam's direction binned ``size`` wide at the ``reference`` range (the scan's median), its range binned
    ``size`` deep, and the consecutive range bins of one direction merged (so a cell is a bin deep or more). A
    sensor's noise lies along its beams: cells cut by a fixed grid split a surface whose noisy ranges straddle a bin
    edge into a near and a far part, each mean pulled along the beam, and those pulls turn the frames
    (docs/decisions/0003-beam-cells.md). Along the beam only an empty bin parts two cells (two
    surfaces, not one surface's noise, while that noise is under a bin). Runs are not capped: a surface seen at a
    grazing angle can make a cell longer than a voxel. Far out the cells are wider (a LiDAR's at three times the
    median range, three times ``size``): the directions are not binned finer there, where a frame would pass its
    share of cells and keep fewer points."""
    if len(distance) == 0:
        return np.zeros(0, np.int64), 0
    direction = np.floor(unit * (reference / size)).astype(np.int64)
    depth = np.floor(distance / size).astype(np.int64)
    depth -= depth.min()
    flat = flat_keys(np.concatenate([direction, depth[:, None]], 1))  # one sort: by direction, then range
    if flat is None:
        direction, _ = group_rows(direction)
        order = np.lexsort((depth, direction))
    else:  # the range bin is the key's last digit (from 0, base depth.max() + 1): the rest is the direction
        direction = flat // (int(depth.max()) + 1)
        order = np.argsort(flat, kind="stable")
    beam, bin_ = direction[order], depth[order]
    starts = np.ones(len(order), bool)
    starts[1:] = (beam[1:] != beam[:-1]) | (bin_[1:] - bin_[:-1] > 1)
    inv = np.empty(len(order), np.int64)
    inv[order] = np.cumsum(starts) - 1
    return inv, int(starts.sum())


def _summed(pts: np.ndarray, inv: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Count, mean and scatter (float64) of the points of each of the ``k`` cells ``inv`` numbers."""
    count = np.bincount(inv, minlength=k).astype(np.float64)
    mean = np.stack([np.bincount(inv, pts[:, a], minlength=k) for a in range(3)], 1) / count[:, None]
    d = pts - mean[inv]
    scatter = np.stack([np.bincount(inv, d[:, i] * d[:, j], minlength=k) for i, j in zip(*_SCATTER, strict=True)],
                       1)
    return count, mean, scatter.reshape(k, 6)


def cells_from_scans(scans: ScanSequence, size: float, per_frame: int, max_cells: int, seed: int = 0,
                     progress: bool = False, keep_scatter: CellScatter = "all",
                     along_beams: bool | None = None) -> Cells:
    """Every scan compressed into cells (scans on threads), at most ``per_frame`` a frame and ``max_cells`` in all (at
    least 64 a frame): a frame with more is summed into cells twice as large (once), and keeps a random subset of
    those if still too many (each kept cell exact: only its points are summed). ``Cells.size`` is the cells' nominal
    size (``size``). ``keep_scatter``: which cells keep their scatter (:func:`kept_scatter`); the others' points are
    taken at their mean. ``along_beams``: cells along the beams (:func:`_beam_cells`), else cubes of a grid in the
    sensor frame; by default along the beams for 3D scans, cubes for planar ones."""
    along_beams = not scans.planar if along_beams is None else along_beams
    share = min(per_frame, max(64, max_cells // max(len(scans), 1)))
    rng = np.random.default_rng(seed)

    def fitted(scan) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray] | None, np.ndarray, np.ndarray, int]:
        """The scan's cells where they fit the share, else None (a subset is drawn in order); its points' ids."""
        pts, inv, k = _grouped(scan.points, size, share, along_beams)
        return (_summed(pts, inv, k) if k <= share else None), pts, inv, k

    bar = progress_of(scans, "dense cells", total=len(scans), unit="scan", enabled=progress)
    parts = []
    for i, (cells, pts, inv, k) in enumerate(ordered_map(fitted, bar)):
        if cells is None:
            kept = np.zeros(k, bool)
            kept[rng.choice(k, share, replace=False)] = True
            on = kept[inv]
            cells = _summed(pts[on], (np.cumsum(kept) - 1)[inv[on]], share)
        count, mean, spread = cells
        spread = np.where(kept_scatter(spread, keep_scatter)[:, None], spread, 0.0)
        parts.append((np.full(len(count), i, np.int32), count.astype(np.float32), mean.astype(np.float32),
                      spread.astype(np.float32)))
    if not parts:
        return Cells(np.zeros(0, np.int32), np.zeros(0, np.float32), np.zeros((0, 3), np.float32),
                     np.zeros((0, 6), np.float32), size)
    return Cells(*(np.concatenate(a) for a in zip(*parts, strict=True)), size)


def kept_scatter(scatter: np.ndarray, which: CellScatter) -> np.ndarray:
    """Which cells (their (K,6) scatter) keep it: "all", "none", or "thin": those thinner than a quarter of their
    width (smallest scatter eigenvalue under :data:`FLATNESS` of the middle one, the voxels' flatness test). A
    thicker cell's thickness is mostly the sensor's range noise, which lies along the beam; in the cost its scatter
    turns the frame to lay its beams along the plane (see the module docstring;
    docs/decisions/0004-thin-cell-scatter.md)."""
    if which == "all":
        return np.ones(len(scatter), bool)
    if which == "none":
        return np.zeros(len(scatter), bool)
    full = np.zeros((len(scatter), 3, 3))
    full[:, _SCATTER[0], _SCATTER[1]] = scatter
    full[:, _SCATTER[1], _SCATTER[0]] = scatter
    lam = np.linalg.eigvalsh(full)
    return lam[:, 0] < FLATNESS * lam[:, 1]


@dataclass
class Assignment:
    """Which cells lie on which plane, fixed for a few rounds: per (frame, voxel) pair its ``frame`` (P,),
    ``voxel`` (P,) and ``moment`` (P,10), the robust-weighted sum of [p 1]^T [p 1] over the frame's points in
    the voxel (sensor frame), as its distinct entries (:func:`expand_moments` makes the 4x4 of a few pairs at a time);
    ``centre`` (V,3) a point of each voxel (the fits are made about it); ``sigma`` the noise scale (m) at the
    poses of the assignment, ``cells`` the cells on planes."""

    frame: np.ndarray
    voxel: np.ndarray
    moment: np.ndarray
    centre: np.ndarray
    sigma: float
    cells: int
    #: each pair's points, unweighted (P,)
    points: np.ndarray | None = None
    #: each voxel's edge (V,) (m)
    size: np.ndarray | None = None

    @property
    def voxels(self) -> int:
        return len(self.centre)


@dataclass
class Planes:
    """The planes ``n . x = d`` (world) of an assignment's voxels at some poses, and their cost: ``residual``
    (V,) the weighted sum of squared distances of the voxel's points to its plane (m^2)."""

    normal: np.ndarray
    offset: np.ndarray
    residual: np.ndarray


def _sum(inv: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Sums of ``values`` rows by group id ``inv`` (one sparse product for every column)."""
    pick = csr_matrix((np.ones(len(inv)), (inv, np.arange(len(inv)))), shape=(n, len(inv)))
    return np.asarray(pick @ values.reshape(len(values), -1)).reshape((n,) + values.shape[1:])


#: the 10 distinct entries of a symmetric 4x4 moment, as (row, column)
_UPPER = np.triu_indices(4)


def columns(a: np.ndarray, rows: np.ndarray, dtype: type | None = None) -> np.ndarray:
    """The rows ``rows`` of ``a`` (K,C) as contiguous columns (C,k) (of ``dtype``, default ``a``'s), a column at a
    time (``np.take``: far faster than fancy indexing a 2D array, the same values)."""
    out = np.empty((a.shape[1], len(rows)), dtype or a.dtype)
    for i in range(a.shape[1]):
        out[i] = np.take(a[:, i], rows)
    return out


def pair_ids(frame: np.ndarray, voxel: np.ndarray, voxels: int) -> tuple[np.ndarray, np.ndarray]:
    """The (frame, voxel) pair of each cell, numbered in the order of frame, then voxel, and one cell of each
    pair (its frame and voxel stand for the pair's)."""
    _, first, inv = np.unique(frame * max(voxels, 1) + voxel, return_index=True, return_inverse=True)
    return inv.ravel(), first


#: pairs (or cells) handled at a time where each needs a few 4x4 and 6x4 temporaries (bounds the memory)
CHUNK = 100_000


def chunks(n: int) -> list[slice]:
    return [slice(i, min(i + CHUNK, n)) for i in range(0, n, CHUNK)]


def placed_sum(a: Assignment, poses: np.ndarray, keep: np.ndarray | None = None) -> np.ndarray:
    """Each voxel's moment in the world (about its centre): the sum of its pairs' (V,4,4), in chunks; ``keep``
    (bool per pair): only those pairs."""
    M = np.zeros((a.voxels, 10))
    for c in chunks(len(a.frame)):
        placed = moments_about(poses, a.frame[c], np.take(a.centre, a.voxel[c], axis=0), a.moment[c])
        M += _sum(a.voxel[c], placed if keep is None else placed * keep[c, None], a.voxels)
    return expand_moments(M)


def moment_sums(cells: Cells, rows: np.ndarray, group: np.ndarray, n: int,
                weight: np.ndarray | None = None) -> np.ndarray:
    """Sums by ``group`` (into ``n``) of the homogeneous moments [p 1]^T [p 1] (sensor frame) of cells ``rows``
    (times ``weight``), as their 10 distinct entries (n,10) in the order of ``_UPPER``: one entry at a time over
    contiguous rows, no (K,10) array of every cell's moment."""
    N = np.take(cells.count, rows).astype(np.float64)
    if weight is not None:
        N *= weight
    mu = columns(cells.mean, rows, np.float64)
    scatter = columns(cells.scatter, rows)
    weighted_mu = N * mu
    out = np.empty((10, n))  # an entry's sums contiguous (returned transposed: a column at a time is slow)
    for j, (r, c) in enumerate(zip(*_UPPER, strict=True)):
        if r == 3:
            v = N
        elif c == 3:
            v = weighted_mu[r]
        else:  # the scatter about the mean plus N mu_r mu_c
            v = weighted_mu[r] * mu[c]
            v += scatter[_SCATTER_AT[r, c]] if weight is None else weight * scatter[_SCATTER_AT[r, c]]
        out[j] = np.bincount(group, v, minlength=n)
    return out.T


#: for each entry of a 4x4 moment (row-major), its column among the 10 distinct ones
_FULL = np.zeros((4, 4), dtype=np.int64)
_FULL[_UPPER] = _FULL[_UPPER[1], _UPPER[0]] = np.arange(10)


def expand_moments(flat: np.ndarray) -> np.ndarray:
    """(P,10) distinct entries -> (P,4,4) symmetric moments."""
    return np.take(flat, _FULL.ravel(), axis=1).reshape(-1, 4, 4)


def _pose_rows(poses: np.ndarray) -> np.ndarray:
    """The top three rows of the poses (N,4,4) entry by entry, (3,4,N) contiguous: a gather a row at a time."""
    return np.ascontiguousarray(poses[:, :3, :].transpose(1, 2, 0))


def moments_about(poses: np.ndarray, frame: np.ndarray, centre: np.ndarray, moment: np.ndarray) -> np.ndarray:
    """Moments of frames ``frame`` in the world, about the points ``centre`` (P,3): T Q T^T with
    T = [R, t - centre] (no cancellation far from the origin), from and to the 10 distinct entries (P,10) of the
    moments (order of ``_UPPER``), one entry at a time over contiguous rows: with Q = [[S, b], [b^T, N]] and
    u = t - centre the result is [[R S R^T + (R b) u^T + u (R b)^T + N u u^T, R b + N u], [., N]]."""
    rows = _pose_rows(poses)
    R = [[np.take(rows[i, j], frame) for j in range(3)] for i in range(3)]
    c = np.ascontiguousarray(centre.T)
    u = [np.take(rows[i, 3], frame) - c[i] for i in range(3)]
    m = np.ascontiguousarray(moment.T)
    S = [[m[_FULL[i, j]] for j in range(3)] for i in range(3)]
    b = [m[_FULL[i, 3]] for i in range(3)]
    N = m[9]
    RS = [[R[i][0] * S[0][j] + R[i][1] * S[1][j] + R[i][2] * S[2][j] for j in range(3)] for i in range(3)]
    Rb = [R[i][0] * b[0] + R[i][1] * b[1] + R[i][2] * b[2] for i in range(3)]
    out = np.empty((10, len(moment)))
    for j, (r, k) in enumerate(zip(*_UPPER, strict=True)):
        if r == 3:
            out[j] = N
        elif k == 3:
            out[j] = Rb[r] + N * u[r]
        else:
            out[j] = (RS[r][0] * R[k][0] + RS[r][1] * R[k][1] + RS[r][2] * R[k][2] + Rb[r] * u[k] + u[r] * Rb[k]
                      + N * u[r] * u[k])
    return out.T


def plane_of(M: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Count, mean (about the moments' origin), eigenvalues (ascending) and normal (the smallest eigenvalue's
    eigenvector) of the scatter of moments M."""
    N = M[:, 3, 3]
    mu = M[:, :3, 3] / N[:, None]

    def entry(i: int, j: int) -> np.ndarray:
        return M[:, i, j] / N - mu[:, i] * mu[:, j]

    lam, normal = smallest_eigen(entry(0, 0), entry(0, 1), entry(0, 2), entry(1, 1), entry(1, 2), entry(2, 2))
    return N, mu, lam, normal


def rotated(vectors: np.ndarray, poses: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """``vectors`` (3,k) of frames ``frame`` turned into the world by ``poses`` (3,k), a coordinate at a time over
    contiguous rows (NaN stays NaN)."""
    return _turned(vectors, _pose_rows(poses), frame)


def _turned(v: np.ndarray, rows: np.ndarray, f: np.ndarray) -> np.ndarray:
    out = np.empty((3, len(f)))
    for i in range(3):
        out[i] = np.take(rows[i, 0], f) * v[0] + np.take(rows[i, 1], f) * v[1] + np.take(rows[i, 2], f) * v[2]
    return out


def placed_means(cells: Cells, poses: np.ndarray, part: slice) -> np.ndarray:
    """The means of cells ``part`` in the world at ``poses`` (k,3), a coordinate at a time over contiguous rows."""
    f = cells.frame[part]
    rows = _pose_rows(poses)
    out = _turned(np.ascontiguousarray(cells.mean[part].T, dtype=np.float64), rows, f)
    for i in range(3):
        out[i] += np.take(rows[i, 3], f)
    return out.T


def assign(cells: Cells, poses: np.ndarray, voxel: float, reference: np.ndarray | None = None,
           kernel: float = KERNEL) -> Assignment:
    """The flat voxels at ``poses`` (adaptive sizes ``voxel / 2^l`` down to the cell size), the cells on them
    and their robust weights. Cells are summed per (frame, voxel) in their sensor frame, then placed.
    ``reference`` (bool per frame, default all): only those frames decide which voxels are flat planes (seen by
    two of them) and the noise scale; the other frames' cells are assigned to those planes, to be judged.
    ``kernel``: the Cauchy width of the cells' weights, in noise sigmas."""
    ref_cell = np.ones(len(cells)) if reference is None else reference[cells.frame].astype(np.float64)
    levels = 1 + max(0, int(np.floor(np.log2(voxel / cells.size + 1e-9))))
    mean = np.empty((len(cells), 3))
    for c in chunks(len(cells)):
        mean[c] = placed_means(cells, poses, c)
    frame_of = cells.frame.astype(np.int64)
    todo = np.arange(len(cells))
    chosen, plane_ids, normals, offsets, centres, sizes = [], [], [], [], [], []
    voxels = 0
    for level in range(levels):
        if len(todo) == 0:
            break
        size = voxel / 2**level
        on, ids, normal, offset, centre, hopeless = _flat_voxels(cells, todo, np.take(mean, todo, axis=0), frame_of,
                                                                 ref_cell, poses, size)
        chosen.append(todo[on])
        plane_ids.append(voxels + ids)
        normals.append(normal)
        offsets.append(offset)
        centres.append(centre)
        sizes.append(np.full(len(centre), size))
        voxels += len(centre)
        todo = todo[~on & ~hopeless]
    cell = np.concatenate(chosen) if chosen else np.zeros(0, int)
    plane = np.concatenate(plane_ids) if plane_ids else np.zeros(0, int)
    normal = np.take(np.concatenate(normals) if normals else np.zeros((0, 3)), plane, axis=0)
    r = (normal * np.take(mean, cell, axis=0)).sum(1) - (np.concatenate(offsets) if offsets else np.zeros(0))[plane]
    del normal, mean
    z = standard_distance(cells.count[cell], r)
    z_ref = z[ref_cell[cell] > 0]
    sigma = max(1.4826 * float(np.median(z_ref)) if len(z_ref) else 0.0, 1e-6)
    weight = cell_weight(z, sigma, kernel)
    frames = frame_of[cell]
    pair, first = pair_ids(frames, plane, voxels)
    n = len(first)
    centre = np.concatenate(centres) if centres else np.zeros((0, 3))
    moment = moment_sums(cells, cell, pair, n, weight)
    points = np.bincount(pair, cells.count[cell].astype(np.float64), minlength=n)
    edge = np.concatenate(sizes) if sizes else np.zeros(0)
    return Assignment(frames[first], plane[first], moment, centre, sigma, len(cell), points, edge)


def standard_distance(count: np.ndarray, distance: np.ndarray) -> np.ndarray:
    """A cell mean's distance to its plane in the units of one point's: times the square root of the cell's
    points (~ |N(0, sigma^2)| on an exact plane)."""
    return np.sqrt(count.astype(np.float64)) * np.abs(distance)


def cell_weight(z: np.ndarray, sigma: float, kernel: float = KERNEL) -> np.ndarray:
    """A cell's robust weight from its :func:`standard_distance` ``z``: Cauchy, ``kernel`` noise sigmas wide."""
    return 1.0 / (1.0 + (z / (kernel * sigma)) ** 2)


def _flat_voxels(cells: Cells, todo: np.ndarray, mean: np.ndarray, frame_of: np.ndarray, ref_cell: np.ndarray,
                 poses: np.ndarray, size: float) -> tuple[np.ndarray, ...]:
    """The flat voxels of edge ``size`` that cells ``todo`` (placed means ``mean``) fall in: which of the cells
    are on one (bool), the plane of each of those (numbered from 0), and per plane its normal, offset (world)
    and voxel centre, and which cells can lie on no plane of a smaller voxel (theirs has too few points or
    frames: its parts have fewer). A surface is seen from one side: the cells whose sensor lies behind their
    voxel's plane (:func:`_behind`, from a first pass) are grouped apart (:func:`_split_sides`), so the two faces
    of a thin panel seen from both sides (a chair's back, a door, a garden wall) are two planes, not one between
    them that pulls the frames of either side towards the other. A function of its own: one level's arrays are released
    before the next level's."""
    first = _voxel_planes(cells, todo, mean, frame_of, ref_cell, poses, size)
    candidate = np.zeros(first.n, bool)
    candidate[first.candidate] = True
    hopeless = ~candidate[first.inv]
    back = _behind(todo, mean, frame_of, poses, first.candidate, first.normal, first.inv, first.n)
    v = _split_sides(cells, todo, mean, frame_of, ref_cell, poses, size, first, back)
    del first, back, candidate
    is_flat = (v.lam[:, 0] < FLATNESS * v.lam[:, 1]) & (v.lam[:, 1] >= (MIN_WIDTH * size) ** 2)
    flat = np.zeros(v.n, bool)
    flat[v.candidate[is_flat]] = True
    on = flat[v.inv]
    normal = v.normal[is_flat]
    centre = v.centre[flat]
    return (on, (np.cumsum(flat) - 1)[v.inv[on]], normal, (normal * (v.mu[is_flat] + centre)).sum(1), centre,
            hopeless)


@dataclass
class _VoxelPlanes:
    """The voxels of one level: each cell's voxel ``inv``, their number ``n`` and centres, the candidates for a
    plane (ascending voxel numbers) and those candidates' mean (about the centre), eigenvalues and normal."""

    inv: np.ndarray
    n: int
    centre: np.ndarray
    candidate: np.ndarray
    mu: np.ndarray
    lam: np.ndarray
    normal: np.ndarray


def _split_sides(cells: Cells, todo: np.ndarray, mean: np.ndarray, frame_of: np.ndarray, ref_cell: np.ndarray,
                 poses: np.ndarray, size: float, first: _VoxelPlanes, back: np.ndarray) -> _VoxelPlanes:
    """``first``'s voxels with those that hold cells of both sides (``back``) regrouped by side: only their cells
    are grouped again (a few percent of them), the others keep the first pass's planes (and numbers, in order)."""
    split = np.bincount(first.inv, back, minlength=first.n) > 0
    if not split.any():
        return first
    sub = np.flatnonzero(split[first.inv])
    second = _voxel_planes(cells, todo[sub], np.take(mean, sub, axis=0), frame_of, ref_cell, poses, size, back[sub])
    keep = ~split
    number = np.cumsum(keep) - 1
    kept = int(keep.sum())
    inv = number[first.inv]
    inv[sub] = kept + second.inv
    stays = keep[first.candidate]
    return _VoxelPlanes(inv, kept + second.n, np.concatenate([first.centre[keep], second.centre]),
                        np.concatenate([number[first.candidate[stays]], kept + second.candidate]),
                        *(np.concatenate([a[stays], b]) for a, b in ((first.mu, second.mu), (first.lam, second.lam),
                                                                     (first.normal, second.normal))))


def _voxel_planes(cells: Cells, todo: np.ndarray, mean: np.ndarray, frame_of: np.ndarray, ref_cell: np.ndarray,
                  poses: np.ndarray, size: float, back: np.ndarray | None = None) -> _VoxelPlanes:
    """The voxels of edge ``size`` of cells ``todo`` (and of their side, ``back``, where given), and their
    candidates for a plane (points enough, seen by two reference frames; :func:`plane_of`)."""
    key = np.floor(mean / size).astype(np.int64)
    inv, n = group_rows(key if back is None else np.concatenate([key, back[:, None].astype(np.int64)], 1))
    level_centre = np.zeros((n, 3))
    level_centre[inv] = key
    level_centre = (level_centre + 0.5) * size
    del key
    pair, first = pair_ids(frame_of[todo], inv, n)
    pair_voxel = inv[first]
    level_pairs = Assignment(frame_of[todo][first], pair_voxel,
                             moment_sums(cells, todo, pair, len(first), ref_cell[todo]), level_centre, 1.0, 0)
    del pair
    M = placed_sum(level_pairs, poses)
    del level_pairs
    several = np.bincount(pair_voxel, ref_cell[todo][first], minlength=n) >= 2  # seen by two frames or more
    candidate = np.flatnonzero((M[:, 3, 3] >= MIN_POINTS) & several)  # (no reference frame's point: N = 0)
    _, mu, lam, normal = plane_of(M[candidate])
    return _VoxelPlanes(inv, n, level_centre, candidate, mu, lam, normal)


def _behind(todo: np.ndarray, mean: np.ndarray, frame_of: np.ndarray, poses: np.ndarray, candidate: np.ndarray,
            normal: np.ndarray, inv: np.ndarray, n: int) -> np.ndarray:
    """Per cell of ``todo``: its sensor lies on the other side of its voxel's plane (``normal`` of the
    ``candidate`` voxels, turned towards the sensors of most of the voxel's cells) than most of the voxel's
    cells' sensors (False in voxels that are not candidates)."""
    oriented = np.zeros((n, 3))
    oriented[candidate] = normal
    sensor = np.take(poses[:, :3, 3], np.take(frame_of, todo), axis=0)
    facing = ((sensor - mean) * np.take(oriented, inv, axis=0)).sum(1)
    flip = np.bincount(inv, np.sign(facing), minlength=n) < 0
    return np.where(flip[inv], facing > 0, facing < 0)


def fit(a: Assignment, poses: np.ndarray) -> Planes:
    """The best plane of each voxel at ``poses`` (smallest eigenvector of its points' scatter) and its cost."""
    N, mu, lam, normal = plane_of(placed_sum(a, poses))
    return Planes(normal, (normal * (mu + a.centre)).sum(1), N * np.maximum(lam[:, 0], 0.0))


def cost(a: Assignment, poses: np.ndarray) -> float:
    """The plane term with each plane fitted to the poses: weighted squared distances over sigma^2."""
    return float(fit(a, poses).residual.sum()) / a.sigma**2


def skew(v: np.ndarray) -> np.ndarray:
    """(K,3) -> (K,3,3) cross-product matrices."""
    z = np.zeros(len(v))
    return np.stack([z, -v[:, 2], v[:, 1], v[:, 2], z, -v[:, 0], -v[:, 1], v[:, 0], z], 1).reshape(-1, 3, 3)


@dataclass
class Linear:
    """The plane term linearised at some poses with the planes as unknowns too (three each: the normal's two
    tilts and the offset), in GTSAM's units (half the squares over sigma^2) and its Pose3 tangent
    ``T Exp([omega, v])`` (rotation first): ``cost``; per frame ``H`` (N,6,6) and ``g`` (N,6); per (frame, voxel)
    pair the pose-plane block ``B`` (P,6,3); per voxel the inverse plane block ``S_inv`` (V,3,3) and the plane
    gradient ``g_plane`` (V,3). With the planes eliminated, a step solves
    ``(H - B S^-1 B^T) x = -(g - B S^-1 g_plane)``: frames that share a plane move together (the planes held,
    a step would treat every plane as fixed and creep along the modes they follow)."""

    cost: float
    H: np.ndarray
    g: np.ndarray
    B: csr_matrix  # (6N, 3V)
    S_inv: bsr_matrix  # (3V, 3V) block diagonal
    g_plane: np.ndarray

    def coupling(self, x: np.ndarray) -> np.ndarray:
        """``B S^-1 B^T x`` for a pose step ``x`` (6N,)."""
        return self.B @ (self.S_inv @ (self.B.T @ x))

    def rhs(self) -> np.ndarray:
        """``-(g - B S^-1 g_plane)`` (6N,)."""
        return -(self.g.ravel() - self.B @ (self.S_inv @ self.g_plane.ravel()))


def linearise(a: Assignment, planes: Planes, poses: np.ndarray) -> Linear:
    """The plane term at ``poses`` and the fitted ``planes`` (see :class:`Linear`).

    With ``m = R^T n`` and ``u = [m, n . t - d]`` a point's distance is ``u . [p 1]``, so a pair's cost is
    ``u^T Q u``; its derivative by ``[omega, v]`` is ``A [p 1]`` with ``A = [[-[m]x, 0], [0, m]]`` (6x4), and by
    the plane's ``[tilt_1, tilt_2, offset]`` (about the voxel's centre c) ``G [p 1]`` with
    ``G = [[E^T R, E^T (t - c)], [0, -1]]`` (E two unit vectors across the normal): Hessian blocks ``A Q A^T``,
    ``A Q G^T``, ``G Q G^T``, gradients ``A Q u``, ``G Q u``."""
    frames, voxels, pairs = len(poses), a.voxels, len(a.frame)
    scale = 1.0 / a.sigma**2
    across = _across(planes.normal)
    cost, H, g = 0.0, np.zeros((frames, 6, 6)), np.zeros((frames, 6))
    S, g_plane = np.zeros((voxels, 3, 3)), np.zeros((voxels, 3))
    coupling = _BlockRows(a.frame, frames, 6, 3)
    for c in chunks(pairs):
        frame, voxel, Q = a.frame[c], a.voxel[c], expand_moments(a.moment[c])
        n, d = planes.normal[voxel], planes.offset[voxel]
        R, t = poses[frame, :3, :3], poses[frame, :3, 3]
        m = (n[:, None, :] @ R)[:, 0]  # R^T n: the normal in the sensor frame
        u = np.concatenate([m, ((n * t).sum(1) - d)[:, None]], 1)
        Qu = (Q @ u[:, :, None])[:, :, 0]
        A = np.zeros((len(m), 6, 4))
        A[:, :3, :3] = -skew(m)
        A[:, 3:, 3] = m
        AQ = A @ Q
        E = across[voxel]  # (P,3,2)
        G = np.zeros((len(m), 3, 4))
        G[:, :2, :3] = E.transpose(0, 2, 1) @ R
        G[:, :2, 3] = (E.transpose(0, 2, 1) @ (t - a.centre[voxel])[:, :, None])[:, :, 0]
        G[:, 2, 3] = -1.0
        cost += float((u * Qu).sum()) * scale * 0.5
        H += _sum(frame, AQ @ A.transpose(0, 2, 1) * scale, frames)
        g += _sum(frame, (A @ Qu[:, :, None])[:, :, 0] * scale, frames)
        S += _sum(voxel, G @ Q @ G.transpose(0, 2, 1) * scale, voxels)
        g_plane += _sum(voxel, (G @ Qu[:, :, None])[:, :, 0] * scale, voxels)
        coupling.put(c, voxel, AQ @ G.transpose(0, 2, 1) * scale)
    S_inv = np.linalg.pinv(S, rcond=1e-9, hermitian=True)  # a plane of few points may leave a direction free
    return Linear(cost, H, g, coupling.matrix(3 * voxels),
                  bsr_matrix((S_inv, np.arange(voxels), np.arange(voxels + 1)), shape=(3 * voxels, 3 * voxels)),
                  g_plane)


class _BlockRows:
    """A sparse matrix of (r,c) blocks, one per pair (block row ``frame``, block column its voxel), written in
    CSR form a few pairs at a time (no dense copy of all the blocks, no conversion). Pairs are ordered by
    frame (see :func:`assign`), then voxel: ``bsr_matrix((blocks, voxel, indptr)).tocsr()``'s layout."""

    def __init__(self, frame: np.ndarray, frames: int, r: int, c: int) -> None:
        self.r, self.c = r, c
        self.first = np.searchsorted(frame, np.arange(frames + 1))  # each frame's first pair
        self.per = np.diff(self.first)
        n = r * c * len(frame)
        index = np.int32 if n < 2**31 else np.int64
        self.data, self.indices = np.empty(n), np.empty(n, index)
        rows = r * c * self.first[:-1, None] + c * np.arange(r) * self.per[:, None]  # each row's first entry
        self.indptr = np.append(rows.ravel(), n).astype(index)
        self.frame, self.frames = frame, frames

    def put(self, pairs: slice, column: np.ndarray, blocks: np.ndarray) -> None:
        """The (P,r,c) ``blocks`` of ``pairs`` (a slice), in block columns ``column`` (P,)."""
        f = self.frame[pairs]
        p = np.arange(pairs.start, pairs.stop)
        at = ((self.r * self.c * self.first[f] + self.c * (p - self.first[f]))[:, None, None]
              + (self.c * self.per[f])[:, None, None] * np.arange(self.r)[:, None] + np.arange(self.c))
        self.data[at] = blocks
        self.indices[at] = (self.c * column)[:, None, None] + np.arange(self.c)

    def matrix(self, columns: int) -> csr_matrix:
        return csr_matrix((self.data, self.indices, self.indptr), shape=(self.r * self.frames, columns))


def _across(normal: np.ndarray) -> np.ndarray:
    """(V,3,2): two unit vectors perpendicular to each normal and to each other."""
    helper = np.where(np.abs(normal[:, [0]]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = np.cross(normal, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return np.stack([e1, np.cross(normal, e1)], 2)


def disagreement(a: Assignment, poses: np.ndarray, cap: float = KERNEL,
                 reference: np.ndarray | None = None, bounded: bool = False,
                 judged: np.ndarray | None = None) -> np.ndarray:
    """Per frame, the mean squared distance (m^2) of its points on planes to the plane the *other* frames make
    in the same voxel (leave-one-out: a frame is judged by the map the others make, never by its own points),
    each (frame, voxel) pair capped at ``cap`` noise sigmas; NaN for a frame with no point on such a plane. The
    others make a plane where their points spread over ``MIN_WIDTH`` of the voxel across two directions, as a
    flat voxel's must: a line or a point (one cell of one other frame) has no normal to measure along.
    ``reference`` (bool per frame, default all):
    the planes are made by those frames only. ``bounded``: the robust-weighted squared distances over all the
    frame's points (each point adds at most the kernel's width squared), instead of the weighted mean (where far
    points hardly count). ``judged`` (bool per frame, default all): only those frames are scored (NaN for the
    others), all still make the planes."""
    ref_pair = np.ones(len(a.frame), bool) if reference is None else reference[a.frame]
    total = placed_sum(a, poses, None if reference is None else ref_pair)
    frames = int(poses.shape[0])
    sq_sum, own_sum = np.zeros(frames), np.zeros(frames)
    pairs = np.arange(len(a.frame)) if judged is None else np.flatnonzero(judged[a.frame])
    for c in chunks(len(pairs)):
        p = pairs[c]
        frame, voxel = a.frame[p], a.voxel[p]
        M_pair = expand_moments(moments_about(poses, frame, np.take(a.centre, voxel, axis=0),
                                              np.take(a.moment, p, axis=0)))
        rest = np.take(total, voxel, axis=0) - M_pair * ref_pair[p, None, None]
        sq, keep = left_out_squares(M_pair, rest, None if a.size is None else a.size[voxel], cap * a.sigma)
        sq_sum += np.bincount(frame, sq, minlength=frames)
        own_sum += np.bincount(frame, (a.points[p] if bounded else M_pair[:, 3, 3]) * keep, minlength=frames)
    with np.errstate(invalid="ignore", divide="ignore"):
        return sq_sum / own_sum


def left_out_squares(M_pair: np.ndarray, rest: np.ndarray, size: np.ndarray | None, cap: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Per (frame, voxel) pair: the weighted sum of its points' squared distances (moments ``M_pair`` (k,4,4),
    about the voxel's centre) to the plane the others' points make (their moments ``rest``), capped at ``cap``
    (m) a point, and whether that plane exists: the others have points that spread over ``MIN_WIDTH`` of the
    voxel's edge ``size`` across two directions (a line or a point has no normal; not tested where ``size`` is
    None). 0 where it does not."""
    keep = rest[:, 3, 3] > 0
    _, mu, lam, normal = plane_of(np.where(keep[:, None, None], rest, np.eye(4)))
    if size is not None:
        keep &= lam[:, 1] >= (MIN_WIDTH * size) ** 2
    u = np.concatenate([normal, -(normal * mu).sum(1)[:, None]], 1)  # n . x - n . mu, centred
    sq = np.einsum("pi,pij,pj->p", u, M_pair, u)
    return np.minimum(np.maximum(sq, 0.0), M_pair[:, 3, 3] * cap**2) * keep, keep


def agreement_score(cells: Cells, candidates: dict[str, np.ndarray], voxel: float,
                    judges: tuple[str, ...] | None = None) -> dict[str, float]:
    """How well each candidate's frames agree with the map the other frames make (lower is better, m^2): the
    mean over frames of :func:`disagreement`, on the voxels flat at each of the ``judges`` candidates in turn
    (default all: a candidate is not judged only on the planes it made flat), averaged."""
    judges = judges or tuple(candidates)
    scores = {name: 0.0 for name in candidates}
    for judge in judges:
        a = assign(cells, candidates[judge], voxel)
        for name, poses in candidates.items():
            scores[name] += float(np.nanmean(disagreement(a, poses))) / len(judges)
    return scores
