"""A scan sequence knows its sensor kind because its reader (or what it read) says so; the place recognition's
``auto`` choice follows it, not a key of ``meta``."""

from __future__ import annotations

import numpy as np
from optim_cases import planar_case
from shared_helpers import DATA, need

from dm2_backend.config.schema import PluginSection
from dm2_backend.formats import ReadOptions, open_scans
from dm2_backend.kernel.scans import DEPTH_CAMERA, LASER_2D, LIDAR, SensorKind
from dm2_backend.pipeline.inputs import load_inputs
from dm2_backend.prepare.steps import resolve_auto
from dm2_backend.simulate.sequence import write_sequence


def test_a_lidar_folder_and_a_planar_one(tmp_path):
    case = planar_case(frames=10)
    write_sequence(tmp_path, case.scans, case.gt, case.warm, 10.0)
    lifted = tmp_path / "lifted"
    lifted.mkdir()
    for i, scan in enumerate(case.scans):  # the same scans with height: a 3D scanner
        pts = np.c_[scan[:, :2], np.linspace(-1, 1, len(scan))].astype(np.float32)
        np.c_[pts, np.zeros(len(pts), np.float32)].tofile(lifted / f"{i:06d}.bin")
    assert open_scans(lifted).sensor is None and open_scans(tmp_path / "velodyne").sensor is None  # a folder
    # cannot tell; the scans' geometry decides, once: in z = 0 a 2D laser, with height a LiDAR
    inputs = load_inputs(tmp_path / "velodyne", None, tmp_path / "warm_start.txt", "kitti", ReadOptions())
    assert inputs.scans.planar and inputs.scans.sensor is SensorKind.LASER_2D
    inputs = load_inputs(lifted, None, tmp_path / "warm_start.txt", "kitti", ReadOptions())
    assert not inputs.scans.planar and inputs.scans.sensor is SensorKind.LIDAR


def test_every_source_that_knows_its_sensor_declares_it():
    from dm2_backend.formats.registry import SCAN_SOURCES

    declared = {name: src.sensor for name, src in SCAN_SOURCES.items()}
    assert declared["carmen"] is LASER_2D and declared["depth"] is DEPTH_CAMERA
    assert declared["kitti-raw"] is declared["nclt"] is LIDAR
    assert declared["folder"] is declared["bag"] is None  # either kind: decided from the scans


def test_carmen_is_a_2d_laser():
    assert open_scans(need(DATA / "carmen" / "intel.clf.bz2")).sensor == LASER_2D


def test_a_depth_sequence_is_a_depth_camera_and_auto_picks_loops3d():
    folder = need(DATA / "depth3d" / "redkitchen_000-499")
    scans = open_scans(folder)
    assert scans.sensor == DEPTH_CAMERA and scans.subset(np.arange(3)).sensor == DEPTH_CAMERA
    assert resolve_auto(PluginSection(name="auto"), scans.sensor == DEPTH_CAMERA).name == "loops3d"
