"""Place-recognition plugins: radius (+ temporal fill), descriptor loops on a drifted estimate with
look-alike corridor candidates rejected, poses/gps from a file, external groups and embeddings."""

from __future__ import annotations

import numpy as np
import pytest
from plugins_scenes import floor_2d, room_3d

from dm2_backend.algorithms import scan_context as sc
from dm2_backend.algorithms.common import temporal_order
from dm2_backend.formats.registry import ReadOptions, write_trajectory
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.prepared import Frames
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.plugins.topology_descriptor import DescriptorTopology
from dm2_backend.plugins.topology_external import ExternalTopology
from dm2_backend.plugins.topology_poses import GpsTopology, PosesTopology
from dm2_backend.plugins.topology_radius import RadiusTopology
from dm2_backend.runtime.errors import InputError
from dm2_backend.simulate.path import drifting_odometry


@pytest.fixture(scope="module")
def floor():
    return floor_2d()


@pytest.fixture(scope="module")
def drifted(floor):
    _, truth = floor
    return drifting_odometry(truth, 1, 0.01, 0.05, 0.004)


def check_groups(topo, n: int, k: int) -> None:
    g = topo.groups
    assert g.shape == (n, k) and g.dtype.kind == "i"
    for i, row in enumerate(g):
        valid = row[row >= 0]
        assert i not in valid and len(set(valid.tolist())) == len(valid)  # no self, no duplicates
        assert (row[len(valid) :] == -1).all()  # -1 pads at the end
    assert len(topo.edge_kind) == len(topo.edges) and (topo.edges[:, 0] < topo.edges[:, 1]).all()


def test_temporal_order():
    assert list(temporal_order(2, 5)) == [1, 3, 0, 4]
    assert list(temporal_order(0, 3)) == [1, 2]
    assert list(temporal_order(0, 1)) == []


def test_radius_within_radius_and_temporal_fill(floor):
    frames, truth = floor
    topo = RadiusTopology(radius=1.2, k=8).run(frames, truth)
    check_groups(topo, len(frames), 8)
    pos = truth[:, :3, 3]
    kinds = dict(zip(map(tuple, topo.edges.tolist()), topo.edge_kind, strict=True))
    fills = 0
    for i, row in enumerate(topo.groups):
        d = np.linalg.norm(pos[row] - pos[i], axis=1)
        spatial = [kinds[(min(i, j), max(i, j))] == "radius" for j in row]
        # radius neighbours first, nearest first, all within the radius; then the temporal fill
        n_sp = int(np.sum(spatial))
        assert all(spatial[:n_sp]) and not any(spatial[n_sp:])
        assert (d[:n_sp] <= 1.2 + 1e-9).all() and (np.diff(d[:n_sp]) >= -1e-9).all()
        fill = row[n_sp:]
        assert set(fill.tolist()) <= set(temporal_order(i, len(frames)))
        fills += len(fill)
    assert fills > 0 and "temporal" in topo.edge_kind and "radius" in topo.edge_kind
    assert topo.log[0]["radius"] == 1.2


def test_radius_default_and_small_inputs(floor):
    frames, truth = floor
    topo = RadiusTopology().run(frames, truth)
    assert topo.log[0]["radius"] == pytest.approx(0.5 * frames.scale.range_median)
    small = Frames(frames.points[:3], None, True, frames.scale)
    topo = RadiusTopology(k=8).run(small, truth[:3])
    check_groups(topo, 3, 8)
    assert (topo.groups[:, 2:] == -1).all()
    with pytest.raises(InputError, match="k must be"):
        RadiusTopology(k=0).run(frames, truth)
    with pytest.raises(InputError, match="poses for"):
        RadiusTopology().run(frames, truth[:4])


