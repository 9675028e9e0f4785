"""``dm2 refine``: refine a SLAM trajectory with DeepMapping2."""

from __future__ import annotations

import click

from dm2_backend.cli.run_setup import cluster_of, command_started, output_folder, path_type, prepare_run, run_options
from dm2_backend.cli.suggest import Choice
from dm2_backend.cli.summary import print_summary
from dm2_backend.runtime import cluster
from dm2_backend.runtime.errors import InputError


@click.command("refine")
@run_options
@click.option("--epochs", type=click.IntRange(min=1), default=None,
              help="First-order epochs (at least 1); they run after the dense stage only with "
                   "optimiser.first_order: on, or without it (optimiser.dense: false).")
@click.option("--device", type=Choice(["auto", "cpu", "cuda"]), default=None, help="Torch device.")
@click.option("--resume", is_flag=True, help="Continue an interrupted run in --out from its checkpoint.")
@click.option("--nproc", type=click.IntRange(min=1), default=None,
              help="Optimise in N processes (torch.distributed: gloo on CPU, NCCL with one GPU each) "
                   "[default: config nproc, 1]. Under torchrun its processes are the ranks.")
@click.option("--rerun", "rerun_path", type=path_type, default=None,
              help="Also write a Rerun recording of the run (needs rerun-sdk; see `dm2 view`).")
def command(epochs, device, resume, nproc, rerun_path, **kw) -> None:
    """Refine the poses of a scan sequence with DeepMapping2 and write a run folder."""
    from dm2_backend.pipeline.refine import refine

    overrides: dict = {}
    if epochs is not None:
        overrides["optimiser"] = {"epochs": epochs, "max_steps": 0}  # explicit epochs: no step cap
    if device is not None:
        overrides["device"] = device
    if nproc is not None:
        overrides["nproc"] = nproc
    spec = cluster_of(kw)
    inputs, cfg, cache = prepare_run(kw, overrides)
    check_device(cfg.device)
    if rerun_path is not None:
        from dm2_backend.cli.view import check_rerun, recording

        check_rerun()  # before the run, not after it
    with output_folder(kw, "refine", cfg, inputs, resume), cluster.engine(spec):
        report = refine(inputs, cfg, kw["out"], cache, resume=resume, progress=not kw["quiet"],
                        started=command_started())
    if report is not None:  # None: a torchrun rank other than 0
        print_summary(report, kw["out"])
        if rerun_path is not None:
            recording(kw["out"], rerun_path, inputs.scans, inputs.gt)
            click.echo(f"wrote {rerun_path}")


def check_device(device: str) -> None:
    """``cuda`` without a usable CUDA device is an input error before any work (not an assertion inside torch
    after the preparation)."""
    if device == "cuda":
        import torch

        if not torch.cuda.is_available():
            raise InputError(None, "--device cuda: no CUDA device is available to this torch build "
                                   f"(torch {torch.__version__}); use --device auto or cpu")
