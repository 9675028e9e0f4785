"""``dm2 eval``: APE/RPE (through evo), the paper ATE and the Freiburg relations metric of estimates."""

from __future__ import annotations

from pathlib import Path

import click

from dm2_backend.cli.options import (
    depth_scale_option,
    duplicate_times_option,
    intrinsics_option,
    read_options,
    smooth_depth_option,
)
from dm2_backend.cli.suggest import Choice
from dm2_backend.evaluation.ape_rpe import ALIGN_MODES, DELTA_UNITS
from dm2_backend.evaluation.consistency_profile import (
    PROFILE_FILES,
)
from dm2_backend.evaluation.evaluate import EvalOptions
from dm2_backend.evaluation.relations import MAX_DT
from dm2_backend.evaluation.report import terminal_text
from dm2_backend.evaluation.report_writers import write_csv, write_evo_results, write_json, write_markdown
from dm2_backend.evaluation.request import (
    Estimate,
    EvalRequest,
    evaluate_request,
    write_evaluation_profiles,
    write_plots,
)
from dm2_backend.formats import ReadOptions
from dm2_backend.pipeline.inputs import looks_planar
from dm2_backend.runtime.errors import InputError

path_type = click.Path(path_type=Path)


def _topics(given: tuple[str, ...], estimates: int) -> list[str | None]:
    """The bag topic of each estimate: none, one for all, or one per estimate in order."""
    if len(given) > 1 and len(given) != estimates:
        raise click.UsageError(f"{len(given)} --est-topic for {estimates} estimates: give one for all, or one per "
                               "--est, in order")
    return list(given) if len(given) > 1 else [given[0] if given else None] * estimates


def _labels(paths: tuple[Path, ...], given: tuple[str, ...] = (), topics: list[str | None] | None = None
            ) -> list[str]:
    """One label per estimate: ``--label`` in order, else the file name (with its topic where the estimates'
    topics differ; made unique with ``#k``)."""
    if given:
        if len(given) != len(paths):
            raise click.UsageError(f"{len(given)} --label for {len(paths)} estimates: give one per estimate, in order")
        if len(set(given)) != len(given):
            raise click.BadParameter("labels must differ", param_hint="--label")
        return list(given)
    labels: list[str] = []
    for p in paths:
        name = p.name
        for suffix in (".gz", ".bz2", ".xz", ".zip"):
            name = name.removesuffix(suffix)
        label = (Path(name).stem if p.is_file() else name) or str(p)
        if topics and len(set(topics)) > 1:
            label = f"{label}:{topics[len(labels)]}"
        while label in labels:
            label = f"{label}#{len(labels) + 1}"
        labels.append(label)
    return labels


def _check_delta(delta: float, unit: str) -> None:
    if delta <= 0:
        raise click.BadParameter("must be positive", param_hint="--delta")
    if unit == "f" and not float(delta).is_integer():
        raise click.BadParameter("must be a whole number of frames with --delta-unit f", param_hint="--delta")


def _free_profile_folder(folder: Path) -> None:
    """``--profile`` is a folder (made when missing) that holds none of the files it gets: nothing of the user's
    is replaced."""
    if folder.exists() and not folder.is_dir():
        raise InputError(folder, "--profile names a folder, and this is a file: give a folder")
    taken = [name for name in PROFILE_FILES if (folder / name).exists() or (folder / name).is_symlink()]
    if taken:
        raise InputError(folder / taken[0], "exists: --profile does not replace files; remove them or give another "
                                            "folder")


#: the alignment line printed above the table
ALIGN_TEXT = {"se3": "SE(3) Umeyama, no scale (evo -a; dm2's default)", "sim3": "Sim(3) Umeyama (evo -as)",
              "none": "none (evo's default)"}

def _positional(files: tuple[Path, ...], gt_path: Path | None, est_paths: tuple[Path, ...]
                ) -> tuple[Path | None, tuple[Path, ...]]:
    """``dm2 eval GT EST...`` as ``evo_ape tum GT EST``: the first file is the ground truth unless --gt is
    given, the others estimates (with any --est)."""
    files = tuple(files)
    if files and gt_path is None:
        gt_path, files = files[0], files[1:]
    est_paths = tuple(est_paths) + files
    if not est_paths:
        raise click.UsageError("give the estimates: dm2 eval GT EST [EST...] or --est EST")
    return gt_path, est_paths


