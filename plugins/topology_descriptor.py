"""Place recognition ``descriptor``: Scan Context loop candidates beyond the radius (3D: highest point
per polar cell; planar laser scans: polar occupancy), each verified by ICP from the descriptor's yaw
and accepted only when fitness, rmse, offset and translation-constraint gates pass; combined with the
radius neighbours on the warm-start poses and temporal neighbours.

Every candidate, accepted or not, is recorded in ``Topology.log`` with its scores; accepted loops carry
``relative`` (T_j^i as nested lists), which the ``icp`` registration uses as its initial guess for that
pair.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from dm2_backend.algorithms import scan_context as sc
from dm2_backend.algorithms.common import (
    Cloud,
    assemble,
    fine_distance,
    lengths,
    path_length,
    planar_pose,
    radius_neighbours,
    resolve_method,
)
from dm2_backend.algorithms.gates import check_alignment, constraint
from dm2_backend.algorithms.icp import register
from dm2_backend.algorithms.topology import check_k, check_poses
from dm2_backend.kernel.prepared import Frames, ScanScale, Topology
from dm2_backend.runtime.progress import progress


@dataclass
class DescriptorTopology:
    """Options; None means derived from the data (``Frames.scale``)."""

    name: ClassVar[str] = "descriptor"

    #: neighbours per frame: the size of each frame's group (at least 1), loop partners first, then radius neighbours
    k: int = 8
    #: radius neighbours on the warm-start poses (m); default half the median range
    radius: float | None = None
    #: at most this many loop partners per anchor (default k // 2), placed first in the group
    max_loops: int | None = None
    #: Scan Context grid: rings (equal range bins out to ``max_range``)
    rings: int = 20
    #: Scan Context grid: sectors (equal bearing bins over 360 degrees; a candidate's yaw comes in these steps)
    sectors: int = 60
    #: descriptor range (m); default the 90th percentile of the ranges
    max_range: float | None = None
    #: ring-key nearest candidates per query, and how many of the best (by Scan Context distance) to verify
    candidates: int = 10
    verify: int = 2
    #: a candidate is verified only when its Scan Context distance (1 - mean cosine of the columns both scans
    #: occupy, at the best rotation; 0 to 1) is at most this
    max_descriptor_distance: float = 0.4
    #: candidates must lie this far along the warm-start path (m; default 4 radii)
    min_path_gap: float | None = None
    #: query every stride-th frame (default: about 2000 queries)
    stride: int | None = None
    #: verification gates: overlap both ways, inlier rmse (m; default 1.5 point spacings), offset (m;
    #: default median range), translation constraint (smallest eigenvalue of mean n n^T; rejects
    #: corridor-like sliding matches)
    min_fitness: float = 0.7
    #: rmse gate: largest inlier rmse of the verifying ICP (m); default 1.5 point spacings
    max_rmse: float | None = None
    #: offset gate: largest translation between the two scans the verifying ICP finds (m); default the median
    #: range; the coarse ICP pass reaches at least a quarter of it
    max_offset: float | None = None
    #: constraint gate: least smallest eigenvalue of the mean n n^T over the matched normals (0 in a corridor,
    #: at most 1/2 for planar scans, 1/3 in 3D)
    min_constraint: float = 0.12
    #: and the fraction of points either scan puts more than ``free_space_margin`` (m) in front of the
    #: other's returns; defaults (measured on real laser logs and simulated rooms): planar 0.1 with a
    #: margin of 4 fine correspondence distances, 3D 0.04 with a margin of one
    max_free_space: float | None = None
    free_space_margin: float | None = None
    #: fill each group up to ``k`` with temporal neighbours i-1, i+1, i-2, ...; frame i+1 is always in frame i's
    #: group (every step is registered)
    temporal_fill: bool = True
    #: report the stage's progress: a bar on a terminal, else one INFO log line when it ends; false: silent
    progress: bool = True

    def run(self, frames: Frames, poses: np.ndarray) -> Topology:
        check_k(self.k)
        check_poses(frames, poses)
        scale = lengths(frames)
        radius = self.radius or 0.5 * scale.range_median
        log: list[dict] = [{"plugin": self.name, "radius": radius, "k": self.k}]
        loops = self._loops(frames, poses, scale, radius, log)
        near = radius_neighbours(poses[:, :3, 3], radius, self.k)
        pairs = zip(loops, near, strict=True)
        rows = [[(j, "loop") for j in lp] + [(j, "radius") for j in nr] for lp, nr in pairs]
        return assemble(rows, self.k, self.temporal_fill, log)

    def _loops(self, frames: Frames, poses: np.ndarray, scale: ScanScale, radius: float, log: list) -> list[list[int]]:
        """Verified loop partners per frame, best fitness first."""
        n = len(frames)
        max_range = self.max_range or scale.range_p90
        descs = np.stack(
            [sc.descriptor(p, self.rings, self.sectors, max_range, frames.planar) for p in frames.points]
        ).astype(np.float32)
        keys = sc.ring_key(descs)
        pos = poses[:, :3, 3]
        path = path_length(poses)
        gap = self.min_path_gap if self.min_path_gap is not None else 4.0 * radius
        stride = self.stride or max(1, n // 2000)
        fine = fine_distance(scale)
        gates = {
            "min_fitness": self.min_fitness,
            "max_rmse": self.max_rmse or 1.5 * max(scale.voxel, scale.spacing),
            "max_offset": self.max_offset or scale.range_median,
            "min_constraint": self.min_constraint,
            "max_free_space": self.max_free_space or (0.1 if frames.planar else 0.04),
            "free_space_margin": self.free_space_margin or (4.0 if frames.planar else 1.0) * fine,
        }
        log[0].update(gates, max_range=max_range, min_path_gap=gap, stride=stride)
        clouds: dict[int, Cloud] = {}
        found: list[list[tuple[float, int]]] = [[] for _ in range(n)]
        done: set[tuple[int, int]] = set()
        for i in progress(range(0, n, stride), "loop candidates", unit="frame", enabled=self.progress):
            ok = (np.abs(path - path[i]) > gap) & (np.linalg.norm(pos - pos[i], axis=1) > radius)
            cand = np.flatnonzero(ok)
            if len(cand) == 0:
                continue
            near = cand[np.argsort(np.abs(keys[cand] - keys[i]).sum(axis=1))[: self.candidates]]
            scored = sorted((*sc.distance(descs[i], descs[j]), int(j)) for j in near)
            for d, shift, j in scored[: self.verify]:
                pair = (min(i, j), max(i, j))
                if d > self.max_descriptor_distance or pair in done:
                    continue
                done.add(pair)
                entry = self._verify(frames, clouds, i, j, d, shift, fine, gates)
                log.append(entry)
                if entry["accepted"]:
                    found[i].append((entry["fitness"], j))
                    found[j].append((entry["fitness"], i))
        limit = self.max_loops if self.max_loops is not None else self.k // 2
        return [[j for _, j in sorted(f, reverse=True)[:limit]] for f in found]

    def _verify(self, frames, clouds, i, j, d, shift, fine, gates) -> dict:
        """ICP of frame j onto frame i from the descriptor's yaw; the gates decide."""
        for f in (i, j):
            if f not in clouds:
                clouds[f] = Cloud(frames.points[f], frames.planar, 2.0 * fine)
        yaw = shift * 2.0 * np.pi / self.sectors
        init = planar_pose(0.0, 0.0, yaw)
        coarse = max(4.0 * fine, 0.25 * gates["max_offset"])
        method = resolve_method("auto", frames.planar)
        m = register(clouds[j], clouds[i], init, (coarse,), method, iterations=15)
        if m.fitness >= 0.5 * gates["min_fitness"]:  # hopeless candidates stop after the coarse pass
            m = register(clouds[j], clouds[i], m.T, (4.0 * fine, fine), method)
        free = check_alignment(clouds[j], clouds[i], m, fine, gates["free_space_margin"])
        c = constraint(clouds[j], clouds[i], m.T, fine) if m.fitness > 0 else 0.0
        offset = float(np.linalg.norm(m.T[:3, 3]))
        reasons = []
        if m.fitness < gates["min_fitness"]:
            reasons.append(f"fitness {m.fitness:.2f} < {gates['min_fitness']:.2f}")
        if m.rmse > gates["max_rmse"]:
            reasons.append(f"rmse {m.rmse:.3f} > {gates['max_rmse']:.3f}")
        if offset > gates["max_offset"]:
            reasons.append(f"offset {offset:.2f} m > {gates['max_offset']:.2f} m")
        if free > gates["max_free_space"]:
            reasons.append(f"free space {free:.2f} > {gates['max_free_space']:.2f} (walls where the other saw none)")
        if c < gates["min_constraint"]:
            reasons.append(f"constraint {c:.3f} < {gates['min_constraint']:.3f} (degenerate: a corridor?)")
        entry = {
            "i": int(i),
            "j": int(j),
            "descriptor_distance": round(d, 4),
            "yaw_deg": round(float(np.degrees(yaw)), 2),
            "fitness": round(m.fitness, 4),
            "rmse": round(m.rmse, 5),
            "offset": round(offset, 3),
            "constraint": round(c, 4),
            "free_space": round(free, 4),
            "accepted": not reasons,
            "reason": "; ".join(reasons) or "accepted",
        }
        if not reasons:
            entry["relative"] = m.T.tolist()  # JSON-friendly (the preparation cache stores the log as JSON)
        return entry
