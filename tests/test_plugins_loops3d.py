"""6-DoF loop closure (``loops3d``): the frame pose graph and the plugin on a drifted two-lap 3D room."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from plugins_scenes import room_3d

from dm2_backend.algorithms.loop_graph3d import Closure3, FrameGraph
from dm2_backend.config.schema import PluginSection
from dm2_backend.kernel.geometry import se3
from dm2_backend.pipeline.live import ate_rmse
from dm2_backend.plugins import topology_loops3d as loops3d_module
from dm2_backend.plugins.registry import load
from dm2_backend.prepare.steps import resolve_auto
from dm2_backend.runtime.errors import InputError

AUTO = PluginSection(name="auto")


def drifted(truth: np.ndarray, yaw: float, roll: float, dz: float, scale: float) -> np.ndarray:
    """The truth with a 6-DoF random walk in every increment: yaw, roll and height bias per step and a
    stretched step length, as a drifting front end gives."""
    rel = se3.relative(truth[:-1], truth[1:])
    bias = se3.from_xyz_euler(np.array([0.0, 0.0, dz, roll, 0.0, yaw]))
    out = [truth[0]]
    for r in rel:
        r = r.copy()
        r[:3, 3] *= scale
        out.append(out[-1] @ r @ bias)
    return np.array(out)


def ate(est: np.ndarray, truth: np.ndarray) -> float:
    return ate_rmse(truth, est)


def test_frame_graph_distributes_the_loop_error_along_the_chain():
    truth = se3.from_xy_yaw(np.column_stack([np.arange(20.0), np.zeros(20), np.zeros(20)]))
    bias = se3.from_xyz_euler(np.array([0.0, 0.0, 0.01, 0.0, 0.0, 0.002]))
    rel = se3.relative(truth[:-1], truth[1:])
    odo = [truth[0]]
    for r in rel:
        odo.append(odo[-1] @ r @ bias)
    odo = np.array(odo)
    g = FrameGraph(odo, np.full(19, 0.03), np.full(19, 0.003), 1e-3, 1e-4)  # the bias is within a sigma
    closure = Closure3(0, 19, se3.relative(truth[0], truth[19]))
    poses, kept, dropped = g.solve([closure], gate=10.0)
    assert kept == [closure] and not dropped
    end = se3.relative(poses[0], poses[19])
    assert np.linalg.norm(end[:3, 3] - closure.z[:3, 3]) < 0.01  # the closure holds
    drift_before = np.linalg.norm(odo[10, :3, 3] - truth[10, :3, 3])
    assert np.linalg.norm(poses[10, :3, 3] - truth[10, :3, 3]) < 0.5 * drift_before  # the middle moves too
    # the residual is GTSAM's whitened error (rotation first in the Pose3 tangent space, very different sigmas)
    g2 = FrameGraph(odo, np.full(19, 0.03), np.full(19, 0.003), 0.5, 1e-4)
    values = gtsam.Values()
    values.insert(0, gtsam.Pose3(odo[0]))
    values.insert(19, gtsam.Pose3(odo[19]))
    factor = gtsam.BetweenFactorPose3(0, 19, gtsam.Pose3(closure.z), gtsam.noiseModel.Diagonal.Sigmas(g2.loop_sigma))
    assert g2.residual(odo, closure) == pytest.approx(np.linalg.norm(factor.whitenedError(values)), rel=1e-6)
    assert g2.residual(odo, closure) > 100  # the rotation part dominates: 0.04 rad at 1e-4
    # a closure that contradicts the rest by metres is dropped by the robust pass
    wrong = Closure3(5, 15, se3.from_xyz_euler(np.array([3.0, 4.0, 0.0, 0.0, 0.0, 1.0])))
    _, kept, dropped = g.solve([closure, wrong], gate=10.0)
    assert dropped == [wrong] and kept == [closure]


@pytest.fixture(scope="module")
def two_laps():
    frames, truth = room_3d(count=30, laps=2)
    return frames, truth, drifted(truth, yaw=np.radians(0.12), roll=np.radians(0.03), dz=0.004, scale=1.01)


def test_loops3d_closes_the_loop_of_a_drifted_3d_sequence(two_laps):
    frames, truth, warm = two_laps
    topo = load("dm2.place_recognition", "loops3d")(progress=False).run(frames, warm)
    summary = topo.log[0]
    assert summary["plugin"] == "loops3d" and summary["closures"] >= 2
    assert topo.poses is not None
    before, after = ate(warm, truth), ate(topo.poses, truth)
    assert after < 0.5 * before, (before, after)
    # loop edges join the laps (frames far apart in time); every accepted closure is near the truth
    loops = [tuple(e) for e, kind in zip(topo.edges, topo.edge_kind) if kind == "loop"]
    assert loops and all(j - i > 10 for i, j in loops)
    for e in topo.log[1:]:
        if e.get("accepted") and not e.get("dropped"):
            err = se3.relative(se3.relative(truth[e["i"]], truth[e["j"]]), np.asarray(e["z"]))
            assert np.linalg.norm(err[:3, 3]) < 0.15
    assert all(set(e) >= {"i", "j", "verified", "accepted", "reason"} for e in topo.log[1:])


def test_loops3d_on_one_thread_or_four_gives_the_same_bits(two_laps, monkeypatch):
    """The steps checked in runs and a keyframe's candidates verified side by side: the topology, its log (in
    order) and the corrected poses are those of one thread, to the bit."""
    frames, truth, warm = two_laps
    runs = []
    for threads in (1, 4):
        monkeypatch.setattr(loops3d_module, "THREADS", threads)
        runs.append(load("dm2.place_recognition", "loops3d")(repair_distance=0.01, progress=False).run(frames, warm))
    one, four = runs
    assert one.log[0]["closures"] >= 2 and len(one.log) > 3
    assert one.log == four.log
    np.testing.assert_array_equal(one.poses, four.poses)
    np.testing.assert_array_equal(one.groups, four.groups)


def test_loops3d_without_a_loop_keeps_the_start(two_laps):
    frames, truth, warm = two_laps
    # no earlier keyframe lies far enough back along the path: nothing to close, the start is kept
    topo = load("dm2.place_recognition", "loops3d")(min_path_gap=1e3, progress=False).run(frames, warm)
    assert topo.poses is None and "loop" not in topo.edge_kind
    assert topo.closures == topo.log[0]["closures"] == 0 and len(topo.log) == 1


def test_loops3d_rejects_bad_options_and_planar_scans(two_laps):
    frames, _, warm = two_laps
    cls = load("dm2.place_recognition", "loops3d")
    with pytest.raises(InputError, match="window=-1"):
        cls(window=-1.0, progress=False).run(frames, warm)
    planar = type(frames)(frames.points, None, True, frames.scale)
    with pytest.raises(InputError, match="planar"):
        cls(progress=False).run(planar, warm)


def test_auto_picks_loops3d_for_depth_cameras():
    assert resolve_auto(AUTO, camera=True).name == "loops3d"
    assert resolve_auto(AUTO, camera=False).name == "loops"


def _path(tilt_deg: float, climb: float, n: int = 200) -> np.ndarray:
    """A 20 m circle driven twice, the sensor swaying by ``tilt_deg`` and rising ``climb`` m per metre."""
    s = np.linspace(0, 4 * np.pi, n)
    v = np.column_stack([10 * np.cos(s), 10 * np.sin(s), climb * 10 * s,
                         np.radians(tilt_deg) * np.sin(7 * s), np.radians(tilt_deg) * np.cos(5 * s), s])
    return se3.from_xyz_euler(v)


def test_auto_picks_by_the_motion():
    assert resolve_auto(AUTO, False, _path(3.0, 0.0)).name == "loops"  # a car on a road
    assert resolve_auto(AUTO, False, _path(35.0, 0.0)).name == "loops3d"  # hand-held
    assert resolve_auto(AUTO, False, _path(3.0, 0.3)).name == "loops3d"  # a climbing drone
    assert resolve_auto(AUTO, False, _path(35.0, 0.0), planar=True).name == "loops"
    radius = PluginSection(name="radius")
    assert resolve_auto(radius, False, _path(35.0, 0.0)) is radius


def test_loops3d_repairs_a_failed_front_end_step(two_laps):
    frames, truth, _ = two_laps
    jump = se3.from_xyz_euler(np.array([0.6, -0.4, 0.0, 0.0, 0.0, 0.05]))
    warm = truth.copy()
    warm[40:] = truth[39] @ jump @ se3.relative(truth[39], truth[40:])  # the front end failed on frame 40
    topo = load("dm2.place_recognition", "loops3d")(progress=False).run(frames, warm)
    assert topo.repaired_steps == (39,) and topo.log[0]["repaired_steps"] == [39]
    assert topo.closures == topo.log[0]["closures"] and topo.loop_closed == (topo.closures > 0)
    assert np.allclose(topo.poses[:40], warm[:40], atol=0.02)  # before the failed step: as it was
    step = se3.relative(topo.poses[39], topo.poses[40])
    assert np.linalg.norm(step[:3, 3] - se3.relative(truth[39], truth[40])[:3, 3]) < 0.05
    assert ate(topo.poses, truth) < 0.1 * ate(warm, truth)
    # with repairs off the step stays as the front end gave it
    kept = load("dm2.place_recognition", "loops3d")(repair_distance=0, min_path_gap=1e3, progress=False)
    assert kept.run(frames, warm).poses is None


def test_loops3d_checks_the_steps_on_a_cluster_as_in_process(two_laps):
    """The odometry check's steps as tasks on a local cluster (frames sent with the tasks): the same repair."""
    from dm2_backend.runtime import cluster

    frames, truth, _ = two_laps
    warm = truth.copy()
    warm[40:] = truth[39] @ se3.from_xyz_euler(np.array([0.6, -0.4, 0.0, 0.0, 0.0, 0.05])) @ \
        se3.relative(truth[39], truth[40:])
    plugin = load("dm2.place_recognition", "loops3d")(progress=False)
    plugin.run(frames, warm)  # its lengths
    here = plugin._repair(frames, warm)
    with cluster.engine(cluster.ClusterSpec(workers=2)):
        there = plugin._repair(frames, warm)
    assert here[1] == there[1] == [39]
    np.testing.assert_allclose(there[0], here[0], atol=1e-9)
