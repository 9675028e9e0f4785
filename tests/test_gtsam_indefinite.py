"""``dm2 baseline gtsam --graph`` on graphs with information matrices that are not positive semi-definite
(issue 53, item 4): GTSAM's own answer (what ``gtsam.readG2o`` + Levenberg-Marquardt gives on the same
file) with one warning, as on SE-Sync's cubicle.g2o; a matrix GTSAM turns into NaN sigmas stays an error."""

from __future__ import annotations

import json
from pathlib import Path

import gtsam
import numpy as np
import pytest
from shared_helpers import gtsam_direct, run

from dm2_backend.formats.g2o import read_g2o, write_g2o
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.pose_graph import PoseGraph, indefinite
from dm2_backend.kernel.solver_options import SolverOptions

GRAPHS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "posegraphs"


def direct_poses(values: gtsam.Values, ids: np.ndarray, is3d: bool) -> np.ndarray:
    if is3d:
        return np.stack([values.atPose3(int(n)).matrix() for n in ids])
    xyt = np.array([[p.x(), p.y(), p.theta()] for p in (values.atPose2(int(n)) for n in ids)])
    return se3.from_xy_yaw(xyt).reshape(-1, 4, 4)


def planar_graph(path: Path) -> None:
    """A half circle of 8 planar poses with drifting odometry and two loop edges whose information matrices
    are indefinite (eigenvalues of [[10, 0, 12], [0, 10, 0], [12, 0, 5]]: -4.8, 10, 19.8)."""
    n = 8
    a = np.linspace(0, np.pi, n)
    gt = se3.from_xy_yaw(np.c_[3 * np.cos(a), 3 * np.sin(a), a + np.pi / 2])
    edges = np.array([(i, i + 1) for i in range(n - 1)] + [(0, n - 1), (1, 5)])
    rel = se3.relative(gt[edges[:, 0]], gt[edges[:, 1]])
    rel[:n - 1] = rel[:n - 1] @ se3.from_xy_yaw(np.array([[0.02, 0.01, 0.03]]))[0]  # drift
    poses = [gt[0]]
    for T in rel[:n - 1]:
        poses.append(poses[-1] @ T)
    init = np.stack(poses)
    info = np.tile(np.diag([10.0, 10.0, 50.0]), (len(edges), 1, 1))
    info[-2:] = [[10.0, 0, 12], [0, 10, 0], [12, 0, 5]]
    write_g2o(PoseGraph(np.arange(n), init, edges, rel, info, planar=True), path)


def spatial_graph(path: Path) -> None:
    """A 3D chain of 6 poses with a loop edge: the loop's 6x6 information couples translation and rotation
    (off-diagonal blocks, as SE-Sync's cubicle.g2o matrices do) and is indefinite."""
    rng = np.random.default_rng(3)
    n = 6
    gt = se3.from_xyz_euler(np.c_[np.arange(n) * 1.0, np.zeros((n, 4)), np.arange(n) * 0.2])
    edges = np.array([(i, i + 1) for i in range(n - 1)] + [(0, n - 1)])
    rel = se3.relative(gt[edges[:, 0]], gt[edges[:, 1]])
    rel = rel @ se3.from_xyz_euler(rng.normal(scale=0.02, size=(len(edges), 6)))
    A = rng.normal(size=(6, 6))
    good = A @ A.T + 5 * np.eye(6)
    bad = good.copy()
    bad[0, 4] = bad[4, 0] = 40.0
    info = np.stack([np.diag([100.0, 100, 100, 400, 400, 400])] * (len(edges) - 1) + [bad])
    poses = [gt[0]]
    for T in rel[:n - 1]:
        poses.append(poses[-1] @ T)
    write_g2o(PoseGraph(np.arange(n), np.stack(poses), edges, rel, info), path)


def assert_gtsams_answer(path: Path, out: Path, is3d: bool, indefinite_count: int) -> dict:
    result = run("baseline", "gtsam", "--graph", path, "-o", out)
    assert result.exit_code == 0, result.output
    warnings = [line for line in result.stderr.splitlines() if "not positive semi-definite" in line]
    assert len(warnings) == 1, result.stderr  # one line, not the reader's and GTSAM's
    assert f"{indefinite_count} of " in warnings[0] and "GTSAM weighs the file as given" in warnings[0]
    report = json.loads((out / "report.json").read_text())
    expected, values = gtsam_direct(path, is3d, SolverOptions())
    assert report["final_error"] == pytest.approx(expected, rel=1e-6)
    graph = read_g2o(path)
    # LM's rounding differs in the last digits of the poses (as in test_baselines' comparison)
    np.testing.assert_allclose(np.load(out / "poses.npy"), direct_poses(values, graph.ids, is3d), atol=1e-4)
    return report


def test_planar_indefinite_graph_gets_gtsams_answer(tmp_path):
    path = tmp_path / "planar.g2o"
    planar_graph(path)
    assert indefinite(read_g2o(path).information).sum() == 2
    report = assert_gtsams_answer(path, tmp_path / "out", False, 2)
    assert report["final_error"] < report["initial_error"]


def test_spatial_indefinite_graph_gets_gtsams_answer(tmp_path):
    path = tmp_path / "cubicle_like.g2o"
    spatial_graph(path)
    assert indefinite(read_g2o(path).information).sum() == 1
    assert_gtsams_answer(path, tmp_path / "out", True, 1)


def test_perturbed_real_graph_gets_gtsams_answer(tmp_path):
    """intel.g2o with every tenth edge's x-theta information coupled beyond positive semi-definite."""
    source = GRAPHS / "intel.g2o"
    if not source.exists():
        pytest.skip(f"{source} absent")
    graph = read_g2o(source)
    info = graph.information.copy()
    k = np.arange(0, len(info), 10)
    info[k, 0, 2] = info[k, 2, 0] = 2 * np.sqrt(info[k, 0, 0] * info[k, 2, 2])
    path = tmp_path / "intel_indefinite.g2o"
    write_g2o(PoseGraph(graph.ids, graph.poses, graph.edges, graph.relative, info, planar=True), path)
    assert_gtsams_answer(path, tmp_path / "out", False, len(k))


def test_nan_sigmas_remain_an_error(tmp_path):
    """A diagonal information matrix with a negative entry gets NaN sigmas in GTSAM: one line, exit 2."""
    path = tmp_path / "negative.g2o"
    planar_graph(path)
    text = path.read_text().splitlines()
    fields = text[-1].split()
    fields[-6:] = ["10.0", "0.0", "0.0", "10.0", "0.0", "-5.0"]  # EDGE_SE2 1 5: diagonal, theta -5
    path.write_text("\n".join([*text[:-1], " ".join(fields)]) + "\n")
    result = run("baseline", "gtsam", "--graph", path, "-o", tmp_path / "out")
    assert result.exit_code == 2, result.output
    err = result.stderr.strip().splitlines()[-1]
    assert "negative.g2o" in err and "not finite" in err and "edge 1-5" in err, result.stderr
    assert "Traceback" not in result.output and not (tmp_path / "out").exists()
