"""The closed-form plane mathematics: eigenpairs of 3x3 scatters, moments placed in the world, and the
leave-one-out planes of :func:`planes.disagreement`, each against a direct computation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from dm2_backend.kernel import planes
from dm2_backend.kernel.geometry.symmetric3 import smallest_eigen


def _eigen(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return smallest_eigen(A[:, 0, 0], A[:, 0, 1], A[:, 0, 2], A[:, 1, 1], A[:, 1, 2], A[:, 2, 2])


def _scatters(rng: np.random.Generator, spreads: np.ndarray) -> np.ndarray:
    R = Rotation.random(len(spreads), random_state=rng).as_matrix()
    return (R * spreads[:, None, :]) @ R.transpose(0, 2, 1)


def test_the_closed_form_matches_eigh_on_planes_lines_points_and_zeros():
    rng = np.random.default_rng(0)
    n = 20_000
    plane = np.stack([10 ** rng.uniform(-12, -2, n), rng.uniform(0.05, 1, n), rng.uniform(0.05, 1, n)], 1)
    line = np.stack([np.zeros(n), 10 ** rng.uniform(-16, -8, n), rng.uniform(0.1, 1, n)], 1)
    A = np.concatenate([_scatters(rng, plane), _scatters(rng, line), np.zeros((10, 3, 3)),
                        np.tile(np.eye(3), (10, 1, 1)), 100.0 + _scatters(rng, plane[:100])])
    lam, vec = _eigen(A)
    want_lam, want_vec = np.linalg.eigh(A)
    scale = np.abs(want_lam).max(1)
    assert np.all(np.abs(lam - want_lam) <= 1e-10 * scale[:, None] + 1e-300)
    np.testing.assert_allclose(np.linalg.norm(vec, axis=1), 1.0, atol=1e-12)
    # an eigenvector of the smallest eigenvalue wherever it is defined; on planes the same as eigh's
    residual = np.linalg.norm((A @ vec[:, :, None])[:, :, 0] - lam[:, :1] * vec, axis=1)
    assert np.all(residual <= 1e-10 * scale + 1e-300)
    on_planes = slice(0, n)
    assert np.all(np.abs((vec[on_planes] * want_vec[on_planes, :, 0]).sum(1)) > 1 - 1e-9)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False), min_size=9, max_size=9))
def test_the_closed_form_is_an_eigenpair_of_any_symmetric_matrix(entries):
    M = np.array(entries).reshape(1, 3, 3)
    A = 0.5 * (M + M.transpose(0, 2, 1))
    lam, vec = _eigen(A)
    want = np.linalg.eigvalsh(A)
    scale = max(float(np.abs(want).max()), 1e-300)
    assert np.all(np.abs(lam - want) <= 1e-9 * scale)
    assert abs(np.linalg.norm(vec) - 1.0) < 1e-9
    assert np.linalg.norm(A[0] @ vec[0] - lam[0, 0] * vec[0]) <= 1e-8 * scale


def test_moments_placed_about_a_centre_equal_t_q_t_transposed():
    rng = np.random.default_rng(1)
    frames, pairs = 30, 500
    poses = np.tile(np.eye(4), (frames, 1, 1))
    poses[:, :3, :3] = Rotation.random(frames, random_state=2).as_matrix()
    poses[:, :3, 3] = rng.normal(size=(frames, 3)) * 50
    frame = rng.integers(0, frames, pairs)
    centre = rng.normal(size=(pairs, 3)) * 50
    h = np.concatenate([rng.normal(size=(pairs, 6, 3)), np.ones((pairs, 6, 1))], 2)
    Q = np.einsum("pki,pkj->pij", h, h)
    T = poses[frame].copy()
    T[:, :3, 3] -= centre
    want = T @ Q @ T.transpose(0, 2, 1)
    got = planes.expand_moments(planes.moments_about(poses, frame, centre, Q[:, planes._UPPER[0], planes._UPPER[1]]))
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-9 * np.abs(want).max())


def _wall(frame: int, n: int, rng: np.random.Generator) -> planes.Cells:
    """``n`` thin cells of a frame on the plane z = 0 within [0, 0.9]^2 (sensor at the origin)."""
    mean = np.column_stack([rng.uniform(0.05, 0.85, (n, 2)), np.zeros(n)]).astype(np.float32)
    scatter = np.zeros((n, 6), np.float32)
    scatter[:, 0] = scatter[:, 3] = 4 * 0.01  # xx, yy: four points spread a few cm; zz (index 5) flat
    return planes.Cells(np.full(n, frame, np.int32), np.full(n, 4, np.float32), mean, scatter, 0.225)


def test_a_frame_is_not_judged_by_one_cell_of_another():
    """Leave-one-out: where the other frames in a voxel are one cell (a point, no normal), a frame's points there
    are not scored against an arbitrary plane through it; the one cell is scored against the frame's wall."""
    rng = np.random.default_rng(3)
    wall = _wall(0, 60, rng)
    point = planes.Cells(np.array([1], np.int32), np.array([12], np.float32),
                         np.array([[0.4, 0.4, 0.01]], np.float32), np.zeros((1, 6), np.float32), 0.225)
    cells = planes.Cells(*(np.concatenate([getattr(wall, f), getattr(point, f)])
                           for f in ("frame", "count", "mean", "scatter")), 0.225)
    poses = np.tile(np.eye(4), (2, 1, 1))
    a = planes.assign(cells, poses, 0.9)
    assert a.voxels == 1 and set(a.frame.tolist()) == {0, 1}
    score = planes.disagreement(a, poses, cap=1e9)
    assert np.isnan(score[0])
    np.testing.assert_allclose(score[1], 0.01**2, rtol=1e-6)
    only = planes.disagreement(a, poses, cap=1e9, judged=np.array([False, True]))
    assert np.isnan(only[0]) and only[1] == score[1]


