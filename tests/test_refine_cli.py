"""``dm2 refine`` end to end through the CLI on a simulated planar sequence: the run-folder contract, the
preparation cache, ``--resume``, and bad inputs (exit code 2 with one line)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import yaml
from click.testing import CliRunner
from optim_cases import one_thread, planar_case

from dm2_backend import config
from dm2_backend.cli.main import cli
from dm2_backend.formats import read_trajectory
from dm2_backend.formats.dm2_priors import read_priors
from dm2_backend.kernel.geometry import se3
from dm2_backend.simulate.sequence import write_sequence


@pytest.fixture(autouse=True, scope="module")
def _single_thread():
    yield from one_thread()


SMALL = {
    "seed": 3,
    "frames": {"max_points": 256},
    "optimiser": {"points_per_frame": 64, "bce_points_per_frame": 32, "batch_groups": 16,
                  "grid_max_cells": 2**14, "dense": False},  # the first-order epochs and their report
}
STEPS = ("frames", "warm_start", "place_recognition", "registration")


@pytest.fixture(scope="module")
def seq(tmp_path_factory) -> Path:
    """velodyne/, poses.txt (ground truth), warm_start.txt, and times.txt with full-precision stamps
    (found next to the scan folder and next to the KITTI files), plus a small config.yaml."""
    case = planar_case()
    root = tmp_path_factory.mktemp("seq")
    write_sequence(root, case.scans, case.gt, case.warm, 10.0)
    n = len(case.scans)
    stamps = 1317384506.123456789 + np.arange(n) * 0.1000003 + np.linspace(0, 1e-6, n)
    (root / "times.txt").write_text("".join(f"{float(t)!r}\n" for t in stamps))
    (root / "config.yaml").write_text(yaml.safe_dump(SMALL))
    return root


def refine(seq: Path, out: Path, *extra: str):
    args = ["refine", "--scans", str(seq / "velodyne"), "--poses", str(seq / "warm_start.txt"), "--gt",
            str(seq / "poses.txt"), "--out", str(out), "-c", str(seq / "config.yaml"), "-q", *extra]
    return CliRunner().invoke(cli, args, obj={})


def ok(result) -> None:
    assert result.exit_code == 0, result.output + repr(result.exception)


@pytest.fixture(scope="module")
def run(seq, tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "run"
    result = refine(seq, out, "--epochs", "2", "--no-cache")
    ok(result)
    return out, result, json.loads((out / "report.json").read_text())


def test_trajectories_with_full_precision_stamps(seq, run):
    out, _, report = run
    poses = np.load(out / "poses.npy")
    n = len(planar_case().scans)
    assert poses.shape == (n, 4, 4) and np.isfinite(poses).all() and se3.is_planar(poses)
    stamps = [float(line.split()[0]) for line in (out / "poses_tum.txt").read_text().splitlines()
              if line.strip() and not line.startswith("#")]
    expected = [float(line) for line in (seq / "times.txt").read_text().split()]
    assert stamps == expected  # exactly: no rounding of the scan timestamps
    tum = read_trajectory(out / "poses_tum.txt", "tum")
    np.testing.assert_allclose(tum.poses, poses, atol=1e-9)
    kitti = read_trajectory(out / "poses_kitti.txt", "kitti")
    np.testing.assert_allclose(kitti.poses, poses, atol=1e-12)
    warm = read_trajectory(out / "warm_start_kitti.txt", "kitti")
    np.testing.assert_allclose(warm.poses, read_trajectory(seq / "warm_start.txt", "kitti").poses, atol=1e-9)
    assert {"poses_tum.txt", "poses_kitti.txt", "poses.npy", "warm_start_tum.txt"} <= set(report["files"])


def test_config_yaml_is_the_effective_config(seq, run):
    out = run[0]
    written = yaml.safe_load((out / "config.yaml").read_text())
    expected = config.load(seq / "config.yaml", {"optimiser": {"epochs": 2, "max_steps": 0}})
    assert written == expected.model_dump() and written["place_recognition"]["name"] == "auto"  # as given, not mutated
    resolved = yaml.safe_load((out / "resolved.yaml").read_text())
    assert resolved["place_recognition"]["name"] == "loops"  # auto, resolved for planar scans
    assert resolved["registration"] == written["registration"]
    assert written["seed"] == 3 and written["optimiser"]["epochs"] == 2
    assert written["optimiser"]["max_steps"] == 0  # an explicit --epochs lifts the step cap
    assert written["optimiser"]["points_per_frame"] == 64 and written["registration"]["name"] == "icp"


def test_report(run):
    out, result, report = run
    assert report["method"] == "dm2 refine" and report["frames"] == len(planar_case().scans)
    assert report["planar"] is True and report["device"] == "cpu" and report["stopped"] is None
    assert report["stop_reason"] == "budget" and report["start"]["dense"] == {}  # dense: false, two epochs
    metrics, before = report["metrics"], report["warm_start_metrics"]
    assert {"ape_trans_rmse_m", "ape_rot_rmse_deg", "rpe_trans_rmse_m", "paper_ate_trans"} <= set(metrics)
    assert set(metrics) == set(before)
    assert metrics["ape_trans_rmse_m"] < 0.8 * before["ape_trans_rmse_m"]
    assert set(STEPS) | {"optimise", "total"} <= set(report["timings"])
    assert report["timings"]["total"] >= report["timings"]["optimise"] > 0
    assert report["peak_rss_mb"] > 50
    # every stage, the outputs' too, timed and its memory peak recorded, in the order they ran
    stages = [*STEPS, "map_sampler", "start", "dense", "optimise", "map_metrics", "trajectories_and_plots",
              "consistency", "maps", "evaluation"]
    assert list(report["peak_rss_mb_by_stage"]) == stages and list(report["timings"]) == [*stages, "total"]
    assert sum(report["timings"][s] for s in stages) <= report["timings"]["total"]
    assert report["prepare"]["cached"] == dict.fromkeys(STEPS, False)
    assert 0 < report["prepare"]["pairs_valid"] <= report["prepare"]["pairs"]
    assert [e["epoch"] for e in report["epochs"]] == [0, 1]
    assert all(np.isfinite(e["ate"]) and np.isfinite(e["loss"]) for e in report["epochs"])
    assert report["best_epoch"] in (0, 1) and report["derived"]["unit"] > 0
    assert "ape_trans_rmse_m" in result.output and "wrote" in result.output
    # map sharpness of every stage, without ground truth; the returned poses never blurrier than the start
    assert report["map_quality"]["radius_m"] > 0 and "map_entropy" in metrics
    assert report["start"]["name"] == "prepared" and report["start_metrics"]["map_entropy"] is not None
    assert metrics["map_entropy"] <= report["start_metrics"]["map_entropy"]
    assert report["selection"].startswith(("sharpest map", "the start"))
    assert [e["map_entropy"] for e in report["epochs"]] and "map_entropy" in result.output


def test_consistency_profile_before_and_after(run):
    out, result, report = run
    assert "consistency of the warm start: frames agree to" in result.output
    assert "consistency of the dm2 refine: frames agree to" in result.output
    # one line per stage: the count of flagged stretches and the worst few, never every frame range
    lines = [ln for ln in result.output.splitlines() if ln.startswith("consistency of the")]
    assert len(lines) == 2 and all(len(ln) < 400 for ln in lines)
    profiles = report["consistency"]
    assert set(profiles) == {"warm start", "dm2 refine"}
    for summary in profiles.values():
        assert summary["frames"] == report["frames"] and summary["thresholds_m"]["all"] > summary["levels_m"]["all"] > 0
    assert {"consistency.json", "consistency.csv", "consistency.png"} <= set(report["files"])
    doc = json.loads((out / "consistency.json").read_text())
    assert len(doc["dm2 refine"]["score"]) == report["frames"]


def test_quiet_prints_no_progress_bars(run):
    output = run[1].output
    assert "\r" not in output and "it/s" not in output, output


def test_map_and_plots(run):
    out, _, report = run
    cloud = o3d.io.read_point_cloud(str(out / "map.ply"))
    pts = np.asarray(cloud.points)
    assert len(pts) > 1000 and np.isfinite(pts).all()
    poses = np.load(out / "poses.npy")
    assert np.abs(pts[:, 2]).max() < 1e-6  # planar scans stay in the plane
    assert np.linalg.norm(pts[:, :2].mean(0) - poses[:, :2, 3].mean(0)) < 10.0
    for name in ("trajectory.png", "errors.png", "epochs.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name


def test_topology_files(run):
    out, _, report = run
    assert {"topology.json", "topology.png"} <= set(report["files"])
    doc = json.loads((out / "topology.json").read_text())
    assert doc["plugin"] == "loops" and doc["summary"]["keyframes"] > 0  # auto = loops for planar scans
    counts, cands = doc["counts"], doc["candidates"]
    assert counts["candidates"] == len(cands) > 0 and counts["accepted"] > 0  # two laps: the loop is closed
    assert counts["accepted"] == sum(c["status"] == "accepted" for c in cands)
    assert sum(counts[k] for k in ("accepted", "dropped", "verified_not_accepted", "rejected")) == len(cands)
    for c in cands:
        assert 0 <= c["i"] < c["j"] < report["frames"] and "reason" in c
        assert c["status"] == "rejected" or len(c["z"]) == 3
    assert doc["edges"].get("loop", 0) > 0 and sum(doc["edges"].values()) == report["prepare"]["topology_edges"]
    assert (out / "topology.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_prior_files(seq, run):
    out, _, report = run
    init, groups, relative = read_priors(out / "prior")
    warm = read_trajectory(seq / "warm_start.txt", "kitti").poses
    np.testing.assert_allclose(init, warm, atol=1e-6)
    assert int((groups >= 0).sum()) == report["prepare"]["pairs"]
    assert relative.shape[:2] == groups.shape
    assert (out / "prior" / "init_pose.npy").is_file()


def test_cache_and_resume(seq, tmp_path):
    cache = tmp_path / "cache"
    first = tmp_path / "first"
    ok(refine(seq, first, "--epochs", "1", "--cache-dir", str(cache)))
    r1 = json.loads((first / "report.json").read_text())
    assert r1["prepare"]["cached"] == dict.fromkeys(STEPS, False)
    assert any(cache.iterdir())
    second = tmp_path / "second"
    ok(refine(seq, second, "--epochs", "1", "--cache-dir", str(cache)))
    r2 = json.loads((second / "report.json").read_text())
    assert r2["prepare"]["cached"] == dict.fromkeys(STEPS, True)
    np.testing.assert_array_equal(np.load(second / "poses.npy"), np.load(first / "poses.npy"))
    # --resume on the finished run: nothing left to train, same result and history
    ok(refine(seq, first, "--epochs", "1", "--cache-dir", str(cache), "--resume"))
    r3 = json.loads((first / "report.json").read_text())
    np.testing.assert_array_equal(np.load(first / "poses.npy"), np.load(second / "poses.npy"))
    assert [e["loss"] for e in r3["epochs"]] == [e["loss"] for e in r1["epochs"]]
    assert r3["prepare"]["cached"] == dict.fromkeys(STEPS, True)


# ---------------------------------------------------------------- bad inputs
def one_error_line(result, *names: str) -> str:
    assert result.exit_code == 2, result.output + repr(result.exception)
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("dm2: error:"), result.output
    for name in names:
        assert name in lines[0], lines[0]
    return lines[0]


def invoke(*args: str):
    return CliRunner().invoke(cli, ["refine", "-q", "--no-cache", *args], obj={})


def test_missing_scans_folder(seq, tmp_path):
    missing = seq / "no_such_folder"
    result = invoke("--scans", str(missing), "--poses", str(seq / "warm_start.txt"),
                    "--out", str(tmp_path / "r"))
    one_error_line(result, str(missing))


def test_pose_count_does_not_match_scan_count(seq, tmp_path):
    short = tmp_path / "short.txt"
    short.write_text("".join((seq / "warm_start.txt").read_text().splitlines(keepends=True)[:-1]))
    n = len(planar_case().scans)
    result = invoke("--scans", str(seq / "velodyne"), "--poses", str(short), "--out", str(tmp_path / "r"))
    one_error_line(result, f"{n} scans but {n - 1} poses")
    result = invoke("--scans", str(seq / "velodyne"), "--poses", str(short),
                    "--times", str(seq / "times.txt"), "--out", str(tmp_path / "r"))
    one_error_line(result, "times.txt", f"{n} times for {n - 1} poses")


def test_ground_truth_count_does_not_match(seq, tmp_path):
    short = tmp_path / "gt.txt"
    short.write_text("".join((seq / "poses.txt").read_text().splitlines(keepends=True)[:-1]))
    result = invoke("--scans", str(seq / "velodyne"), "--poses", str(seq / "warm_start.txt"),
                    "--gt", str(short), "--out", str(tmp_path / "r"))
    one_error_line(result, str(short), "ground truth")


@pytest.mark.parametrize("option,group", [("--warm-start", "dm2.warm_start"),
                                          ("--place-recognition", "dm2.place_recognition"),
                                          ("--registration", "dm2.registration")])
def test_unknown_plugin(seq, tmp_path, option, group):
    result = invoke("--scans", str(seq / "velodyne"), "--poses", str(seq / "warm_start.txt"), option, "nope",
                    "--out", str(tmp_path / "r"))
    one_error_line(result, group, "'nope'", "choices")


@pytest.mark.parametrize("text,message", [
    ("optimiser:\n  epochs: 2\n  bogus: 1\n", "optimiser.bogus: Extra inputs are not permitted"),
    ("optimizer:\n  epochs: 2\n", "unknown config sections: optimizer"),
    ("optimiser: {epochs: 2\n", "invalid YAML"),
    ("- 1\n- 2\n", "must be a mapping"),
    ("optimiser: {select: best}\n", "optimiser.select: Input should be 'map' or 'loss' (got 'best')"),
    ("optimiser: {start: gtsam}\n", "optimiser.start: Input should be 'auto', 'graph' or 'prepared' (got 'gtsam')"),
    ("optimiser: {chamfer_metric: l1}\n", "optimiser.chamfer_metric: Input should be 'point' or 'plane'"),
    ("optimiser: {consistency_kernel: huber}\n", "optimiser.consistency_kernel: Input should be 'cauchy' or"),
    ("optimiser: {epochs: three}\n", "optimiser.epochs: Input should be a valid integer (got 'three')"),
    ("optimiser: {epochs: 2.5}\n", "optimiser.epochs: Input should be a valid integer"),
    ("optimiser: {use_bce: 1}\n", "optimiser.use_bce: Input should be 'auto', 'on' or 'off'"),
    ("optimiser: {first_order: maybe}\n", "optimiser.first_order: Input should be 'auto', 'on' or 'off'"),
    ("optimiser: {dense: auto}\n", "optimiser.dense: Input should be a valid boolean"),
    ("optimiser: {epochs: 0}\n", "optimiser.epochs: Input should be greater than or equal to 1"),
    ("optimiser: {grid_levels: 0}\n", "optimiser.grid_levels: Input should be greater than or equal to 1"),
    ("optimiser: {batch_groups: 0}\n", "optimiser.batch_groups: Input should be greater than or equal to 1"),
    ("optimiser: {samples_per_ray: 1000000000}\n", "optimiser.samples_per_ray: Input should be less than or equal"),
    ("seed: 1\noptimiser: {epochs: 2}\nseed: 2\n", "the key 'seed' is given twice"),
    ("optimiser:\n  epochs: 2\n  epochs: 3\n", "the key 'epochs' is given twice"),
    ("optimiser: {lr_field: 0.0}\n", "optimiser.lr_field: Input should be greater than 0"),
    ("optimiser: {lr_pose: fast}\n", "optimiser.lr_pose: Input should be a valid number"),
    ("seed: abc\n", "seed: Input should be a valid integer"),
    ("device: gpu\n", "device: auto, cpu, cuda or cuda:N"),
    ("nproc: 0\n", "nproc: Input should be greater than 0"),
    ("frames: {max_points: many}\n", "frames.max_points: Input should be a valid integer"),
    ("frames: {voxle: 0.1}\n", "frames.voxle: Extra inputs are not permitted"),
    ("registration: icp\n", "registration: Input should be a valid dictionary"),
    ("place_recognition: {name: loops, options: {bogus: 1}}\n", "loops has no option 'bogus'"),
    ("registration: {name: icp, options: {max_distance: far}}\n", "registration.options.max_distance: Input should"),
])
def test_bad_config(seq, tmp_path, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    result = invoke("--scans", str(seq / "velodyne"), "--poses", str(seq / "warm_start.txt"), "-c", str(path),
                    "--out", str(tmp_path / "r"))
    one_error_line(result, str(path), message)
    assert not (tmp_path / "r").exists()  # nothing written before the config is known to be good


@pytest.mark.parametrize("epochs", ["0", "-1"])
def test_epochs_must_be_positive(seq, tmp_path, epochs):
    result = invoke("--scans", str(seq / "velodyne"), "--poses", str(seq / "warm_start.txt"), "--epochs", epochs,
                    "--out", str(tmp_path / "r"))
    assert result.exit_code == 2 and "--epochs" in result.output
    assert not (tmp_path / "r").exists()


def test_cuda_without_a_device_is_one_line_before_any_work(seq, tmp_path, monkeypatch):
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    result = invoke("--scans", str(seq / "velodyne"), "--poses", str(seq / "warm_start.txt"), "--device", "cuda",
                    "--out", str(tmp_path / "r"))
    one_error_line(result, "--device cuda", "no CUDA device")
    assert not (tmp_path / "r").exists()


def test_default_warm_start_fuses_a_logs_odometry(tmp_path):
    """No --poses: icp; a 2D log's own odometry: icp (it fuses the odometry) unless a warm start was asked for;
    a trajectory given with --poses, or 3D scans with carried odometry: poses."""
    from types import SimpleNamespace

    from dm2_backend.pipeline.inputs import default_to_icp

    cfg = config.load(None, {})
    planar, lidar = SimpleNamespace(planar=True), SimpleNamespace(planar=False)
    log = SimpleNamespace(given=object(), given_path=None, scans=planar)
    assert default_to_icp(cfg, SimpleNamespace(given=None, given_path=None, scans=lidar), False)
    assert default_to_icp(cfg, log, False)
    assert not default_to_icp(cfg, log, True)  # --warm-start poses, or warm_start in the config
    assert not default_to_icp(cfg, SimpleNamespace(given=object(), given_path=Path("p.txt"), scans=planar), False)
    assert not default_to_icp(cfg, SimpleNamespace(given=object(), given_path=None, scans=lidar), False)
    yaml_file = tmp_path / "c.yaml"
    yaml_file.write_text("warm_start:\n  name: poses\n")
    assert config.sets(yaml_file, "warm_start") and not config.sets(yaml_file, "optimiser")
    assert not config.sets(None, "warm_start")


def test_plugin_options_reach_the_plugin_as_the_types_they_declare(tmp_path):
    """YAML reads ``1.0e9`` (no sign in the exponent) as a string: the option is checked as a float and the plugin
    gets the float, not the string its comparisons would fail on."""
    path = tmp_path / "c.yaml"
    path.write_text("place_recognition: {name: loops, options: {drift_margin: 1.0e9, k: '6'}}\n")
    options = config.load(path).place_recognition.options
    assert options == {"drift_margin": 1e9, "k": 6} and isinstance(options["drift_margin"], float)


def test_auto_place_recognition_checks_its_options_once_resolved():
    """``auto`` names no class at load: its options are converted and checked against the plugin it resolves to,
    an option the resolved plugin lacks is one line naming both."""
    from dm2_backend.config.schema import PluginSection
    from dm2_backend.prepare.steps import resolve_auto
    from dm2_backend.runtime.errors import InputError

    section = PluginSection(name="auto", options={"drift_margin": "1.0e9"})
    assert resolve_auto(section, camera=False).options == {"drift_margin": 1e9}
    with pytest.raises(InputError, match="loops3d has no option 'drift_margin'"):
        resolve_auto(section, camera=True)
