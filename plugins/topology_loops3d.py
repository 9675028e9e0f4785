"""Place recognition ``loops3d``: loop closure in full 6-DoF for sensors that move freely (hand-held depth
cameras, drones), whose drift over a loop is moderate.

0. Each increment of the input is checked by a frame-to-frame GICP, which replaces the steps where the
   front end failed (a jump); the rest of the trajectory moves with the repaired step.
1. Keyframes every ``keyframe_distance`` of travel or ``keyframe_angle`` of turn; each has a submap: the
   scans from the previous to the next keyframe, moved into its frame with the (locally accurate) input
   poses and voxel-down-sampled.
2. Candidates for a keyframe are the earlier keyframes far enough back along the path whose submap its own
   submap overlaps when placed with the current estimate, allowing a search window that grows with the
   distance travelled since the last accepted closure.
3. Verification: coarse-to-fine GICP of the two submaps from the current estimate, gated on the overlap
   both ways, the inlier rmse, how well the surfaces pin down translation, and a correction within the
   window.
4. Closures and the input's increments form a pose graph over every frame (GTSAM); a robust batch solve
   drops closures the rest of the graph disagrees with. A second round searches again from the corrected
   poses, which brings loops that drifted out of reach into it.
5. The topology is built on the corrected poses: loop partners (far along the path, near in space and
   looking at the same place) first, then radius and temporal neighbours. ``Topology.poses`` carries the
   corrected poses when a loop was closed.

Every verification, accepted or not, is logged with its scores and reason.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np

from dm2_backend.algorithms.common import (
    Cloud,
    assemble,
    fine_distance,
    lengths,
    loop_rows,
    orthonormal,
    path_length,
    repeatable_registration,
    rotation_angle,
    voxel_cloud,
)
from dm2_backend.algorithms.gates import (
    Gate,
    GateFailure,
    constraint,
    coverage,
    significantly_worse,
)
from dm2_backend.algorithms.icp import register
from dm2_backend.algorithms.loop_graph3d import Closure3, FrameGraph
from dm2_backend.algorithms.topology import check_k, check_poses
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.prepared import Frames, FramesPart, Topology
from dm2_backend.runtime import cluster
from dm2_backend.runtime.errors import InputError
from dm2_backend.runtime.progress import progress
from dm2_backend.runtime.threads import ordered_map

#: threads that register side by side (each registration on one thread: ``common.repeatable_registration``)
THREADS = min(8, os.cpu_count() or 1)


@dataclass
class Loops3dTopology:
    """Options; None means derived from the data (``Frames.scale``)."""

    name: ClassVar[str] = "loops3d"

    #: neighbours per frame: the size of each frame's group (at least 1), loop partners first, then radius neighbours
    k: int = 8
    #: radius neighbours on the corrected poses (m); default half the median range
    radius: float | None = None
    #: at most this many loop partners per frame (default k // 2), placed first in the group
    max_loops: int | None = None
    #: keyframe spacing (m; default a tenth of the median range) and turn (degrees)
    keyframe_distance: float | None = None
    #: a new keyframe also after this rotation about any axis since the last keyframe (degrees)
    keyframe_angle: float = 15.0
    #: a candidate must lie this far back along the path (m; default 4 keyframe spacings)
    min_path_gap: float | None = None
    #: search window (m) at a fresh closure (default the keyframe spacing), growing by ``drift`` m per metre
    #: travelled since the last accepted closure, capped at ``max_window`` (default half the median range)
    window: float | None = None
    drift: float = 0.05
    #: cap of the search window (m); default half the median range
    max_window: float | None = None
    #: candidates verified per keyframe (the best predicted overlaps) and the least predicted overlap
    candidates: int = 3
    #: least predicted overlap of a candidate: the share of a sample of the keyframe's submap points, placed with
    #: the current estimate, within the window plus one fine distance of the earlier keyframe's submap
    min_predicted: float = 0.3
    #: gates: overlap (the smaller of both directions), inlier rmse (m; default 1.5 point spacings),
    #: translation constraint (smallest eigenvalue of the matched normals' scatter, at most 1/3)
    min_overlap: float = 0.4
    #: rmse gate: largest inlier rmse of the submaps' GICP (m); default 1.5 point spacings
    max_rmse: float | None = None
    #: constraint gate: least smallest eigenvalue of the mean n n^T over the matched normals (0 where the surfaces
    #: let the match slide, at most 1/3)
    min_constraint: float = 0.05
    #: final solve: closures with a whitened residual above this are dropped
    gate: float = 10.0
    #: repair a front-end step that a frame-to-frame GICP moves by more than this (m; default 3 point
    #: spacings; 0 = trust the input's increments)
    repair_distance: float | None = None
    #: search rounds (each from the poses the previous round corrected)
    rounds: int = 2
    #: fill each group up to ``k`` with temporal neighbours i-1, i+1, i-2, ...; frame i+1 is always in frame i's
    #: group (every step is registered)
    temporal_fill: bool = True
    #: report the stage's progress: a bar on a terminal, else one INFO log line when it ends; false: silent
    progress: bool = True

    def run(self, frames: Frames, poses: np.ndarray) -> Topology:
        check_k(self.k)
        check_poses(frames, poses)
        if frames.planar:
            raise InputError(None, "place recognition loops3d: planar scans; use loops")
        self._setup(frames)
        log: list[dict] = [{"plugin": self.name, **self._lengths}]
        with repeatable_registration():  # registrations side by side, each on one thread
            corrected, closures, repaired = self._close_loops(frames, poses, log)
        return self._topology(frames, corrected, log, closures, repaired)

    # ------------------------------------------------------------------ set-up
    def _setup(self, frames: Frames) -> None:
        lengths_ = ("radius", "keyframe_distance", "min_path_gap", "window", "max_window", "max_rmse")
        bad = [f"{n}={getattr(self, n)}" for n in lengths_ if getattr(self, n) is not None and not getattr(self, n) > 0]
        bad += [f"{n}={getattr(self, n)}" for n in ("candidates", "rounds") if getattr(self, n) < 1]
        bad += [f"{n}={getattr(self, n)}" for n in ("drift", "repair_distance") if (getattr(self, n) or 0) < 0]
        if bad:
            raise InputError(None, f"place recognition loops3d: invalid options {', '.join(bad)}")
        s = lengths(frames)
        spacing = max(s.spacing, s.voxel, 1e-3)
        kf_dist = self.keyframe_distance or s.range_median / 10.0
        self._lengths = {
            "radius": self.radius or 0.5 * s.range_median,
            "keyframe_distance": kf_dist,
            "min_path_gap": self.min_path_gap or 4.0 * kf_dist,
            "window": self.window or kf_dist,
            "max_window": self.max_window or 0.5 * s.range_median,
            "max_rmse": self.max_rmse or 1.5 * spacing,
            "fine": fine_distance(s),
            "voxel": spacing,
            "range": s.range_median,
        }

    # ------------------------------------------------------------------ loop closing
    def _close_loops(self, frames: Frames, poses: np.ndarray, log: list) -> tuple[np.ndarray, int, list[int]]:
        L = self._lengths
        poses, repaired = self._repair(frames, poses)
        self._keys = keys = _keyframes(poses, L["keyframe_distance"], np.radians(self.keyframe_angle))
        self._maps = [self._submap(frames, poses, b) for b in range(len(keys))]
        path = path_length(poses)
        increments = se3.relative(poses[:-1], poses[1:])
        steps = np.linalg.norm(increments[:, :3, 3], axis=1)
        turns = se3.rotation_angle(increments[:, :3, :3])
        floor = 0.05 * L["voxel"]
        graph = FrameGraph(poses, floor + 0.02 * steps, floor / L["range"] + 0.02 * turns + 0.005 * steps,
                           0.25 * L["voxel"], 0.25 * L["voxel"] / L["range"])
        closures: list[Closure3] = []
        tried: dict[tuple[int, int], np.ndarray | None] = {}
        estimate = poses
        for r in range(self.rounds):
            found = self._search(estimate, path, tried, log, r)
            if not found:
                break
            closures += found
            estimate, closures, dropped = graph.solve(closures, self.gate)
            for c in dropped:
                c.entry.update(accepted=False, dropped=True, reason="dropped by the final robust solve")
        log[0].update(keyframes=len(keys), closures=len(closures), repaired_steps=repaired,
                      dropped=sum(1 for e in log[1:] if e.get("dropped")))
        return estimate, len(closures), repaired

    def _repair(self, frames: Frames, poses: np.ndarray) -> tuple[np.ndarray, list[int]]:
        """The input trajectory with its failed steps repaired: each increment is checked by GICP of the frame
        onto the one before, and where the two disagree by more than ``repair_distance`` the front end failed
        on that frame (a jump of the front end that the frame pair's registration does not make): the
        registration replaces the increment and the rest of the trajectory
        moves with it. Returns the poses and the repaired step indices."""
        if self.repair_distance == 0 or len(poses) < 2:
            return poses, []
        steps = se3.relative(poses[:-1], poses[1:])
        engine = cluster.current()
        if engine is None:  # runs of steps on threads (each registration on one: repeatable_registration)
            size = max(2, -(-len(steps) // (4 * THREADS)))
            runs = range(0, len(steps), size)

            def run(k0: int) -> dict[int, np.ndarray]:
                part = steps[k0 : k0 + size]
                return self._checked(frames, part, range(len(part)), k0)

            done = ordered_map(run, runs, workers=THREADS)
            replaced = {k: T for part in progress(done, "odometry check", total=len(runs), unit="run",
                                                  enabled=self.progress) for k, T in part.items()}
        else:  # runs of steps as tasks, each on its frames
            size = engine.run_length(len(steps), smallest=2)
            light = replace(self)  # the options; not the submaps of an earlier run (open3d clouds do not pickle)
            light._lengths = self._lengths
            tasks = [StepTask(light, frames.part(np.arange(k0, min(k0 + size, len(steps)) + 1)),
                              steps[k0 : k0 + size], k0) for k0 in range(0, len(steps), size)]
            done = engine.map(check_steps, tasks, "odometry check", enabled=self.progress)
            replaced = {k: T for part in done for k, T in part.items()}
        repaired = sorted(replaced)
        for k in repaired:
            steps[k] = replaced[k]
        if not repaired:
            return poses, []
        out = [poses[0]]
        for step in steps:
            out.append(out[-1] @ step)
        return np.array(out), repaired

    def _search(self, estimate: np.ndarray, path: np.ndarray, tried: dict, log: list, round_: int) -> list[Closure3]:
        """Verify the candidates of every keyframe at ``estimate``; a pair is verified again in a later round
        only when its starting relative pose moved by more than the fine distance (accepted pairs are
        settled: their starts agree with the closure)."""
        L, keys = self._lengths, self._keys
        kpath = path[keys]
        found: list[Closure3] = []
        last = 0.0
        bar = progress(range(len(keys)), f"loop closure 3d ({round_ + 1})", unit="keyframe", enabled=self.progress)
        for b in bar:
            window = min(L["max_window"], L["window"] + self.drift * (kpath[b] - last))
            todo = []
            for a, predicted in self._candidates(estimate, kpath, b, window):
                init = se3.relative(estimate[keys[a]], estimate[keys[b]])
                if (a, b) in tried and (tried[(a, b)] is None or
                                        np.linalg.norm(se3.relative(tried[(a, b)], init)[:3, 3]) <= L["fine"]):
                    continue  # accepted, or verified from (nearly) this start already
                tried[(a, b)] = init
                todo.append((a, predicted, init))
            # a keyframe's candidates side by side (the window moves only after them), their submaps' covariances,
            # normals and trees built first, in turn (open3d clouds are not filled from two threads at once)
            for k in (b, *(a for a, _, _ in todo)) if todo else ():
                self._maps[k].ensure("gicp", "both").normals  # noqa: B018
            verified = ordered_map(lambda c, b=b, w=window: self._verify(c[0], b, c[2], w), todo, workers=THREADS)
            for (a, predicted, _), entry in zip(todo, verified, strict=True):
                entry.update(predicted_overlap=round(predicted, 4), round=round_ + 1)
                log.append(entry)
                if entry["verified"]:
                    tried[(a, b)] = None  # settled: never verified again
                    entry.update(accepted=True)
                    found.append(Closure3(int(keys[a]), int(keys[b]), np.asarray(entry["z"]), entry))
                    last = kpath[b]
            bar.set_postfix(closures=len(found))
        return found

    def _candidates(self, estimate: np.ndarray, kpath: np.ndarray, b: int, window: float) -> list[tuple[int, float]]:
        """Earlier keyframes whose submap keyframe b's submap overlaps at the estimate (best first)."""
        L = self._lengths
        far = np.flatnonzero(kpath[b] - kpath[:b] > L["min_path_gap"])
        if len(far) == 0 or len(self._maps[b]) == 0:
            return []
        kb = estimate[self._keys[b]]
        near = far[np.linalg.norm(estimate[self._keys[far], :3, 3] - kb[:3, 3], axis=1) < L["range"] + window]
        probe = self._maps[b].points[:: max(1, len(self._maps[b]) // 300)]
        reach = window + L["fine"]
        scored = []
        for a in near:
            if len(self._maps[a]) == 0:
                continue
            rel = se3.relative(estimate[self._keys[a]], kb)
            dist, _ = self._maps[a].tree.query(se3.transform_points(rel, probe), distance_upper_bound=reach)
            overlap = float(np.isfinite(dist).mean())
            if overlap >= self.min_predicted:
                scored.append((overlap, int(a)))
        return [(a, o) for o, a in sorted(scored, reverse=True)[: self.candidates]]

    def _verify(self, a: int, b: int, init: np.ndarray, window: float) -> dict:
        """GICP of keyframe b's submap onto a's from ``init`` (b in a's frame at the estimate), then the gates."""
        L = self._lengths
        i, j = int(self._keys[a]), int(self._keys[b])
        src, tgt = self._maps[b], self._maps[a]
        fine = L["fine"]
        m = register(src, tgt, init, (max(window, 4.0 * fine), 2.0 * fine, fine), "gicp")
        entry = {"i": i, "j": j, "window": round(window, 3), "fitness": round(m.fitness, 4),
                 "rmse": round(m.rmse, 5), "verified": False, "accepted": False}
        if m.fitness <= 0 or not np.isfinite(m.T).all():
            entry["reason"] = "ICP found no correspondences"
            return entry
        offset = se3.relative(init, m.T)
        shift = float(np.linalg.norm(offset[:3, 3]))
        entry.update(offset=round(shift, 4), offset_deg=round(float(np.degrees(rotation_angle(offset[:3, :3]))), 3))
        reasons = [str(f) for f in self._gates(src, tgt, m, entry)]
        if shift > window + fine:
            reasons.append(f"correction {shift:.2f} m beyond the window {window:.2f} m")
        entry["verified"] = not reasons
        entry["reason"] = "; ".join(reasons) or "verified"
        entry["z"] = m.T.tolist()  # pose of frame j in frame i
        return entry

    def _gates(self, src: Cloud, tgt: Cloud, m, entry: dict) -> list[GateFailure]:
        """The gates an alignment fails: overlap (the smaller of both directions), inlier rmse, translation
        constraint; the scores go into ``entry``."""
        L = self._lengths
        overlap = min(m.fitness, coverage(tgt, src, se3.inverse(m.T), L["fine"])[0])
        c = constraint(src, tgt, m.T, L["fine"])
        entry.update(overlap=round(overlap, 4), constraint=round(c, 4))
        failed = []
        if overlap < self.min_overlap:
            failed.append(GateFailure(Gate.OVERLAP, overlap, self.min_overlap))
        if m.rmse > L["max_rmse"]:
            failed.append(GateFailure(Gate.RMSE, m.rmse, L["max_rmse"]))
        if c < self.min_constraint:
            failed.append(GateFailure(Gate.DEGENERATE, c, self.min_constraint))
        return failed

    def _checked(self, frames: Frames, steps: np.ndarray, ks, first: int = 0) -> dict[int, np.ndarray]:
        """Of the steps ``first + i`` for ``i`` in ``ks`` (``steps[i]``: frame ``first + i + 1`` in frame
        ``first + i``), those whose frames' GICP replaces the front end's, with the step that replaces it."""
        fine = self._lengths["fine"]
        limit = self.repair_distance or fine
        replaced = {}
        target = None
        for i in ks:
            k = first + i
            if target is None:
                target = Cloud(frames.points[k], False, 2.0 * fine)
            source = Cloud(frames.points[k + 1], False, 2.0 * fine)
            m = register(source, target, steps[i], (4.0 * fine, fine), "gicp")
            if np.isfinite(m.T).all() and np.linalg.norm(se3.relative(steps[i], m.T)[:3, 3]) > limit and \
                    self._replaces(source, target, m, steps[i]):
                replaced[k] = orthonormal(m.T)
            target = source
        return replaced

    def _replaces(self, src: Cloud, tgt: Cloud, m, step: np.ndarray) -> bool:
        """A frame-pair registration replaces the front end's ``step`` when it passes the closure gates, or fails
        only the translation constraint (a view of few surfaces, where a scan matcher slides) while the two
        frames' residual at the front end's step is beyond what their noise explains
        (:func:`~dm2_backend.algorithms.gates.significantly_worse`)."""
        if m.fitness <= 0:
            return False
        failed = {f.gate for f in self._gates(src, tgt, m, {})}
        if not failed:
            return True
        return failed == {Gate.DEGENERATE} and significantly_worse(src, tgt, step, m.T, self._lengths["fine"])

    def _submap(self, frames: Frames, poses: np.ndarray, b: int) -> Cloud:
        """Scans from keyframe b-1 to b+1, in keyframe b's frame, voxel-down-sampled."""
        keys = self._keys
        lo = int(keys[b - 1]) if b > 0 else 0
        hi = int(keys[b + 1]) if b + 1 < len(keys) else len(poses) - 1
        inv = se3.inverse(poses[keys[b]])
        pts = np.concatenate([se3.transform_points(inv @ poses[f], frames.points[f].astype(np.float64))
                              for f in range(lo, hi + 1)])
        return voxel_cloud(pts, self._lengths["voxel"], False, 2.0 * self._lengths["fine"])

    # ------------------------------------------------------------------ topology
    def _topology(self, frames: Frames, corrected: np.ndarray, log: list, closures: int,
                  repaired: list[int]) -> Topology:
        """Loop partners: far along the path, within the radius, and looking at the same place (the centroids
        of their scans in the world within the radius too); then radius and temporal neighbours."""
        L = self._lengths
        pos = corrected[:, :3, 3]
        centroid = np.array([se3.transform_points(T, p.mean(axis=0, keepdims=True).astype(np.float64))[0]
                             if len(p) else T[:3, 3] for T, p in zip(corrected, frames.points)])
        limit = self.max_loops if self.max_loops is not None else self.k // 2
        rows = loop_rows(pos, path_length(corrected), L["radius"], L["min_path_gap"], self.k, limit, centroid)
        topo = assemble(rows, self.k, self.temporal_fill, log)
        # corrected only when a loop was closed or a failed step repaired
        poses = corrected if closures or repaired else None
        # (Topology.loop_closed tells the two apart: the optimiser treats only loop-closed starts as accurate)
        return replace(topo, closures=closures, repaired_steps=tuple(repaired), poses=poses,
                       loop_closed=poses is not None and closures > 0)


def _keyframes(poses: np.ndarray, spacing: float, angle: float) -> np.ndarray:
    """The first pose, then each pose ``spacing`` m away from the last keyframe or turned by ``angle`` rad
    about any axis (``keyframes.select`` measures travel and yaw only, as suits ground vehicles)."""
    keep = [0]
    for i in range(1, len(poses)):
        rel = se3.relative(poses[keep[-1]], poses[i])
        if np.linalg.norm(rel[:3, 3]) >= spacing or rotation_angle(rel[:3, :3]) >= angle:
            keep.append(i)
    return np.asarray(keep, dtype=np.int64)


@dataclass(frozen=True)
class StepTask:
    """A run of the front end's steps for one worker: the plugin (its options and lengths), the frames of those
    steps, the steps and the first one's number."""

    plugin: Loops3dTopology
    frames: FramesPart
    steps: np.ndarray
    first: int


def check_steps(task: StepTask) -> dict[int, np.ndarray]:
    """A worker's run of :meth:`Loops3dTopology._checked` (open3d on one thread)."""
    with repeatable_registration():
        return task.plugin._checked(task.frames.frames(), task.steps, range(len(task.steps)), task.first)
