"""`dm2 eval --scans` reads depth sequences as refine does, read options key the cache in one spelling, and
estimates can be labelled (issue 30, items 4 and 5)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image
from test_formats_depth import tum_layout

from dm2_backend.cli.main import cli
from dm2_backend.cli.options import read_options
from dm2_backend.formats import open_scans
from dm2_backend.kernel.geometry import se3
from dm2_backend.prepare.cache_keys import source_key


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args], obj={})


@pytest.fixture
def depth_folder(tmp_path):
    folder, depth_t, *_ = tum_layout(tmp_path / "tum")
    stamps = np.array([float(f"{t:.6f}") for t in depth_t])
    poses = se3.from_xyz_euler(np.c_[0.01 * np.arange(len(stamps)), np.zeros((len(stamps), 5))])
    xyz, q = se3.to_xyz_quat(poses, "xyzw")
    est = tmp_path / "est.txt"
    np.savetxt(est, np.c_[stamps, xyz, q], fmt="%.6f")
    return folder, est


def entropy(result, path) -> float:
    assert result.exit_code == 0, result.output
    return json.loads(path.read_text())["estimates"][0]["metrics"]["map"]["entropy"]


def test_eval_scans_takes_refines_depth_options(depth_folder, tmp_path):
    folder, est = depth_folder
    default = entropy(run("eval", "--scans", folder, "--est", est, "--json", tmp_path / "a.json"), tmp_path / "a.json")
    same = entropy(run("eval", "--scans", folder, "--est", est, "--intrinsics", "525,525,319.5,239.5",
                       "--depth-scale", "5000", "--json", tmp_path / "b.json"), tmp_path / "b.json")
    other = entropy(run("eval", "--scans", folder, "--est", est, "--intrinsics", "300 300 319.5 239.5",
                        "--depth-scale", "2500", "--json", tmp_path / "c.json"), tmp_path / "c.json")
    assert same == pytest.approx(default) and other != pytest.approx(default)
    r = run("eval", "--scans", folder, "--est", est, "--intrinsics", "1,2,3")
    assert r.exit_code == 2 and "--intrinsics" in r.output


def test_read_options_key_the_cache_in_one_spelling(depth_folder):
    folder, _ = depth_folder

    def key(**kw):
        return source_key(open_scans(folder, options=read_options(**kw)))

    commas = key(intrinsics="525,525,319.5,239.5", depth_scale=5000.0)
    assert key(intrinsics="525 525 319.5 239.5", depth_scale=5000.0) == commas
    assert key(intrinsics=" 525, 525 ,319.5, 239.5 ") == commas  # the layout's default scale, left out
    assert key() == commas  # TUM's default intrinsics and scale, given or not: the same scans
    assert key(intrinsics="525 525 319.5 239.6") != commas


def test_eval_smooth_depth_reaches_the_reader(depth_folder, tmp_path):
    """--smooth-depth scores the smoothed scans (refine's option, parsed by the same function): noisy walls score
    sharper smoothed (a plane is smoothed onto itself, so the fixture's exact walls get noise first)."""
    folder, est = depth_folder
    rng = np.random.default_rng(0)
    for png in sorted((folder / "depth").glob("*.png")):
        depth = np.asarray(Image.open(png), dtype=np.float64)
        noisy = np.clip(depth + rng.normal(0, 0.01 * 5000, depth.shape), 1, 65534)
        Image.fromarray(noisy.astype(np.uint16)).save(png)
    default = entropy(run("eval", "--scans", folder, "--est", est, "--json", tmp_path / "a.json"), tmp_path / "a.json")
    smoothed = entropy(run("eval", "--scans", folder, "--est", est, "--smooth-depth", "--json", tmp_path / "s.json"),
                       tmp_path / "s.json")
    assert smoothed < default - 0.1


def test_eval_labels(depth_folder, tmp_path):
    folder, est = depth_folder
    r = run("eval", "--scans", folder, "--est", est, "--est", est, "--label", "orb", "--label", "dm2",
            "--json", tmp_path / "l.json")
    assert r.exit_code == 0, r.output
    assert [e["label"] for e in json.loads((tmp_path / "l.json").read_text())["estimates"]] == ["orb", "dm2"]
    r = run("eval", "--scans", folder, "--est", est, "--est", est, "--label", "orb")
    assert r.exit_code == 2 and "--label" in r.output
    r = run("eval", "--scans", folder, "--est", est, "--est", est, "--label", "x", "--label", "x")
    assert r.exit_code == 2 and "labels must differ" in r.output
