"""Place recognition ``external``: neighbour lists from another tool, either an (N, k) integer group
matrix (.npy, -1 pads; a first column equal to the anchor index, as in DeepMapping2's
``group_matrix.npy``, is dropped) or (N, D) float embeddings (e.g. TF-VPR's), whose k nearest in
embedding space form the groups."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
from scipy.spatial import cKDTree

from dm2_backend.algorithms.common import assemble
from dm2_backend.algorithms.topology import check_k, check_poses
from dm2_backend.kernel.prepared import Frames, Topology
from dm2_backend.runtime.errors import InputError


@dataclass
class ExternalTopology:
    """Options: ``path`` to the .npy file; ``k`` None keeps the matrix's width (8 for embeddings)."""

    name: ClassVar[str] = "external"

    path: str | None = None
    k: int | None = None
    #: drop neighbours farther than this on the warm-start poses (m); None keeps all
    radius: float | None = None
    #: fill each group up to k with temporal neighbours i-1, i+1, i-2, ... after the given neighbours
    temporal_fill: bool = True

    def run(self, frames: Frames, poses: np.ndarray) -> Topology:
        check_poses(frames, poses)
        data = self._load(len(frames))
        groups = data.dtype.kind in "iu"
        if groups:
            if self._self_column(data):
                data = data[:, 1:]
            k = self.k or max(1, data.shape[1])
            rows = [[int(j) for j in row if j >= 0] for row in data]
        else:
            k = self.k or 8
            rows = self._nearest(data, k)
        check_k(k)
        if self.radius is not None:
            pos = poses[:, :3, 3]
            near = [np.linalg.norm(pos[row] - pos[i], axis=1) <= self.radius for i, row in enumerate(rows)]
            rows = [[j for j, ok in zip(row, keep, strict=True) if ok] for row, keep in zip(rows, near, strict=True)]
        topo = assemble([[(j, "external") for j in row] for row in rows], k, self.temporal_fill,
                        successor=False)  # the groups as given
        kind = "group matrix" if groups else "embeddings"
        topo.log.append({"plugin": self.name, "path": str(self.path), "k": k, "input": kind})
        return topo

    def _load(self, n: int) -> np.ndarray:
        if not self.path:
            raise InputError(None, "place recognition 'external' needs option 'path' (an .npy file)")
        path = Path(self.path)
        if not path.is_file():
            raise InputError(path, "no such file")
        try:
            data = np.load(path, allow_pickle=False)
        except (ValueError, OSError) as exc:
            raise InputError(path, f"not a readable .npy array ({exc})") from None
        if data.ndim != 2 or data.shape[0] != n:
            raise InputError(path, f"expected ({n}, k) neighbour indices or ({n}, D) embeddings, got {data.shape}")
        if data.dtype.kind == "f":
            if not np.isfinite(data).all():
                row = int(np.flatnonzero(~np.isfinite(data).all(axis=1))[0])
                raise InputError(path, f"embedding of frame {row} is not finite")
        elif data.dtype.kind not in "iu":
            raise InputError(path, f"unsupported array type {data.dtype}")
        if data.dtype.kind in "iu":
            bad = (data < -1) | (data >= n)
            if bad.any():
                r, c = np.argwhere(bad)[0]
                raise InputError(path, f"row {r}: neighbour index {data[r, c]} outside 0..{n - 1}")
        return data

    @staticmethod
    def _self_column(data: np.ndarray) -> bool:
        return bool(np.array_equal(data[:, 0], np.arange(len(data))))

    @staticmethod
    def _nearest(emb: np.ndarray, k: int) -> list[list[int]]:
        n = len(emb)
        kk = min(k + 1, n)
        _, idx = cKDTree(emb).query(emb, k=kk)
        return [[int(j) for j in row if j != i] for i, row in enumerate(idx.reshape(n, kk))]
