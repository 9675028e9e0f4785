"""Map quality without ground truth: mean map entropy and plane variance against a hand computation, their
rise as poses are perturbed, identical values for identical maps, and the CLI (``dm2 eval --scans``)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from dm2_backend.cli.main import cli
from dm2_backend.evaluation.map_quality import MapSampler, MapSettings, map_quality, voxelise
from dm2_backend.formats.kitti import write_kitti
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.scans import Scan, ScanSequence
from dm2_backend.kernel.trajectory import Trajectory


def test_entropy_and_plane_variance_by_hand():
    """Four points, one neighbourhood each (the radius holds them all): the covariance by hand."""
    pts = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 2]])
    q = map_quality(pts, np.arange(4), radius=10.0, min_points=4)
    cov = np.cov(pts.T, bias=True)
    h = 0.5 * np.log(np.linalg.det(2 * np.pi * np.e * cov))
    assert q.entropy == pytest.approx(h, rel=1e-12)
    assert q.plane_variance == pytest.approx(np.linalg.eigvalsh(cov)[0], rel=1e-12)
    assert q.queries == 4 and q.points == 4
    # too few neighbours: no query counts, the metric is undefined rather than made up
    assert np.isnan(map_quality(pts, np.arange(4), radius=10.0, min_points=5).entropy)


def test_planar_maps_use_2d_covariances():
    pts = np.array([[0.0, 0], [1, 0], [0, 1], [1, 1], [0.5, 0.5]])
    cov = np.cov(pts.T, bias=True)
    q = map_quality(pts, np.arange(5), radius=10.0, min_points=5)
    assert q.entropy == pytest.approx(0.5 * np.log(np.linalg.det(2 * np.pi * np.e * cov)))


def test_voxelise_averages_each_voxel():
    pts = np.array([[0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [1.5, 0.0, 0.0]])
    out = voxelise(pts, 1.0)
    np.testing.assert_allclose(out[np.argsort(out[:, 0])], [[0.2, 0.2, 0.2], [1.5, 0.0, 0.0]])
    # voxel indices too many for one integer: the row-wise path gives the same
    far = np.array([[0.0, 0.0, 0.0], [2e-6, 0.0, 0.0], [1e7, 1e7, 1e7]])
    np.testing.assert_allclose(voxelise(far, 1e-5), [[1e-6, 0.0, 0.0], [1e7, 1e7, 1e7]])


def room_scans(n: int = 12, seed: int = 0) -> tuple[ScanSequence, np.ndarray]:
    """A sensor moving through a box room (walls, floor, ceiling), each scan in its own frame."""
    rng = np.random.default_rng(seed)
    faces = []
    for axis in range(3):
        for side in (-1.0, 1.0):
            p = rng.uniform(-4, 4, (3000, 3))
            p[:, axis] = side * (4.0 if axis < 2 else 2.0)
            faces.append(p)
    world = np.concatenate(faces)
    poses = np.stack([se3.from_xyz_euler(np.array([0.2 * i, 0.1 * np.sin(i), 0.0, 0.0, 0.0, 0.05 * i]))
                      for i in range(n)])
    clouds = []
    for T in poses:
        pick = world[rng.choice(len(world), 6000, replace=False)]
        clouds.append(se3.transform_points(se3.inverse(T), pick).astype(np.float32))
    seq = ScanSequence(lambda i: Scan(clouds[i]), n, np.arange(n, dtype=float))
    return seq, poses


def perturbed(poses: np.ndarray, sigma: float, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = np.concatenate([rng.normal(0, sigma, (len(poses), 3)), rng.normal(0, sigma / 4, (len(poses), 3))], 1)
    return np.stack([T @ se3.from_xyz_euler(d) for T, d in zip(poses, noise, strict=True)])


def test_entropy_rises_with_the_pose_error():
    seq, poses = room_scans()
    sampler = MapSampler.from_scans(seq, MapSettings(queries=3000))
    values = [sampler.evaluate(perturbed(poses, s)) for s in (0.0, 0.02, 0.05, 0.1, 0.2)]
    entropy = [v.entropy for v in values]
    plane = [v.plane_variance for v in values]
    assert all(a < b for a, b in zip(entropy, entropy[1:])), entropy
    assert all(a < b for a, b in zip(plane, plane[1:])), plane
    assert sampler.radius == pytest.approx(3 * sampler.voxel)


def test_identical_maps_score_identically():
    seq, poses = room_scans()
    sampler = MapSampler.from_scans(seq, MapSettings(queries=2000))
    a = sampler.evaluate(poses)
    assert sampler.evaluate(poses.copy()) == a
    assert MapSampler.from_scans(seq, MapSettings(queries=2000)).evaluate(poses) == a  # built again: the same
    # the same map moved rigidly as a whole is the same map
    moved = se3.from_xyz_euler(np.array([3.0, -2.0, 1.0, 0.1, -0.2, 0.7])) @ poses
    b = sampler.evaluate(moved)
    assert b.entropy == pytest.approx(a.entropy, abs=1e-9) and b.queries == a.queries


def test_eval_cli_reports_map_metrics_without_ground_truth(tmp_path):
    seq, poses = room_scans(8)
    folder = tmp_path / "scans"
    folder.mkdir()
    for i in range(len(seq)):
        pts = seq[i].points
        np.hstack([pts, np.zeros((len(pts), 1), np.float32)]).astype(np.float32).tofile(folder / f"{i:06d}.bin")
    write_kitti(Trajectory(poses), tmp_path / "good.txt")
    write_kitti(Trajectory(perturbed(poses, 0.1)), tmp_path / "bad.txt")
    out = tmp_path / "eval.json"
    result = CliRunner().invoke(cli, ["eval", "--scans", str(folder), "--est", str(tmp_path / "good.txt"),
                                      "--est", str(tmp_path / "bad.txt"), "--json", str(out)])
    assert result.exit_code == 0, result.output
    assert "map entropy" in result.output and "radius" in result.output
    data = json.loads(out.read_text())
    good, bad = (e["metrics"]["map"] for e in data["estimates"])
    assert good["entropy"] < bad["entropy"] and good["plane_variance"] < bad["plane_variance"]
    assert data["map"]["radius_m"] == pytest.approx(good["radius"])