def _alignment(align: str | None, align_flag: bool, scale_flag: bool, align_origin: bool) -> str:
    if scale_flag and not align_flag:
        raise click.UsageError("-s corrects the scale of an alignment: give -as (scale-only alignment is not "
                               "supported)")
    if align_flag:
        flag = "sim3" if scale_flag else "se3"
        if align not in (None, flag):
            raise click.UsageError(f"-a{'s' if scale_flag else ''} contradicts --align {align}")
        align = flag
    if align_origin and align not in (None, "none"):
        raise click.UsageError("--align-origin excludes --align se3/sim3 (as in evo)")
    return align or ("none" if align_origin else "se3")


@click.command("eval")
@click.argument("files", nargs=-1, type=path_type)
@click.option("--gt", "gt_path", type=path_type, default=None, help="Ground-truth trajectory.")
@click.option("--est", "est_paths", type=path_type, multiple=True,
              help="Estimated trajectory (repeat for several).")
@click.option("--gt-format", default=None, help="Format of --gt (detected when unambiguous).")
@click.option("--est-format", default=None, help="Format of every --est (detected when unambiguous).")
@click.option("--gt-topic", default=None, help="Bag topic of the ground truth.")
@click.option("--est-topic", "est_topics", multiple=True,
              help="Bag topic of the estimates: one for every --est, or one per --est in order.")
@click.option("--gt-times", type=path_type, default=None, help="KITTI times.txt for --gt.")
@click.option("--est-times", type=path_type, default=None, help="KITTI times.txt for --est.")
@click.option("--scans", "scans_path", type=path_type, default=None,
              help="Scan source: adds the map entropy and plane variance of the scans at each estimate "
                   "(no ground truth needed).")
@click.option("--scans-format", default=None, help="Format of --scans (detected otherwise).")
@click.option("--scans-topic", default=None, help="Bag topic of --scans.")
@click.option("--scans-times", type=path_type, default=None, help="KITTI times.txt for --scans.")
@intrinsics_option
@depth_scale_option
@smooth_depth_option
@click.option("--profile", "profile_dir", type=path_type, default=None,
              help="With --scans: write each estimate's consistency profile into this folder (consistency.json, "
                   ".csv, .png): per frame, how far its points lie from the planes the other frames make, and "
                   "the stretches that stand out (no ground truth needed).")
@click.option("--relations", "relations_path", type=path_type, default=None,
              help="Freiburg .relations file (t1 t2 x y z roll pitch yaw); --gt may then be omitted.")
@click.option("--relations-max-dt", type=float, default=MAX_DT, show_default=True,
              help="Max. seconds between a relation stamp and the nearest estimated pose.")
@click.option("--align", type=Choice(ALIGN_MODES), default=None,
              help="Alignment onto the ground truth [default: se3; none with --align-origin].")
@click.option("--align-origin", is_flag=True, help="Align the first poses only (evo's --align_origin).")
@click.option("-a", "align_flag", is_flag=True, help="SE(3) Umeyama alignment, as evo's -a (= --align se3).")
@click.option("-s", "scale_flag", is_flag=True, help="With -a: also correct the scale, as evo's -as (= --align sim3).")
@click.option("--max-diff", type=float, default=0.01, show_default=True,
              help="Max. seconds between associated stamps (association by index when a file has none).")
@click.option("--by-index", is_flag=True,
              help="Pair the poses in order (the first min(N, M)), whatever their stamps and counts.")
@click.option("--label", "labels", multiple=True,
              help="Name of each estimate in the table and outputs (repeat, in the order of the estimates).")
@click.option("--delta", type=float, default=1.0, show_default=True, help="RPE pair distance.")
@click.option("--delta-unit", type=Choice(list(DELTA_UNITS)), default="f", show_default=True,
              help="RPE delta unit: f frames, m metres.")