def test_scan_context_yaw_and_distance():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-10, 10, (3000, 3))
    pts[:, 2] = rng.uniform(0, 3, len(pts))
    yaw = np.radians(48.0)  # the candidate's frame is rotated by yaw relative to the query's
    cand = se3.transform_points(se3.inverse(se3.from_xy_yaw(np.array([0.0, 0.0, yaw]))), pts)
    for planar in (False, True):
        q = sc.descriptor(pts, 20, 60, 15.0, planar)
        d, shift = sc.distance(q, sc.descriptor(cand, 20, 60, 15.0, planar))
        assert d < 1e-9 and shift * 6 == 48
        other = sc.descriptor(rng.uniform(-10, 10, (3000, 3)), 20, 60, 15.0, planar)
        assert sc.distance(q, other)[0] > 0.05
    np.testing.assert_allclose(sc.ring_key(q), sc.ring_key(sc.descriptor(cand, 20, 60, 15.0, True)))


def test_descriptor_finds_revisit_and_rejects_corridor(floor, drifted):
    frames, truth = floor
    topo = DescriptorTopology(progress=False).run(frames, drifted)
    check_groups(topo, len(frames), 8)
    radius = topo.log[0]["radius"]
    true_pos, est_pos = truth[:, :3, 3], drifted[:, :3, 3]
    entries = topo.log[1:]
    accepted = [e for e in entries if e["accepted"]]
    rejected = [e for e in entries if not e["accepted"]]
    assert accepted and rejected
    for e in entries:
        assert {"i", "j", "descriptor_distance", "fitness", "rmse", "constraint", "reason"} <= set(e)
    # every accepted loop is a true revisit, with the verified relative pose close to the truth
    for e in accepted:
        i, j = e["i"], e["j"]
        assert np.linalg.norm(true_pos[i] - true_pos[j]) < 1.0
        err = se3.relative(se3.relative(truth[i], truth[j]), np.array(e["relative"]))
        assert np.linalg.norm(err[:3, 3]) < 0.05 and np.degrees(se3.rotation_angle(err[:3, :3])) < 1.0
    # the return to room A is found although the drifted estimate puts it far beyond the radius
    closing = [e for e in accepted if min(e["i"], e["j"]) < 60 and max(e["i"], e["j"]) > 200]
    assert closing
    assert all(np.linalg.norm(est_pos[e["i"]] - est_pos[e["j"]]) > radius for e in closing)
    kinds = dict(zip(map(tuple, topo.edges.tolist()), topo.edge_kind, strict=True))
    for e in closing:
        assert kinds[(min(e["i"], e["j"]), max(e["i"], e["j"]))] == "loop"
        assert e["j"] in topo.groups[e["i"]] and e["i"] in topo.groups[e["j"]]
    # look-alike corridor places metres apart were proposed and rejected as degenerate
    false = [e for e in rejected if np.linalg.norm(true_pos[e["i"]] - true_pos[e["j"]]) > 5.0]
    assert any("constraint" in e["reason"] and e["descriptor_distance"] < 0.05 for e in false)
    assert any("free space" in e["reason"] for e in false)
    # radius-only topology on the drifted estimate misses the closure
    plain = RadiusTopology().run(frames, drifted)
    assert not any(e["j"] in plain.groups[e["i"]] for e in closing)


def test_descriptor_3d_symmetric_room():
    # two laps of a point-symmetric path in a box room: frames half a lap apart see a near copy of the room
    # rotated by 180 degrees; only the few boxes and pillars tell them apart
    frames, truth = room_3d(count=30, laps=2)
    drifted = drifting_odometry(truth, 4, 0.01, 0.05, 0.03)
    topo = DescriptorTopology(progress=False).run(frames, drifted)
    check_groups(topo, len(frames), 8)
    dist = {(e["i"], e["j"]): np.linalg.norm(truth[e["i"], :3, 3] - truth[e["j"], :3, 3]) for e in topo.log[1:]}
    accepted = [e for e in topo.log[1:] if e["accepted"]]
    assert len(accepted) >= 10 and all(dist[(e["i"], e["j"])] < 0.5 for e in accepted)
    look_alikes = [e for e in topo.log[1:] if dist[(e["i"], e["j"])] > 3.0]
    assert len(look_alikes) >= 10 and all("free space" in e["reason"] for e in look_alikes)
    for e in accepted:
        err = se3.relative(se3.relative(truth[e["i"]], truth[e["j"]]), np.array(e["relative"]))
        assert np.linalg.norm(err[:3, 3]) < 0.05 and np.degrees(se3.rotation_angle(err[:3, :3])) < 1.0


