"""Where a trajectory went wrong, without ground truth: each frame judged by the map the *other* frames make.

Every scan is summed into cells once (``kernel.planes``); planes come from many frames in adaptive voxels. Each
frame is measured (m) in three views of "the others":

- **past** and **future**: the planes of the neighbouring blocks of frames before / after it
  (``profile_views``): a front-end jump makes the frames after it disagree with the sharp map of the block before;
- **all**: every other frame (leave-one-out, robust weights), which sees a revisit that does not line up (a
  wrong loop closure, a drift that shows where the path comes back).

A frame needs its cells at full density (``profile_cells.CELLS_PER_FRAME``) for its score to mean anything (fewer
cells a frame make a true frame's score noise): the scans are summed into cells once (``profile_cells``: in memory,
or for a long sequence in temporary files), and a long sequence is judged a stretch of frames at a time
(``profile_stretches``), so memory stays bounded and every frame is judged as in a short sequence.

The views have levels and spreads of their own (a frame's flat cells against the dense planes of its neighbours
agree several times closer than its points against the sparser map of all others), so each is judged against its
own. A view flags a frame that stands out from the sequence's frames: ``SPREAD`` robust standard deviations (1.4826
times the median absolute deviation) above the view's median, which are the agreeing frames' while most frames
agree. The threshold is at least ``FLOOR`` times the noise the planes measure: a frame placed within the sensor's
own noise is not misplaced, however sharp the rest (a depth camera's noise is not averaged away in a cell's mean).
A frame's score is its largest view over that view's threshold (flagged above 1); flagged frames make segments with
their frame and time ranges. Cases and their results: ``benchmarks/consistency_cases.py`` and the tests (true,
refined-to-floor and broken poses of 3D and 2D simulations, real LiDAR keyframes, a ray-cast through their map, a
simulated depth camera, the noise-free DeepMapping set); why these thresholds:
docs/decisions/0013-consistency-profile-thresholds.md.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dm2_backend.evaluation import plots
from dm2_backend.evaluation.profile_cells import full_cells
from dm2_backend.evaluation.profile_stretches import cluster_for, stretched_views
from dm2_backend.evaluation.profile_views import window_frames
from dm2_backend.evaluation.report_writers import safe_name
from dm2_backend.kernel.prepared import ScanScale
from dm2_backend.kernel.scan_scale import derive_scale
from dm2_backend.kernel.scans import ScanSequence
from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.runtime.memory import release_freed_memory

#: a view flags a frame this many robust standard deviations above the view's median ...
SPREAD = 12.0
#: ... and at least this multiple of the noise the planes measure (sigma of a point's distance to its plane)
FLOOR = 1.0
#: the noise is taken as at least this share of the scans' point spacing (a noise-free simulation's planes measure
#: the float rounding of its coordinates: no map shows a misplacement that fine)
RESOLUTION = 0.01
#: flagged frames this close (frames) are one segment
GAP = 2


@dataclass(frozen=True)
class Segment:
    """Consecutive flagged frames ``first``..``last`` (inclusive), their stamps (s) when known, and the frame
    with the highest score: its score (its view over that view's threshold) and that view."""

    first: int
    last: int
    start_s: float | None
    end_s: float | None
    peak_frame: int
    peak: float
    peak_view: str


@dataclass(frozen=True)
class ConsistencyProfile:
    """Per frame: each view's RMS distance (m; NaN where a frame has no point on a plane of it) and ``score``,
    its largest view over that view's threshold (flagged above 1; NaN where no view measures it); each view's
    level and flag threshold (m); the flagged segments."""

    score: np.ndarray
    views_m: dict[str, np.ndarray]
    levels_m: dict[str, float]
    thresholds_m: dict[str, float]
    segments: list[Segment]
    voxel_m: float
    window: int
    stamps: np.ndarray | None
    #: the sensor's noise as the planes measure it (robust sigma of a point's distance to its plane, m; at the
    #: sharpest of the poses profiled together, at least ``RESOLUTION`` of the point spacing)
    noise_m: float = float("nan")

    @property
    def flagged(self) -> np.ndarray:
        out = np.zeros(len(self.score), bool)
        for s in self.segments:
            out[s.first:s.last + 1] = True
        return out

    def summary(self) -> dict:
        """The numbers a report shows (no per-frame arrays)."""
        finite = self.score[np.isfinite(self.score)]
        return {"frames": len(self.score), "frames_scored": len(finite),
                "levels_m": {view: _number(v) for view, v in self.levels_m.items()},
                "thresholds_m": {view: _number(v) for view, v in self.thresholds_m.items()},
                "median_score": float(np.median(finite)) if len(finite) else None,
                "p90_score": float(np.percentile(finite, 90)) if len(finite) else None,
                "noise_m": _number(self.noise_m), "voxel_m": self.voxel_m, "window_frames": self.window,
                "flagged_frames": int(self.flagged.sum()), "segments": [vars(s) for s in self.segments]}


#: flagged stretches a console line names (the worst first); the rest are in ``consistency.csv``
NAMED = 3


def flag_text(summary: dict) -> str:
    """One line from a profile's :meth:`ConsistencyProfile.summary`: each view's level and threshold, how many
    stretches are flagged and the worst ``NAMED`` of them (by peak score)."""
    levels = {view: v for view, v in summary["levels_m"].items() if v is not None}
    if not levels:
        return "no frame scored"
    level = ("frames agree to " + ", ".join(f"{v:.3g} m ({view})" for view, v in levels.items()) + ", flagged above "
             + ", ".join(f"{summary['thresholds_m'][view]:.3g} m ({view})" for view in levels))
    segments = summary["segments"]
    if not segments:
        return f"{level}: no flagged frame"
    worst = sorted(segments, key=lambda s: -s["peak"])[:NAMED]
    named = ", ".join(f"{s['first']}-{s['last']}" + (f" ({s['start_s']:.3f}-{s['end_s']:.3f} s)"
                                                      if s["start_s"] is not None else "")
                      + f" peak {s['peak']:.3g}x the {s['peak_view']} view's threshold at {s['peak_frame']}"
                      for s in worst)
    rest = f"; the other {len(segments) - len(worst)} in consistency.csv" if len(segments) > len(worst) else ""
    return (f"{level}: {len(segments)} flagged stretch{'es' if len(segments) > 1 else ''} "
            f"({summary['flagged_frames']} frames), worst {named}{rest}")


def profile_voxel(scans: ScanSequence, scale: ScanScale | None = None) -> float:
    """The largest plane voxel, from the data as the dense stage takes it: a few per median range, its finest
    quarter at least a point spacing."""
    scale = scale or derive_scale(scans)
    return max(scale.range_median / 8.0, 4.0 * scale.spacing_raw, 1e-3)


def _segments(score: np.ndarray, worst_view: np.ndarray, stamps: np.ndarray | None) -> list[Segment]:
    over = np.flatnonzero(np.nan_to_num(score, nan=0.0) > 1.0)
    if len(over) == 0:
        return []
    breaks = np.flatnonzero(np.diff(over) > GAP + 1)
    out = []
    for run in np.split(over, breaks + 1):
        first, last = int(run[0]), int(run[-1])
        peak = first + int(np.nanargmax(score[first:last + 1]))
        out.append(Segment(first, last, None if stamps is None else float(stamps[first]),
                           None if stamps is None else float(stamps[last]), peak, float(score[peak]),
                           str(worst_view[peak])))
    return out


def threshold_of(distance: np.ndarray, floor: float = 0.0) -> tuple[float, float]:
    """A view's level (the median of its ``distance``) and flag threshold: ``SPREAD`` robust standard deviations
    (1.4826 times the median absolute deviation) above that level, and at least ``floor`` (m)."""
    finite = distance[np.isfinite(distance)]
    if len(finite) == 0:
        return float("nan"), float("inf")
    level = float(np.median(finite))
    spread = 1.4826 * float(np.median(np.abs(finite - level)))
    return level, max(level + SPREAD * spread, floor)


def consistency_profiles(scans: ScanSequence, candidates: dict[str, np.ndarray], stamps: np.ndarray | None = None,
                         planar: bool = False, voxel: float | None = None, seed: int = 0,
                         progress: bool = False, folder: Path | None = None) -> dict[str, ConsistencyProfile]:
    """The profile of each set of poses (one per scan). The scans are summed into cells once, at full density
    (:func:`~dm2_backend.evaluation.profile_cells.full_cells`: in memory, or for a long sequence temporary files in
    ``folder``), and judged a stretch at a time (:func:`stretched_views`; on a cluster, :func:`cluster_for`: the
    workers read the files, so on several machines ``folder`` must be on storage they share). ``planar``: 2D
    scans, their lines seen as vertical walls."""
    scale = derive_scale(scans)
    voxel = voxel or profile_voxel(scans, scale)
    release_freed_memory()
    candidates = {name: np.asarray(poses, dtype=np.float64) for name, poses in candidates.items()}
    # on a cluster the stretches are tasks, which map the cells from files (in ``folder``: storage they all see)
    engine = cluster_for(len(scans), len(candidates), folder is not None)
    with full_cells(scans, voxel, seed, planar, progress, folder, engine is not None) as cells:
        views = stretched_views(len(scans), cells, candidates, voxel, seed, progress, engine)
    # the sensor's: as measured at the poses that make the sharpest planes, at least the scans' resolution
    noise = max(min(measured for _, measured in views.values()), RESOLUTION * scale.spacing_raw)
    return {name: _profile(views[name][0], noise, stamps, voxel, window_frames(poses, voxel))
            for name, poses in candidates.items()}


def consistency_profile(scans: ScanSequence, poses: np.ndarray, stamps: np.ndarray | None = None,
                        planar: bool = False, voxel: float | None = None, seed: int = 0) -> ConsistencyProfile:
    """The profile of one set of poses (:func:`consistency_profiles`)."""
    return consistency_profiles(scans, {"poses": poses}, stamps, planar, voxel, seed)["poses"]


def _profile(views: dict[str, np.ndarray], noise: float, stamps: np.ndarray | None, voxel: float, window: int
             ) -> ConsistencyProfile:
    levels, thresholds = {}, {}
    for view, distance in views.items():
        levels[view], thresholds[view] = threshold_of(distance, FLOOR * noise)
    names = list(views)
    over = np.stack([views[view] / thresholds[view] for view in names])
    measured = np.isfinite(over)
    filled = np.where(measured, over, -np.inf)
    score = np.where(measured.any(0), filled.max(0), np.nan)
    worst = np.asarray(names)[filled.argmax(0)]
    return ConsistencyProfile(score, views, levels, thresholds, _segments(score, worst, stamps), voxel, window,
                              stamps, noise)


#: what :func:`write_profiles` writes (stem "consistency")
PROFILE_FILES = ("consistency.json", "consistency.csv", "consistency.png")


def write_profiles(folder: Path, profiles: dict[str, ConsistencyProfile],
                   positions: np.ndarray | dict[str, np.ndarray],
                   stem: str = "consistency", steps: dict[str, list[int]] | None = None) -> list[str]:
    """``{stem}.json`` (each profile's summary, per-frame scores and views), ``{stem}.csv`` (one row per frame) and
    ``{stem}.png`` (:func:`plots.consistency_figure` over ``positions``, or each estimate's: label -> positions).
    ``steps``: per-step marks (e.g. the step guard's ``held`` and ``contradicted`` steps: frame i marks its step to
    i+1), a column ``step_<name>`` each and a ``steps`` entry in the JSON. Returns the names written."""
    folder.mkdir(parents=True, exist_ok=True)
    first = next(iter(profiles.values()))
    steps = steps or {}
    doc = {label: {**p.summary(), "score": _floats(p.score), "views_m": {k: _floats(v) for k, v in
                                                                         p.views_m.items()}}
           for label, p in profiles.items()}
    if steps:
        doc["steps"] = {name: sorted(int(i) for i in marked) for name, marked in steps.items()}
    with atomic_write(folder / f"{stem}.json") as fh:
        json.dump(doc, fh, indent=1, allow_nan=False)
    columns = ["frame", "stamp_s"] + [f"{safe_name(label)}_{c}" for label, p in profiles.items()
                                      for c in ("score", "flagged", *(f"{view}_m" for view in p.views_m))]
    columns += [f"step_{name}" for name in steps]
    marks = {name: set(int(i) for i in marked) for name, marked in steps.items()}
    with atomic_write(folder / f"{stem}.csv", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(columns)
        flags = {label: p.flagged for label, p in profiles.items()}
        for i in range(len(first.score)):
            row = [i, "" if first.stamps is None else repr(float(first.stamps[i]))]
            for label, p in profiles.items():
                row += [_cell(p.score[i]), int(flags[label][i]), *(_cell(v[i]) for v in p.views_m.values())]
            w.writerow(row + [int(i in marked) for marked in marks.values()])
    plots.save(plots.consistency_figure(positions, profiles), folder / f"{stem}.png")
    return [f"{stem}.json", f"{stem}.csv", f"{stem}.png"]


def _cell(v: float) -> str:
    return "" if not np.isfinite(v) else f"{v:.6g}"


def _number(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def _floats(a: np.ndarray) -> list[float | None]:
    return [float(v) if np.isfinite(v) else None for v in a]