@click.option("--json", "json_path", type=path_type, default=None, help="Write the results as JSON.")
@click.option("--csv", "csv_path", type=path_type, default=None, help="Write the table as CSV.")
@click.option("--markdown", "md_path", type=path_type, default=None, help="Write the table as Markdown.")
@click.option("--plot", "plot_dir", type=path_type, default=None, help="Write plots (PNG) into this folder.")
@click.option("--run-report", type=path_type, default=None,
              help="A refine run's report.json (or its folder): adds an error-vs-epoch plot to --plot.")
@click.option("--save-evo", "evo_dir", type=path_type, default=None,
              help="Write evo result archives (.zip, readable by evo_res) into this folder.")
@duplicate_times_option
def command(files, gt_path, est_paths, gt_format, est_format, gt_topic, est_topics, gt_times, est_times,
            scans_path, scans_format, scans_topic, scans_times, intrinsics, depth_scale, smooth_depth, profile_dir,
            relations_path, relations_max_dt, align, align_origin, align_flag, scale_flag, max_diff, by_index, labels,
            delta, delta_unit, json_path, csv_path, md_path, plot_dir, run_report, evo_dir, duplicate_times) -> None:
    """Evaluate one or more estimated trajectories against a ground truth, relations and/or the map they make.

    APE and RPE (translation m, rotation deg) are computed with evo and equal evo_ape / evo_rpe;
    "paper ATE" is the DeepMapping2 paper's own definition; --relations adds the Freiburg relations metric;
    --scans the mean map entropy and plane variance (lower = sharper) of the scans at each estimate.
    """
    gt_path, est_paths = _positional(files, gt_path, est_paths)
    if gt_path is None and relations_path is None and scans_path is None:
        raise click.UsageError("give --gt, --relations, --scans or several")
    align = _alignment(align, align_flag, scale_flag, align_origin)
    _check_delta(delta, delta_unit)
    if max_diff < 0:
        raise click.BadParameter("must not be negative", param_hint="--max-diff")
    if relations_max_dt < 0:
        raise click.BadParameter("must not be negative", param_hint="--relations-max-dt")
    if profile_dir is not None and scans_path is None:
        raise click.UsageError("--profile scores the scans at each estimate: give --scans too")
    if profile_dir is not None:
        _free_profile_folder(profile_dir)
    if run_report is not None and plot_dir is None:
        raise click.UsageError("--run-report is used for the error-vs-epoch plot: give --plot DIR too")
    topics = _topics(est_topics, len(est_paths))
    est_labels = _labels(est_paths, labels, topics)
    # the scans are read as refine reads them (the same options, parsed by the same function)
    scan_options = read_options(scans_topic, scans_times, None, intrinsics, depth_scale, duplicate_times, smooth_depth)

    options = EvalOptions(align=align, align_origin=align_origin, max_diff=max_diff, by_index=by_index,
                          delta=delta, delta_unit=delta_unit, relations_max_dt=relations_max_dt)
    estimates = tuple(Estimate(path, label, ReadOptions(topic=topic, times=est_times, duplicate_times=duplicate_times),
                               est_format) for path, label, topic in zip(est_paths, est_labels, topics, strict=True))
    request = EvalRequest(estimates, options, gt_path, gt_format,
                          ReadOptions(topic=gt_topic, times=gt_times, duplicate_times=duplicate_times),
                          relations_path, scans_path, scans_format, scan_options, profile=profile_dir is not None)
    evaluation = evaluate_request(request)
    report = evaluation.report
    click.echo(f"alignment: {ALIGN_TEXT[align] if not align_origin else 'first poses only (--align-origin)'}")
    click.echo(terminal_text(report))
    written = []
    if json_path:
        write_json(report, json_path)
        written.append(json_path)
    if csv_path:
        write_csv(report, csv_path)
        written.append(csv_path)
    if md_path:
        write_markdown(report, md_path)
        written.append(md_path)
    if plot_dir:
        plotted, note = write_plots(plot_dir, evaluation, run_report)
        if note:
            click.echo(note, err=True)
        written += plotted
    if evo_dir:
        written += write_evo_results(report, evo_dir)
    if profile_dir:
        profiled, lines = write_evaluation_profiles(profile_dir, evaluation, looks_planar(evaluation.scans, None))
        for line in lines:
            click.echo(line)
        written += profiled
    for p in written:
        click.echo(f"wrote {p}")
