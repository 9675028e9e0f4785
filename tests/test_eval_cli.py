"""`dm2 eval` / `dm2 compare`: outputs parse back, plots exist, bad input exits 2 with one line."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from evo.tools import file_interface

from dm2_backend.cli.main import cli
from dm2_backend.kernel.geometry import se3


def _write_tum(path: Path, stamps: np.ndarray, poses: np.ndarray) -> Path:
    xyz, q = se3.to_xyz_quat(poses, "xyzw")
    np.savetxt(path, np.c_[stamps, xyz, q], fmt="%.9f")
    return path


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    rng = np.random.default_rng(7)
    folder = tmp_path_factory.mktemp("eval")
    n = 200
    stamps = 1000.0 + 0.1 * np.arange(n)
    walk = np.cumsum(np.c_[rng.normal(0, 0.5, (n, 3)), rng.normal(0, 0.05, (n, 3))], axis=0)
    gt = se3.from_xyz_euler(walk)
    noisy = se3.from_xyz_euler(se3.to_xyz_euler(gt) + rng.normal(0, 0.02, (n, 6)))
    moved = se3.make_poses(se3.euler_xyz_to_matrix([0, 0, 1.0]), [4.0, 1.0, 0.0]) @ noisy
    out = {
        "gt": _write_tum(folder / "gt.txt", stamps, gt),
        "est": _write_tum(folder / "slam.txt", stamps + 0.002, moved),
        "est2": _write_tum(folder / "other.txt", stamps[::2], noisy[::2]),
    }
    d = se3.relative(gt[:-5], gt[5:])
    rel = np.c_[stamps[:-5], stamps[5:], d[:, :3, 3], se3.matrix_to_rpy(d[:, :3, :3])]
    np.savetxt(folder / "gt.relations", rel, fmt="%.9f")
    out["relations"] = folder / "gt.relations"
    garbage = folder / "garbage.txt"
    garbage.write_text("hello world\nthis is not a trajectory\n")
    out["garbage"] = garbage
    return out


def run(*args: str):
    return CliRunner().invoke(cli, [str(a) for a in args])


def test_outputs_parse_back_and_plots_exist(files, tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "report.json").write_text(json.dumps(
        {"method": "dm2 refine", "epochs": [{"epoch": 1, "loss": 2.0, "ate": 0.5}, {"epoch": 2, "loss": 1.0},
                                            {"epoch": 3, "ate": 0.3}]}))
    out = tmp_path / "out"
    r = run("eval", "--gt", files["gt"], "--est", files["est"], "--est", files["est2"], "--relations",
            files["relations"], "--json", out / "r.json", "--csv", out / "r.csv", "--markdown", out / "r.md",
            "--plot", out / "plots", "--save-evo", out / "evo", "--run-report", run_dir)
    assert r.exit_code == 0, r.output
    assert "paper ATE" in r.output and "APE trans" in r.output and "relations rot" in r.output

    data = json.loads((out / "r.json").read_text())
    assert data["format"] == "dm2-eval/1" and [e["label"] for e in data["estimates"]] == ["slam", "other"]
    slam = data["estimates"][0]
    assert slam["association"]["mode"] == "time" and slam["association"]["matched"] == 200
    assert slam["alignment"]["mode"] == "se3" and len(slam["alignment"]["sim3"]) == 4
    assert slam["metrics"]["ape_trans"]["rmse"] < 0.2  # the rigid offset is aligned away
    assert slam["metrics"]["relations"]["used"] == 195
    assert slam["metrics"]["paper_ate"]["label"] == "paper ATE"
    assert data["estimates"][1]["association"]["matched"] == 100

    with open(out / "r.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 2 * (4 + 2 + 4)
    by_key = {(row["estimate"], row["metric"]): row for row in rows}
    assert float(by_key[("slam", "ape_trans")]["rmse"]) == pytest.approx(slam["metrics"]["ape_trans"]["rmse"])
    assert float(by_key[("slam", "relations_rot")]["mean"]) == pytest.approx(
        slam["metrics"]["relations"]["rot_mean"])
    assert by_key[("slam", "paper_ate_trans")]["rmse"] == ""

    md = (out / "r.md").read_text().splitlines()
    table = [line for line in md if line.startswith("|")]
    assert len(table) == 2 + len(rows) and all(line.count("|") == 12 for line in table)

    plots = out / "plots"
    for name in ("trajectories.png", "errors_slam.png", "errors_other.png", "epochs.png"):
        assert (plots / name).stat().st_size > 1000, name
    archived = file_interface.load_res_file(out / "evo" / "slam_ape_trans.zip")
    assert archived.stats["rmse"] == pytest.approx(slam["metrics"]["ape_trans"]["rmse"])


def test_relations_only_and_no_epoch_ate(files, tmp_path):
    report = tmp_path / "report.json"
    report.write_text(json.dumps({"method": "x", "epochs": [{"epoch": 1, "loss": 3.0}]}))
    r = run("eval", "--relations", files["relations"], "--est", files["est"], "--plot", tmp_path / "p",
            "--run-report", report)
    assert r.exit_code == 0, r.output
    assert "relations trans" in r.output and "APE" not in r.output
    assert (tmp_path / "p" / "trajectories.png").exists() and not (tmp_path / "p" / "epochs.png").exists()
    assert "no epoch has an 'ate' entry" in r.output


def test_align_modes_change_the_numbers(files, tmp_path):
    values = {}
    for flags in (["--align", "none"], ["--align", "se3"], ["--align", "sim3"], ["--align-origin"]):
        out = tmp_path / f"{'_'.join(flags)}.json"
        r = run("eval", "--gt", files["gt"], "--est", files["est"], *flags, "--json", out)
        assert r.exit_code == 0, r.output
        e = json.loads(out.read_text())["estimates"][0]
        values[flags[-1]] = e["metrics"]["ape_trans"]["rmse"]
        assert e["alignment"]["align_origin"] == (flags == ["--align-origin"])
    assert values["none"] > 3 > values["se3"] and values["sim3"] <= values["se3"] + 1e-9


@pytest.mark.parametrize("evo_form, dm2_form", [
    (["-a"], ["--align", "se3"]), (["-as"], ["--align", "sim3"]), ([], ["--align", "se3"]),
])
def test_evo_habits_positional_files_and_short_alignment_flags(files, tmp_path, evo_form, dm2_form):
    """``dm2 eval GT EST EST2 -as`` (as ``evo_ape tum GT EST -as``) equals the --gt/--est/--align form, and
    the alignment used is the first line printed."""
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    r1 = run("eval", files["gt"], files["est"], files["est2"], *evo_form, "--json", a)
    r2 = run("eval", "--gt", files["gt"], "--est", files["est"], "--est", files["est2"], *dm2_form, "--json", b)
    assert r1.exit_code == 0 and r2.exit_code == 0, r1.output + r2.output
    ours, theirs = json.loads(a.read_text()), json.loads(b.read_text())
    assert [e["metrics"] for e in ours["estimates"]] == [e["metrics"] for e in theirs["estimates"]]
    assert len(ours["estimates"]) == 2
    first = r1.output.splitlines()[0]
    assert first.startswith("alignment: ") and ("Sim(3)" if evo_form == ["-as"] else "SE(3)") in first


@pytest.mark.parametrize("args, text", [(["-s"], "-as"), (["-a", "--align", "none"], "contradicts")])
def test_contradicting_alignment_flags(files, args, text):
    r = run("eval", files["gt"], files["est"], *args)
    assert r.exit_code == 2 and text in r.output


def test_a_straight_path_warns_that_the_rotation_is_free(tmp_path):
    n = 50
    stamps = np.arange(n) * 0.1
    wiggle = 1e-3 * np.sin(np.arange(n))  # a straight line within a millimetre (evo needs some spread)
    gt = se3.make_poses(np.tile(np.eye(3), (n, 1, 1)), np.c_[np.arange(n) * 0.5, wiggle, wiggle[::-1]])
    est = se3.make_poses(se3.euler_xyz_to_matrix(np.tile([0.0, 0.0, 0.02], (n, 1))), gt[:, :3, 3] + 0.01)
    g, e = _write_tum(tmp_path / "gt.txt", stamps, gt), _write_tum(tmp_path / "est.txt", stamps, est)
    r = run("eval", g, e, "-a")
    assert r.exit_code == 0 and "nearly a straight line" in r.output and "rotation" in r.output
    r = run("eval", g, e, "--align-origin")
    assert "nearly a straight line" not in r.output  # no rotation is fitted


@pytest.mark.parametrize("case", ["missing", "garbage"])
def test_wrong_est_file_exits_2_with_one_line(files, tmp_path, case):
    bad = tmp_path / "nope.txt" if case == "missing" else files["garbage"]
    r = run("eval", "--gt", files["gt"], "--est", bad)
    assert r.exit_code == 2, r.output
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and str(bad) in lines[0] and lines[0].startswith("dm2: error:")


@pytest.mark.parametrize("args, text", [
    (["--align", "se3", "--align-origin"], "--align-origin"),
    (["--delta", "1.5"], "--delta"),
    (["--max-diff", "0.00001", "--est-format", "tum"], "--max-diff"),
    (["--max-diff", "-1"], "--max-diff"),
    (["--run-report", "report.json"], "--plot"),
])
def test_bad_options_exit_2(files, args, text):
    r = run("eval", "--gt", files["gt"], "--est", files["est"], *args)
    assert r.exit_code == 2, r.output
    assert text in r.output


def test_needs_gt_or_relations(files):
    r = run("eval", "--est", files["est"])
    assert r.exit_code == 2 and "--gt, --relations, --scans" in r.output


def _report(folder: Path, **data) -> Path:
    folder.mkdir()
    (folder / "report.json").write_text(json.dumps(data))
    return folder


def test_compare_prints_one_table(tmp_path):
    a = _report(tmp_path / "warm", method="KISS-ICP", metrics={"ape_trans_rmse_m": 1.5},
                timings={"odometry": 10.0}, peak_rss_mb=900)
    b = _report(tmp_path / "refined", method="dm2 refine",
                metrics={"ape_trans_rmse_m": 0.5, "rpe_rot_rmse_deg": 0.1},
                timings={"prepare": 5.0, "refine": 100.0}, peak_rss_mb=2048.5)
    r = run("compare", a, b)
    assert r.exit_code == 0, r.output
    lines = r.output.splitlines()
    assert "warm" in lines[0] and "refined" in lines[0]
    assert any("KISS-ICP" in x and "dm2 refine" in x for x in lines)
    row = next(x for x in lines if x.startswith("ape_trans_rmse_m"))
    assert "1.500000" in row and "0.500000" in row
    assert next(x for x in lines if x.startswith("rpe_rot_rmse_deg")).split()[1] == "-"
    assert "105.000000" in next(x for x in lines if x.startswith("time total"))


def test_compare_counts_a_run_total_once_and_says_what_was_cached(tmp_path):
    a = _report(tmp_path / "refine", method="dm2 refine", timings={"registration": 30.0, "optimise": 60.0,
                "total": 95.0}, prepare={"cached": {"frames": False, "registration": False}})
    b = _report(tmp_path / "gtsam", method="gtsam", timings={"registration": 0.1, "optimise": 1.0, "total": 2.0},
                prepare={"cached": {"frames": True, "registration": True}})
    lines = run("compare", a, b).output.splitlines()
    totals = [x for x in lines if x.startswith("time total")]
    assert len(totals) == 1 and totals[0].split()[-2:] == ["95.000000", "2.000000"]
    assert next(x for x in lines if x.startswith("preparation cached")).split()[-2:] == ["no", "frames,registration"]


def test_compare_bad_reports_exit_2(tmp_path):
    r = run("compare", tmp_path / "absent")
    assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1 and "absent" in r.output
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "report.json").write_text("{not json")
    r = run("compare", bad)
    assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1 and "not valid JSON" in r.output


def test_each_estimate_takes_its_own_bag_topic(tmp_path):
    """Two estimates from one bag (as `evo_ape bag` takes one topic per estimate): each --est-topic goes with its
    --est, in order; the labels name the topics."""
    from shared_helpers import DATA, need

    bag = DATA / "bags" / "ROS_example.bag"
    need(bag)
    args = ["eval", "--gt", str(bag), "--gt-topic", "groundtruth", "-a", "--json", str(tmp_path / "e.json")]
    result = CliRunner().invoke(cli, args + ["--est", str(bag), "--est-topic", "ORB-SLAM", "--est", str(bag),
                                             "--est-topic", "S-PTAM"], obj={})
    assert result.exit_code == 0, result.output
    estimates = json.loads((tmp_path / "e.json").read_text())["estimates"]
    assert [e["label"] for e in estimates] == ["ROS_example:ORB-SLAM", "ROS_example:S-PTAM"]
    single = {}
    for topic in ("ORB-SLAM", "S-PTAM"):
        r = CliRunner().invoke(cli, args[:-2] + ["--json", str(tmp_path / f"{topic}.json"), "--est", str(bag),
                                                 "--est-topic", topic], obj={})
        assert r.exit_code == 0, r.output
        single[topic] = json.loads((tmp_path / f"{topic}.json").read_text())["estimates"][0]["metrics"]
    for e, topic in zip(estimates, ("ORB-SLAM", "S-PTAM"), strict=True):
        assert e["metrics"]["ape_trans"] == single[topic]["ape_trans"]
    assert estimates[0]["metrics"]["ape_trans"] != estimates[1]["metrics"]["ape_trans"]
    wrong = CliRunner().invoke(cli, args + ["--est", str(bag)] * 3 + ["--est-topic", "a", "--est-topic", "b"], obj={})
    assert wrong.exit_code == 2 and "2 --est-topic for 3 estimates" in wrong.output


def test_the_evaluation_is_a_library_call_the_command_only_prints(files, tmp_path):
    """``evaluate_request`` gives the numbers ``dm2 eval --json`` writes; a shifted copy of the truth has an
    aligned APE of zero and, unaligned, exactly its shift."""
    from dm2_backend.evaluation.evaluate import EvalOptions
    from dm2_backend.evaluation.request import Estimate, EvalRequest, evaluate_request

    shifted = tmp_path / "shifted.txt"
    data = np.loadtxt(files["gt"])
    data[:, 1] += 0.5
    np.savetxt(shifted, data, fmt="%.9f")
    request = EvalRequest((Estimate(files["est"], "slam"), Estimate(shifted, "shifted")), gt_path=files["gt"])
    evaluation = evaluate_request(request)
    ape = {e.label: e.poses.metrics["ape_trans"].stats["rmse"] for e in evaluation.report.estimates}
    assert ape["shifted"] < 1e-6 and evaluation.at_scans == {} and evaluation.gt is not None
    raw = evaluate_request(EvalRequest((Estimate(shifted, "shifted"),), EvalOptions(align="none"), files["gt"]))
    assert raw.report.estimates[0].poses.metrics["ape_trans"].stats["rmse"] == pytest.approx(0.5)
    out = tmp_path / "eval.json"
    result = CliRunner().invoke(cli, ["eval", str(files["gt"]), str(files["est"]), str(shifted), "--json", str(out)])
    assert result.exit_code == 0, result.output
    written = {e["label"]: e for e in json.loads(out.read_text())["estimates"]}
    assert written["slam"]["metrics"]["ape_trans"]["rmse"] == pytest.approx(ape["slam"], rel=1e-12)
