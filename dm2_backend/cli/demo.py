"""``dm2 demo``: the whole pipeline on a built-in simulated sample, printing ATE before and after."""

from __future__ import annotations

import getpass
import tempfile
from pathlib import Path

import click


def default_folder() -> Path:
    """One demo folder per user in the temporary directory."""
    try:
        user = getpass.getuser()
    except (KeyError, OSError):  # no user name to be had (a container's numeric uid)
        user = "user"
    return Path(tempfile.gettempdir()) / f"dm2-demo-{user}"


@click.command("demo")
@click.option("--out", "-o", type=click.Path(path_type=Path), default=None,
              help="Folder for the sample and the run [default: dm2-demo-USER in the temporary folder, replaced by "
                   "the next demo].")
@click.option("--frames", type=int, default=300, show_default=True, help="Frames to simulate.")
@click.option("--epochs", type=click.IntRange(min=1), default=None,
              help="First-order epochs (default: the config; after the dense stage only with "
                   "optimiser.first_order: on)")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--force", is_flag=True, help="Write into a non-empty --out (a previous demo's files are replaced).")
@click.option("--quiet", "-q", is_flag=True)
def command(out: Path | None, frames: int, epochs: int | None, seed: int, force: bool, quiet: bool) -> None:
    """Simulate a drifting 2D laser sequence with two loops, refine it, and report ATE."""
    from dm2_backend import config
    from dm2_backend.cli.summary import print_summary
    from dm2_backend.formats import ReadOptions
    from dm2_backend.pipeline.inputs import load_inputs
    from dm2_backend.pipeline.refine import refine
    from dm2_backend.pipeline.run_folder import adopt_unrecorded, run_folder
    from dm2_backend.simulate.sequence import SimSettings, simulate, write_sequence

    root = out or default_folder()
    # the default folder is the demo's own: each demo replaces the last one's files (as --force) instead of
    # leaving another folder in the temporary directory, those of an earlier dm2's demo too
    if out is None:
        adopt_unrecorded(root, "demo")
    with run_folder(root, "demo", force=force or out is None):
        sample = root / "sample"
        click.echo(f"simulating {frames} planar laser frames (seed {seed}) into {sample}")
        scans, gt, warm = simulate(SimSettings(frames=frames, seed=seed, planar=True), progress=not quiet)
        write_sequence(sample, scans, gt, warm, 10.0)
        inputs = load_inputs(sample / "velodyne", None, sample / "warm_start.txt", "kitti",
                             ReadOptions(times=sample / "times.txt"), sample / "poses.txt", "kitti")
        overrides: dict = {"seed": seed}
        if epochs is not None:
            overrides["optimiser"] = {"epochs": epochs, "max_steps": 0}  # explicit epochs: no step cap
        cfg = config.load(None, overrides)
        click.echo(f"refining: dm2 refine --scans {sample / 'velodyne'} --poses {sample / 'warm_start.txt'} "
                   f"--gt {sample / 'poses.txt'} --out {root / 'run'}")
        report = refine(inputs, cfg, root / "run", cache_dir=None, progress=not quiet)
        print_summary(report, root / "run")
