"""Issue 27: hospital-like CARMEN logs (ROBOTLASER1 only, laser 0.22 m ahead, interlaced quarter scans, max-range
codes, isolated long returns, pauses, good but drifting wheel odometry, long wide corridors) and a fused warm start
that ends no worse than the odometry on them, with a per-window record of which source won and why."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from dm2_backend.algorithms.drift_windows import WindowVerdict, apply_verdicts, window_bounds
from dm2_backend.formats.carmen import open_carmen_scans
from dm2_backend.formats.registry import ReadOptions
from dm2_backend.kernel.geometry import se3
from dm2_backend.plugins.warm_start_icp import IcpWarmStart
from dm2_backend.prepare.frames import load_frames
from dm2_backend.simulate.hospital import MAX_RANGE_CODE, HospitalSettings, HospitalTraits, write_hospital

FRAMES = 400  # 80 m: one long side of the ring, a corner and most of a short side


def ate(poses: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((poses[:, :2, 3] - truth[:, :2, 3]) ** 2, axis=1))))


def relation_error(poses: np.ndarray, truth: np.ndarray, span: int) -> float:
    """Mean translation error of the relative poses ``span`` frames apart (the Freiburg metric on local relations)."""
    a, b = se3.relative(poses[:-span], poses[span:]), se3.relative(truth[:-span], truth[span:])
    return float(np.mean(np.linalg.norm(se3.relative(b, a)[:, :2, 3], axis=1)))


def simulated(tmp_path_factory, name: str, traits: HospitalTraits | None = None, frames: int = FRAMES):
    out = tmp_path_factory.mktemp(name)
    write_hospital(out, HospitalSettings(frames=frames, traits=traits or HospitalTraits()))
    truth = np.array([np.eye(4)] * frames)
    rows = np.loadtxt(out / "truth.tum")
    truth[:, 0, 3], truth[:, 1, 3] = rows[:, 1], rows[:, 2]
    yaw = 2.0 * np.arctan2(rows[:, 6], rows[:, 7])
    truth[:, :2, :2] = np.stack([np.cos(yaw), -np.sin(yaw), np.sin(yaw), np.cos(yaw)], -1).reshape(-1, 2, 2)
    return out / "hospital.clf", truth


def warm_start(log, options: ReadOptions | None = None, **kw):
    seq = open_carmen_scans(log, options)
    frames = load_frames(seq, 1024, None, 0, progress=False)
    odometry = seq.trajectories["odometry"]
    ws = IcpWarmStart(progress=False, **kw)
    return ws.run(frames, odometry), odometry.poses, ws


@pytest.fixture(scope="module")
def hospital(tmp_path_factory):
    return simulated(tmp_path_factory, "hospital")


def test_the_log_has_the_hospital_traits(hospital):
    log, truth = hospital
    lines = [w.split() for w in log.read_text().split("\n") if w.startswith("ROBOTLASER1")]
    assert len(lines) == FRAMES and {int(w[8]) for w in lines} == {180, 181}
    assert {round(np.degrees(float(w[2])), 2) for w in lines} == {-90.0, -89.75, -89.5, -89.25}
    ranges = np.concatenate([np.array(w[9:9 + int(w[8])], float) for w in lines])
    assert 0.05 < np.mean(ranges == MAX_RANGE_CODE) < 0.2
    assert float(lines[0][5]) > MAX_RANGE_CODE  # the field declares more than the code
    stamps = np.array([float(w[-3]) for w in lines])
    assert (np.diff(stamps) > 5.0).sum() == 15 and np.median(np.diff(stamps)) == pytest.approx(1 / 1.6, rel=0.1)
    seq = open_carmen_scans(log)
    np.testing.assert_allclose(seq.meta["laser_offset"], (0.22, 0.0, 0.0), atol=1e-5)
    assert np.linalg.norm(seq.trajectories["odometry"].poses[-1, :2, 3] - truth[-1, :2, 3]) > 0.3  # it drifts


def test_max_range_codes_are_not_points(hospital):
    """The messages declare 100 m, the scanner codes "no return" as 81.91 m: the repeated largest reading is the
    code and no point lies there (before: every code was a point, a ring around the robot)."""
    seq = open_carmen_scans(hospital[0])
    assert seq.meta["max_range"] == pytest.approx(MAX_RANGE_CODE, abs=1e-4)
    laser = np.array([0.22, 0.0, 0.0])
    r = np.concatenate([np.linalg.norm(seq[i].points - laser, axis=1) for i in range(0, FRAMES, 7)])
    assert not (np.abs(r - MAX_RANGE_CODE) < 5e-3).any()
    assert ((r > 30) & (r < 50)).mean() > 0.01  # the isolated long returns stay (they are readings)


@pytest.mark.parametrize("weigh", ["whole", "auto"])
def test_warm_start_no_worse_than_the_odometry_on_a_hospital_log(hospital, weigh):
    """Against the simulator's truth, with no margin but rounding: ATE and the mean relation error at 5 m and 20 m at
    or below the odometry's (before issue 27: 1.72 m ATE against the odometry's 0.51 m). By default the match
    cycles find this odometry the more precise source on every axis (pairwise matches of interlaced scans with codes
    and long returns): the warm start is the odometry (to rounding, so the bound holds by construction there), which
    the dense stage straightens (docs/decisions/0015-scan-weights-from-match-cycles.md, "Revisited")."""
    log, truth = hospital
    poses, odometry, ws = warm_start(log, weigh=weigh)
    rounding = 1e-9 if weigh == "auto" else 0.0
    assert ate(poses, truth) <= ate(odometry, truth) + rounding
    for span in (25, 100):
        assert relation_error(poses, truth, span) <= relation_error(odometry, truth, span) + rounding
    assert ws.report["windows"] and all(isinstance(v, WindowVerdict) for v in ws.verdicts)
    assert ws.report["match_weights"]["weighed"] == {"whole": "whole", "auto": "cycles"}[weigh]


@pytest.mark.parametrize("trait", ["interlaced", "laser_offset", "codes", "long_share", "gaps"])
def test_each_trait_alone(tmp_path_factory, trait):
    """Each trait of the hospital log alone: the warm start no worse than the odometry (ATE, 20 m relations)."""
    full, plain = HospitalTraits(), HospitalTraits().plain()
    alone = {"interlaced": {"interlaced": True}, "laser_offset": {"laser_offset": full.laser_offset},
             "codes": {"code_share": full.code_share, "declared_max_range": full.declared_max_range},
             "long_share": {"long_share": full.long_share}, "gaps": {"gaps": full.gaps}}[trait]
    log, truth = simulated(tmp_path_factory, trait, dataclasses.replace(plain, **alone), frames=300)
    for weigh in ("whole", "auto"):
        poses, odometry, ws = warm_start(log, weigh=weigh)
        weighed = ws.report["match_weights"]["weighed"]
        assert weighed == "whole" or weigh == "auto"
        rounding = 1e-9 if weighed == "cycles" else 0.0  # weights of 0 make the warm start the odometry, to rounding
        assert ate(poses, truth) <= ate(odometry, truth) + rounding
        assert relation_error(poses, truth, 100) <= relation_error(odometry, truth, 100) + rounding


def test_windows_catch_scan_matching_that_drifted(hospital):
    """The codes read as points (a reader told the range is 100 m): scan matching loses 2 m along a hall at the
    corner (the failure of the hospital log). The per-window check names that window, says why, and takes the
    odometry there: the warm start ends no worse than the odometry in ATE (per-step tests alone: 1.8x worse; 3x
    before the reader dropped isolated codes)."""
    log, truth = hospital
    as_points = ReadOptions(max_range=100.0)
    plain, odometry, _ = warm_start(log, as_points, windows="off", weigh="whole")
    assert ate(plain, truth) > 1.5 * ate(odometry, truth)  # the failure, reproduced (isolated codes are dropped)
    poses, _, ws = warm_start(log, as_points, weigh="whole")
    assert ate(poses, truth) <= ate(odometry, truth)
    wrong = []
    for v in ws.verdicts:  # windows where the truth says scan matching was wrong by a metre more than the odometry
        true = se3.relative(truth[v.start], truth[v.end])
        err_scan = np.linalg.norm(se3.relative(true, se3.relative(plain[v.start], plain[v.end]))[:2, 3])
        err_odo = np.linalg.norm(se3.relative(true, se3.relative(odometry[v.start], odometry[v.end]))[:2, 3])
        if err_scan > err_odo + 1.0:
            wrong.append(v)
    assert wrong and all(v.source == "odometry" and "scan matching" in v.reason for v in wrong)
    named = [w for w in ws.report["windows"] if w["source"] == "odometry"]
    assert {(w["start"], w["end"]) for w in named} >= {(v.start, v.end) for v in wrong}
    assert f"{wrong[0].start}-{wrong[0].end}" in ws.report["summary"]


def test_an_ordinary_log_is_unchanged(tmp_path_factory):
    """The same run without the hospital's traits: the window check keeps the fused warm start as it was (today's
    code: ``windows: off``), within a millimetre."""
    log, truth = simulated(tmp_path_factory, "plain", HospitalTraits().plain())
    before, odometry, _ = warm_start(log, windows="off")
    after, _, ws = warm_start(log)
    assert ate(after, truth) <= ate(before, truth) + 1e-3
    assert ate(after, truth) < 0.5 * ate(odometry, truth)
    assert all(v.source == "scan" for v in ws.verdicts)


def test_simulate_cli_writes_a_hospital_log(tmp_path):
    from click.testing import CliRunner

    from dm2_backend.cli.main import cli
    from dm2_backend.formats import read_trajectory
    from dm2_backend.formats.relations import read_relations

    out = tmp_path / "h"
    result = CliRunner().invoke(cli, ["simulate", "--scene", "hospital", "-n", "40", "--out", str(out)], obj={})
    assert result.exit_code == 0, result.output
    seq = open_carmen_scans(out / "hospital.clf")
    truth = read_trajectory(out / "truth.tum")
    assert len(seq) == len(truth) == 40 and seq.meta["carmen_message"] == "ROBOTLASER1"
    np.testing.assert_allclose(truth.timestamps, seq.timestamps)
    rel = read_relations(out / "hospital.relations")
    nearest = np.abs(rel[:, :2, None] - seq.timestamps[None, None, :]).min(axis=-1)
    assert nearest.max() < 1e-5  # every relation joins two scans of the log
    again = CliRunner().invoke(cli, ["simulate", "--scene", "hospital", "-n", "40", "--out", str(out)], obj={})
    assert again.exit_code == 2 and "not empty" in again.output  # nothing of the user's overwritten


def test_windows_cover_the_path_and_fall_back_only_where_judged():
    rng = np.random.default_rng(3)
    steps = np.column_stack([rng.uniform(0.1, 0.3, 60), rng.normal(0, 0.02, 60), rng.normal(0, 0.02, 60)])
    odometry = [np.eye(4)]
    for T in se3.from_xy_yaw(steps):
        odometry.append(odometry[-1] @ T)
    odometry = np.array(odometry)
    warm = odometry @ se3.from_xy_yaw(rng.normal(0, 0.05, (61, 3)))
    bounds = window_bounds(odometry, 2.0, 3)
    assert bounds[0][0] == 0 and bounds[-1][1] == 60 and all(b[1] == c[0] for b, c in zip(bounds, bounds[1:]))
    fields = dict(length_m=0, along_m=0, across_m=0, yaw_deg=0, explained_along_m=0, explained_across_m=0,
                  explained_deg=0, overlap_scan=None, overlap_odometry=None, margin=None, reason="")
    verdicts = [WindowVerdict(0, 20, source="scan", **fields), WindowVerdict(20, 30, source="odometry", **fields),
                WindowVerdict(30, 60, source="scan", **fields)]
    out = apply_verdicts(warm, odometry, verdicts)
    np.testing.assert_array_equal(out[:21], warm[:21])
    inc = se3.relative(out[:-1], out[1:])
    np.testing.assert_allclose(inc[20:30], se3.relative(odometry[20:30], odometry[21:31]), atol=1e-9)
    np.testing.assert_allclose(inc[30:], se3.relative(warm[30:-1], warm[31:]), atol=1e-9)
    assert apply_verdicts(warm, odometry, verdicts[:1]) is warm


def test_refine_run_folder_shows_the_windows(tmp_path_factory):
    """``dm2 refine`` on a hospital-like log: ``warm_start.json`` holds every window's verdict, ``report.json`` the
    count and the windows taken from the odometry, the console the summary."""
    import json

    from click.testing import CliRunner

    from dm2_backend.cli.main import cli

    log, _ = simulated(tmp_path_factory, "refine", frames=120)
    out = log.parent / "run"
    result = CliRunner().invoke(cli, ["refine", "-q", "--no-cache", "--scans", str(log), "--epochs", "1",
                                      "--relations", str(log.with_name("hospital.relations")), "--out", str(out)],
                                obj={})
    assert result.exit_code == 0, result.output
    windows = json.loads((out / "warm_start.json").read_text())["windows"]
    assert windows and {"start", "end", "source", "reason", "along_m", "explained_along_m"} <= set(windows[0])
    assert windows[0]["start"] == 0 and windows[-1]["end"] == 119
    details = json.loads((out / "report.json").read_text())["warm_start"]
    assert details["windows_checked"] == len(windows) and "windows" not in details and "per_step" not in details
    assert details["windows_from_odometry"] == [w for w in windows if w["source"] == "odometry"]
    assert f"windows of {details['settings']['range_median_m']:.1f} m" in details["summary"]


def test_aces_rewritten_as_robotlaser1_reads_the_same_scans(tmp_path):
    """Real data: 400 scans of ACES (its SICK codes "no return" as 50 m) rewritten as ROBOTLASER1 messages that
    declare a 100 m range: the 50 m codes are still no points, the scans read as from the original FLASER log
    (before: 1 % of the readings came back as points 50 m away)."""
    from pathlib import Path

    from dm2_backend.formats.carmen import load, robotlaser1_line
    from dm2_backend.kernel.planar_returns import isolated_long_returns

    aces = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "carmen" / "aces.clf.bz2"
    if not aces.exists():
        pytest.skip(f"{aces} absent")
    msgs = load(aces).messages["FLASER"][4200:4600]
    out = tmp_path / "aces-robotlaser1.clf"
    out.write_text("\n".join(robotlaser1_line(m.ranges, m.start_angle, m.angular_resolution, 100.0, m.laser_pose,
                                              m.robot_pose, m.timestamp) for m in msgs) + "\n")
    seq = open_carmen_scans(out)
    assert seq.meta["max_range"] == 50.0 and len(seq) == len(msgs)
    for i in range(0, len(msgs), 37):
        valid = (msgs[i].ranges > 0) & (msgs[i].ranges < 50.0)
        valid &= ~isolated_long_returns(msgs[i].ranges, valid, msgs[i].angular_resolution)  # as both readers do
        a = msgs[i].start_angle + msgs[i].angular_resolution * np.flatnonzero(valid)
        r = msgs[i].ranges[valid]
        # the same points, but for the angles' %.6f rad in the message (at most 3 mm at 50 m)
        np.testing.assert_allclose(seq[i].points[:, :2], np.column_stack([r * np.cos(a), r * np.sin(a)]), atol=3e-3)


def test_windows_option_checked(hospital):
    from dm2_backend.runtime.errors import InputError

    with pytest.raises(InputError, match="unknown windows 'maybe'"):
        warm_start(hospital[0], windows="maybe")
