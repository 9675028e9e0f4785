"""Helpers shared by the format tests: the real-data folder, skipping when it is absent, and CLI checks."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from dm2_backend.cli.main import cli

#: ../shared/data relative to the repository root
DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def need(path: Path) -> Path:
    """``path``, or skip the test with the reason when the shared data is absent."""
    if not path.exists():
        pytest.skip(f"{path} absent")
    return path


def run(*args: str):
    """Invoke ``dm2`` in-process."""
    return CliRunner().invoke(cli, list(args), obj={})


def assert_one_line_error(result, name: str) -> None:
    """Exit code 2 and a single stderr line naming ``name``."""
    assert result.exit_code == 2, result.output
    err = result.stderr.strip()
    assert "\n" not in err and name in err, err
