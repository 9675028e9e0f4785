"""``benchmarks/closures.py``: precision and recall of loop closures against relations fabricated from a
known two-lap trajectory (a correct closure, two wrong ones, an unverifiable one, a missed loop)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from dm2_backend.formats import write_trajectory
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "closures.py"
N = 200  # two laps of a 10 m circle: 0.63 m of path per frame, 62.8 m per lap


@pytest.fixture(scope="module")
def closures():
    spec = importlib.util.spec_from_file_location("bench_closures", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def truth() -> tuple[np.ndarray, np.ndarray]:
    a = np.linspace(0, 4 * np.pi, N, endpoint=False)
    xy_yaw = np.column_stack([10 * np.cos(a), 10 * np.sin(a), a + np.pi / 2])
    return se3.from_xy_yaw(xy_yaw), 1000.0 + 0.5 * np.arange(N)


def relation(poses, stamps, f1, f2) -> list[float]:
    x, y, yaw = se3.to_xy_yaw(se3.relative(poses[f1], poses[f2])[None])[0]
    return [stamps[f1], stamps[f2], x, y, 0.0, 0.0, 0.0, yaw]


def z_of(poses, i, j, dx=0.0, dyaw_deg=0.0) -> list[float]:
    x, y, yaw = se3.to_xy_yaw(se3.relative(poses[i], poses[j])[None])[0]
    return [x + dx, y, yaw + np.radians(dyaw_deg)]


def case():
    poses, stamps = truth()
    rels = [relation(poses, stamps, k, k + 1) for k in range(N - 1)]  # local, not loop-crossing
    rels += [relation(poses, stamps, 110, 14)]  # loop-crossing, given later -> earlier (covered swapped)
    rels += [relation(poses, stamps, a, a + 97) for a in (50, 70, 80)]  # loop-crossing; 80 is missed
    accepted = {"verified": True, "accepted": True, "status": "accepted"}
    doc = {"plugin": "loops", "summary": {"plugin": "loops", "min_path_gap": 20.0, "submap_half_length": 3.0},
           "candidates": [
               {"i": 12, "j": 111, "z": z_of(poses, 12, 111), **accepted},  # correct
               {"i": 48, "j": 149, "z": z_of(poses, 48, 149, dx=0.5), **accepted},  # 0.5 m off
               {"i": 71, "j": 168, "z": z_of(poses, 71, 168, dyaw_deg=3.0), **accepted},  # 3 degrees off
               {"i": 30, "j": 190, "z": z_of(poses, 30, 190), **accepted},  # no relation near: unverifiable
               {"i": 80, "j": 177, "z": z_of(poses, 80, 177, dx=3.0), "verified": False, "accepted": False,
                "status": "rejected"},  # rejected candidates neither count nor cover
           ]}
    return poses, stamps, doc, np.array(rels)


def test_precision_and_recall(closures):
    poses, stamps, doc, rels = case()
    r = closures.evaluate(poses, stamps, doc, rels)
    assert r["relations"]["matched"] == len(rels)
    assert r["relations"]["loop_crossing"] == 4 and r["relations"]["covered"] == 3
    assert r["relations"]["recall"] == pytest.approx(0.75)
    c = r["closures"]
    assert (c["accepted"], c["counted"], c["correct"], c["wrong"], c["unverifiable"]) == (4, 3, 1, 2, 1)
    assert c["precision"] == pytest.approx(1 / 3)
    rows = {(row["i"], row["j"]): row for row in r["per_closure"]}
    assert rows[(12, 111)]["correct"] and rows[(12, 111)]["error_m"] < 1e-6
    assert rows[(12, 111)]["frames"] == [14, 110]  # the reversed relation, used swapped
    assert rows[(48, 149)]["error_m"] == pytest.approx(0.5, abs=1e-3) and not rows[(48, 149)]["correct"]
    assert rows[(71, 168)]["error_deg"] == pytest.approx(3.0, abs=1e-2) and not rows[(71, 168)]["correct"]
    assert not rows[(30, 190)]["verifiable"]
    assert [m["frames"] for m in r["missed_relations"]] == [[80, 177]]


def test_the_gap_decides_what_crosses_a_loop(closures):
    poses, stamps, doc, rels = case()
    doc["summary"] = {}  # no min_path_gap: 10 m, covering within 2.5 m of path
    r = closures.evaluate(poses, stamps, doc, rels)
    assert r["settings"]["min_path_gap_m"] == 10.0 and r["settings"]["cover_m"] == 2.5
    assert r["relations"]["loop_crossing"] == 4
    assert closures.evaluate(poses, stamps, doc, rels, gap=100.0)["relations"]["loop_crossing"] == 0


def test_main_reads_a_run_folder(closures, tmp_path):
    poses, stamps, doc, rels = case()
    run = tmp_path / "run"
    run.mkdir()
    np.save(run / "poses.npy", poses)
    write_trajectory(Trajectory(poses, stamps, planar=True), run / "poses_tum.txt", "tum")
    (run / "topology.json").write_text(json.dumps(doc))
    rel_file = tmp_path / "loop.relations"
    rel_file.write_text("".join(" ".join(f"{v:.9f}" for v in row) + "\n" for row in rels))
    assert closures.main([str(run), str(rel_file), "--out", str(tmp_path / "results")]) == 0
    result = json.loads((tmp_path / "results" / "closures-loop.json").read_text())
    assert result["closures"]["correct"] == 1 and result["relations"]["covered"] == 3
    md = (tmp_path / "results" / "closures-loop.md").read_text()
    assert "**75.0 %**" in md and "48-149" in md
    assert closures.main([str(tmp_path), str(rel_file), "--out", str(tmp_path / "results")]) == 2
