"""g2o pose graphs: agreement with gtsam.readG2o, round trips, trajectory view, bad input, CLI."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from shared_helpers import DATA, assert_one_line_error, need, run

from dm2_backend.formats import detect_trajectory_format, read_trajectory, write_trajectory
from dm2_backend.formats.g2o import read_g2o, write_g2o
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.pose_graph import PoseGraph
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.runtime.errors import InputError

GRAPHS = DATA / "posegraphs"
NAMES = ["MIT", "intel", "kitti_00", "parking-garage", "sphere2500", "tinyGrid3D"]


def _pose2_to_4x4(M2: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:2, :2] = M2[:2, :2]
    T[:2, 3] = M2[:2, 2]
    return T


def assert_agrees_with_gtsam(graph: PoseGraph, path: Path) -> None:
    import gtsam

    factors, values = gtsam.readG2o(str(path), not graph.planar)
    assert sorted(values.keys()) == graph.ids.tolist()
    if graph.planar:
        poses = [_pose2_to_4x4(values.atPose2(n).matrix()) for n in graph.ids.tolist()]
    else:
        poses = [values.atPose3(n).matrix() for n in graph.ids.tolist()]
    np.testing.assert_allclose(graph.poses, np.array(poses), atol=1e-9, rtol=0)
    assert factors.size() == len(graph.edges)
    edges = [factors.at(e) for e in range(factors.size())]
    assert [list(f.keys()) for f in edges] == graph.edges.tolist()
    measured = np.array([f.measured().matrix() for f in edges])
    if graph.planar:
        measured = np.array([_pose2_to_4x4(M) for M in measured])
    np.testing.assert_allclose(graph.relative, measured, atol=1e-9, rtol=0)
    info = np.array([f.noiseModel().information() for f in edges])
    scale = np.maximum(1.0, np.abs(info).max(axis=(1, 2)))[:, None, None]
    np.testing.assert_allclose(graph.information_rotation_first() / scale, info / scale, atol=1e-9, rtol=0)


@pytest.mark.parametrize("name", NAMES)
def test_agrees_with_gtsam_and_round_trips(tmp_path, name):
    path = need(GRAPHS / f"{name}.g2o")
    graph = read_g2o(path)
    assert graph.planar == (name in ("MIT", "intel", "kitti_00"))
    assert graph.information.shape[1:] == ((3, 3) if graph.planar else (6, 6))
    assert_agrees_with_gtsam(graph, path)
    out = tmp_path / "out.g2o"
    write_g2o(graph, out)
    back = read_g2o(out)
    np.testing.assert_array_equal(back.ids, graph.ids)
    np.testing.assert_array_equal(back.edges, graph.edges)
    np.testing.assert_allclose(back.poses, graph.poses, atol=1e-12, rtol=0)
    np.testing.assert_allclose(back.relative, graph.relative, atol=1e-12, rtol=0)
    np.testing.assert_array_equal(back.information, graph.information)
    assert_agrees_with_gtsam(back, out)  # gtsam reads our file the same way


def test_edges_only_graph_chains_odometry():
    graph = read_g2o(need(GRAPHS / "kitti_00.g2o"))
    assert graph.meta["initialised_from_edges"] == len(graph) == 4541
    np.testing.assert_array_equal(graph.poses[0], np.eye(4))
    odo = graph.edges[:, 1] == graph.edges[:, 0] + 1
    rows = graph.edge_rows()[odo]
    chained = graph.poses[rows[:, 0]] @ graph.relative[odo]
    np.testing.assert_allclose(graph.poses[rows[:, 1]], chained, atol=1e-9)


def test_trajectory_view_and_writer(tmp_path):
    path = need(GRAPHS / "intel.g2o")
    assert detect_trajectory_format(path) == "g2o"
    traj = read_trajectory(path)
    assert traj.planar and traj.frame_ids[:3] == ["0", "1", "2"] and traj.meta["edges"] == 2512
    out = tmp_path / "traj.g2o"
    write_trajectory(traj, out, "g2o")
    graph = read_g2o(out)
    assert graph.planar and len(graph.edges) == len(traj) - 1
    np.testing.assert_array_equal(graph.information, np.tile(np.eye(3), (len(traj) - 1, 1, 1)))
    np.testing.assert_allclose(graph.poses, traj.poses, atol=1e-12)
    assert_agrees_with_gtsam(graph, out)
    with pytest.raises(InputError, match="leave the z = 0 plane"):
        bumped = traj.poses.copy()
        bumped[3, 2, 3] = 0.5
        write_trajectory(Trajectory(bumped, planar=True), tmp_path / "bad.g2o", "g2o")


def test_fix_and_unknown_lines(tmp_path):
    path = tmp_path / "g.g2o"
    path.write_text(
        "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0.1\nFIX 0\nVERTEX_XY 7 1 2\n"
        "EDGE_SE2 0 1 1 0 0.1 1 0 0 1 0 1\nEDGE_SE2_XY 1 7 1 1 1 0 1\nEDGE_SE2_XY 0 7 1 1 1 0 1\n"
    )
    graph = read_g2o(path)
    assert graph.fixed == [0] and len(graph) == 2 and len(graph.edges) == 1
    assert graph.meta["skipped"] == {"VERTEX_XY": 1, "EDGE_SE2_XY": 2}
    write_g2o(graph, tmp_path / "h.g2o")
    assert "FIX 0" in (tmp_path / "h.g2o").read_text() and read_g2o(tmp_path / "h.g2o").fixed == [0]


@st.composite
def graphs(draw):
    planar = draw(st.booleans())
    n = draw(st.integers(1, 8))
    ids = np.array(sorted(draw(st.sets(st.integers(0, 10_000), min_size=n, max_size=n))))
    coords = st.floats(-1e4, 1e4)
    if planar:
        poses = se3.from_xy_yaw(np.array(draw(st.lists(st.tuples(coords, coords, st.floats(-3, 3)),
                                                       min_size=n, max_size=n))))
    else:
        q = draw(st.lists(st.lists(st.floats(-1, 1), min_size=4, max_size=4)
                          .filter(lambda v: np.linalg.norm(v) > 0.1), min_size=n, max_size=n))
        t = draw(st.lists(st.tuples(coords, coords, coords), min_size=n, max_size=n))
        poses = se3.from_xyz_quat(np.array(t), np.array(q), "xyzw")
    m = n - 1 + draw(st.integers(0, 3)) if n > 1 else 0
    pairs = [(k, k + 1) for k in range(n - 1)] + [tuple(draw(st.permutations(range(n)))[:2])
                                                   for _ in range(m - (n - 1))]
    rows = np.array(pairs, dtype=int).reshape(-1, 2)
    dim = 3 if planar else 6
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    A = rng.normal(0, 10, (len(rows), dim, dim)) * 10.0 ** rng.integers(-3, 4, (len(rows), 1, 1))
    info = A @ np.swapaxes(A, 1, 2) + np.eye(dim)
    return PoseGraph(ids=ids, poses=poses.reshape(-1, 4, 4), edges=ids[rows].reshape(-1, 2),
                     relative=se3.relative(poses[rows[:, 0]], poses[rows[:, 1]]).reshape(-1, 4, 4),
                     information=info, planar=planar)


@settings(max_examples=40, deadline=None)
@given(graphs())
def test_property_write_read(tmp_path_factory, graph):
    out = tmp_path_factory.mktemp("g") / "g.g2o"
    write_g2o(graph, out)
    back = read_g2o(out)
    assert back.planar == graph.planar
    np.testing.assert_array_equal(back.ids, graph.ids)
    np.testing.assert_array_equal(back.edges, graph.edges)
    np.testing.assert_allclose(back.poses, graph.poses, atol=1e-8, rtol=0)
    np.testing.assert_allclose(back.relative, graph.relative, atol=1e-8, rtol=0)
    np.testing.assert_allclose(back.information, graph.information, rtol=1e-15, atol=0)


V0 = "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n"
V1 = "VERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
INFO6 = " ".join("1" if (r == c) else "0" for r in range(6) for c in range(r, 6))


@pytest.mark.parametrize(
    "text, line, problem",
    [
        (V0 + "VERTEX_SE3:QUAT 1 1 0 0 0 0 1\n", 2, "has 7 fields, expected 8"),
        (V0 + "VERTEX_SE3:QUAT 1 1 nan 0 0 0 0 1\n", 2, "NaN"),
        (V0 + "VERTEX_SE3:QUAT 1 1 0 0 0 0 0 3\n", 2, "quaternion norm 3"),
        (V0 + "VERTEX_SE2 1 1 0 0\n", 2, "2D and 3D mixed"),
        (V0 + V1 + "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n", 3, "vertex 0 defined twice"),
        (V0 + V1 + f"EDGE_SE3:QUAT 1 1 0 0 0 0 0 0 1 {INFO6}\n", 3, "to itself"),
        (V0 + "VERTEX_SE3:QUAT a 1 0 0 0 0 0 1\n", 2, "node id 'a' is not an integer"),
        (V0 + V1 + f"EDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1 {INFO6.replace('1', 'x', 1)}\n", 3, "not a number"),
        (V0 + "FIX 5\n", 2, "FIX of unknown node 5"),
        ("# nothing\nVERTEX_XY 1 2 3\n", None, "no VERTEX_SE2"),
    ],
)
def test_bad_input(tmp_path, text, line, problem):
    path = tmp_path / "bad.g2o"
    path.write_text(text)
    with pytest.raises(InputError, match=problem) as info:
        read_g2o(path)
    assert info.value.line == line and info.value.source == str(path)
    assert_one_line_error(run("info", str(path)), "bad.g2o")
    assert_one_line_error(run("convert", str(path), str(tmp_path / "o.tum")), "bad.g2o")


def _indefinite_graph(path: Path) -> np.ndarray:
    """An SE-Sync-style 3D graph (cubicle.g2o has such edges): edge 1-2 has an indefinite information matrix
    (a 2x2 translation block with eigenvalues -100 and 300), edge 0-2 a negative diagonal entry. Returns the
    matrix of edge 1-2."""
    info = np.diag([100.0, 100, 100, 400, 400, 400])
    bad = info.copy()
    bad[0, 1] = bad[1, 0] = 200.0
    neg = info.copy()
    neg[0, 0] = -5.0
    iu = np.triu_indices(6)
    text = V0 + V1 + "VERTEX_SE3:QUAT 2 2 0.1 0 0 0 0 1\n"
    for (i, j, x), M in (((0, 1, 1.0), info), ((1, 2, 1.0), bad), ((0, 2, 2.0), neg)):
        text += f"EDGE_SE3:QUAT {i} {j} {x} 0 0 0 0 0 1 " + " ".join(map(repr, M[iu].tolist())) + "\n"
    path.write_text(text)
    return bad


def test_indefinite_information_is_read_as_the_nearest_psd_with_one_warning(tmp_path, caplog):
    path = tmp_path / "cubicle.g2o"
    bad = _indefinite_graph(path)
    with caplog.at_level("WARNING", logger="dm2_backend.formats.g2o"):
        graph = read_g2o(path, "nearest-psd")
    (record,) = caplog.records
    assert "2 of 3 information matrices are not positive semi-definite (first on line 5)" in record.getMessage()
    assert graph.meta["information_projected"] == 2
    w, V = np.linalg.eigh(bad)
    nearest = V @ np.diag(np.clip(w, 0, None)) @ V.T  # the nearest PSD matrix (Frobenius norm)
    np.testing.assert_allclose(graph.information[1], nearest, atol=1e-5)
    assert (np.linalg.eigvalsh(graph.information) > 0).all()  # invertible: the solvers factorise them
    np.testing.assert_array_equal(graph.information[0], np.diag([100.0, 100, 100, 400, 400, 400]))
    result = run("info", str(path))
    assert result.exit_code == 0 and "g2o" in result.output, result.output
    assert result.stderr.count("\n") == 1 and "not positive semi-definite" in result.stderr


def test_baselines_solve_a_graph_with_indefinite_information(tmp_path):
    from dm2_backend.kernel import gtsam_solver

    path = tmp_path / "cubicle.g2o"
    _indefinite_graph(path)
    result = gtsam_solver.optimize(read_g2o(path, "nearest-psd"))
    assert np.isfinite(result.poses).all()
    np.testing.assert_allclose(result.poses[1, :3, 3], [1, 0, 0], atol=0.1)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        read_g2o(tmp_path / "none.g2o")
    assert_one_line_error(run("info", str(tmp_path / "none.g2o")), "none.g2o")


def test_cli_convert_g2o_to_tum_and_info(tmp_path):
    path = need(GRAPHS / "tinyGrid3D.g2o")
    out = tmp_path / "tiny.tum"
    result = run("convert", str(path), str(out))
    assert result.exit_code == 0, result.output
    tum = read_trajectory(out)
    np.testing.assert_array_equal(tum.timestamps, np.arange(9.0))
    np.testing.assert_allclose(tum.poses, read_g2o(path).poses, atol=1e-12)
    info = run("info", str(path))
    assert info.exit_code == 0 and "g2o" in info.output and "9" in info.output
