"""Pairwise registration plugins: icp/gicp recover true relative poses from perturbed warm starts, the
gates mark non-overlapping pairs invalid, verified loop transforms seed far-off pairs; discovery."""

from __future__ import annotations

import dataclasses
import threading
import typing

import numpy as np
import open3d as o3d
import pytest
from click.testing import CliRunner
from plugins_scenes import floor_2d, room_3d

from dm2_backend.algorithms.common import repeatable_registration
from dm2_backend.cli.main import cli
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.prepared import Topology
from dm2_backend.plugins.registration_icp import GicpRegistration, IcpRegistration
from dm2_backend.plugins.registration_small_gicp import SmallGicpRegistration
from dm2_backend.plugins.registry import GROUPS, discover
from dm2_backend.runtime.errors import InputError
from dm2_backend.simulate.sequence import SimSettings, generate

EXPECTED = {
    "dm2.warm_start": {"poses", "icp", "kiss-icp"},
    "dm2.place_recognition": {"radius", "descriptor", "poses", "gps", "external"},
    "dm2.registration": {"icp", "gicp", "small-gicp"},
}


@pytest.fixture(scope="module")
def floor():
    return floor_2d()


def perturb(poses: np.ndarray, seed: int, trans: float, yaw_deg: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = poses.copy()
    for i in range(len(out)):
        v = np.array([*rng.uniform(-trans, trans, 2), np.radians(rng.uniform(-yaw_deg, yaw_deg))])
        out[i] = out[i] @ se3.from_xy_yaw(v)
    return out


def pose_error(T: np.ndarray, want: np.ndarray) -> tuple[float, float]:
    e = se3.relative(want, T)
    return float(np.linalg.norm(e[:3, 3])), float(np.degrees(se3.rotation_angle(e[:3, :3])))


def test_icp_recovers_relative_and_gates_non_overlap(floor):
    frames, truth = floor
    # anchors in room A; frame 120 is in room C: no overlap with anything in room A
    groups = np.array([[12, 14, 120], [10, 14, -1], [10, 12, 120], [10, 14, -1]])
    anchors = np.array([10, 12, 14, 120])
    full = np.full((len(frames), 3), -1)
    full[anchors] = groups
    warm = perturb(truth, 0, 0.15, 4.0)
    pw = IcpRegistration(progress=False).run(frames, warm, Topology(full))
    assert pw.relative.shape == (len(frames), 3, 4, 4) and pw.valid.shape == (len(frames), 3)
    for i in anchors:
        for col, j in enumerate(full[i]):
            if j < 0:
                assert not pw.valid[i, col] and (i, j) not in pw.reason
                continue
            init = se3.relative(warm[i], warm[j])
            if 120 in (i, j):
                assert not pw.valid[i, col] and "fitness" in pw.reason[(i, j)]
                np.testing.assert_allclose(pw.relative[i, col], init, atol=1e-9)  # keeps the warm start
            else:
                assert pw.valid[i, col] and pw.fitness[i, col] > 0.8
                assert pose_error(init, se3.relative(truth[i], truth[j]))[0] > 0.05
                t, r = pose_error(pw.relative[i, col], se3.relative(truth[i], truth[j]))
                assert t < 0.02 and r < 0.3
    # each pair is registered once: the reverse direction is the exact inverse
    np.testing.assert_allclose(pw.relative[12, 0], se3.inverse(pw.relative[10, 0]), atol=1e-9)
    assert se3.is_planar(pw.relative[anchors])


def test_verified_loop_seeds_far_off_pair(floor):
    frames, truth = floor
    full = np.full((len(frames), 1), -1)
    full[5, 0] = 230  # the robot's return to its start
    warm = truth.copy()
    warm[230] = warm[230] @ se3.from_xy_yaw(np.array([2.5, -1.5, 0.6]))  # drift: far beyond ICP's reach
    true_rel = se3.relative(truth[5], truth[230])
    loop = {"i": 230, "j": 5, "accepted": True, "relative": se3.inverse(true_rel).tolist()}
    topo = Topology(full, log=[{"plugin": "descriptor"}, loop])
    pw = IcpRegistration(progress=False).run(frames, warm, topo)
    assert pw.valid[5, 0]
    assert pose_error(pw.relative[5, 0], true_rel)[0] < 0.02
    pw = IcpRegistration(progress=False, use_loops=False).run(frames, warm, topo)
    assert not pw.valid[5, 0] and (5, 230) in pw.reason


@pytest.mark.parametrize(
    "cls, median, worst, worst_deg", [(IcpRegistration, 0.03, 0.15, 1.5), (GicpRegistration, 0.01, 0.03, 0.5)]
)
def test_3d_pairs(cls, median, worst, worst_deg):
    frames, truth = room_3d(count=24)
    n = len(frames)
    groups = np.stack([(np.arange(n) + 1) % n, (np.arange(n) + 2) % n], axis=1)
    warm = truth.copy()
    rng = np.random.default_rng(1)
    for i in range(n):
        warm[i] = warm[i] @ se3.make_poses(se3.exp_so3(rng.normal(0, 0.02, 3)), rng.uniform(-0.15, 0.15, 3))
    pw = cls(progress=False).run(frames, warm, Topology(groups))
    assert pw.valid.all()
    errs = np.array(
        [pose_error(pw.relative[i, c], se3.relative(truth[i], truth[groups[i, c]])) for i in range(n) for c in range(2)]
    )
    # the sparse random 1024-point samples suit GICP's covariances better than point-to-plane's normals
    assert np.median(errs[:, 0]) < median and errs[:, 0].max() < worst and errs[:, 1].max() < worst_deg


@pytest.mark.parametrize("cls", [IcpRegistration, GicpRegistration])
def test_clouds_built_per_chunk_give_the_same_pairs(cls):
    """Pairs run a chunk at a time with only the clouds the next chunk needs kept (bounded memory): the result
    is that of one chunk holding every cloud, also for pairs reaching back across chunks (n-1 -> 0)."""
    frames, truth = room_3d(count=16)
    n = len(frames)
    groups = np.stack([(np.arange(n) + 1) % n, (np.arange(n) + 5) % n], axis=1)
    warm = perturb(truth, 2, 0.05, 1.0)
    one = cls(progress=False).run(frames, warm, Topology(groups))
    chunked = cls(progress=False, chunk=3).run(frames, warm, Topology(groups))
    np.testing.assert_allclose(chunked.relative, one.relative, atol=1e-9)
    np.testing.assert_array_equal(chunked.valid, one.valid)
    np.testing.assert_allclose(chunked.fitness, one.fitness, atol=1e-12)


@pytest.mark.parametrize("cls", [IcpRegistration, GicpRegistration])
def test_pairs_registered_side_by_side_give_the_same_bits_every_run(cls):
    """As the preparation runs it (open3d on one thread, the pairs on threads of dm2's own), the registration is
    the same to the last bit however many threads share the pairs, run after run."""
    frames, truth = room_3d(count=16)
    n = len(frames)
    groups = np.stack([(np.arange(n) + 1) % n, (np.arange(n) + 3) % n], axis=1)
    warm = perturb(truth, 3, 0.05, 1.0)
    before = o3d.utility.get_max_threads()
    with repeatable_registration():
        assert o3d.utility.get_max_threads() == 1
        runs = [cls(progress=False, workers=w).run(frames, warm, Topology(groups)) for w in (1, 2, 2, 4)]
    assert o3d.utility.get_max_threads() == before
    for other in runs[1:]:
        np.testing.assert_array_equal(other.relative, runs[0].relative)
        np.testing.assert_array_equal(other.fitness, runs[0].fitness)
        np.testing.assert_array_equal(other.valid, runs[0].valid)


def test_registration_blocks_nest_and_overlap_across_threads():
    """open3d stays on one thread until the last block open on any thread ends, then gets its setting back."""
    before = o3d.utility.get_max_threads()
    inside, release = threading.Event(), threading.Event()

    def other() -> None:
        with repeatable_registration():
            inside.set()
            release.wait(10)

    thread = threading.Thread(target=other)
    with repeatable_registration():
        thread.start()
        assert inside.wait(10)
        with repeatable_registration():
            assert o3d.utility.get_max_threads() == 1
        assert o3d.utility.get_max_threads() == 1
    assert o3d.utility.get_max_threads() == 1  # the other thread's block is still open
    release.set()
    thread.join(10)
    assert o3d.utility.get_max_threads() == before


def test_a_run_registers_every_pair_on_one_of_open3d_s_threads(tmp_path, monkeypatch):
    """Every open3d registration of a 3D run (icp warm start, loops3d, pairwise, the baseline) sees one thread."""
    sim = tmp_path / "sim"
    generate(SimSettings(frames=24, laps=1.0), sim, progress=False)
    seen = []
    for name in ("registration_icp", "registration_generalized_icp"):
        original = getattr(o3d.pipelines.registration, name)

        def spy(*args, _original=original, **kwargs):
            seen.append(o3d.utility.get_max_threads())
            return _original(*args, **kwargs)

        monkeypatch.setattr(o3d.pipelines.registration, name, spy)
    result = CliRunner().invoke(cli, ["baseline", "gtsam", "-s", str(sim / "velodyne"), "--warm-start", "icp",
                                      "-o", str(tmp_path / "run"), "--no-cache", "-q"], obj={})
    assert result.exit_code == 0, result.output
    assert len(seen) > 50 and set(seen) == {1}, (len(seen), set(seen))


def test_options_checked(floor):
    frames, truth = floor
    topo = Topology(np.full((len(frames), 1), -1))
    with pytest.raises(InputError, match="ICP method"):
        IcpRegistration(method="wishful").run(frames, truth, topo)
    try:
        import small_gicp  # noqa: F401
    except ImportError:
        with pytest.raises(InputError, match=r"install dm2\[gicp\]"):
            SmallGicpRegistration().run(frames, truth, topo)
    else:
        with pytest.raises(InputError, match="unknown method"):
            SmallGicpRegistration(method="NDT").run(frames, truth, topo)


def test_small_gicp_when_installed():
    pytest.importorskip("small_gicp")
    frames, truth = room_3d(count=12)
    n = len(frames)
    groups = ((np.arange(n) + 1) % n)[:, None]
    warm = perturb(truth, 2, 0.1, 2.0)
    pw = SmallGicpRegistration(progress=False).run(frames, warm, Topology(groups))
    assert pw.valid.all()
    for i in range(n):
        assert pose_error(pw.relative[i, 0], se3.relative(truth[i], truth[groups[i, 0]]))[0] < 0.05


def test_plugins_discovered_through_entry_points():
    result = CliRunner().invoke(cli, ["plugins"])
    assert result.exit_code == 0, result.output
    for group, names in EXPECTED.items():
        assert group in result.output
        found = discover(group)
        assert names <= set(found), (group, set(found))
        for name in names:
            assert f"    {name} " in result.output
            cls = found[name].load()
            assert dataclasses.is_dataclass(cls) and cls.name == name and callable(cls.run)
            hints = typing.get_type_hints(cls)
            for f in dataclasses.fields(cls):
                assert f.name in hints and f.default is not dataclasses.MISSING  # typed, with a default
            cls()  # every option has a default
    assert set(EXPECTED) == set(GROUPS)
