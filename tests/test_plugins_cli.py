"""``dm2 plugins``: every registered plugin listed, and what is not installed marked with its install hint."""

from __future__ import annotations

import importlib.util

from click.testing import CliRunner

from dm2_backend.cli import plugins as plugins_cli
from dm2_backend.cli.main import cli


def test_lists_every_group_and_marks_missing_packages(monkeypatch):
    real = importlib.util.find_spec
    missing = {"kiss_icp", "small_gicp", "rerun"}
    monkeypatch.setattr(plugins_cli.importlib.util, "find_spec",
                        lambda name, *a: None if name in missing else real(name, *a))
    out = CliRunner().invoke(cli, ["plugins"]).output
    lines = {line.split()[0]: line for line in out.splitlines() if line.startswith("    ")}
    assert "not installed: pip install 'dm2[kiss]'" in lines["kiss-icp"]
    assert "not installed: pip install 'dm2[gicp]'" in lines["small-gicp"]
    assert "not installed" not in lines["icp"] and "not installed" not in lines["loops"]
    assert "dm2 view / refine --rerun    not installed: pip install 'dm2[view]'" in out
    for group in ("dm2.warm_start", "dm2.place_recognition", "dm2.registration"):
        assert group in out
