"""The optimiser's building blocks: the torch SE(3) twin, the DeepMapping2 losses (minimal at the ground
truth on a simulated scene), the occupancy grid (M-Net) and the pose model."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from optim_cases import Case, one_thread, perturb, planar_case, small_config

from dm2_backend.kernel.geometry import se3, se3_torch
from dm2_backend.kernel.prepared import Topology
from dm2_backend.optim import losses
from dm2_backend.optim.occupancy import GridOccupancy
from dm2_backend.optim.pose_model import PoseModel
from dm2_backend.optim.problem import Execution, Problem
from dm2_backend.optim.trainer import Optimiser, sample_points
from dm2_backend.plugins.topology_radius import RadiusTopology

#: the optimiser on the CPU without a progress bar
CPU = Execution(device="cpu", progress=False)


@pytest.fixture(autouse=True, scope="module")
def _single_thread():
    yield from one_thread()


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return se3.make_poses(se3.exp_so3(rng.normal(0, 1.0, (n, 3))), rng.normal(0, 5.0, (n, 3)))


# ---------------------------------------------------------------- se3_torch
def test_exp_so3_matches_numpy():
    rng = np.random.default_rng(1)
    w = np.concatenate([rng.normal(0, 1, (20, 3)), rng.normal(0, 1e-5, (5, 3)), np.zeros((1, 3)),
                        [[np.pi - 1e-3, 0, 0], [0, 1e-9, 0]]])
    got = se3_torch.exp_so3(torch.from_numpy(w)).numpy()
    np.testing.assert_allclose(got, se3.exp_so3(w), atol=1e-12)


def test_exp_so3_gradient_finite_at_zero():
    w = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    se3_torch.exp_so3(w)[0, 1].backward()
    assert torch.isfinite(w.grad).all()
    assert w.grad[2].item() == pytest.approx(-1.0)  # d R01 / d wz = -1 at the identity


def test_correction_zero_is_identity_and_rotates_about_centre():
    centres = torch.from_numpy(np.random.default_rng(2).normal(0, 10, (7, 3)))
    eye = torch.eye(4, dtype=torch.float64).expand(7, 4, 4)
    assert torch.equal(se3_torch.correction(torch.zeros(7, 6, dtype=torch.float64), centres), eye)
    xi = torch.zeros(7, 6, dtype=torch.float64)
    xi[:, 3:] = torch.from_numpy(np.random.default_rng(3).normal(0, 0.5, (7, 3)))
    C = se3_torch.correction(xi, centres)
    np.testing.assert_allclose(se3_torch.transform(C, centres.unsqueeze(1)).squeeze(1), centres, atol=1e-12)
    xi[:, :3] = 1.5  # then translate
    C2 = se3_torch.correction(xi, centres)
    np.testing.assert_allclose(C2[:, :3, 3] - C[:, :3, 3], np.full((7, 3), 1.5), atol=1e-12)


@pytest.mark.parametrize("n", [1, 2, 3, 5, 8, 13])
def test_prefix_product_equals_sequential(n):
    M = random_poses(n, seed=n)
    got = se3_torch.prefix_product(torch.from_numpy(M)).numpy()
    expected, acc = [], np.eye(4)
    for T in M:
        acc = acc @ T
        expected.append(acc)
    np.testing.assert_allclose(got, np.stack(expected), atol=1e-9)


def test_inverse_and_transform_match_numpy():
    T = random_poses(6)
    Ti = se3_torch.inverse(torch.from_numpy(T)).numpy()
    np.testing.assert_allclose(Ti, se3.inverse(T), atol=1e-12)
    np.testing.assert_allclose(Ti @ T, np.tile(np.eye(4), (6, 1, 1)), atol=1e-12)
    pts = np.random.default_rng(4).normal(0, 3, (6, 10, 3))
    got = se3_torch.transform(torch.from_numpy(T), torch.from_numpy(pts)).numpy()
    np.testing.assert_allclose(got, [se3.transform_points(t, p) for t, p in zip(T, pts)], atol=1e-12)


# ---------------------------------------------------------------- losses
def test_consistency_zero_when_relatives_agree_and_grows_with_error():
    T = torch.from_numpy(random_poses(5, seed=5))
    pts = torch.from_numpy(np.random.default_rng(6).normal(0, 10, (50, 3)))
    relative = se3_torch.inverse(T[0]) @ T[1:]  # T_j^i = inv(T_i) T_j, i = 0
    assert float(losses.consistency(T[0], T[1:], relative, pts)) < 1e-12
    previous = 0.0
    for d in (0.01, 0.1, 1.0):
        moved = T[0].clone()
        moved[:3, 3] += torch.tensor([d, -d, 0.5 * d], dtype=torch.float64)
        value = float(losses.consistency(moved, T[1:], relative, pts))
        assert value == pytest.approx(d * 1.5, rel=1e-9)  # a pure translation moves every point by |t|
        assert value > previous
        previous = value
    turned = T[0] @ torch.from_numpy(se3.from_xy_yaw(np.array([0.0, 0.0, 0.05])))
    assert float(losses.consistency(turned, T[1:], relative, pts)) > 0.1


def test_free_space_samples_of_a_grazing_ray_are_dropped_near_the_ground():
    # a LiDAR 1.8 m above flat ground sees it 20 m ahead: the ray runs within 0.3 m of the ground for its last
    # 3 m, where the other rays observed ground points; those samples must not be labelled free
    g = torch.Generator().manual_seed(0)
    x = torch.linspace(0.0, 25.0, 251, dtype=torch.float64)
    ground = torch.stack([x, torch.zeros_like(x), torch.zeros_like(x)], -1)[None]  # (1, 251, 3)
    origin = torch.tensor([[0.0, 0.0, 1.8]], dtype=torch.float64)
    hit = torch.tensor([[[20.0, 0.0, 0.0]]], dtype=torch.float64)
    free = losses.free_space_samples(hit, origin, 200, 0.3, g)
    kept = losses.clear_of(free, ground, 0.3)
    height = free[..., 2].reshape(-1)
    assert (height < 0.3).sum() > 10  # the ray alone leaves samples next to the ground
    assert len(kept) == int((height >= 0.3).sum()) and (kept[:, 2] >= 0.3).all()
    assert kept.requires_grad == free.requires_grad
    # nothing left to label free: the BCE keeps its occupied term only (finite)
    field = GridOccupancy(np.zeros(3), np.full(3, 25.0), 1.0)
    bce = losses.occupancy_bce(field, ground, losses.clear_of(free, ground, 10.0))
    assert torch.isfinite(bce) and float(bce.detach()) > 0


def test_free_space_samples_on_segments_stop_margin_short():
    g = torch.Generator().manual_seed(0)
    rng = np.random.default_rng(7)
    origins = torch.from_numpy(rng.normal(0, 2, (3, 3)))
    points = origins[:, None, :] + torch.from_numpy(rng.normal(0, 8, (3, 40, 3)))
    points[0, 0] = origins[0] + torch.tensor([0.1, 0.0, 0.0], dtype=torch.float64)  # shorter than the margin
    margin, per_ray = 0.5, 3
    s = losses.free_space_samples(points, origins, per_ray, margin, g)
    assert s.shape == (3, 40 * per_ray, 3)
    s = s.reshape(3, 40, per_ray, 3)
    ray = (points - origins[:, None])[:, :, None, :]
    rel = s - origins[:, None, None, :]
    length2 = (ray * ray).sum(-1)
    u = (rel * ray).sum(-1) / length2
    np.testing.assert_allclose(torch.linalg.cross(rel, ray.expand_as(rel)), 0, atol=1e-9)  # on the ray
    assert (u >= 0).all()
    long = length2.sqrt() > margin
    assert ((points[:, :, None, :] - s).norm(dim=-1)[long.expand_as(u)] >= margin - 1e-9).all()
    np.testing.assert_allclose(s[0, 0], origins[0].expand(per_ray, 3), atol=1e-12)  # short ray: the origin
    assert u.max() > 0.8 and u.std() > 0.1  # spread along the rays, not bunched at the origin


@pytest.fixture(scope="module")
def case() -> Case:
    return planar_case()


@pytest.fixture(scope="module")
def gt_opt(case) -> Optimiser:
    """An optimiser whose warm start, topology and pairwise relatives are the ground truth."""
    topo = RadiusTopology().run(case.frames, case.gt)
    return Optimiser(Problem(case.frames, topo, case.pairwise_from(case.gt, topo), case.gt), small_config(), CPU)


def chamfer_at(opt: Optimiser, poses: np.ndarray) -> float:
    T = torch.from_numpy(poses)
    world = se3_torch.transform(T.float(), opt.points)
    idx = np.arange(opt.n)
    return float(opt._chamfer(idx, opt.groups, idx, T, world, torch.from_numpy(idx)))


def test_chamfer_lowest_at_ground_truth(case, gt_opt):
    at_gt = chamfer_at(gt_opt, case.gt)
    assert at_gt > 0  # sampled noisy scans do not coincide point for point
    previous = at_gt
    for sigma_t, sigma_yaw in ((0.1, 0.005), (0.3, 0.01), (1.0, 0.03)):
        value = chamfer_at(gt_opt, perturb(case.gt, sigma_t, sigma_yaw, seed=1))
        assert value > previous + 0.02
        previous = value
    assert chamfer_at(gt_opt, perturb(case.gt, 0.0, 0.03, seed=1)) > at_gt + 0.02  # rotation alone
    assert chamfer_at(gt_opt, case.warm) > at_gt + 0.02


def test_trainer_consistency_zero_at_consistent_poses(case, gt_opt):
    anchors = np.arange(len(case.frames))
    parts = gt_opt._step_loss(anchors, torch.Generator().manual_seed(0))
    assert float(parts["consistency"].detach()) < 1e-4  # float32 world points
    topo = Topology(gt_opt.topo_groups)
    moved = Optimiser(Problem(case.frames, topo, case.pairwise_from(case.gt, topo), perturb(case.gt, 0.2, 0.01)),
                      small_config(), CPU)
    assert float(moved._step_loss(anchors, torch.Generator().manual_seed(0))["consistency"].detach()) > 0.1


def test_bce_lower_at_ground_truth_with_field_fitted_there(case):
    pts = torch.from_numpy(sample_points(case.frames, 64, seed=0))
    gt = torch.from_numpy(case.gt).float()

    def world_and_origins(T):
        return se3_torch.transform(T, pts), T[:, :3, 3]

    world, origins = world_and_origins(gt)
    unit = 2 * case.frames.scale.spacing
    lo, hi = world.reshape(-1, 3).min(0).values.numpy(), world.reshape(-1, 3).max(0).values.numpy()
    field = GridOccupancy(lo[:2] - 2, hi[:2] + 2, unit, levels=6, max_cells=2**14)
    opt = torch.optim.Adam(field.parameters(), lr=1e-2)
    g = torch.Generator().manual_seed(0)
    for _ in range(100):
        loss = losses.occupancy_bce(field, world, losses.free_space_samples(world, origins, 2, unit, g))
        opt.zero_grad()
        loss.backward()
        opt.step()

    def bce(poses: np.ndarray) -> float:
        w, o = world_and_origins(torch.from_numpy(poses).float())
        with torch.no_grad():
            free = losses.free_space_samples(w, o, 2, unit, torch.Generator().manual_seed(1))
            return float(losses.occupancy_bce(field, w, free))

    at_gt = bce(case.gt)
    assert at_gt < 0.3  # the field learned the map (chance level is 2 ln 2 = 1.39)
    for sigma_t, sigma_yaw in ((0.5, 0.0), (0.0, 0.03), (1.0, 0.05)):
        assert bce(perturb(case.gt, sigma_t, sigma_yaw, seed=2)) > at_gt + 0.1


# ---------------------------------------------------------------- M-Net
@pytest.mark.parametrize("dim", [2, 3])
def test_grid_occupancy_shape_and_gradients(dim):
    lo, hi = np.full(dim, -5.0), np.array([20.0, 10.0, 3.0][:dim])
    field = GridOccupancy(lo, hi, finest_cell=0.1, levels=5, features=2, max_cells=2**12)
    finest = max(field.grids, key=lambda p: p.numel())
    assert np.prod(finest.shape[2:]) <= 2**12  # memory bound
    assert finest.shape[2:][::-1][0] == max(finest.shape[2:])  # x (longest side) has most cells
    with torch.no_grad():
        for p in field.grids:
            p.normal_()
    x = (torch.rand(4, 7, dim, generator=torch.Generator().manual_seed(0)) * torch.tensor(hi - lo) +
         torch.tensor(lo)).float().requires_grad_(True)
    out = field(x)
    assert out.shape == (4, 7)
    out.sum().backward()
    assert torch.isfinite(x.grad).all() and (x.grad.abs().sum(-1) > 0).all()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in field.grids)
    assert field(x[0, 0]).shape == ()


# ---------------------------------------------------------------- pose model
@pytest.mark.parametrize("kind", ["direct", "lnet"])
@pytest.mark.parametrize("drift", [False, True])
@pytest.mark.parametrize("planar", [False, True])
def test_pose_model_zero_parameters_reproduce_warm_start(kind, drift, planar):
    warm = random_poses(9, seed=8)
    if planar:
        warm = se3.from_xy_yaw(se3.to_xy_yaw(warm))
    points = torch.randn(9, 16, 3, generator=torch.Generator().manual_seed(0))
    model = PoseModel(warm, planar, 0.05, 0.01, kind=kind, drift=drift, points=points, length_scale=10.0)
    assert torch.equal(model(), torch.from_numpy(warm))
    idx = torch.tensor([4, 0, 8])
    assert torch.equal(model(idx), torch.from_numpy(warm[[4, 0, 8]]))


def randomise(model: PoseModel, seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            p.copy_(torch.randn(p.shape, generator=g, dtype=p.dtype) * 3)


@pytest.mark.parametrize("kind", ["direct", "lnet"])
def test_planar_pose_model_changes_only_x_y_yaw(kind):
    warm = se3.from_xy_yaw(np.random.default_rng(9).normal(0, 5, (9, 3)))
    points = torch.randn(9, 16, 3, generator=torch.Generator().manual_seed(0))
    for planar in (True, False):
        model = PoseModel(warm, planar, 0.05, 0.01, kind=kind, drift=True, points=points, length_scale=10.0)
        randomise(model, seed=1)
        T = model().detach().numpy()
        assert np.abs(T - warm).max() > 1e-3  # the parameters do move the poses
        assert se3.is_planar(T, tol=1e-12) == planar
        R = T[:, :3, :3]
        np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.tile(np.eye(3), (9, 1, 1)), atol=1e-12)


def test_pose_model_forward_subset_and_gradients():
    warm = random_poses(9, seed=10)
    model = PoseModel(warm, False, 0.05, 0.01, kind="direct", drift=True)
    randomise(model, seed=2)
    idx = torch.tensor([7, 2])
    np.testing.assert_allclose(model(idx).detach(), model().detach()[[7, 2]], atol=1e-12)
    model(idx)[:, :3, 3].sum().backward()
    assert model.local.grad[[2, 7]].abs().sum() > 0 and model.local.grad[[0, 1, 3]].abs().sum() == 0
    assert model.drift.grad[:8].abs().sum() > 0 and model.drift.grad[8].abs().sum() == 0  # drift: frames <= 7
