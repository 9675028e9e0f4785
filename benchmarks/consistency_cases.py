"""The consistency profile on trajectories broken on purpose: hits and false flags.

    python benchmarks/consistency_cases.py [--out benchmarks/results]

Cases: the real LiDAR keyframes' front-end poses (../shared/data, skipped when absent), the true poses of the LiDAR
ray-cast through their map and of the benchmark's 2,000-frame street (when the benchmark cache holds them) and of a
simulated street, each as given and broken
four ways (a 0.3 m / 2 degree jump at one frame, the same jump carried on, a drift building up to it over 10 frames,
a closure 1 m / 5 degrees off forced into their pose graph). A hit is a flag within the profile's resolution (a
neighbouring stretch and a gap) of a broken frame; a false flag lies farther from every one. Writes
``consistency-cases.json`` / ``.md`` and ``docs/consistency-keyframes.png`` (the keyframes with the carried jump,
the README's picture). Not part of the test suite.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from dm2_backend.evaluation import plots
from dm2_backend.evaluation.consistency_profile import GAP, consistency_profiles
from dm2_backend.formats import ReadOptions
from dm2_backend.kernel.scans import Scan, ScanSequence
from dm2_backend.pipeline.inputs import load_inputs
from dm2_backend.simulate.broken import (
    broken_frames,
    bump,
    drifting,
    hits_and_false_flags,
    jump_from,
    one_frame,
    wrong_closure,
)
from dm2_backend.simulate.sequence import SimSettings, simulate

REPO = Path(__file__).resolve().parents[1]
KEYFRAMES = REPO.parent / "shared" / "data" / "lidar3d" / "balm_realworld_000-079"
BENCH_CACHE = Path(os.environ.get("DM2_BENCH_CACHE", Path.home() / ".cache" / "dm2" / "bench"))


def sequences() -> dict[str, tuple[ScanSequence, np.ndarray]]:
    out = {}
    if (KEYFRAMES / "poses.txt").is_file():
        real = load_inputs(KEYFRAMES / "velodyne", None, KEYFRAMES / "poses.txt", None,
                           ReadOptions(times=KEYFRAMES / "times.txt"))
        out["real keyframes (front end)"] = (real.scans, real.given.poses)
    else:
        print(f"skipped the real keyframes: {KEYFRAMES} absent", file=sys.stderr)
    for folder in sorted(BENCH_CACHE.glob("realmap-balm-*"))[-1:]:  # made by `benchmarks/run.py --only sim-realmap`
        sim = load_inputs(folder / "velodyne", None, folder / "poses.txt", None,
                          ReadOptions(times=folder / "times.txt"))
        out["LiDAR ray-cast through the keyframes' map (truth)"] = (sim.scans, sim.given.poses)
    for folder in sorted(BENCH_CACHE.glob("sim-frames-2000-seed-0-extent-*[0-9a-f]"))[-1:]:  # `run.py --set 3d`
        sim = load_inputs(folder / "velodyne", None, folder / "poses.txt", None,
                          ReadOptions(times=folder / "times.txt"))
        out["simulated street, 2,000 frames at 0.5 m (truth)"] = (sim.scans, sim.given.poses)
    scans, gt, _ = simulate(SimSettings(frames=80, seed=3, extent=10.0, laps=1.5), progress=False)
    out["simulated street (truth)"] = (ScanSequence(lambda i: Scan(scans[i]), len(scans),
                                                    timestamps=np.arange(len(scans)) * 0.1, planar=False), gt)
    return out


def broken_cases(poses: np.ndarray) -> dict[str, np.ndarray]:
    k = len(poses) // 2
    pos = poses[:, :3, 3]
    steps = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    radius = 4.0 * float(np.median(steps))  # each frame's graph neighbours: a few steps around it
    far = np.linalg.norm(pos[:, None] - pos[None], axis=2)
    i, j = next(((a, b) for a in range(len(poses)) for b in range(a + 10, len(poses)) if far[a, b] < radius),
                (2, len(poses) - 3))  # a revisit when the path has one
    return {"as given": poses, "one frame": one_frame(poses, k), "jump": jump_from(poses, k),
            "drift": drifting(poses, k, 10),
            f"wrong closure {i}-{j}": wrong_closure(poses, i, j, bump(1.0, 5.0), radius=max(radius, 1.0))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    args = parser.parse_args()
    rows = []
    for name, (seq, poses) in sequences().items():
        cases = broken_cases(poses)
        t = time.perf_counter()
        profiles = consistency_profiles(seq, cases, seq.timestamps)
        seconds = (time.perf_counter() - t) / len(cases)
        for case, prof in profiles.items():
            broken = broken_frames(poses, cases[case])
            hit, false = hits_and_false_flags(prof.flagged, broken, prof.window + GAP)
            summary = prof.summary()
            rows.append({"sequence": name, "case": case, "frames": len(poses),
                         "broken_frames": [int(b) for b in np.flatnonzero(broken)],
                         "flagged": [[s.first, s.last] for s in prof.segments], "hit": hit if broken.any() else None,
                         "false_flags": false, "levels_m": summary["levels_m"],
                         "thresholds_m": summary["thresholds_m"],
                         "seconds_per_profile": seconds})
            print(f"{name:28s} {case:22s} broken {rows[-1]['broken_frames'][:3]}... flagged {rows[-1]['flagged']} "
                  f"hit {rows[-1]['hit']} false {false}")
        if name.startswith("real"):
            show = {"as given": profiles["as given"], "jump at frame 40": profiles["jump"]}
            plots.save(plots.consistency_figure(cases["jump"][:, :3, 3], show,
                                                "real LiDAR keyframes: a 0.3 m / 2 degree jump inserted at frame 40"),
                       REPO / "docs" / "consistency-keyframes.png")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "consistency-cases.json").write_text(json.dumps(rows, indent=1))
    lines = ["| sequence | case | broken frames | flagged stretches | hit | false flags |",
             "|---|---|---|---|---|---:|"]
    for r in rows:
        b = r["broken_frames"]
        broken = "none" if not b else (f"{b[0]}-{b[-1]}" if len(b) < 6 else f"{len(b)} frames, {b[0]}-{b[-1]}")
        lines.append(f"| {r['sequence']} | {r['case']} | {broken} | "
                     f"{', '.join(f'{a}-{z}' for a, z in r['flagged']) or 'none'} | "
                     f"{'-' if r['hit'] is None else ('yes' if r['hit'] else 'no')} | {r['false_flags']} |")
    (args.out / "consistency-cases.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
