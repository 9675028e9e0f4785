"""Precision and recall of a run's loop closures against the Freiburg relations.

    python benchmarks/closures.py RUN_FOLDER DATASET.relations [--dataset NAME] [--out benchmarks/results]

RUN_FOLDER is a ``dm2 refine`` / ``dm2 baseline`` run folder: ``topology.json`` and the final poses
(``poses.npy`` with the stamps of ``poses_tum.txt``, of another ``poses_*`` file such as ``poses_carmen.*``,
or of ``--stamps``). Each relation ``t1 t2 x y z roll pitch yaw`` is the pose at t2 in the frame of t1.

- A relation is *loop-crossing* when its two stamps lie more than G metres apart along the run's path
  (G: the place recognition's ``min_path_gap``, else 10 m).
- An accepted closure (frames i, j) *covers* a relation (frames f1, f2) when both ends are within H metres
  of path of each other, (i, f1) and (j, f2) or swapped (H: ``submap_half_length``, else G / 4).
- Recall: the fraction of loop-crossing relations covered by an accepted closure.
- Precision: for each accepted closure covered by a relation (the one with the smallest path offsets), the
  true pose of j in i is ``local(i -> f1) * relation * local(f2 -> j)``, the local poses taken from the final
  estimate; the closure is correct when its measured pose is within 0.2 m and 2 degrees of it. Closures
  that no relation covers are unverifiable. A closure across a corridor (``axis`` in its log entry) is
  measured across its free axis only.
- Also reported: the same test on the median error over every relation that covers the closure (the
  relations near a fast turn disagree with one another by up to ~0.2 m in any rigid map, ACES frame 158).
Writes ``<out>/closures-<dataset>.json`` and ``.md``. Not part of the test suite.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from dm2_backend.algorithms.common import path_length
from dm2_backend.evaluation.relations import MAX_DT, load_relations
from dm2_backend.formats import read_trajectory
from dm2_backend.kernel.geometry import se3
from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.runtime.errors import InputError

REPO = Path(__file__).resolve().parents[1]
DEFAULT_GAP = 10.0


def load_run(folder: Path, stamps: Path | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """Final poses (N,4,4) in frame order, their stamps (N,) and ``topology.json`` of a run folder."""
    doc = json.loads((folder / "topology.json").read_text())
    poses = np.load(folder / "poses.npy") if (folder / "poses.npy").is_file() else None
    sources = ([stamps] if stamps else []) + [folder / "poses_tum.txt"] + sorted(folder.glob("poses_carmen*"))
    for src in sources:
        if not src.is_file():
            continue
        try:
            traj = read_trajectory(src)
        except InputError:  # e.g. Intel's laser stamps go backwards: TUM refuses them, the CARMEN copy keeps them
            continue
        if poses is None:
            poses = traj.poses
        if traj.timestamps is not None and len(traj.timestamps) == len(poses):
            return poses, np.asarray(traj.timestamps, dtype=np.float64), doc
    raise InputError(folder, "no poses with timestamps (poses_tum.txt, poses_carmen.*, or --stamps)")


def frames_at(stamps: np.ndarray, t: np.ndarray, max_dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Frame index nearest in time to each ``t`` (stamps may be unsorted) and whether it is within max_dt."""
    order = np.argsort(stamps, kind="stable")
    s = stamps[order]
    right = np.clip(np.searchsorted(s, t), 0, len(s) - 1)
    left = np.clip(right - 1, 0, len(s) - 1)
    pick = np.where(np.abs(s[left] - t) <= np.abs(s[right] - t), left, right)
    return order[pick], np.abs(s[pick] - t) <= max_dt


def closure_pose(c: dict) -> np.ndarray:
    """Measured pose (4,4) of frame j in frame i: ``z`` (x, y, yaw) or ``relative`` (4x4)."""
    if c.get("z") is not None:
        return se3.from_xy_yaw(np.asarray(c["z"], dtype=np.float64)[None])[0]
    return np.asarray(c["relative"], dtype=np.float64)


def relation_pose(r: np.ndarray) -> np.ndarray:
    """Pose (4,4) of a relation row ``t1 t2 x y z roll pitch yaw``."""
    return se3.make_poses(se3.rpy_to_matrix(r[5:8])[None], r[None, 2:5])[0]


