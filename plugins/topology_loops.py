"""Place recognition ``loops``: loop closure that survives large drift, for ground robots and vehicles
(planar laser scans, or 3D scans seen from above).

1. Keyframes every ``keyframe_distance`` of travel, each with a submap of the scans around it.
2. Keyframes are visited in order on an iSAM2 pose graph (odometry = the warm start). Candidates are the
   earlier keyframes within reach of the current estimate; the search window (translation and yaw)
   grows with the distance travelled since the last accepted closure, so a loop that drifted many
   metres is still searched (guessed rates). A candidate ambiguous there is searched again in the window
   that a multiple of the drift rates the accepted closures measured allows (their corrections over the
   path before each): a window far wider than the drift makes a building's repeated halls ambiguous.
3. Verification is global inside that window: correlative scan matching with branch and bound
   (``correlative.py``), rejected when a clearly different alignment scores nearly as well, unless every
   such alignment lies on one line at the same heading (a corridor): then the closure fixes only the
   direction across that line and yaw, and the graph settles the position along it. Then a fine
   correlative pass and ICP on the submaps, gated on overlap, translation constraint (not for a corridor
   closure) and (planar) free space of the two keyframe scans.
   A match whose score lies a little under the gate and that passes every other test is weak.
   A verified closure is measured again on short submaps (the median range either side), which the warm
   start's drift bends less; that measurement replaces the first where the two differ beyond its own noise.
4. A verified closure is trusted only once a second one agrees with it around a cycle through the
   odometry; a weak one (overlap or score a little under the gate, every other test passed: two visits that
   share only part of their submaps) only once two others agree, or one that passed every gate. Trusted closures
   correct the graph at once. A final robust batch solve drops closures the
   rest of the graph disagrees with.
5. The loop-closed keyframe poses correct every frame (interpolated between keyframes); the topology is
   built on the corrected poses: loop partners (far along the path, near in space) first, then radius
   and temporal neighbours. ``Topology.poses`` carries the corrected poses.

Every verification, accepted or not, is logged with its scores and reason.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import chi2

from dm2_backend.algorithms import correlative as cm
from dm2_backend.algorithms import keyframes as kf
from dm2_backend.algorithms.common import (
    Cloud,
    Match,
    assemble,
    fine_distance,
    lengths,
    loop_rows,
    path_length,
    planar_pose,
)
from dm2_backend.algorithms.gates import Gate, GateFailure, constraint, free_space
from dm2_backend.algorithms.icp import information_2d, register
from dm2_backend.algorithms.loop_graph import Closure, KeyframeGraph, between, confirms, cycle_error
from dm2_backend.algorithms.topology import check_k, check_poses
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.prepared import Frames, Topology
from dm2_backend.runtime.errors import InputError
from dm2_backend.runtime.progress import progress


@dataclass
class LoopsTopology:
    """Options; None means derived from the data (``Frames.scale``)."""

    name: ClassVar[str] = "loops"

    #: neighbours per frame: the size of each frame's group (at least 1), loop partners first, then radius neighbours
    k: int = 8
    #: radius neighbours on the corrected poses (m); default half the median range
    radius: float | None = None
    #: at most this many loop partners per frame (default k // 2), placed first in the group
    max_loops: int | None = None
    #: keyframe spacing (m; default half the median range) and turn (degrees)
    keyframe_distance: float | None = None
    #: a new keyframe also after this turn in yaw since the last keyframe (degrees); see ``keyframe_distance``
    keyframe_angle: float = 30.0
    #: path length on either side of a keyframe that its submap covers (m; default the 90th-percentile range)
    submap_half_length: float | None = None
    #: a verified closure is measured again on submaps this long on either side (m; default the median range; 0:
    #: off), from the first measurement: a long submap carries the warm start's own drift, a degree or more of yaw
    #: over its length, into the closure. A direction the short submaps leave free is held at the first
    #: measurement (see ``_measure_short``; docs/decisions/0012-loop-closures-on-short-submaps.md)
    short_half_length: float | None = None
    #: the short measurement replaces the first only when they differ beyond this chi-square quantile of the short
    #: match's own noise (its point-to-line information over its residuals' variance, each normal's neighbourhood
    #: counted once): from an unbent start (the truth) the long submaps measure more precisely
    short_gate: float = 0.999
    #: matching grid cell (m; default 2 point spacings)
    resolution: float | None = None
    #: a submap point is kept only when another lies within this (m; default 2 cells, twice the likelihood's sigma):
    #: isolated returns (glass, open doors) match nothing and let different alignments score alike; 0 keeps all
    #: (docs/decisions/0011-loop-closure-overlap-and-support.md)
    support: float | None = None
    #: search window: translation (m) and yaw (degrees) at a fresh closure, growing by ``drift`` m and ``yaw_drift``
    #: degrees per metre travelled since the last accepted closure, capped (an ambiguous match: see ``drift_margin``)
    window: float | None = None
    drift: float = 0.1
    #: a candidate ambiguous in that window is searched again in one grown by this many times the drift rates the
    #: accepted closures measured (their corrections over the path travelled before each, pooled; a closure across
    #: a corridor measures yaw only), where narrower: the warm start's own drift, not a guess, bounds the search.
    #: 1e9 turns it off (docs/decisions/0021-loop-search-learns-the-drift.md)
    drift_margin: float = 3.0
    #: yaw search window at a fresh closure (degrees either side of the estimate); see ``window``
    yaw_window: float = 10.0
    #: growth of the yaw window (degrees per metre travelled since the last accepted closure), capped at 180 degrees
    yaw_drift: float = 0.5
    #: cap of the translation window (m); default 4 times the 90th-percentile range
    max_window: float | None = None
    #: candidates verified per keyframe (the nearest keyframe of each earlier visit)
    candidates: int = 3
    #: a candidate must lie this far back along the path (m; default 4 submap half lengths)
    min_path_gap: float | None = None
    #: acceptance: correlation score, ambiguity (runner-up / best), overlap, translation constraint,
    #: free space (planar keyframe scans)
    min_score: float = 0.5
    #: a match scoring in [weak_score, min_score) that passes every other test is weak, as for ``weak_fitness``:
    #: two visits that share only part of their submaps score low at the right place
    weak_score: float = 0.4
    #: ambiguity gate: a match is rejected when a clearly different alignment scores more than this share of the
    #: best (runner-up / best, in (0, 1]), unless it is a closure across a corridor (``across_corridors``)
    max_ambiguity: float = 0.9
    #: overlap gate: the smaller, over both directions, of the share of one submap's points within a grid cell of
    #: the other's (see ``weak_fitness``; docs/decisions/0011-loop-closure-overlap-and-support.md); also the
    #: least ICP fitness of the short measurement (``short_half_length``)
    min_fitness: float = 0.5
    #: a closure whose overlap lies in [weak_fitness, min_fitness) and that passes every other test is weak:
    #: trusted only when two other closures (or one that is not weak) agree with it around a cycle
    #: (docs/decisions/0011-loop-closure-overlap-and-support.md)
    weak_fitness: float = 0.4
    #: constraint gate: least smallest eigenvalue of the mean n n^T over the matched normals (0 in a corridor, at
    #: most 1/2; not applied to a closure across a corridor); on the short submaps a direction below it is held
    min_constraint: float = 0.1
    #: free-space gate (planar scans): largest fraction of either keyframe scan's points lying more than 4 fine
    #: correspondence distances in front of the other's returns
    max_free_space: float = 0.1
    #: overlap gate over the points in sight of the other visit (within ``reach`` of one of its scan positions)
    #: instead of over whole submaps; off by default: it restores recall that the weak closures also restore, with
    #: extra closures that are off (docs/decisions/0011-loop-closure-overlap-and-support.md)
    overlap_in_sight: bool = False
    #: a match ambiguous only along one line (a corridor) becomes a closure across it: it fixes the other
    #: direction and yaw, the graph settles the position along it; trusted like a weak closure
    across_corridors: bool = True
    #: cycle check between two closures: translation (m; default 4 cells) + this fraction of their span
    cycle_tolerance: float | None = None
    #: the cycle check's translation tolerance grows by this much per metre of the two closures' span (m per m; the
    #: span: the path between their first keyframes plus the path between their second ones)
    cycle_drift: float = 0.05
    #: closures within this many keyframes of each other are checked against each other
    consistency_window: int = 20
    #: final batch solve: closures with a whitened residual above this are dropped
    gate: float = 10.0
    #: fill each group up to ``k`` with temporal neighbours i-1, i+1, i-2, ...; frame i+1 is always in frame i's
    #: group (every step is registered)
    temporal_fill: bool = True
    #: seed of the random subset of submap points the correlative search matches (the same seed, the same closures)
    seed: int = 0
    #: report the stage's progress: a bar on a terminal, else one INFO log line when it ends; false: silent
    progress: bool = True

    def run(self, frames: Frames, poses: np.ndarray) -> Topology:
        check_k(self.k)
        check_poses(frames, poses)
        self._check()
        self._setup(frames)
        log: list[dict] = [{"plugin": self.name, **self._lengths}]
        corrected, closures = self._close_loops(frames, poses, log)
        return self._topology(frames, corrected, log, closures)

    # ------------------------------------------------------------------ set-up
    def _check(self) -> None:
        lengths_ = ("radius", "keyframe_distance", "submap_half_length", "resolution", "window", "max_window",
                    "min_path_gap", "cycle_tolerance")
        bad = [f"{n}={getattr(self, n)}" for n in lengths_ if getattr(self, n) is not None and not getattr(self, n) > 0]
        bad += [f"support={self.support}"] if self.support is not None and self.support < 0 else []
        bad += ([f"short_half_length={self.short_half_length}"]
                if self.short_half_length is not None and not self.short_half_length >= 0 else [])
        bad += [f"short_gate={self.short_gate} (a probability in (0, 1))"] if not 0 < self.short_gate < 1 else []
        bad += [f"{n}={getattr(self, n)}" for n in ("candidates", "consistency_window") if getattr(self, n) < 1]
        bad += [f"{n}={getattr(self, n)}" for n in ("drift", "yaw_drift", "cycle_drift", "drift_margin")
                if getattr(self, n) < 0]
        if not 0 < self.max_ambiguity <= 1:
            bad.append(f"max_ambiguity={self.max_ambiguity} (a ratio in (0, 1])")
        if not 0 <= self.weak_score <= self.min_score:
            bad.append(f"weak_score={self.weak_score} (between 0 and min_score={self.min_score})")
        if not 0 <= self.weak_fitness <= self.min_fitness:
            bad.append(f"weak_fitness={self.weak_fitness} (between 0 and min_fitness={self.min_fitness})")
        if bad:
            raise InputError(None, f"place recognition loops: invalid options {', '.join(bad)}")

    def _setup(self, frames: Frames) -> None:
        s = lengths(frames)
        res = self.resolution or 2.0 * max(s.spacing, s.voxel, 1e-3)
        half = self.submap_half_length or s.range_p90
        self._lengths = {
            "radius": self.radius or 0.5 * s.range_median,
            "keyframe_distance": self.keyframe_distance or 0.5 * s.range_median,
            "submap_half_length": half,
            "short_half_length": s.range_median if self.short_half_length is None else self.short_half_length,
            "resolution": res,
            "support": 2.0 * res if self.support is None else self.support,
            "window": self.window or 0.5 * s.range_median,
            "max_window": self.max_window or 4.0 * s.range_p90,
            "min_path_gap": self.min_path_gap or 4.0 * half,
            "cycle_tolerance": self.cycle_tolerance or 4.0 * res,
            "fine": fine_distance(s),
            "reach": s.range_p90,
        }
        self._rng = np.random.default_rng(self.seed)
        self._grids: dict[tuple[int, float], cm.LikelihoodGrid] = {}

    # ------------------------------------------------------------------ loop closing
    def _close_loops(self, frames: Frames, poses: np.ndarray, log: list) -> tuple[np.ndarray, int]:
        L = self._lengths
        keys = kf.select(poses, L["keyframe_distance"], np.radians(self.keyframe_angle))
        path = path_length(poses)
        self._maps = [kf.submap(frames, poses, path, int(f), L["submap_half_length"], L["resolution"] / 2,
                                L["support"]) for f in keys]
        self._short_maps: dict[int, np.ndarray] = {}
        self._poses, self._path = poses, path
        self._origins = [kf.origins(poses, path, int(f), L["submap_half_length"]) for f in keys]
        self._keys, self._frames = keys, frames
        odo = se3.to_xy_yaw(poses[keys])
        kpath = path[keys]
        steps = np.maximum(np.diff(kpath), 1e-3)
        odo_sigma = np.stack([0.01 * steps + 0.25 * L["resolution"]] * 2
                             + [0.002 * steps + 0.25 * L["resolution"] / L["reach"]], axis=1)
        graph = KeyframeGraph(odo, odo_sigma, np.array([L["resolution"]] * 2 + [L["resolution"] / L["reach"]]))
        pending: list[Closure] = []
        learnt = DriftRates()
        last = 0.0
        bar = progress(range(len(keys)), "loop closure", unit="keyframe", enabled=self.progress)
        for b in bar:
            graph.extend(b)
            travelled = kpath[b] - last  # the windows'; a closure accepted at b resets it for b's later candidates
            window, yaw_window = self._window(self.drift, self.yaw_drift, travelled)
            narrow = self._window(*learnt.rates(self.drift, self.yaw_drift, self.drift_margin), travelled)
            for a in self._candidates(graph.estimate[: b + 1], kpath, b, window):
                entry = self._verify(a, b, graph.estimate, window, yaw_window)
                if entry.get("ambiguous") and narrow < (window, yaw_window):  # searched again where the drift allows
                    wide = {k: entry[k] for k in ("window", "yaw_window_deg", "score", "ambiguity", "reason")}
                    entry = {**self._verify(a, b, graph.estimate, *narrow), "wide": wide}
                entry["travelled"] = round(float(kpath[b] - last), 2)
                log.append(entry)
                if not entry["verified"]:
                    continue
                new = Closure(a, b, np.array(entry["z"]), entry, weak=bool(entry.get("weak")),
                              axis=np.array(entry["axis"]) if "axis" in entry else None)
                agreeing = self._consistent(new, pending + graph.closures, odo, kpath)
                trusted = confirms(new, agreeing)
                entry["accepted"] = trusted
                if trusted:
                    # a pending closure that agrees with the new one is trusted with it when the new one and the
                    # others that agree with it are enough for it too (a weak one needs more); Closure compares
                    # by identity
                    others = pending + graph.closures
                    promote = [c for c in pending if c in agreeing and confirms(
                        c, [new] + self._consistent(c, [o for o in others if o is not c], odo, kpath))]
                    pending = [c for c in pending if c not in promote]
                    for c in promote:
                        c.entry.update(accepted=True, reason=f"{c.entry['reason']}; confirmed by a later closure")
                    graph.close(promote + [new])
                    learnt.add(promote + [new])
                    last = kpath[b]
                else:
                    pending.append(new)
                pending = [c for c in pending if b - c.b <= self.consistency_window]
            bar.set_postfix(closures=len(graph.closures))
        key_poses, kept, dropped = graph.solve_batch(self.gate)
        log[0].update(keyframes=len(keys), closures=len(kept), dropped=len(dropped))
        for c in dropped:
            c.entry.update(accepted=False, dropped=True, reason="dropped by the final robust solve")
        return correct(poses, keys, odo, key_poses), len(kept)

    def _window(self, drift: float, yaw_drift: float, travelled: float) -> tuple[float, float]:
        """Search window (m, rad) after ``travelled`` metres at the growth rates (m and degrees per metre)."""
        L = self._lengths
        return (min(L["max_window"], L["window"] + drift * travelled),
                float(np.radians(min(180.0, self.yaw_window + yaw_drift * travelled))))

    def _candidates(self, estimate: np.ndarray, kpath: np.ndarray, b: int, window: float) -> list[int]:
        """Earlier keyframes that may overlap keyframe b: one (the nearest) per earlier visit."""
        L = self._lengths
        far = np.flatnonzero(kpath[b] - kpath[: b + 1] > L["min_path_gap"])
        if len(far) == 0:
            return []
        d = np.linalg.norm(estimate[far, :2] - estimate[b, :2], axis=1)
        near = far[d < window + L["reach"]]
        d = d[d < window + L["reach"]]
        visits: dict[int, tuple[float, int]] = {}
        run = np.concatenate([[0], np.cumsum(np.diff(near) > 1)]) if len(near) else []
        for r, a, da in zip(run, near, d):
            if r not in visits or da < visits[r][0]:
                visits[r] = (da, int(a))
        return [a for _, a in sorted(visits.values())[: self.candidates]]

    def _grid(self, a: int, res: float) -> cm.LikelihoodGrid:
        if (a, res) not in self._grids:
            self._grids[(a, res)] = cm.LikelihoodGrid(self._maps[a], res)
        return self._grids[(a, res)]

    def _verify(self, a: int, b: int, estimate: np.ndarray, window: float, yaw_window: float) -> dict:
        """Global correlative search for keyframe b's submap in keyframe a's, then ICP and the gates."""
        L = self._lengths
        res = L["resolution"]
        coarse_res = res * 2.0 ** max(0, int(np.ceil(np.log2(window / (32 * res)))))
        init = between(estimate[a], estimate[b])
        src = self._maps[b]
        if min(len(src), len(self._maps[a])) < 10:
            return {"i": int(self._keys[a]), "j": int(self._keys[b]), "score": 0.0, "verified": False,
                    "accepted": False, "reason": "fewer than 10 points in a submap"}
        coarse = cm.match(kf.thin(src, coarse_res, 400, self._rng), self._grid(a, coarse_res), tuple(init),
                          window, yaw_window, ratio=self.max_ambiguity, floor=self.max_ambiguity * self.weak_score)
        entry = {"i": int(self._keys[a]), "j": int(self._keys[b]), "window": round(window, 2),
                 "yaw_window_deg": round(float(np.degrees(yaw_window)), 1), "score": round(coarse.score, 4),
                 "ambiguity": round(coarse.runner_up / max(coarse.score, 1e-9), 4), "verified": False,
                 "accepted": False, "ambiguous": False}
        low_score = coarse.score < self.weak_score
        under_gate = not low_score and coarse.score < self.min_score  # a weak closure at best
        ambiguous = coarse.runner_up > self.max_ambiguity * coarse.score
        reasons = []
        if low_score or (under_gate and ambiguous):
            reasons.append(str(GateFailure(Gate.SCORE, coarse.score, self.weak_score if low_score else self.min_score)))
        if ambiguous:
            reasons.append(f"ambiguous: a different alignment scores {entry['ambiguity']:.2f} of the best")
        # ambiguous only along one line (a corridor): certain across it and in yaw; the position along it is
        # the prediction's, and the graph settles it
        across = self.across_corridors and coarse.axis is not None and ambiguous and not (low_score or under_gate)
        axis = np.array(coarse.axis) if across else None
        if reasons and not across:
            entry.update(reason="; ".join(reasons), ambiguous=ambiguous)
            return entry
        if across:
            along = float((init[:2] - (coarse.x, coarse.y)) @ axis)
            start = (coarse.x + along * axis[0], coarse.y + along * axis[1], coarse.yaw)
            m = self._icp(a, b, planar_pose(*start), hold=axis)
            entry["axis"] = [round(float(v), 4) for v in axis]
        else:
            step = 2 * coarse_res
            fine = cm.match(kf.thin(src, res, 800, self._rng), self._grid(a, res), (coarse.x, coarse.y, coarse.yaw),
                            step, step / L["reach"] * 2, ratio=1.0)
            m = self._icp(a, b, planar_pose(fine.x, fine.y, fine.yaw))
        z = se3.to_xy_yaw(m.T)
        entry.update(z=[float(v) for v in z], fitness=round(m.fitness, 4), rmse=round(m.rmse, 5),
                     offset=round(float(np.linalg.norm(z[:2] - init[:2])), 3),
                     offset_deg=round(float(np.degrees(abs(se3.wrap_angle(z[2] - init[2])))), 3))
        failed = self._gates(a, b, m, entry, across)
        if under_gate:
            failed.insert(0, GateFailure(Gate.SCORE, coarse.score, self.min_score))
        weak = len(failed) == 1 and (failed[0].gate is Gate.SCORE or (
            failed[0].gate is Gate.OVERLAP and entry["overlap"] >= self.weak_fitness))
        entry["verified"] = not failed or weak
        if entry["verified"] and L["short_half_length"] > 0:
            self._measure_short(a, b, m.T, entry, axis)
        entry["weak"] = entry["verified"] and (weak or across)
        if across and entry["verified"]:
            entry["reason"] = (f"verified across a corridor (free along {entry['axis']}; {reasons[0]})"
                               + (f"; weak: {failed[0]}" if weak else ""))
        else:
            entry["reason"] = (f"verified, weak: {failed[0]}" if weak
                               else "; ".join([*reasons, *map(str, failed)]) or "verified")
        return entry

    def _measure_short(self, a: int, b: int, T: np.ndarray, entry: dict, axis: np.ndarray | None) -> None:
        """The verified closure ``T`` measured again on the short submaps of its keyframes (``short_half_length``).
        Where they leave a direction free (translation constraint under ``min_constraint``: a stretch of corridor)
        that direction is held at ``T``, as a corridor closure holds its axis. The new ``z`` replaces the first
        (kept as ``z_long``) when its ICP fitness reaches ``min_fitness`` and it differs from the first by more
        than its own noise allows (``short_gate``; the noise: its point-to-line information over its residuals'
        variance, each normal's neighbourhood counted once): then the first is bent; else the first, which sees more
        structure, stands."""
        res = self._lengths["resolution"]
        maps = (self._short_map(b), self._short_map(a))
        if min(len(maps[0]), len(maps[1])) < 10:
            entry["short"] = {"kept": False, "reason": "fewer than 10 points in a short submap"}
            return
        m = self._icp(a, b, T, axis, maps=maps)
        fit = information_2d(self._clouds[0].xy, self._clouds[1], m.T, res)
        held = axis
        if axis is None and fit["weak"] < self.min_constraint:
            held = fit["weak_axis"]
            m = self._icp(a, b, T, held, maps=maps)
            fit = information_2d(self._clouds[0].xy, self._clouds[1], m.T, res)
        z, first = se3.to_xy_yaw(m.T), np.asarray(entry["z"])
        dz = z - first  # b's position in a's frame and its yaw about it: information_2d's parametrisation
        dz[2] = se3.wrap_angle(dz[2])
        if held is not None:  # the held direction did not move; what is left has one degree of freedom less
            dz[:2] -= (dz[:2] @ held) * held
        # the residuals' rms, at least that of a point's place in its submap cell (one point per half resolution);
        # each target normal is fitted to the points within its radius, so neighbouring residuals share its error:
        # the information counts each such neighbourhood once
        sigma = max(fit["line_rmse"], 0.5 * res / np.sqrt(12.0))
        sigmas = float(np.sqrt(max(float(dz @ fit["info"] @ dz), 0.0) / _shared(self._clouds[1])) / sigma)
        gate = float(np.sqrt(chi2.ppf(self.short_gate, 3 if held is None else 2)))
        keep = fit["count"] >= 3 and m.fitness >= self.min_fitness and sigmas > gate
        entry["short"] = {"fitness": round(m.fitness, 4), "constraint": round(fit["weak"], 4),
                          "moved_sigmas": round(float(sigmas), 2), "kept": bool(keep),
                          "moved_m": round(float(np.linalg.norm(dz[:2])), 4),
                          "moved_deg": round(float(np.degrees(dz[2])), 3)}
        if held is not None and axis is None:
            entry["short"]["held"] = [round(float(v), 4) for v in held]
        if keep:
            entry["z_long"], entry["z"] = entry["z"], [float(v) for v in z]

    def _short_map(self, k: int) -> np.ndarray:
        """Keyframe k's short submap (``short_half_length`` either side), made on first use and kept."""
        if k not in self._short_maps:
            L = self._lengths
            self._short_maps[k] = kf.submap(self._frames, self._poses, self._path, int(self._keys[k]),
                                            L["short_half_length"], L["resolution"] / 2, L["support"])
        return self._short_maps[k]

    def _icp(self, a: int, b: int, init: np.ndarray, hold: np.ndarray | None = None,
             maps: tuple[np.ndarray, np.ndarray] | None = None) -> Match:
        """ICP of b's submap onto a's (or of ``maps``: source, target); ``hold``: a direction (a's frame) kept at
        ``init``."""
        res = self._lengths["resolution"]
        cloud = lambda xy: Cloud(np.column_stack([xy, np.zeros(len(xy))]), True, 2.0 * res)  # noqa: E731
        src, tgt = maps or (self._maps[b], self._maps[a])
        self._clouds = (cloud(src), cloud(tgt))
        prior = None
        if hold is not None:
            prior = np.zeros((3, 3))
            prior[:2, :2] = 100.0 * len(src) * np.outer(hold, hold)
        return register(self._clouds[0], self._clouds[1], init, (2.0 * res, res), "point-to-plane",
                        prior_info=prior)

    def _gates(self, a: int, b: int, m: Match, entry: dict, across: bool = False) -> list[GateFailure]:
        src, tgt = self._clouds
        res = self._lengths["resolution"]
        visible, whole = self._overlap(a, b, m.T)
        overlap = visible if self.overlap_in_sight else whole
        c = constraint(src, tgt, m.T, res)
        entry.update(overlap=round(overlap, 4), overlap_in_sight=round(visible, 4), overlap_whole=round(whole, 4),
                     constraint=round(c, 4))
        failed = []
        if overlap < self.min_fitness:
            failed.append(GateFailure(Gate.OVERLAP, overlap, self.min_fitness))
        if c < self.min_constraint and not across:  # a closure across a corridor is degenerate by design
            failed.append(GateFailure(Gate.CORRIDOR, c, self.min_constraint))
        if self._frames.planar:
            fa, fb = int(self._keys[a]), int(self._keys[b])
            sa = Cloud(self._frames.points[fa], True, 2.0 * res)
            sb = Cloud(self._frames.points[fb], True, 2.0 * res)
            margin = 4.0 * self._lengths["fine"]
            free = max(free_space(sb, sa, m.T, margin), free_space(sa, sb, se3.inverse(m.T), margin))
            entry["free_space"] = round(free, 4)
            if free > self.max_free_space:
                failed.append(GateFailure(Gate.WALLS, free, self.max_free_space))
        return failed

    def _overlap(self, a: int, b: int, T: np.ndarray) -> tuple[float, float]:
        """Overlap of the two submaps at ``T`` (b's frame in a's): the smaller, over the two directions, of the
        share of one submap's points within a cell of the other's, counted only over the points that lie within
        sensor reach (``reach``: the 90th-percentile range) of a scan position of the other visit, since the
        rest was out of its sight: two visits that share a stretch and then part ways see each other's far ends
        only from one side. Also the share over all points (both directions, the plain overlap)."""
        src, tgt = self._clouds
        L = self._lengths
        res, reach = L["resolution"], L["reach"]
        inv = se3.inverse(T)
        out, whole = [], []
        for moving, fixed, M, seen_from in ((src, tgt, T, self._origins[a]), (tgt, src, inv, self._origins[b])):
            c, s = M[0, 0], M[1, 0]
            p = moving.xy @ np.array([[c, s], [-s, c]]) + M[:2, 3]
            hit = np.isfinite(fixed.tree.query(p, distance_upper_bound=res)[0])
            near = cKDTree(seen_from).query(p, distance_upper_bound=reach)[0] < reach
            whole.append(float(hit.mean()) if len(hit) else 0.0)
            # at least a tenth of the points must be in sight, else the plain share
            out.append(float(hit[near].mean()) if near.sum() >= max(10, 0.1 * len(p)) else whole[-1])
        return min(out), min(whole)

    def _consistent(self, new: Closure, others: list[Closure], odo: np.ndarray, kpath: np.ndarray) -> list[Closure]:
        """The closures (``new`` excluded) that agree with ``new`` around a cycle; empty if none."""
        L = self._lengths
        agree = []
        for c in others:
            if abs(c.b - new.b) > self.consistency_window:
                continue
            span = abs(kpath[c.a] - kpath[new.a]) + abs(kpath[c.b] - kpath[new.b])
            et, er = cycle_error(odo, new, c)
            if et <= L["cycle_tolerance"] + self.cycle_drift * span and er <= np.radians(2.0) + 1e-3 * span:
                agree.append(c)
        return agree

    # ------------------------------------------------------------------ topology
    def _topology(self, frames: Frames, corrected: np.ndarray, log: list, closures: int) -> Topology:
        L = self._lengths
        limit = self.max_loops if self.max_loops is not None else self.k // 2
        rows = loop_rows(corrected[:, :3, 3], path_length(corrected), L["radius"], L["min_path_gap"], self.k, limit)
        topo = assemble(rows, self.k, self.temporal_fill, log)
        poses = corrected if closures else None  # loop-closed only when a loop was closed
        return replace(topo, closures=closures, poses=poses, loop_closed=poses is not None)


class DriftRates:
    """The warm start's drift measured by the accepted closures: translation (m) and yaw (degrees) of their
    corrections over the path each was searched after (m), pooled over all of them. A closure across a corridor
    holds the prediction along its axis: it measures yaw only."""

    def __init__(self) -> None:
        self.offset_m = self.offset_deg = self.path_m = self.path_deg = 0.0

    def add(self, closures: list[Closure]) -> None:
        for c in closures:
            if c.axis is None:
                self.offset_m += c.entry["offset"]
                self.path_m += c.entry["travelled"]
            self.offset_deg += c.entry["offset_deg"]
            self.path_deg += c.entry["travelled"]

    def rates(self, drift: float, yaw_drift: float, margin: float) -> tuple[float, float]:
        """Window growth (m and degrees per metre): ``margin`` times the pooled rates, at most the priors
        ``drift`` and ``yaw_drift``; each the prior until a closure has measured it over some path."""
        return (drift if self.path_m <= 0 else min(drift, margin * self.offset_m / self.path_m),
                yaw_drift if self.path_deg <= 0 else min(yaw_drift, margin * self.offset_deg / self.path_deg))


def _shared(cloud: Cloud, sample: int = 200) -> float:
    """The median number of the cloud's points within its normal radius of one of them (at least 1): how many
    residuals share one normal's error."""
    xy = cloud.xy[:: max(1, len(cloud.xy) // sample)]
    counts = cloud.tree.query_ball_point(xy, cloud.normal_radius, return_length=True)
    return max(1.0, float(np.median(counts)))


def correct(poses: np.ndarray, keys: np.ndarray, odo: np.ndarray, key_poses: np.ndarray) -> np.ndarray:
    """Apply the keyframes' planar corrections to every frame, interpolated by frame index between the two
    keyframes around it (yaw unwrapped); keyframes get exactly their own."""
    corr = se3.to_xy_yaw(se3.from_xy_yaw(key_poses) @ se3.inverse(se3.from_xy_yaw(odo)))
    corr[:, 2] = np.unwrap(corr[:, 2])
    frames = np.arange(len(poses))
    c = np.stack([np.interp(frames, keys, corr[:, d]) for d in range(3)], axis=1)
    return se3.from_xy_yaw(c) @ poses
