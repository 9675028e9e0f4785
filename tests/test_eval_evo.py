"""APE/RPE of dm2_backend.evaluation equal evo_ape / evo_rpe (evo's CLI run in-process) to 1e-6."""

from __future__ import annotations

import functools
import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from evo.tools import file_interface

from dm2_backend.cli.main import cli
from dm2_backend.evaluation.ape_rpe import STAT_KEYS, evaluate_poses
from dm2_backend.kernel.trajectory import Trajectory

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "trajectories"
KITTI = (DATA / "KITTI_00_gt.txt", DATA / "KITTI_00_ORB.txt")
TUM = (DATA / "fr2_desk_groundtruth.txt", DATA / "fr2_desk_ORB.txt")
MODES = {"se3": ("se3", False), "sim3": ("sim3", False), "none": ("none", False), "origin": ("none", True)}
EVO_FLAGS = {"se3": ["-a"], "sim3": ["-as"], "none": [], "origin": ["--align_origin"]}

pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason=f"shared data absent ({DATA})")


def evo_stats(tool: str, fmt: str, ref: Path, est: Path, relation: str, mode: str, out: Path) -> dict:
    """Run evo_ape / evo_rpe's main function in-process and read back its --save_results archive."""
    from evo.cli import ape, ape_parser, rpe, rpe_parser

    main, parser = (ape, ape_parser) if tool == "ape" else (rpe, rpe_parser)
    zip_path = out / f"evo_{tool}_{relation}_{mode}_{ref.stem}.zip"
    argv = [fmt, str(ref), str(est), "-r", relation, *EVO_FLAGS[mode], "--save_results", str(zip_path),
            "--no_warnings", "--silent"]
    main.run(parser.parser().parse_args(argv))
    return file_interface.load_res_file(zip_path).stats


@functools.cache
def _evo_traj(fmt: str, path: Path) -> Trajectory:
    """A Trajectory through evo's own readers (fr2_desk's ground truth repeats a timestamp, which dm2's
    TUM reader rejects)."""
    if fmt == "kitti":
        t = file_interface.read_kitti_poses_file(str(path))
        return Trajectory(np.array(t.poses_se3))
    t = file_interface.read_tum_trajectory_file(str(path))
    return Trajectory(np.array(t.poses_se3), timestamps=t.timestamps)


@functools.cache
def ours(fmt: str, ref: Path, est: Path, mode: str):
    align, origin = MODES[mode]
    return evaluate_poses(_evo_traj(fmt, ref), _evo_traj(fmt, est), align=align, align_origin=origin)


@pytest.fixture(scope="module")
def short_files(tmp_path_factory) -> dict:
    """The first seconds of the same files (evo's per-pose rotation log is slow on whole files)."""
    folder = tmp_path_factory.mktemp("short")
    out = {}
    for name, fmt, files, keep in (("kitti", "kitti", KITTI, lambda i, _: i < 400),
                                   ("fr2_desk", "tum", TUM, lambda _, t: t < 1311868163.87 + 12.0)):
        short = []
        for src in files:
            lines = [ln for ln in src.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
            dst = folder / src.name
            kept = [ln for i, ln in enumerate(lines) if keep(i, float(ln.split()[0]))]
            dst.write_text("\n".join(kept) + "\n")
            short.append(dst)
        out[name] = (fmt, *short)
    return out


def _assert_stats(mine: dict, theirs: dict) -> None:
    for k in STAT_KEYS:
        assert mine[k] == pytest.approx(theirs[k], abs=1e-6, rel=0), k


@pytest.mark.parametrize("mode", list(MODES))
@pytest.mark.parametrize("which", ["kitti", "fr2_desk"])
def test_ape_rpe_equal_evo(which, mode, short_files, tmp_path):
    """Every metric and alignment mode, on the first 400 KITTI poses / the first 12 s of fr2_desk."""
    fmt, ref, est = short_files[which]
    res = ours(fmt, ref, est, mode)
    assert res.n_matched > 250
    for tool in ("ape", "rpe"):
        for part, relation in (("trans", "trans_part"), ("rot", "angle_deg")):
            theirs = evo_stats(tool, fmt, ref, est, relation, mode, tmp_path)
            _assert_stats(res.metrics[f"{tool}_{part}"].stats, theirs)


@pytest.mark.parametrize("mode", list(MODES))
@pytest.mark.parametrize("files", [KITTI, TUM], ids=["kitti", "fr2_desk"])
def test_ape_equals_evo_on_whole_files(files, mode, tmp_path):
    fmt = "kitti" if files is KITTI else "tum"
    res = ours(fmt, *files, mode)
    _assert_stats(res.metrics["ape_trans"].stats, evo_stats("ape", fmt, *files, "trans_part", mode, tmp_path))


@pytest.mark.parametrize("files", [KITTI, TUM], ids=["kitti", "fr2_desk"])
def test_rpe_equals_evo_on_whole_files(files, tmp_path):
    fmt = "kitti" if files is KITTI else "tum"
    res = ours(fmt, *files, "sim3")
    theirs = evo_stats("rpe", fmt, *files, "trans_part", "sim3", tmp_path)
    _assert_stats(res.metrics["rpe_trans"].stats, theirs)


def test_rpe_delta_in_metres_equals_evo(short_files, tmp_path):
    from evo.cli import rpe, rpe_parser

    fmt, ref, est = short_files["kitti"]
    res = evaluate_poses(_evo_traj(fmt, ref), _evo_traj(fmt, est), align="se3", delta=20.0, delta_unit="m")
    zip_path = tmp_path / "rpe_m.zip"
    argv = [fmt, str(ref), str(est), "-a", "-d", "20", "-u", "m", "--save_results", str(zip_path),
            "--no_warnings", "--silent"]
    rpe.run(rpe_parser.parser().parse_args(argv))
    assert res.metrics["rpe_trans"].count > 10
    _assert_stats(res.metrics["rpe_trans"].stats, file_interface.load_res_file(zip_path).stats)


def test_cli_json_and_evo_archives_equal_evo(tmp_path):
    """`dm2 eval` reading the KITTI files with dm2's own reader, --json and --save-evo."""
    out = tmp_path / "eval.json"
    args = ["eval", "--gt", str(KITTI[0]), "--est", str(KITTI[1]), "--gt-format", "kitti", "--est-format",
            "kitti", "--align", "sim3", "--json", str(out), "--save-evo", str(tmp_path / "evo")]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 0, r.output
    metrics = json.loads(out.read_text())["estimates"][0]["metrics"]
    _assert_stats(metrics["ape_trans"], evo_stats("ape", "kitti", *KITTI, "trans_part", "sim3", tmp_path))
    _assert_stats(metrics["rpe_trans"], ours("kitti", *KITTI, "sim3").metrics["rpe_trans"].stats)
    for key in ("ape_trans", "ape_rot", "rpe_trans", "rpe_rot"):
        archived = file_interface.load_res_file(tmp_path / "evo" / f"KITTI_00_ORB_{key}.zip")
        _assert_stats(archived.stats, metrics[key])
        assert len(archived.np_arrays["error_array"]) == metrics[key]["count"]
