"""``topology.json`` / ``topology.png`` of a run folder: the place recognition's log with a status per
candidate, counts and reasons, and the plot of the closures over the trajectory."""

from __future__ import annotations

import json

import numpy as np
import pytest
from optim_cases import planar_case

from dm2_backend.evaluation import plots
from dm2_backend.evaluation.topology_log import DROPPED, candidates, document, pairs_by_status
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.prepared import Topology
from dm2_backend.pipeline import outputs
from dm2_backend.plugins.registry import load


def fake_topology() -> Topology:
    log = [
        {"plugin": "loops", "min_path_gap": 20.0, "closures": 2, "dropped": 1},
        {"i": 0, "j": 30, "score": 0.31, "verified": False, "accepted": False,
         "reason": "score 0.31 < 0.50; ambiguous: a different alignment scores 0.97 of the best"},
        {"i": 1, "j": 31, "score": 0.42, "verified": False, "accepted": False, "reason": "score 0.42 < 0.50"},
        {"i": 2, "j": 32, "score": 0.8, "verified": True, "accepted": False, "reason": "verified", "z": [1, 0, 0]},
        {"i": 3, "j": 33, "score": 0.9, "verified": True, "accepted": True, "reason": "verified", "z": [0, 0, 0]},
        {"i": 4, "j": 34, "score": 0.7, "verified": True, "accepted": False, "dropped": True, "reason": DROPPED,
         "z": [0, 1, 0]},
    ]
    pos = np.column_stack([np.cos(np.linspace(0, 4 * np.pi, 40)), np.sin(np.linspace(0, 4 * np.pi, 40)),
                           np.zeros(40)]) * 5
    poses = se3.make_poses(np.tile(np.eye(3), (40, 1, 1)), pos)
    edges = np.array([[5, 25], [6, 26], [7, 8]])
    return Topology(np.zeros((40, 2), int), edges, ["loop", "loop", "temporal"], log, poses)


def test_document_gives_each_candidate_a_status():
    topo = fake_topology()
    doc = document(topo)
    assert doc["plugin"] == "loops" and doc["summary"] == topo.log[0]
    assert [c["status"] for c in doc["candidates"]] == ["rejected", "rejected", "verified", "accepted", "dropped"]
    assert doc["counts"] == {"candidates": 5, "verified": 3, "accepted": 1, "dropped": 1, "rejected": 2,
                             "verified_not_accepted": 1}
    # rejections by cause with the numbers masked; the others by status
    assert doc["reasons"] == {"score # < #": 2, "ambiguous: a different alignment scores # of the best": 1,
                              "verified, not accepted": 1, "accepted": 1, DROPPED: 1}
    assert doc["edges"] == {"loop": 2, "temporal": 1}
    for c, e in zip(doc["candidates"], topo.log[1:]):  # the log's scores are kept as they are
        assert {k: v for k, v in c.items() if k != "status"} == e
    assert "status" not in topo.log[5]  # the topology's own log is not changed
    pairs = pairs_by_status(doc)
    assert pairs["accepted"].tolist() == [[3, 33]] and pairs["dropped"].tolist() == [[4, 34]]
    assert pairs["rejected"].shape == (2, 2)


def test_descriptor_style_log_counts_accepted_as_verified():
    log = [{"plugin": "descriptor"}, {"i": 0, "j": 9, "accepted": True, "reason": "accepted"},
           {"i": 1, "j": 8, "accepted": False, "reason": "fitness 0.20 < 0.50"}]
    assert [c["status"] for c in candidates(log)] == ["accepted", "rejected"]
    doc = document(Topology(np.zeros((10, 1), int), log=log))
    assert doc["counts"]["verified"] == 1 and doc["reasons"] == {"accepted": 1, "fitness # < #": 1}


def test_no_candidates(tmp_path):
    topo = Topology(np.zeros((5, 1), int), log=[{"plugin": "radius", "radius": 2.0}])
    poses = se3.make_poses(np.tile(np.eye(3), (5, 1, 1)), np.arange(15.0).reshape(5, 3))
    assert outputs.write_topology(tmp_path, topo, poses) == ["topology.json", "topology.png"]
    doc = json.loads((tmp_path / "topology.json").read_text())
    assert doc["counts"]["candidates"] == 0 and doc["plugin"] == "radius" and doc["candidates"] == []
    assert (tmp_path / "topology.png").is_file()
    ax = outputs.topology_plot(topo, poses).axes[0]
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("x [m]", "y [m]") and not ax.collections  # nothing to draw
    np.testing.assert_array_equal(ax.lines[0].get_xdata(), poses[:, 0, 3])  # x on the horizontal axis


@pytest.fixture(scope="module")
def loops_topology() -> Topology:
    case = planar_case()
    return load("dm2.place_recognition", "loops")(progress=False).run(case.frames, case.warm)


def test_written_files_match_the_loops_log(loops_topology, tmp_path):
    topo = loops_topology
    assert outputs.write_topology(tmp_path, topo, topo.poses) == ["topology.json", "topology.png"]
    doc = json.loads((tmp_path / "topology.json").read_text())
    log = json.loads(json.dumps(topo.log, default=outputs._json_default))
    assert doc["summary"] == log[0] and doc["plugin"] == "loops"
    entries = log[1:]
    assert len(doc["candidates"]) == len(entries) == doc["counts"]["candidates"] > 0
    for c, e in zip(doc["candidates"], entries):
        assert {k: v for k, v in c.items() if k != "status"} == e
        status = "accepted" if e["accepted"] else "verified" if e["verified"] else "rejected"
        assert c["status"] == ("dropped" if e.get("dropped") else status)
    assert doc["counts"]["accepted"] == sum(e["accepted"] for e in entries) > 0
    assert doc["counts"]["verified"] == sum(e["verified"] for e in entries)
    assert sum(doc["reasons"].values()) >= doc["counts"]["candidates"]
    assert doc["edges"]["loop"] == topo.edge_kind.count("loop") > 0
    assert (tmp_path / "topology.png").is_file()
    ax = outputs.topology_plot(topo, topo.poses).axes[0]
    labels = [c.get_label() for c in ax.collections]
    assert f"loop edges ({doc['edges']['loop']})" in labels
    assert any(lb.startswith(f"accepted closures ({doc['counts']['accepted']})") for lb in labels)


def test_closures_across_a_corridor_are_drawn_apart(tmp_path):
    topo = fake_topology()
    topo.log[4] = {**topo.log[4], "axis": [1.0, 0.0], "reason": "verified across a corridor"}  # the accepted one
    topo.log.append({"i": 5, "j": 35, "score": 0.9, "verified": True, "accepted": True, "reason": "verified",
                     "z": [0, 0, 0]})
    pairs = pairs_by_status(document(topo))
    assert pairs["across"].tolist() == [[3, 33]] and pairs["accepted"].tolist() == [[5, 35]]
    fig = plots.topology_figure(topo.poses[:, :3, 3], pairs, topo.edges[:2])
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert "accepted across a corridor (free along it) (1)" in labels and "accepted closures (1)" in labels
