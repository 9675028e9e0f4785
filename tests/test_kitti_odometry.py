"""The KITTI odometry metric (issue 53, item 6): the library against a literal transcription of the devkit's
``evaluate_odometry.cpp``, known values, the not-applicable case, ``dm2 eval`` and a run's evaluation."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from dm2_backend.cli.main import cli
from dm2_backend.cli.summary import print_summary
from dm2_backend.evaluation.kitti_odometry import LENGTHS_M, kitti_odometry_error, result_line
from dm2_backend.formats import read_trajectory
from dm2_backend.formats.kitti import camera_to_lidar, read_calib_tr
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.pipeline.inputs import RunInputs
from dm2_backend.pipeline.run_report import PrepareSummary, RunReport
from dm2_backend.pipeline.run_writer import run_evaluation

# --- the devkit (devkit_odometry/cpp/evaluate_odometry.cpp), transcribed literally with plain loops ---------------

lengths = [100, 200, 300, 400, 500, 600, 700, 800]
num_lengths = 8


def trajectoryDistances(poses):  # noqa: N802 (the devkit's names)
    dist = [0.0]
    for i in range(1, len(poses)):
        P1 = poses[i - 1]
        P2 = poses[i]
        dx = P1[0][3] - P2[0][3]
        dy = P1[1][3] - P2[1][3]
        dz = P1[2][3] - P2[2][3]
        dist.append(dist[i - 1] + math.sqrt(dx * dx + dy * dy + dz * dz))
    return dist


def lastFrameFromSegmentLength(dist, first_frame, len_):  # noqa: N802
    for i in range(first_frame, len(dist)):
        if dist[i] > dist[first_frame] + len_:
            return i
    return -1


def rotationError(pose_error):  # noqa: N802
    a = pose_error[0][0]
    b = pose_error[1][1]
    c = pose_error[2][2]
    d = 0.5 * (a + b + c - 1.0)
    return math.acos(max(min(d, 1.0), -1.0))


def translationError(pose_error):  # noqa: N802
    dx = pose_error[0][3]
    dy = pose_error[1][3]
    dz = pose_error[2][3]
    return math.sqrt(dx * dx + dy * dy + dz * dz)


def calcSequenceErrors(poses_gt, poses_result):  # noqa: N802
    """(first_frame, r_err, t_err, len) per segment, as ``errors`` (r_err rad/m, t_err a fraction)."""
    err = []
    step_size = 10
    dist = trajectoryDistances(poses_gt)
    for first_frame in range(0, len(poses_gt), step_size):
        for i in range(num_lengths):
            len_ = lengths[i]
            last_frame = lastFrameFromSegmentLength(dist, first_frame, len_)
            if last_frame == -1:
                continue
            inv = np.linalg.inv  # Matrix::inv: a general inverse
            pose_delta_gt = inv(poses_gt[first_frame]) @ poses_gt[last_frame]
            pose_delta_result = inv(poses_result[first_frame]) @ poses_result[last_frame]
            pose_error = inv(pose_delta_result) @ pose_delta_gt
            r_err = rotationError(pose_error)
            t_err = translationError(pose_error)
            err.append((first_frame, r_err / len_, t_err / len_, len_))
    return err


def saveStats(err):  # noqa: N802
    """stats.txt: mean t_err (a fraction) and mean r_err (rad/m) over every segment."""
    t_err = 0.0
    r_err = 0.0
    for e in err:
        t_err += e[2]
        r_err += e[1]
    num = len(err)
    return t_err / num, r_err / num


# --- trajectories -------------------------------------------------------------------------------------------------


def drive(n: int, step: float, rng: np.random.Generator, turn: float = 0.02, tilt: float = 0.002) -> np.ndarray:
    """A vehicle-like 3D random walk: forward ``step`` m a frame, heading and attitude wandering."""
    motion = np.zeros((n - 1, 6))
    motion[:, 0] = step * (1 + 0.2 * rng.uniform(-1, 1, n - 1))
    motion[:, 1:3] = rng.normal(0, 0.02, (n - 1, 2))
    motion[:, 3:5] = rng.normal(0, tilt, (n - 1, 2))
    motion[:, 5] = turn * np.sin(np.arange(n - 1) / 60.0) + rng.normal(0, 0.01, n - 1)
    return chain(se3.from_xyz_euler(motion))


def chain(steps: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
    """Chained motions, the rotations kept orthonormal: the library's inverse is the rigid one, the devkit's
    ``Matrix::inv`` a general one; they agree to the rotations' orthonormality times the distances."""
    poses = [np.eye(4) if start is None else start]
    for d in steps:
        poses.append(poses[-1] @ d)
    poses = np.array(poses)
    poses[:, :3, :3] = se3.project_to_so3(poses[:, :3, :3])
    return poses


