"""Formats from other packages: a module named by a ``dm2.formats`` entry point registers its format when dm2
loads add-ons, and is then detected and read like a built-in one; a broken add-on is logged, not fatal."""

from __future__ import annotations

import importlib.metadata
import logging

import numpy as np

from dm2_backend.formats import TRAJECTORY_FORMATS, read_trajectory, registry

ADDON = '''
import numpy as np
from dm2_backend.formats.registry import TrajectoryFormat, trajectory_format
from dm2_backend.kernel.trajectory import Trajectory


def read(path, options):
    xs = np.loadtxt(path, ndmin=1)
    poses = np.tile(np.eye(4), (len(xs), 1, 1))
    poses[:, 0, 3] = xs
    return Trajectory(poses)


trajectory_format(TrajectoryFormat("xonly", "x positions, one a line", read, suffixes=(".xonly",)))
'''


def test_an_entry_point_adds_a_format_and_a_broken_one_is_skipped(monkeypatch, tmp_path, caplog):
    (tmp_path / "dm2_test_addon.py").write_text(ADDON)
    monkeypatch.syspath_prepend(str(tmp_path))
    eps = [importlib.metadata.EntryPoint("xonly", "dm2_test_addon", registry.FORMAT_GROUP),
           importlib.metadata.EntryPoint("broken", "dm2_no_such_module", registry.FORMAT_GROUP)]
    monkeypatch.setattr(importlib.metadata, "entry_points", lambda group=None: [e for e in eps if e.group == group])
    try:
        with caplog.at_level(logging.WARNING):
            assert registry.load_third_party() == ["xonly"]
        assert "broken" in caplog.text and "not loaded" in caplog.text
        path = tmp_path / "walk.xonly"
        path.write_text("0\n1.5\n3\n")
        traj = read_trajectory(path)
        assert traj.meta["format"] == "xonly"
        np.testing.assert_allclose(traj.positions[:, 0], [0, 1.5, 3])
    finally:
        TRAJECTORY_FORMATS.pop("xonly", None)