def test_poses_and_gps_topology(tmp_path, floor, drifted):
    frames, truth = floor
    path = tmp_path / "gt.txt"
    stamps = np.arange(len(truth)) * 0.1
    write_trajectory(Trajectory(truth, stamps), path, "tum", ReadOptions())
    want = RadiusTopology(radius=1.5).run(frames, truth)
    for cls in (PosesTopology, GpsTopology):
        topo = cls(path=str(path), radius=1.5).run(frames, drifted)
        np.testing.assert_array_equal(topo.groups, want.groups)
    # a reference at another rate is interpolated at the frames' stamps
    write_trajectory(Trajectory(truth[::2], stamps[::2]), path, "tum", ReadOptions())
    topo = PosesTopology(path=str(path), radius=1.5).run(frames, drifted)
    assert (topo.groups[:, 0] >= 0).all()
    with pytest.raises(InputError, match="needs option 'path'"):
        PosesTopology().run(frames, drifted)
    with pytest.raises(InputError, match="no such file"):
        PosesTopology(path=str(tmp_path / "missing.txt")).run(frames, drifted)
    short = tmp_path / "short.txt"
    write_trajectory(Trajectory(truth[:10], stamps[:10]), short, "tum", ReadOptions())
    with pytest.raises(InputError, match="outside the trajectory's time span"):
        PosesTopology(path=str(short)).run(frames, drifted)


def test_external_groups_and_embeddings(tmp_path, floor):
    frames, truth = floor
    n = len(frames)
    # DeepMapping2 group_matrix.npy layout: the anchor first, then its neighbours
    gm = np.column_stack([np.arange(n), (np.arange(n) + 1) % n, (np.arange(n) + 2) % n])
    np.save(tmp_path / "gm.npy", gm)
    topo = ExternalTopology(path=str(tmp_path / "gm.npy")).run(frames, truth)
    np.testing.assert_array_equal(topo.groups, gm[:, 1:])
    assert set(topo.edge_kind) == {"external"}
    # embeddings: the nearest in embedding space (here: the true positions) form the groups
    np.save(tmp_path / "emb.npy", truth[:, :2, 3].astype(np.float32))
    topo = ExternalTopology(path=str(tmp_path / "emb.npy"), k=4).run(frames, truth)
    near = RadiusTopology(radius=1e9, k=4, temporal_fill=False).run(frames, truth)
    d_ext = np.linalg.norm(truth[topo.groups, :3, 3] - truth[:, None, :3, 3], axis=-1)
    d_rad = np.linalg.norm(truth[near.groups, :3, 3] - truth[:, None, :3, 3], axis=-1)
    np.testing.assert_allclose(np.sort(d_ext, axis=1), np.sort(d_rad, axis=1), atol=1e-5)
    # radius filter then temporal fill, as the official recipe does
    topo = ExternalTopology(path=str(tmp_path / "emb.npy"), k=4, radius=0.3).run(frames, truth)
    assert set(topo.edge_kind) == {"external", "temporal"}
    for (i, j), kind in zip(topo.edges, topo.edge_kind, strict=True):
        if kind == "external":
            assert np.linalg.norm(truth[i, :3, 3] - truth[j, :3, 3]) <= 0.3
        else:
            assert abs(i - j) <= 4  # at the ends the fill is one-sided


@pytest.mark.parametrize(
    "content, match",
    [
        (np.zeros((3, 2), int), "expected"),
        (np.full((4, 2), 7), "outside"),
        (np.full((4, 2), np.nan), "not finite"),
        (np.array([["a", "b"]] * 4), "unsupported"),
    ],
)
def test_external_bad_input(tmp_path, content, match):
    frames = Frames([np.zeros((5, 3), np.float32) + i for i in range(4)], None, False, {"range_median": 1.0})
    np.save(tmp_path / "x.npy", content)
    with pytest.raises(InputError, match=match):
        ExternalTopology(path=str(tmp_path / "x.npy")).run(frames, se3.identity(4))
    (tmp_path / "junk.npy").write_text("not numpy")
    with pytest.raises(InputError, match="readable"):
        ExternalTopology(path=str(tmp_path / "junk.npy")).run(frames, se3.identity(4))