def evaluate(poses: np.ndarray, stamps: np.ndarray, doc: dict, relations: np.ndarray, gap: float | None = None,
             half: float | None = None, max_dt: float = MAX_DT, tol_m: float = 0.2, tol_deg: float = 2.0) -> dict:
    """Recall over loop-crossing relations and precision of the accepted closures (see the module doc)."""
    summary = doc.get("summary") or {}
    gap = float(gap or summary.get("min_path_gap") or DEFAULT_GAP)
    half = float(half or summary.get("submap_half_length") or gap / 4.0)
    s = path_length(poses)
    f1, ok1 = frames_at(stamps, relations[:, 0], max_dt)
    f2, ok2 = frames_at(stamps, relations[:, 1], max_dt)
    ok = ok1 & ok2
    rel, f1, f2 = relations[ok], f1[ok], f2[ok]
    crossing = np.abs(s[f2] - s[f1]) > gap
    closures = [c for c in doc.get("candidates", []) if c.get("status") == "accepted"]
    ij = np.array([(c["i"], c["j"]) for c in closures], dtype=int).reshape(-1, 2)
    # path offsets (relations x closures), direct (f1~i, f2~j) and swapped (f1~j, f2~i)
    direct = np.maximum(np.abs(s[f1][:, None] - s[ij[:, 0]]), np.abs(s[f2][:, None] - s[ij[:, 1]]))
    swapped = np.maximum(np.abs(s[f1][:, None] - s[ij[:, 1]]), np.abs(s[f2][:, None] - s[ij[:, 0]]))
    offset = np.minimum(direct, swapped)
    covers = offset < half
    covered = covers.any(axis=1) if len(closures) else np.zeros(len(rel), bool)
    def covering(r: int, k: int) -> tuple[int, int, np.ndarray]:
        """Frames (a, b) and pose of relation r, turned to run from closure k's i side to its j side."""
        a, b, R = int(f1[r]), int(f2[r]), relation_pose(rel[r])
        return (b, a, se3.inverse(R)) if swapped[r, k] < direct[r, k] else (a, b, R)

    rows = []
    for k, c in enumerate(closures):
        i, j = int(ij[k, 0]), int(ij[k, 1])
        row = {"i": i, "j": j, "verifiable": bool(covers[:, k].any())}
        if row["verifiable"]:
            r = int(np.argmin(np.where(covers[:, k], offset[:, k], np.inf)))
            a, b, R = covering(r, k)
            et, er = closure_error(poses, c, i, j, a, b, R)
            each = [closure_error(poses, c, i, j, *covering(int(q), k)) for q in np.flatnonzero(covers[:, k])]
            all_t, all_r = zip(*each)
            mt, mr = float(np.median(all_t)), float(np.median(all_r))
            row.update(relation=[float(rel[r, 0]), float(rel[r, 1])], frames=[a, b],
                       path_offset_m=round(float(offset[r, k]), 3), error_m=round(et, 4), error_deg=round(er, 3),
                       correct=bool(et <= tol_m and er <= tol_deg), covering=len(all_t),
                       median_error_m=round(mt, 4), median_error_deg=round(mr, 3),
                       correct_median=bool(mt <= tol_m and mr <= tol_deg))
        rows.append(row)
    counted = [r for r in rows if r["verifiable"]]
    correct = sum(r["correct"] for r in counted)
    correct_median = sum(r["correct_median"] for r in counted)
    n_cross, n_hit = int(crossing.sum()), int((crossing & covered).sum())
    missed = np.flatnonzero(crossing & ~covered)
    return {
        "plugin": doc.get("plugin"),
        "settings": {"min_path_gap_m": gap, "cover_m": half, "max_dt_s": max_dt, "tol_m": tol_m, "tol_deg": tol_deg},
        "relations": {"total": len(relations), "matched": int(ok.sum()), "loop_crossing": n_cross,
                      "covered": n_hit, "recall": n_hit / n_cross if n_cross else None},
        "closures": {"accepted": len(rows), "counted": len(counted), "correct": correct,
                     "wrong": len(counted) - correct, "unverifiable": len(rows) - len(counted),
                     "precision": correct / len(counted) if counted else None,
                     "correct_median": correct_median,
                     "precision_median": correct_median / len(counted) if counted else None,
                     "max_error_m": max((r["error_m"] for r in counted), default=None),
                     "max_error_deg": max((r["error_deg"] for r in counted), default=None)},
        "per_closure": rows,
        "missed_relations": [{"t1": float(rel[m, 0]), "t2": float(rel[m, 1]), "frames": [int(f1[m]), int(f2[m])],
                              "path_gap_m": round(float(abs(s[f2[m]] - s[f1[m]])), 2)} for m in missed],
    }