def test_near_ties_and_round_patches_are_eigenpairs_to_eighs_accuracy():
    """Where the cubic's roots nearly coincide (a round patch: the two largest equal; a near line: the two
    smallest within 1e-7 to 1e-3 of the largest, where the residual check decides), the eigenvalues match
    ``eigh``'s and the vector is an eigenvector of the smallest to the same accuracy."""
    rng = np.random.default_rng(4)
    n = 20_000
    width = rng.uniform(0.1, 1, n)
    round_patch = np.stack([10 ** rng.uniform(-9, -3, n), width, width], 1)
    near_line = np.stack([np.zeros(n), 10 ** rng.uniform(-7, -3, n), np.ones(n)], 1)
    near_line[:, 0] = near_line[:, 1] * rng.uniform(0.0, 0.999, n)
    A = np.concatenate([_scatters(rng, round_patch), _scatters(rng, near_line)])
    lam, vec = _eigen(A)
    want = np.linalg.eigvalsh(A)
    scale = np.abs(want).max(1)
    assert np.all(np.abs(lam - want) <= 1e-12 * scale[:, None])
    residual = np.linalg.norm((A @ vec[:, :, None])[:, :, 0] - lam[:, :1] * vec, axis=1)
    assert np.all(residual <= 1e-12 * scale)


def test_cells_too_sparse_for_any_plane_are_not_split_and_the_assignment_is_the_same(monkeypatch):
    """A voxel without points or frames enough for a plane has no part with more: dropping its cells from the
    finer levels leaves the assignment as it was (to rounding)."""
    rng = np.random.default_rng(5)
    frames, n = 6, 3000
    mean = np.column_stack([rng.uniform(-2, 2, (frames * n, 2)), rng.normal(0, 0.005, frames * n)])
    mean[rng.random(frames * n) < 0.02, 2] += rng.uniform(-0.3, 0.3)  # a few strays: sparse voxels
    cells = planes.Cells(np.repeat(np.arange(frames), n).astype(np.int32), np.full(frames * n, 4, np.float32),
                         mean.astype(np.float32), np.zeros((frames * n, 6), np.float32), 0.1)
    poses = np.tile(np.eye(4), (frames, 1, 1))
    poses[:, :3, 3] = rng.normal(size=(frames, 3)) * 0.02
    poses[3:, :3, :3] = Rotation.from_euler("x", 90, degrees=True).as_matrix()  # two walls crossing
    pruned = planes.assign(cells, poses, 0.8)
    original = planes._flat_voxels
    monkeypatch.setattr(planes, "_flat_voxels", lambda *a: (*original(*a)[:5], np.zeros(len(a[1]), bool)))
    every = planes.assign(cells, poses, 0.8)
    for field in ("frame", "voxel", "centre", "points", "size"):
        np.testing.assert_array_equal(getattr(pruned, field), getattr(every, field))
    np.testing.assert_allclose(pruned.moment, every.moment, rtol=1e-12, atol=1e-12)
    assert pruned.sigma == pytest.approx(every.sigma, rel=1e-12) and pruned.voxels > 10
