"""Maps from runs through the CLI: ``refine`` and ``baseline`` write them, ``dm2 map RUN`` rebuilds them, and
``dm2 view RUN`` / ``refine --rerun`` write a Rerun recording (when rerun-sdk is installed)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from click.testing import CliRunner
from optim_cases import one_thread, planar_case, write_planar_sequence

from dm2_backend.cli.main import cli
from dm2_backend.maps import occupancy_grid, run_maps
from dm2_backend.optim import mnet_file

#: ``first_order``: the epochs after the dense stage, which train the M-Net
SMALL = {"seed": 3, "frames": {"max_points": 256},
         "optimiser": {"points_per_frame": 64, "bce_points_per_frame": 32, "batch_groups": 16,
                       "grid_max_cells": 2**14, "first_order": True}}


@pytest.fixture(autouse=True, scope="module")
def _single_thread():
    yield from one_thread()


def invoke(*args: str):
    result = CliRunner().invoke(cli, list(args), obj={})
    assert result.exit_code == 0, result.output + repr(result.exception)
    return result


@pytest.fixture(scope="module")
def seq(tmp_path_factory) -> Path:
    return write_planar_sequence(tmp_path_factory.mktemp("seq"), SMALL)


@pytest.fixture(scope="module")
def run(seq, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("runs") / "refine"
    invoke("refine", "--scans", str(seq / "velodyne"), "--poses", str(seq / "warm_start.txt"), "--gt",
           str(seq / "poses.txt"), "--out", str(out), "-c", str(seq / "config.yaml"), "--epochs", "1", "-q",
           "--no-cache")
    return out


def test_refine_writes_the_maps(run):
    report = json.loads((run / "report.json").read_text())
    assert {"map.pgm", "map.yaml", "mnet_map.pgm", "mnet_map.yaml", "maps.json"} <= set(report["files"])
    grid = occupancy_grid.read_map_server(run / "map.yaml")
    mnet = occupancy_grid.read_map_server(run / "mnet_map.yaml")
    assert grid.image.shape == mnet.image.shape and grid.origin == mnet.origin
    assert (grid.classes() == 1).sum() > 100 and (grid.classes() == 0).sum() > 1000
    # the refined scan end points fall on occupied cells (within one cell)
    poses = np.load(run / "poses.npy")
    case = planar_case()
    ends = np.concatenate([p[:, :2] @ T[:2, :2].T + T[:2, 3] for p, T in zip(case.scans[::6], poses[::6])])
    rows, cols = grid.pixel(ends)
    classes = grid.classes()
    h, w = classes.shape
    near = np.zeros(len(rows), bool)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            near |= classes[np.clip(rows + dr, 0, h - 1), np.clip(cols + dc, 0, w - 1)] == 1
    assert near.mean() > 0.9
    state = mnet_file.load_mnet(run / mnet_file.MNET)
    assert state.trained and state.dim == 2
    summary = run_maps.read_summary(run)
    assert summary["scans"]["source"] == str((Path(summary["scans"]["source"])).resolve())
    assert summary["frames_used"] == len(poses) and summary["skipped"] == {}


def test_dm2_map_rebuilds_them(run, seq):
    before = {name: (run / name).read_bytes() for name in ("map.pgm", "mnet_map.pgm")}
    for name in ("map.pgm", "map.yaml", "mnet_map.pgm", "mnet_map.yaml"):
        (run / name).unlink()
    result = invoke("map", str(run))  # the scans recorded in maps.json
    assert "wrote map.pgm, map.yaml, mnet_map.pgm, mnet_map.yaml, maps.json" in result.output
    assert "maps: map.pgm" in result.output  # a progress line per stage (stderr)
    assert {name: (run / name).read_bytes() for name in before} == before  # the same maps again
    invoke("map", str(run), "--scans", str(seq / "velodyne"), "-q")
    assert (run / "map.pgm").read_bytes() == before["map.pgm"]


def test_dm2_map_needs_scans(tmp_path, run):
    bare = tmp_path / "bare"
    bare.mkdir()
    np.save(bare / "poses.npy", np.load(run / "poses.npy"))
    result = CliRunner().invoke(cli, ["map", str(bare)], obj={})
    assert result.exit_code == 2 and "give --scans" in result.output


def test_baseline_writes_the_grid_only(seq, tmp_path):
    out = tmp_path / "icp"
    invoke("baseline", "icp", "--scans", str(seq / "velodyne"), "--poses", str(seq / "warm_start.txt"),
           "--out", str(out), "-c", str(seq / "config.yaml"), "-q", "--no-cache")
    report = json.loads((out / "report.json").read_text())
    assert {"map.pgm", "map.yaml", "maps.json"} <= set(report["files"])
    assert not (out / "mnet_map.pgm").exists()
    assert "dm2 refine" in run_maps.read_summary(out)["skipped"]["mnet"]


def rrd_entities(path: Path) -> set[str]:
    try:
        from rerun.chunk import RrdReader
    except ImportError:  # rerun-sdk before 0.32
        from rerun.dataframe import load_recording

        return {c.entity_path for c in load_recording(str(path)).schema().component_columns()}
    return {str(c.entity_path) for c in RrdReader(path).stream()}


def test_dm2_view_writes_a_recording(run, seq, tmp_path):
    pytest.importorskip("rerun", reason="Rerun recordings need rerun-sdk (pip install 'dm2[view]')")
    rrd = tmp_path / "run.rrd"
    result = invoke("view", str(run), "--out", str(rrd), "--gt", str(seq / "poses.txt"))
    assert rrd.exists() and "wrote" in result.output
    entities = rrd_entities(rrd)
    expected = {"/world/warm_start/path", "/world/refined/path", "/world/ground_truth/path", "/world/map",
                "/world/loop_closures/accepted", "/world/loop_closures/rejected", "/maps/grid", "/maps/mnet",
                "/world/mnet_map", "/world/refined/pose", "/world/warm_start/pose", "/world/scan",
                "/metrics/translation_error"}
    assert expected <= entities, expected - entities


def test_missing_rerun_is_one_line(run, tmp_path, monkeypatch):
    import builtins

    real = builtins.__import__

    def no_rerun(name, *args, **kw):
        if name == "rerun" or name.startswith("rerun."):
            raise ImportError("No module named 'rerun'")
        return real(name, *args, **kw)

    monkeypatch.setattr(builtins, "__import__", no_rerun)
    result = CliRunner().invoke(cli, ["view", str(run), "--out", str(tmp_path / "x.rrd")], obj={})
    assert result.exit_code == 2 and "pip install 'dm2[view]'" in result.output


def test_a_refine_without_epochs_makes_no_mnet_map(seq, tmp_path):
    """By default the dense stage ends a planar refine and no epoch trains the M-Net: its map is not made, and
    ``maps.json`` says why."""
    cfg = tmp_path / "config.yaml"
    cfg.write_text(yaml.safe_dump({**SMALL, "optimiser": {**SMALL["optimiser"], "first_order": None}}))
    out = tmp_path / "refine"
    invoke("refine", "--scans", str(seq / "velodyne"), "--poses", str(seq / "warm_start.txt"), "--out", str(out),
           "-c", str(cfg), "-q", "--no-cache")
    assert (out / "map.pgm").exists() and not (out / "mnet_map.pgm").exists()
    assert "no first-order epoch" in run_maps.read_summary(out)["skipped"]["mnet"]