def closure_error(poses: np.ndarray, c: dict, i: int, j: int, a: int, b: int, R: np.ndarray) -> tuple[float, float]:
    """Translation (m; across the free axis for a corridor closure) and rotation (deg) error of closure c
    (frames i, j) against the pose derived from relation R between frames a (near i) and b (near j)."""
    true = se3.relative(poses[i], poses[a]) @ R @ se3.relative(poses[b], poses[j])
    est = closure_pose(c)
    d = est[:2, 3] - true[:2, 3]
    if c.get("axis") is not None:
        u = np.asarray(c["axis"], dtype=np.float64)
        d = d - (d @ u) * u
    et = float(np.hypot(np.linalg.norm(d), est[2, 3] - true[2, 3]))
    return et, float(np.degrees(se3.rotation_angle(true[:3, :3].T @ est[:3, :3])))


def markdown(dataset: str, result: dict) -> str:
    rel, c, st = result["relations"], result["closures"], result["settings"]
    pct = lambda v: "n/a" if v is None else f"{100 * v:.1f} %"  # noqa: E731
    wrong = [r for r in result["per_closure"] if r.get("verifiable") and not r["correct"]]
    lines = [
        f"# Loop closures on {dataset} ({result['plugin']})", "",
        f"Generated by `python benchmarks/closures.py` from {result.get('run', 'a run folder')}.", "",
        "| | count |", "|---|---|",
        f"| relations (matched to frames) | {rel['total']} ({rel['matched']}) |",
        f"| loop-crossing (> {st['min_path_gap_m']:.1f} m of path apart) | {rel['loop_crossing']} |",
        f"| covered by an accepted closure (within {st['cover_m']:.1f} m of path) | {rel['covered']} |",
        f"| **recall** | **{pct(rel['recall'])}** |",
        f"| accepted closures | {c['accepted']} |",
        f"| counted (covered by a relation) / correct / wrong / unverifiable | "
        f"{c['counted']} / {c['correct']} / {c['wrong']} / {c['unverifiable']} |",
        f"| **precision** (within {st['tol_m']} m and {st['tol_deg']} deg of the nearest covering relation) | "
        f"**{pct(c['precision'])}** |",
        f"| precision by the median error over all covering relations | {pct(c.get('precision_median'))} "
        f"({c.get('correct_median')} of {c['counted']}) |",
        f"| largest error of a counted closure | {c['max_error_m']} m, {c['max_error_deg']} deg |", "",
    ]
    if wrong:
        lines += ["Wrong closures (frames i-j: error):", ""]
        lines += [f"- {r['i']}-{r['j']}: {r['error_m']} m, {r['error_deg']} deg (relation frames {r['frames'][0]}-"
                  f"{r['frames'][1]}; median over {r['covering']} covering relations {r['median_error_m']} m, "
                  f"{r['median_error_deg']} deg)" for r in wrong[:20]]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="run folder with topology.json and the final poses")
    ap.add_argument("relations", type=Path, help="Freiburg .relations file")
    ap.add_argument("--dataset", help="name in the output files (default: the relations file's stem)")
    ap.add_argument("--stamps", type=Path, help="trajectory file with the frames' timestamps")
    ap.add_argument("--gap", type=float, help="loop-crossing path gap, m (default: from topology.json)")
    ap.add_argument("--cover", type=float, help="path distance for a closure to cover a relation, m")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    args = ap.parse_args(argv)
    try:
        poses, stamps, doc = load_run(args.run, args.stamps)
        result = evaluate(poses, stamps, doc, load_relations(args.relations), args.gap, args.cover)
    except (InputError, OSError, KeyError, ValueError) as exc:
        print(f"closures: error: {exc}", file=sys.stderr)
        return 2
    dataset = args.dataset or args.relations.name.split(".")[0]
    result.update(dataset=dataset, run=str(args.run), relations_file=str(args.relations))
    stem = args.out / f"closures-{dataset}"
    with atomic_write(stem.with_suffix(".json")) as fh:
        json.dump(result, fh, indent=2)
    with atomic_write(stem.with_suffix(".md")) as fh:
        fh.write(markdown(dataset, result))
    print(markdown(dataset, result))
    print(f"wrote {stem}.json and .md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
