"""Helpers shared by the format tests: the real-data folder, skipping when it is absent, and CLI checks."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from dm2_backend.cli.main import cli

#: the smallest settings a refine in a test runs with (few points, a small occupancy grid; the dense stage on)
SMALL_RUN = {"frames": {"max_points": 256},
             "optimiser": {"points_per_frame": 64, "bce_points_per_frame": 32, "batch_groups": 16,
                           "grid_max_cells": 2**14}}

#: ../shared/data relative to the repository root
DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def need(path: Path) -> Path:
    """``path``, or skip the test with the reason when the shared data is absent."""
    if not path.exists():
        pytest.skip(f"{path} absent")
    return path


def run(*args):
    """Invoke ``dm2`` in-process (each argument as its text)."""
    return CliRunner().invoke(cli, [str(a) for a in args], obj={})


def one_line_error(result, *needles: str) -> None:
    """Exit code 2, one line of output without a traceback, holding every one of ``needles``."""
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.strip().splitlines() if line]
    assert len(lines) == 1 and "Traceback" not in result.output, result.output
    for needle in needles:
        assert needle in lines[0], lines[0]


def gtsam_direct(path: Path, is3d: bool, options):
    """gtsam.readG2o + a prior on node 0 (``options``' sigma) + Levenberg-Marquardt, nothing from dm2: the
    final error and the values."""
    import gtsam
    import numpy as np

    graph, initial = gtsam.readG2o(str(path), is3d)
    if is3d:
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.full(6, options.prior_sigma))
        graph.add(gtsam.PriorFactorPose3(0, initial.atPose3(0), noise))
    else:
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.full(3, options.prior_sigma))
        graph.add(gtsam.PriorFactorPose2(0, initial.atPose2(0), noise))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(options.max_iterations)
    params.setRelativeErrorTol(options.relative_error_tol)
    result = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
    return graph.error(result), result


def assert_one_line_error(result, name: str) -> None:
    """Exit code 2 and a single stderr line naming ``name``."""
    assert result.exit_code == 2, result.output
    err = result.stderr.strip()
    assert "\n" not in err and name in err, err
