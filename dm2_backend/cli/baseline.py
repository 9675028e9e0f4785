"""``dm2 baseline``: classical back-ends on the same inputs and preparation as ``dm2 refine``."""

from __future__ import annotations

from pathlib import Path

import click

from dm2_backend.baselines.methods import GRAPH_METHODS, METHODS
from dm2_backend.cli.run_setup import cluster_of, command_started, output_folder, prepare_run, run_options
from dm2_backend.cli.suggest import Choice
from dm2_backend.cli.summary import print_summary
from dm2_backend.formats.g2o import INFORMATION_MODES
from dm2_backend.kernel.solver_options import KERNELS, SolverOptions
from dm2_backend.pipeline.run_folder import refuse_overlap, run_folder
from dm2_backend.runtime import cluster

path_type = click.Path(path_type=Path)
_HELP = "\n".join(f"  {name:<9} {text}" for name, text in METHODS.items())


#: options of a run from scans that mean nothing for an existing graph (refused, not ignored, with --graph)
SCAN_ONLY = ("poses", "scans_format", "poses_format", "config_path", "relations", "warm_start",
             "place_recognition", "registration", "topic", "times", "calib", "intrinsics", "depth_scale",
             "smooth_depth")


def check_graph_options(kw: dict) -> None:
    given = [name for name in SCAN_ONLY if kw.get(name)]
    if given:
        names = ", ".join("--" + ("config" if n == "config_path" else n.replace("_", "-")) for n in given)
        raise click.UsageError(f"{names}: not used with --graph (the graph file is the whole input)")


def read_graph_gt(kw: dict):
    """--gt for --graph: the ground truth of the graph's vertices, one pose per vertex in id order."""
    if kw["gt"] is None:
        return None
    from dm2_backend.cli.options import read_options
    from dm2_backend.formats import read_trajectory

    return read_trajectory(kw["gt"], kw["gt_format"], read_options(duplicate_times=kw["duplicate_times"]))



@click.command("baseline", help=f"""Run a baseline back-end METHOD and write a run folder like refine's.

\b
{_HELP}

\b
With --graph FILE.g2o (gtsam, g2o) an existing pose graph is optimised instead of scans.""")
@click.argument("method", type=Choice(list(METHODS)))
@run_options(scans_required=False)
@click.option("--graph", "graph_path", type=path_type, default=None,
              help="Optimise this g2o pose graph (no scans needed).")
@click.option("--information", type=Choice(INFORMATION_MODES), default="file", show_default=True,
              help="With --graph: information matrices that are not positive semi-definite are optimised as the "
                   "file writes them (g2o; gtsam: weighed as gtsam.readG2o weighs them, with a warning), or read as "
                   "the nearest positive-definite ones.")
@click.option("--robust", type=Choice([*KERNELS, "none"]), default=None,
              help="Robust kernel on every edge [default: cauchy for graphs built from scans (registrations "
                   "have outliers), none for --graph].")
@click.option("--robust-k", type=float, default=None, help="Kernel threshold (whitened residual).")
@click.option("--max-iterations", type=int, default=100, show_default=True)
@click.option("--relative-tol", type=float, default=1e-5, show_default=True,
              help="Stop when the error decreases by less than this fraction.")
def command(method, graph_path, information, robust, robust_k, max_iterations, relative_tol, **kw) -> None:
    if robust is None:
        robust = "none" if graph_path is not None else "cauchy"
    robust = None if robust == "none" else robust
    options = SolverOptions(max_iterations=max_iterations, relative_error_tol=relative_tol, robust=robust,
                            robust_k=robust_k)
    options.check()
    if graph_path is not None:
        from dm2_backend.pipeline.baseline import optimise_file

        if method not in GRAPH_METHODS:
            raise click.UsageError(f"--graph works with {' and '.join(GRAPH_METHODS)}, not {method}")
        if kw["scans"] is not None:
            raise click.UsageError("give either --graph or --scans")
        check_graph_options(kw)
        refuse_overlap(kw["out"], {"--graph": graph_path, "--gt": kw["gt"], "--config": kw.get("config_path")})
        gt = read_graph_gt(kw)
        with run_folder(kw["out"], "baseline", force=kw["force"]):
            report = optimise_file(method, graph_path, kw["out"], options, gt=gt, started=command_started(),
                                   information=information)
        r = report
        click.echo(f"{r['nodes']} nodes, {r['edges']} edges: error {r['initial_error']:.6g} -> "
                   f"{r['final_error']:.6g} in {r['iterations']} iterations, "
                   f"{r['timings']['optimise']:.2f} s")
        for key, value in r.get("metrics", {}).items():
            click.echo(f"{key:<28} graph {r['initial_metrics'][key]:10.4f}  ->  {method} {value:10.4f}")
        for text in r.get("cautions", []):
            click.echo(f"caution: {text}")
        click.echo(f"wrote {kw['out']}")
        return
    if kw["scans"] is None:
        raise click.UsageError("Missing option '--scans' / '-s' (or --graph).")
    from dm2_backend.pipeline.baseline import baseline

    overrides: dict = {}
    if method == "icp" and not kw["warm_start"]:
        overrides["warm_start"] = {"name": "icp"}
    spec = cluster_of(kw)
    inputs, cfg, cache = prepare_run(kw, overrides)
    with output_folder(kw, "baseline", cfg, inputs), cluster.engine(spec):
        report = baseline(method, inputs, cfg, kw["out"], cache, options, progress=not kw["quiet"],
                          started=command_started())
    print_summary(report, kw["out"])
