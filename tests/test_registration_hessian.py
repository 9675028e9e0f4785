"""The registration's own information (its point-to-plane Hessian) and what it does in the pose graph."""

from __future__ import annotations

import numpy as np

from dm2_backend.algorithms.common import Cloud
from dm2_backend.algorithms.icp import point_to_plane_hessian, register
from dm2_backend.config.schema import PluginSection
from dm2_backend.kernel import gtsam_solver
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.graph_edges import EIGEN_FLOOR, InformationModel, build_graph, hessian_information
from dm2_backend.kernel.prepared import Frames, Pairwise, ScanScale, Topology


def _exp(xi: np.ndarray) -> np.ndarray:
    """Exp of a g2o-order tangent [x y z rx ry rz] to first and second order (small steps only)."""
    T = np.eye(4)
    T[:3, :3] = se3.exp_so3(xi[3:])
    T[:3, 3] = xi[:3]
    return T


def test_hessian_is_the_gauss_newton_system_of_a_right_perturbation():
    rng = np.random.default_rng(0)
    p = rng.uniform(-5, 5, (50, 3))
    n = rng.normal(size=(50, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    T = se3.from_xyz_euler(np.array([[1.0, -2.0, 0.5, 0.2, -0.1, 0.7]]))[0]
    q = se3.transform_points(T, p)

    def residuals(xi: np.ndarray) -> np.ndarray:
        return np.einsum("ij,ij->i", n, se3.transform_points(T @ _exp(xi), p) - q)

    h = 1e-6
    J = np.column_stack([(residuals(h * e) - residuals(-h * e)) / (2 * h) for e in np.eye(6)])
    np.testing.assert_allclose(point_to_plane_hessian(p, n, T), J.T @ J, rtol=1e-5, atol=1e-6)


def test_one_plane_pins_three_directions_only():
    rng = np.random.default_rng(1)
    p = np.column_stack([rng.uniform(-5, 5, (200, 2)), np.zeros(200)])  # the floor, normal z
    H = point_to_plane_hessian(p, np.tile([0.0, 0.0, 1.0], (200, 1)), np.eye(4))
    free = H[np.ix_([0, 1, 5], [0, 1, 5])]  # x, y, yaw
    assert np.abs(free).max() < 1e-9 and H[2, 2] == 200 and H[3, 3] > 100 and H[4, 4] > 100


def _corridor(rng: np.random.Generator, length: float = 40.0) -> np.ndarray:
    """Two walls 3 m apart and a floor, along x: nothing fixes x."""
    x = rng.uniform(-length / 2, length / 2, 6000)
    walls = np.column_stack([x[:4000], np.where(np.arange(4000) % 2, 1.5, -1.5), rng.uniform(0, 2.5, 4000)])
    floor = np.column_stack([x[4000:], rng.uniform(-1.5, 1.5, 2000), np.zeros(2000)])
    return np.vstack([walls, floor]) + rng.normal(0, 0.005, (6000, 3))


def test_open3d_registration_of_a_corridor_reports_the_free_direction():
    rng = np.random.default_rng(2)
    target = Cloud(_corridor(rng), planar=False, normal_radius=0.5)
    source = Cloud(_corridor(rng), planar=False, normal_radius=0.5)
    for method in ("gicp", "point-to-plane"):
        assert register(source, target, np.eye(4), (0.3,), method).hessian is None  # only when asked
        m = register(source, target, np.eye(4), (0.3,), method, hessian=True)
        assert m.fitness > 0.9 and m.hessian is not None
        assert m.plane_rmse < 0.5 * m.rmse, (m.plane_rmse, m.rmse)  # the surfaces' noise, not the points' spacing
        w, v = np.linalg.eigh(m.hessian[:3, :3])
        assert w[0] < 0.01 * w[-1]  # the translation block is (up to the normals' noise) singular ...
        assert abs(v[0, 0]) > 0.99  # ... along the corridor


def test_hessian_information_keeps_a_slid_corridor_match_from_moving_the_graph():
    """A corridor registration slid 1 m along the corridor (its degenerate direction) against exact odometry:
    with the registration's Hessian the graph ignores the slide; with isotropic information it bends."""
    rng = np.random.default_rng(3)
    n = 6
    gt = se3.from_xyz_euler(np.column_stack([np.arange(n) * 1.0, np.zeros((n, 5))]))
    cloud = _corridor(rng).astype(np.float32)
    frames = Frames([cloud] * n, None, planar=False, scale=ScanScale(voxel=0.1, spacing=0.1))
    groups = np.array([[i + 3 if i + 3 < n else -1] for i in range(n)])
    rel = np.tile(np.eye(4), (n, 1, 1, 1))
    hess = np.zeros((n, 1, 6, 6), np.float32)
    H = point_to_plane_hessian(cloud[:4000].astype(float), np.tile([0.0, 1.0, 0.0], (4000, 1)), np.eye(4))
    H += point_to_plane_hessian(cloud[4000:].astype(float), np.tile([0.0, 0.0, 1.0], (2000, 1)), np.eye(4))
    for i in range(n - 3):
        rel[i, 0] = se3.relative(gt[i], gt[i + 3]) @ _exp(np.array([1.0, 0, 0, 0, 0, 0]))  # slid 1 m
        hess[i, 0] = H
    err = {}
    for kind in ("hessian", "isotropic"):
        pair = Pairwise(rel, groups >= 0, np.full((n, 1), 0.9), np.full((n, 1), 0.3),
                        hessian=hess if kind == "hessian" else None,
                        plane_rmse=np.full((n, 1), 0.01) if kind == "hessian" else None)
        graph = build_graph(frames, gt, Topology(groups), pair, InformationModel(use_hessians=True))
        assert graph.built.hessian_edges == (n - 3 if kind == "hessian" else 0)
        solved = gtsam_solver.optimize(graph).poses
        err[kind] = np.abs(solved[:, 0, 3] - gt[:, 0, 3]).max()
    assert err["hessian"] < 0.01 < 0.2 < err["isotropic"]
    # recorded but not asked for (the pose graph's default): isotropic
    assert build_graph(frames, gt, Topology(groups), pair).built.hessian_edges == 0


def test_hessian_information_is_positive_definite_and_scaled_by_the_residual():
    H = np.diag([4.0, 4.0, 0.0, 9.0, 9.0, 1.0])
    info = hessian_information(H, rmse=0.02, floor=0.01)
    assert np.linalg.eigvalsh(info).min() > 0  # positive definite, though z is not seen
    np.testing.assert_allclose(info[2, 2], EIGEN_FLOOR * 8.0 / 3 / 0.02**2)  # in the translations' own units
    np.testing.assert_allclose(info[0, 0], 4.0 / 0.02**2, rtol=1e-5)
    np.testing.assert_allclose(hessian_information(H, rmse=0.001, floor=0.01)[0, 0], 4.0 / 0.01**2, rtol=1e-5)


def test_the_registration_plugin_keeps_the_hessians_when_asked():
    from dm2_backend.plugins.registration_icp import IcpRegistration

    rng = np.random.default_rng(4)
    clouds = [_corridor(rng).astype(np.float32) for _ in range(3)]
    scale = ScanScale(voxel=0.1, spacing=0.1, spacing_raw=0.1, range_median=5.0, range_p90=15.0)
    frames = Frames(clouds, None, planar=False, scale=scale)
    topology = Topology(np.array([[1, 2], [0, 2], [0, 1]]))
    plain = IcpRegistration(progress=False).run(frames, np.tile(np.eye(4), (3, 1, 1)), topology)
    assert plain.valid.all() and plain.hessian is None and plain.plane_rmse is None
    kept = IcpRegistration(information="hessian", progress=False).run(frames, np.tile(np.eye(4), (3, 1, 1)), topology)
    assert kept.hessian.shape == (3, 2, 6, 6) and np.all(kept.hessian[:, :, 2, 2] > 0)
    assert np.all(kept.plane_rmse < kept.rmse)
    np.testing.assert_array_equal(kept.hessian[0, 0], kept.hessian[1, 0])  # one registration of the pair (0, 1)


def _planar_corridor(rng: np.random.Generator, length: float = 30.0) -> np.ndarray:
    """A 2D laser's view of a corridor 2 m wide along x (two lines): nothing fixes x."""
    x = rng.uniform(-length / 2, length / 2, 1500)
    y = np.where(np.arange(1500) % 2, 1.0, -1.0) + rng.normal(0, 0.005, 1500)
    return np.column_stack([x, y, np.zeros(1500)]).astype(np.float32)


def test_a_planar_match_carries_its_point_to_line_information():
    """Planar scans: the point-to-line information on [x y yaw] is the planar block of the point-to-plane one (a
    right perturbation: the tangent of a Pose2 between factor), weak only along a corridor."""
    rng = np.random.default_rng(5)
    target = Cloud(_planar_corridor(rng), planar=True, normal_radius=0.5)
    source = Cloud(_planar_corridor(rng), planar=True, normal_radius=0.5)
    init = se3.from_xy_yaw(np.array([0.0, 0.03, 0.01]))
    assert register(source, target, init, (0.3,)).hessian is None  # only when asked
    m = register(source, target, init, (0.3,), hessian=True)
    assert m.hessian.shape == (3, 3) and 0 < m.plane_rmse < 0.02
    p = se3.transform_points(m.T, source.points.astype(np.float64))
    _, idx = target.tree.query(p[:, :2], distance_upper_bound=0.3)
    ok = idx < len(target.xy)
    normals = np.column_stack([target.normals[idx[ok]], np.zeros(ok.sum())])
    full = point_to_plane_hessian(source.points[ok].astype(np.float64), normals, m.T)
    np.testing.assert_allclose(m.hessian, full[np.ix_([0, 1, 5], [0, 1, 5])], rtol=1e-9)
    w, v = np.linalg.eigh(m.hessian[:2, :2])
    assert w[0] < 0.01 * w[1] and abs(v[0, 0]) > 0.99  # free along the corridor (x) only (up to the normals' noise)


def test_planar_registrations_keep_their_own_information():
    """The plugin keeps the point-to-line information of planar scans (the dense stage weighs by it); the pose
    graph weighs each planar registration by it with ``information: hessian`` only."""
    from dm2_backend.plugins.registration_icp import IcpRegistration

    rng = np.random.default_rng(6)
    clouds = [_planar_corridor(rng) for _ in range(3)]
    scale = ScanScale(voxel=0.05, spacing=0.05, spacing_raw=0.05, range_median=5.0, range_p90=12.0)
    frames = Frames(clouds, None, planar=True, scale=scale)
    topology = Topology(np.array([[1, 2], [0, 2], [0, 1]]))
    kept = IcpRegistration(progress=False).run(frames, np.tile(np.eye(4), (3, 1, 1)), topology)
    assert kept.valid.all() and kept.hessian.shape == (3, 2, 3, 3)
    plugin = PluginSection(name="icp", options={"information": "hessian"})
    asked = InformationModel.from_resolved({"registration": plugin})
    default = InformationModel.from_resolved({"registration": PluginSection(name="icp")})
    assert asked.use_hessians and not default.use_hessians
    graph = build_graph(frames, np.tile(np.eye(4), (3, 1, 1)), topology, kept, asked)
    assert graph.planar and graph.built.hessian_edges == 3  # every registration has its own
    loop = graph.information[-1]
    assert loop[1, 1] > 100 * loop[0, 0]  # across the corridor, not along it
    plain = build_graph(frames, np.tile(np.eye(4), (3, 1, 1)), topology, kept)
    assert plain.built.hessian_edges == 0
    np.testing.assert_array_equal(plain.information[-1], np.diag(np.diag(plain.information[-1])))  # isotropic


def test_the_planar_block_is_the_gauss_newton_system_of_a_right_pose2_perturbation():
    """Rows and columns [x y yaw] of :func:`point_to_plane_hessian` on planar points, normals and pose are J^T J
    of the point-to-line residuals under ``T Exp(x, y, yaw)``: the tangent of a Pose2 between factor."""
    from dm2_backend.kernel.pose_graph import PLANAR_AXES

    rng = np.random.default_rng(7)
    p = np.column_stack([rng.uniform(-5, 5, (40, 2)), np.zeros(40)])
    angle = rng.uniform(0, 2 * np.pi, 40)
    n = np.column_stack([np.cos(angle), np.sin(angle), np.zeros(40)])
    T = se3.from_xy_yaw(np.array([3.0, -1.0, 0.5]))
    q = se3.transform_points(T, p)

    def residuals(xi: np.ndarray) -> np.ndarray:
        return np.einsum("ij,ij->i", n, se3.transform_points(T @ se3.from_xy_yaw(xi), p) - q)

    h = 1e-6
    J = np.column_stack([(residuals(h * e) - residuals(-h * e)) / (2 * h) for e in np.eye(3)])
    block = point_to_plane_hessian(p, n, T)[np.ix_(PLANAR_AXES, PLANAR_AXES)]
    np.testing.assert_allclose(block, J.T @ J, rtol=1e-5, atol=1e-6)


def test_planar_hessian_information_floors_translation_and_yaw_apart():
    info = hessian_information(np.diag([4.0, 0.0, 9.0]), rmse=0.02, floor=0.01)
    np.testing.assert_allclose(info[1, 1], EIGEN_FLOOR * 2.0 / 0.02**2)  # the translations' mean, not yaw's
    np.testing.assert_allclose(info[2, 2], (9.0 + EIGEN_FLOOR * 9.0) / 0.02**2)
    assert np.linalg.eigvalsh(info).min() > 0
