"""SE-Sync graphs with indefinite information matrices (issue 30, item 6): one warning, and the file's own
matrices optimised unless --information nearest-psd asks for the nearest positive-definite ones."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from dm2_backend.cli.main import cli
from dm2_backend.formats.g2o import read_g2o, write_g2o
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.pose_graph import PoseGraph

pytest.importorskip("g2opy")


def indefinite_graph(path) -> PoseGraph:
    """Half a circle of 6 planar poses and a loop edge that disagrees with the odometry, whose information
    matrix has eigenvalues -4.76, 10 and 19.76 (as SE-Sync's cubicle.g2o holds such matrices)."""
    n = 6
    a = np.linspace(0, np.pi, n)
    gt = se3.from_xy_yaw(np.c_[3 * np.cos(a), 3 * np.sin(a), a + np.pi / 2])
    edges = np.array([(i, i + 1) for i in range(n - 1)] + [(0, n - 1)])
    rel = se3.relative(gt[edges[:, 0]], gt[edges[:, 1]])
    rel[-1] = rel[-1] @ se3.from_xy_yaw(np.array([[0.3, -0.2, 0.2]]))[0]
    info = np.tile(np.diag([10.0, 10.0, 50.0]), (len(edges), 1, 1))
    info[-1] = [[10.0, 0, 12], [0, 10, 0], [12, 0, 5]]
    graph = PoseGraph(np.arange(n), gt, edges, rel, info, planar=True)
    write_g2o(graph, path)
    return graph


def file_cost(graph: PoseGraph, poses: np.ndarray) -> float:
    """0.5 * sum e' W e with the file's own matrices W (g2o's EDGE_SE2 error: Z^-1 Xi^-1 Xj as x, y, theta)."""
    d = se3.relative(poses[graph.edges[:, 0]], poses[graph.edges[:, 1]])
    e = se3.to_xy_yaw(np.linalg.inv(graph.relative) @ d).reshape(-1, 3)
    return 0.5 * float(np.einsum("ei,eij,ej->", e, graph.information, e))


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args], obj={})


def test_the_files_matrices_are_optimised_unless_asked_otherwise(tmp_path):
    graph = indefinite_graph(tmp_path / "g.g2o")
    np.testing.assert_array_equal(read_g2o(tmp_path / "g.g2o").information, graph.information)  # as written
    r = run("baseline", "g2o", "--graph", tmp_path / "g.g2o", "-o", tmp_path / "file")
    assert r.exit_code == 0, r.output
    assert "not positive semi-definite" in r.output and "optimised as the file writes them" in r.output
    r = run("baseline", "g2o", "--graph", tmp_path / "g.g2o", "-o", tmp_path / "psd", "--information", "nearest-psd")
    assert r.exit_code == 0 and "nearest positive-definite" in r.output
    as_written, nearest = (np.load(tmp_path / name / "poses.npy") for name in ("file", "psd"))
    assert np.abs(as_written - nearest).max() > 0.05  # the two problems have different optima
    # under the file's own information, what was optimised as written is better than the nearest-PSD optimum
    assert file_cost(graph, as_written) < file_cost(graph, nearest) - 0.03
    report = json.loads((tmp_path / "file" / "report.json").read_text())
    assert report["final_error"] == pytest.approx(file_cost(graph, as_written), abs=1e-9)
    assert report["graph_meta"]["information_not_psd"] == 1


def test_gtsam_weighs_them_as_gtsam_does_with_one_warning(tmp_path):
    """Issue 53, item 4: GTSAM's answer (as gtsam.readG2o weighs the file, see test_gtsam_indefinite.py),
    not a refusal; --information nearest-psd still gives the nearest positive-definite problem."""
    indefinite_graph(tmp_path / "g.g2o")
    r = run("baseline", "gtsam", "--graph", tmp_path / "g.g2o", "-o", tmp_path / "out")
    assert r.exit_code == 0, r.output
    assert r.stderr.count("not positive semi-definite") == 1 and "GTSAM weighs the file as given" in r.stderr
    r = run("baseline", "gtsam", "--graph", tmp_path / "g.g2o", "-o", tmp_path / "psd", "--information", "nearest-psd")
    assert r.exit_code == 0 and "nearest positive-definite ones (--information nearest-psd)" in r.stderr, r.output
    as_given, nearest = (np.load(tmp_path / name / "poses.npy") for name in ("out", "psd"))
    assert np.abs(as_given - nearest).max() > 1e-3  # two different problems