def drifted(gt: np.ndarray, rng: np.random.Generator, sigma_t: float = 0.01, sigma_r: float = 0.001) -> np.ndarray:
    """An odometry-like estimate: gt's relative motions with noise, chained (drifts), from another origin."""
    rel = se3.relative(gt[:-1], gt[1:])
    noise = se3.from_xyz_euler(np.c_[rng.normal(0, sigma_t, (len(rel), 3)), rng.normal(0, sigma_r, (len(rel), 3))])
    origin = se3.make_poses(se3.euler_xyz_to_matrix([0.1, -0.2, 0.7]), [5.0, -3.0, 1.0])
    return chain(rel @ noise, origin)


def straight(n: int, step: float) -> np.ndarray:
    poses = se3.identity(n)
    poses[:, 0, 3] = step * np.arange(n)
    return poses


@pytest.fixture(scope="module")
def long_pair() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(53)
    gt = drive(1500, 1.0, rng)  # about 1.5 km
    return gt, drifted(gt, rng)


# --- the library against the devkit -------------------------------------------------------------------------------


def test_equals_the_devkit_on_a_long_drive(long_pair):
    gt, est = long_pair
    ours = kitti_odometry_error(gt, est)
    ref = calcSequenceErrors(list(gt), list(est))
    assert ours.path_m == pytest.approx(trajectoryDistances(list(gt))[-1], rel=1e-12)
    assert ours.path_m > 1400 and ours.segments == len(ref) > 800
    assert ours.segment_first.tolist() == [e[0] for e in ref]
    assert ours.segment_length_m.tolist() == [e[3] for e in ref]
    np.testing.assert_allclose(ours.segment_t_err_percent, [100 * e[2] for e in ref], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(ours.segment_r_err_deg_per_100m, [np.degrees(e[1]) * 100 for e in ref],
                               rtol=1e-9, atol=1e-12)
    t_frac, r_rad_per_m = saveStats(ref)
    assert ours.t_err_percent == pytest.approx(100 * t_frac, rel=1e-9)
    assert ours.r_err_deg_per_100m == pytest.approx(np.degrees(r_rad_per_m) * 100, rel=1e-9)
    assert 0.05 < ours.t_err_percent < 20 and ours.r_err_deg_per_100m > 0.01  # a real, non-trivial error
    for k in ours.per_length:  # the devkit's per-length plots: the mean of the segments of each length
        mine = [e for e in ref if e[3] == k.length_m]
        assert k.segments == len(mine)
        assert k.t_err_percent == pytest.approx(100 * np.mean([e[2] for e in mine]), rel=1e-9)
    assert sum(k.segments for k in ours.per_length) == ours.segments
    assert [k.length_m for k in ours.per_length] == list(LENGTHS_M)


def test_no_alignment_needed_and_the_frame_argument(long_pair):
    """Only relative poses count: moving either trajectory as a whole changes nothing; ``frame`` conjugates."""
    gt, est = long_pair
    base = kitti_odometry_error(gt, est)
    moved = se3.make_poses(se3.euler_xyz_to_matrix([0.3, 0.2, -1.0]), [100.0, -50.0, 3.0])
    again = kitti_odometry_error(moved @ gt, est)
    assert again.t_err_percent == pytest.approx(base.t_err_percent, rel=1e-9)
    assert again.r_err_deg_per_100m == pytest.approx(base.r_err_deg_per_100m, rel=1e-9)
    Tr = se3.make_poses(se3.euler_xyz_to_matrix([-1.57, 0.01, -1.58]), [0.0, -0.08, -0.27])  # KITTI-like
    lidar = kitti_odometry_error(camera_to_lidar(gt, Tr), camera_to_lidar(est, Tr), frame=Tr)
    np.testing.assert_allclose(lidar.segment_t_err_percent, base.segment_t_err_percent, rtol=1e-9)
    assert lidar.r_err_deg_per_100m == pytest.approx(base.r_err_deg_per_100m, rel=1e-9)


# --- known values -------------------------------------------------------------------------------------------------


def test_the_truth_scores_zero(long_pair):
    gt, _ = long_pair
    res = kitti_odometry_error(gt, gt)
    assert res.t_err_percent == pytest.approx(0.0, abs=1e-9)
    assert res.r_err_deg_per_100m == pytest.approx(0.0, abs=1e-4)  # acos near 1: ~1e-8 rad of rounding


def test_a_scale_error_of_one_percent_is_one_percent():
    gt = straight(1300, 0.7)
    est = gt.copy()
    est[:, :3, 3] *= 1.01
    res = kitti_odometry_error(gt, est)
    # |E's translation| = 1 % of the segment's chord; the chord overshoots the length by less than one step
    assert 1.0 <= res.t_err_percent < 1.0 * (1 + 0.7 / 100)
    assert res.t_err_percent == pytest.approx(1.0, abs=5e-3)
    assert res.r_err_deg_per_100m == pytest.approx(0.0, abs=1e-6)


def test_a_yaw_bias_per_frame():
    """Each frame turns ``bias`` more than the truth: a segment of k frames is off by k * bias."""
    n, step, bias = 1300, 0.7, np.radians(0.001)
    gt = straight(n, step)
    est = chain(np.repeat(se3.make_poses(se3.exp_so3([0, 0, bias]), [step, 0, 0])[None], n - 1, axis=0))
    res = kitti_odometry_error(gt, est)
    # the last frame of a segment from first frame f: the first k with k * step > L (no L / step is near a whole
    # number): k = floor(L / step) + 1 frames of bias
    expected = [(math.floor(L / step) + 1) * np.degrees(bias) / L * 100 for L in res.segment_length_m]
    np.testing.assert_allclose(res.segment_r_err_deg_per_100m, expected, rtol=1e-9)
    assert res.r_err_deg_per_100m == pytest.approx(np.mean(expected), rel=1e-9)
    assert res.r_err_deg_per_100m == pytest.approx(np.degrees(bias) * 100 / step, rel=1e-2)  # 0.143 deg/100 m


# --- not applicable -----------------------------------------------------------------------------------------------


def test_a_short_path_has_no_segment():
    short = kitti_odometry_error(straight(50, 1.0), straight(50, 1.0))
    assert not short.applicable and short.segments == 0 and short.t_err_percent is None
    assert short.metrics() == {} and short.as_dict()["applicable"] is False
    assert short.line() == "KITTI odometry metric: path 49.0 m is shorter than 100 m"
    # the devkit's "exceeds" is strict: a path of exactly 100 m has no segment, 101 m has one
    assert not kitti_odometry_error(straight(101, 1.0), straight(101, 1.0)).applicable
    one = kitti_odometry_error(straight(102, 1.0), straight(102, 1.0))
    assert one.segments == 1 and one.segment_first.tolist() == [0] and one.segment_last.tolist() == [101]
    assert not kitti_odometry_error(se3.identity(0), se3.identity(0)).applicable
    with pytest.raises(ValueError):
        kitti_odometry_error(straight(10, 1.0), straight(9, 1.0))


# --- dm2 eval and a run's report ----------------------------------------------------------------------------------


def _write_kitti(path: Path, poses: np.ndarray) -> Path:
    np.savetxt(path, poses[:, :3, :].reshape(len(poses), 12), fmt="%.12e")
    return path


def test_dm2_eval_prints_and_writes_the_librarys_numbers(tmp_path):
    rng = np.random.default_rng(6)
    gt_poses = drive(1200, 1.0, rng)
    g = _write_kitti(tmp_path / "gt.txt", gt_poses)
    e = _write_kitti(tmp_path / "odom.txt", drifted(gt_poses, rng, 0.02, 0.002))
    out = tmp_path / "eval.json"
    r = CliRunner().invoke(cli, ["eval", str(g), str(e), "--json", str(out), "--markdown", str(tmp_path / "e.md")])
    assert r.exit_code == 0, r.output
    gt_read = read_trajectory(g, None).poses
    lib = kitti_odometry_error(gt_read, read_trajectory(e, None).poses)
    assert lib.applicable and lib.segments > 500
    line = f"odom: {result_line(lib.t_err_percent, lib.r_err_deg_per_100m, lib.segments)}"
    assert line in r.output.splitlines()
    m = re.search(r"odom: KITTI odometry: t_err ([\d.]+) % r_err ([\d.]+) deg/100 m over (\d+) segments", r.output)
    assert float(m[1]) == pytest.approx(lib.t_err_percent, rel=5e-3)
    assert float(m[2]) == pytest.approx(lib.r_err_deg_per_100m, rel=5e-3)
    assert int(m[3]) == lib.segments
    doc = json.loads(out.read_text())["estimates"][0]["metrics"]["kitti_odometry"]
    assert doc["applicable"] is True and doc["segments"] == lib.segments
    assert doc["t_err_percent"] == pytest.approx(lib.t_err_percent, rel=1e-12)
    assert doc["r_err_deg_per_100m"] == pytest.approx(lib.r_err_deg_per_100m, rel=1e-12)
    assert len(doc["per_length"]) == 8
    assert line in (tmp_path / "e.md").read_text()

    # a short pair: one line saying why, nothing in the table's place
    short = drive(40, 1.0, rng)
    gs = _write_kitti(tmp_path / "gs.txt", short)
    r = CliRunner().invoke(cli, ["eval", str(gs), str(gs), "--label", "same"])
    assert r.exit_code == 0, r.output
    path = kitti_odometry_error(short, short).path_m
    assert 30 < path < 50 and f"same: KITTI odometry metric: path {path:.1f} m is shorter than 100 m" in r.output
    assert "t_err" not in r.output


def test_a_runs_evaluation_in_the_camera_frame(long_pair, tmp_path, capsys):
    """A refine run with a KITTI ground truth read through its calib.txt holds LiDAR-frame poses: the metric is
    computed back in the camera frame (the devkit's), into report.json's ``kitti_odometry`` and the summary."""
    gt, est = long_pair
    calib = tmp_path / "calib.txt"
    Tr = se3.make_poses(se3.euler_xyz_to_matrix([-1.57, 0.01, -1.58]), [0.0, -0.08, -0.27])
    calib.write_text("Tr: " + " ".join(f"{v:.12e}" for v in Tr[:3].ravel()) + "\n")
    Tr = read_calib_tr(calib)
    stamps = np.arange(len(gt)) * 0.1
    gt_lidar = Trajectory(camera_to_lidar(gt, Tr), stamps, meta={"calib": str(calib)})
    inputs = RunInputs(scans=None, given=None, given_format=None, given_path=None, gt=gt_lidar)
    metrics, _, kitti = run_evaluation(Trajectory(camera_to_lidar(est, Tr), stamps), inputs)
    cam = kitti_odometry_error(gt, est)
    assert kitti.t_err_percent == pytest.approx(cam.t_err_percent, rel=1e-9)
    assert metrics["kitti_t_err_percent"] == kitti.t_err_percent
    assert metrics["kitti_r_err_deg_per_100m"] == pytest.approx(cam.r_err_deg_per_100m, rel=1e-9)

    report = RunReport(method="dm2", frames=len(gt), planar=False, metrics=metrics, warm_start_metrics=metrics,
                       map_quality={}, timings={"total": 1.0}, peak_rss_mb=1.0,
                       prepare=PrepareSummary({}, {}, 0, 0, 0), files=[],
                       details={"kitti_odometry": kitti.as_dict()})
    assert report.to_dict()["kitti_odometry"]["segments"] == kitti.segments
    print_summary(report, tmp_path)
    assert kitti.line() in capsys.readouterr().out.splitlines()
