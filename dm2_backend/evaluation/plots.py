"""Evaluation plots (matplotlib, Agg canvas, no pyplot state), each written atomically.

- trajectories overlaid, top view and (for 3D data) side view;
- per-frame errors coloured along the estimate (heat map);
- error versus epoch from a refine run's ``report.json`` ``epochs`` list;
- the place recognition's closures and loop edges over the trajectory (``topology.png``).

One orientation in every plot, so that plots of one run can be laid side by side: the top view looks along
the axis in which the trajectory extends least (z for LiDAR/world data, y for camera-frame KITTI) and draws
the other two in their index order, the lower one to the right and the higher one up (x right, y up; or x
right, z up), never mirrored, with equal scales on both axes. The side view draws the longer of the two
top-view axes to the right and the least-extended axis up; data that stays in a plane gets no side view.

Each ``plot_*`` function writes a file and returns its path; the ``*_figure`` function of the same plot
returns the :class:`~matplotlib.figure.Figure` it draws (tests read axis labels, limits and data from it).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.patches import Patch
from matplotlib.ticker import MaxNLocator

from dm2_backend.runtime.atomic import atomic_write

AXES = "xyz"
#: an axis whose extent is below this fraction of the largest extent (or 1 um) counts as flat: no side view
FLAT = 1e-6

#: the per-epoch metrics a refine run records (``epochs[i]["ate_metric"]``), named and with units as
#: ``dm2 eval`` and ``report.json``'s metrics name them
EPOCH_METRICS = {
    "ape_trans_rmse_m": "APE trans RMSE, SE(3)-aligned [m]",
    "relations_trans_mean_m": "relations trans mean [m]",
}
#: label of an epoch record without ``ate_metric`` (runs written before it was recorded)
UNNAMED_METRIC = "accuracy (metric not recorded)"


def save(fig: Figure, path: str | Path) -> Path:
    """Write ``fig`` to ``path`` (format from the suffix, atomically)."""
    path = Path(path)
    FigureCanvasAgg(fig)
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format=path.suffix.lstrip(".") or "png", dpi=120, bbox_inches="tight")
    return path


def view_axes(positions: np.ndarray) -> tuple[tuple[int, int], tuple[int, int] | None]:
    """Index pairs (horizontal, vertical) of the top view and of the side view (None for flat data).

    Top view: the two axes other than the least-extended one, in index order (x right and y up when z is
    the flat axis). Side view: the longer of those two right, the least-extended axis up."""
    extent = np.ptp(np.asarray(positions, dtype=np.float64).reshape(-1, 3), axis=0) if len(positions) else np.zeros(3)
    normal = 2 - int(np.argmin(extent[::-1]))  # on a tie z, then y: x right and y up where it can be
    h, v = (a for a in range(3) if a != normal)
    side_h = h if extent[h] >= extent[v] else v
    flat = extent[normal] <= FLAT * max(float(extent.max()), 1.0)
    return (h, v), (None if flat else (side_h, normal))


def _setup(ax, axes: tuple[int, int], title: str) -> None:
    ax.set_xlabel(f"{AXES[axes[0]]} [m]")
    ax.set_ylabel(f"{AXES[axes[1]]} [m]")
    ax.set_title(title)
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)


def trajectory_figure(gt: np.ndarray | None, estimates: dict[str, np.ndarray], title: str = "") -> Figure:
    """Ground-truth (dashed grey) and estimated positions (N,3): a top view and, for 3D data, a side view.
    ``title`` (e.g. how the estimates were aligned) heads the figure."""
    basis = gt if gt is not None else np.concatenate([np.asarray(p).reshape(-1, 3) for p in estimates.values()])
    top, side = view_axes(basis)
    views = [(top, "top view")] + ([(side, "side view")] if side is not None else [])
    fig = Figure(figsize=(6.5 * len(views), 6), layout="constrained")  # room for a title of several lines
    for k, (axes, name) in enumerate(views):
        ax = fig.add_subplot(1, len(views), k + 1)
        if gt is not None:
            ax.plot(gt[:, axes[0]], gt[:, axes[1]], "--", color="0.4", lw=1.2, label="ground truth")
        for label, p in estimates.items():
            ax.plot(p[:, axes[0]], p[:, axes[1]], lw=1.0, label=label)
        _setup(ax, axes, name)
        ax.legend(loc="best", fontsize=8)
    if title:
        fig.suptitle(title)
    return fig


def plot_trajectories(path: str | Path, gt: np.ndarray | None, estimates: dict[str, np.ndarray],
                      title: str = "") -> Path:
    """:func:`trajectory_figure`, written to ``path``."""
    return save(trajectory_figure(gt, estimates, title), path)


def error_map_figure(label: str, positions: np.ndarray, errors: dict[str, tuple[np.ndarray, str]],
                     gt: np.ndarray | None = None, title: str = "") -> Figure:
    """Per-frame errors (name -> (values, unit)) coloured along the top view of ``positions``; ``gt``
    (drawn dashed) must be in the same frame as ``positions`` (e.g. the estimate after its alignment)."""
    top, _ = view_axes(gt if gt is not None else positions)
    fig = Figure(figsize=(6.5 * len(errors), 6), layout="constrained")
    for i, (name, (values, unit)) in enumerate(errors.items()):
        ax = fig.add_subplot(1, len(errors), i + 1)
        if gt is not None:
            ax.plot(gt[:, top[0]], gt[:, top[1]], "--", color="0.6", lw=0.8, label="ground truth")
        size = float(np.clip(4000.0 / max(len(values), 1), 4, 30))
        x, y = positions[:, top[0]], positions[:, top[1]]
        sc = ax.scatter(x, y, c=values, s=size, cmap="jet", linewidths=0, label=label)
        fig.colorbar(sc, ax=ax, label=f"{name} [{unit}]")
        _setup(ax, top, f"{label}: {name}")
        if gt is not None:
            ax.legend(loc="best", fontsize=8)
    if title:
        fig.suptitle(title)
    return fig


def plot_error_map(
    path: str | Path, label: str, positions: np.ndarray, errors: dict[str, tuple[np.ndarray, str]],
    gt: np.ndarray | None = None, title: str = "",
) -> Path:
    """:func:`error_map_figure`, written to ``path``."""
    return save(error_map_figure(label, positions, errors, gt, title), path)


def epoch_series(epochs: list) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``name -> (epochs trained, value)`` from a run report's ``epochs``; entries without ``ate`` are skipped.

    A record's ``epoch`` counts from 0 (the first epoch trained), so it is plotted at ``epoch + 1``: x is the
    number of epochs trained and 0 is the start. ``name`` is the record's ``ate_metric`` (see
    :data:`EPOCH_METRICS`) or, for an ``ate`` dict, its keys."""
    series: dict[str, tuple[list, list]] = {}
    for i, entry in enumerate(epochs):
        if not isinstance(entry, dict) or "ate" not in entry:
            continue
        ep = entry.get("epoch", i)
        if not isinstance(ep, (int, float)) or isinstance(ep, bool):
            ep = i
        ate = entry["ate"]
        values = ate if isinstance(ate, dict) else {str(entry.get("ate_metric") or "ate"): ate}
        for name, v in values.items():
            if isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v):
                xs, ys = series.setdefault(name, ([], []))
                xs.append(ep + 1)
                ys.append(float(v))
    return {k: (np.asarray(x, dtype=float), np.asarray(y)) for k, (x, y) in series.items()}


def metric_label(name: str) -> str:
    """The axis label of a per-epoch metric (its ``dm2 eval`` name and unit)."""
    if name in EPOCH_METRICS:
        return EPOCH_METRICS[name]
    return UNNAMED_METRIC if name == "ate" else name


def epochs_figure(epochs: list, start: float | dict[str, float] | None = None,
                  returned: int | None = None) -> Figure | None:
    """Error versus epochs trained, the start (``start``: its value, or name -> value) at epoch 0; None when
    no epoch has an ``ate`` entry. The y-axis starts at 0, so a small change looks small; the relative
    change from the start (or the first epoch) to the epoch whose poses the run returned (``returned``: the
    report's ``best_epoch``, counted from 0, -1 the start itself; None: the last epoch) is written on the
    plot, and that epoch is marked."""
    series = epoch_series(epochs)
    if not series:
        return None
    fig = Figure(figsize=(7.5, 4.8))
    ax = fig.add_subplot(1, 1, 1)
    notes, top = [], 0.0
    for name, (x, y) in series.items():
        s = start.get(name) if isinstance(start, dict) else (start if len(series) == 1 else None)
        if s is not None and np.isfinite(s):
            x, y = np.concatenate([[0.0], x]), np.concatenate([[float(s)], y])
        line, = ax.plot(x, y, marker="o", ms=3, label=metric_label(name))
        if x[0] == 0:
            ax.plot([0.0], [y[0]], "s", ms=7, color=line.get_color(), label="start")
        first = "start" if x[0] == 0 else f"epoch {x[0]:.0f}"
        k = _returned_index(x, returned)
        if returned is not None and k is not None:
            ax.plot([x[k]], [y[k]], "*", ms=12, color=line.get_color(), label="returned")
        k = len(x) - 1 if k is None else k
        end = "start" if x[k] == 0 else f"epoch {x[k]:.0f}"
        end += " (returned)" if returned is not None else ""
        if y[0] != 0:
            notes.append(f"{first} {y[0]:.4g} -> {end} {y[k]:.4g} ({100 * (y[k] / y[0] - 1):+.1f} %)")
        top = max(top, float(np.max(y)))
    ax.set_ylim(0.0, 1.1 * top if top > 0 else 1.0)
    ax.set_xlim(-0.25, max(float(max(x.max() for x, _ in series.values())), 1.0) + 0.25)
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("epochs trained (0 = start)")
    names = list(series)
    ax.set_ylabel(metric_label(names[0]) if len(names) == 1 else "error")
    ax.set_title("error vs epoch" + ("\n" + "; ".join(notes) if notes else ""), fontsize=10)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="lower left")
    return fig


def _returned_index(x: np.ndarray, returned: int | None) -> int | None:
    """Index in ``x`` (epochs trained, 0 the start) of the returned epoch (counted from 0; -1 the start)."""
    if returned is None or isinstance(returned, bool) or not isinstance(returned, (int, float)):
        return None
    hits = np.flatnonzero(x == returned + 1)
    return int(hits[0]) if len(hits) else None


def plot_error_vs_epoch(path: str | Path, epochs: list, start: float | dict[str, float] | None = None,
                        returned: int | None = None) -> Path | None:
    """:func:`epochs_figure`, written to ``path``; None (nothing written) when it has nothing to draw."""
    fig = epochs_figure(epochs, start, returned)
    return None if fig is None else save(fig, path)


def run_start(report: dict) -> dict[str, float]:
    """Per-epoch metric name -> its value at the optimiser's start, from a run's ``report.json``
    (``start_metrics``; the metric named by the epoch records, else every metric of :data:`EPOCH_METRICS`)."""
    start = report.get("start_metrics") or {}
    epochs = report.get("epochs") or []
    named = {e.get("ate_metric") for e in epochs if isinstance(e, dict) and e.get("ate_metric")}
    out = {k: float(start[k]) for k in (named or EPOCH_METRICS)
           if isinstance(start.get(k), (int, float)) and not isinstance(start.get(k), bool)}
    if not named and len(out) == 1:  # records without a name: the run's only per-epoch metric
        out["ate"] = next(iter(out.values()))
    return out


def plot_run_epochs(path: str | Path, report: dict) -> Path | None:
    """The epoch plot of a run's ``report.json``, with the start from its ``start_metrics`` and the epoch it
    returned (``best_epoch``) marked."""
    return plot_error_vs_epoch(path, report.get("epochs") or [], run_start(report), report.get("best_epoch"))


#: how each closure status is drawn on the topology plot: colour, line width, line style, opacity, label
CLOSURE_STYLE = {
    "rejected": ("0.55", 0.5, "solid", 0.25, "rejected candidates"),
    "verified": ("tab:red", 1.0, "dashed", 0.8, "verified, not accepted"),
    "dropped": ("tab:red", 1.2, "solid", 0.9, "dropped by the final solve"),
    "accepted": ("tab:green", 1.4, "solid", 0.9, "accepted closures"),
    "across": ("tab:cyan", 1.4, "dotted", 0.9, "accepted across a corridor (free along it)"),
}


def _segments(pos: np.ndarray, pairs: np.ndarray, limit: int) -> np.ndarray:
    """(M,2,2) line segments between the frames of each pair, evenly subsampled to at most ``limit``."""
    pairs = np.asarray(pairs, dtype=int).reshape(-1, 2)
    if len(pairs) > limit:
        pairs = pairs[np.linspace(0, len(pairs) - 1, limit).astype(int)]
    return np.stack([pos[pairs[:, 0]], pos[pairs[:, 1]]], axis=1)


#: loop edges of the topology (the optimiser's groups across a revisit): colour, line width, opacity
LOOP_EDGE_STYLE = ("tab:purple", 1.0, 0.6)


def topology_figure(positions: np.ndarray, closures: dict[str, np.ndarray], loop_edges: np.ndarray,
                    title: str = "topology", limit: int = 3000) -> Figure:
    """Top view of the trajectory (light, underneath) with the topology's loop edges and the loop-closure
    candidates (``status -> (M,2)`` frame pairs) drawn as lines between the two frames' positions."""
    positions = np.asarray(positions)
    top, _ = view_axes(positions)
    pos = positions[:, list(top)]
    fig = Figure(figsize=(9, 8))
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(pos[:, 0], pos[:, 1], color="0.55", lw=0.8, zorder=1, label="trajectory")
    if len(loop_edges):
        drawn = f", {limit} drawn" if len(loop_edges) > limit else ""
        colour, width, alpha = LOOP_EDGE_STYLE
        seg = _segments(pos, loop_edges, limit)
        ax.add_collection(LineCollection(seg, colors=colour, linewidths=width, alpha=alpha, zorder=2,
                                         label=f"loop edges ({len(loop_edges)}{drawn})"))
        # a revisit's edge joins two frames at about the same place: its ends show where the edges are
        ax.scatter(seg[:, :, 0].ravel(), seg[:, :, 1].ravel(), s=5, color=colour, alpha=alpha, zorder=2)
    for status, (colour, width, style, alpha, label) in CLOSURE_STYLE.items():
        pairs = np.asarray(closures.get(status, np.zeros((0, 2))), dtype=int).reshape(-1, 2)
        if len(pairs):
            shown = f", {limit} drawn" if len(pairs) > limit else ""
            seg = _segments(pos, pairs, limit)
            ax.add_collection(LineCollection(seg, colors=colour, linewidths=width, linestyles=style, alpha=alpha,
                                             zorder=3, label=f"{label} ({len(pairs)}{shown})"))
            if status != "rejected":  # closures along a corridor lie on the trajectory: mark their ends
                ax.scatter(seg[:, :, 0].ravel(), seg[:, :, 1].ravel(), s=8, color=colour, alpha=alpha, zorder=4)
    ax.plot(pos[0, 0], pos[0, 1], "k^", ms=6, zorder=5, label="start")
    _setup(ax, top, title)
    ax.legend(loc="best", fontsize=8)
    return fig


def plot_topology(path: str | Path, positions: np.ndarray, closures: dict[str, np.ndarray],
                  loop_edges: np.ndarray, title: str = "topology", limit: int = 3000) -> Path:
    """:func:`topology_figure`, written to ``path``."""
    return save(topology_figure(positions, closures, loop_edges, title, limit), path)


#: title of a consistency map panel (``{label}``: the estimate's)
CONSISTENCY_MAP_TITLE = "{label}: where frames disagree with the map"


#: the consistency profile's score, as its pictures label it
CONSISTENCY_SCORE_LABEL = "worst view / its flag threshold"


def consistency_figure(positions: np.ndarray | dict[str, np.ndarray], profiles: dict[str, object],
                       title: str = "", positions_by_label: dict[str, np.ndarray] | None = None) -> Figure:
    """Consistency profiles (:mod:`dm2_backend.evaluation.consistency_profile`) along the trajectory: one top-view
    panel per profile, of that estimate's positions coloured by its own per-frame score (its worst view over that
    view's flag threshold; one colour scale for all, from 0) with its flagged frames ringed, and a panel of every
    profile's score over the frames in the colour of its map's path, the flag threshold (1, dashed) and its flagged
    frames shaded in that colour, each profile in a band of its own (one legend entry ``flagged: <label>`` each, so
    no two shadings blend).

    ``positions``: (N,3) positions (the last profile's poses: every panel is drawn over them), or a dict
    label -> positions; ``positions_by_label`` adds or overrides labels' own positions."""
    own = dict(positions) if isinstance(positions, dict) else {}
    own.update(positions_by_label or {})
    fallback = positions if not isinstance(positions, dict) else list(positions.values())[-1]
    items = list(profiles.items())
    k_all = len(items)
    scores = [np.asarray(p.score, dtype=np.float64) for _, p in items]
    finite = np.concatenate([s[np.isfinite(s)] for s in scores]) if scores else np.zeros(0)
    vmax = max(float(finite.max()) if len(finite) else 0.0, 1.0)  # the threshold (1) the top colour at least
    n = max((len(s) for s in scores), default=0)
    # the colour bar beside the maps, clear of the series
    if k_all == 1:
        fig = Figure(figsize=(13, 5.5), layout="constrained")
        grid = fig.add_gridspec(1, 2)
        map_slots, series_slot = [grid[0, 0]], grid[0, 1]
    else:
        fig = Figure(figsize=(max(13.0, 5.5 * k_all), 11), layout="constrained")
        grid = fig.add_gridspec(2, k_all)
        map_slots, series_slot = [grid[0, k] for k in range(k_all)], grid[1, :]
    maps, sc = [], None
    for k, ((label, prof), score) in enumerate(zip(items, scores, strict=True)):
        pos = np.asarray(own.get(label, fallback), dtype=np.float64).reshape(-1, 3)
        top, _ = view_axes(pos)
        ax = fig.add_subplot(map_slots[k])
        maps.append(ax)
        size = float(np.clip(4000.0 / max(len(score), 1), 4, 30))
        x, y = pos[:, top[0]], pos[:, top[1]]
        ax.plot(x, y, color=f"C{k}", lw=0.8, alpha=0.6)
        sc = ax.scatter(x, y, c=score, s=size, cmap="viridis", linewidths=0, vmin=0.0, vmax=vmax)
        flagged = np.asarray(prof.flagged, dtype=bool)
        if flagged.any():
            ax.scatter(x[flagged], y[flagged], s=size * 4, facecolors="none", edgecolors="red", linewidths=1.0,
                       label=f"flagged ({int(flagged.sum())} frames)")
            ax.legend(loc="best", fontsize=8)
        _setup(ax, top, CONSISTENCY_MAP_TITLE.format(label=label))
    if sc is not None:
        fig.colorbar(sc, ax=maps, label=CONSISTENCY_SCORE_LABEL)
    ax2 = fig.add_subplot(series_slot)
    handles = []
    for k, ((label, prof), score) in enumerate(zip(items, scores, strict=True)):
        colour = f"C{k}"
        line, = ax2.plot(np.arange(len(score)), score, lw=1.0, color=colour, label=label)
        band = (1.0 - (k + 1) / k_all, 1.0 - k / k_all)  # the first profile's band on top
        for seg in prof.segments:
            ax2.axvspan(seg.first - 0.5, seg.last + 0.5, ymin=band[0], ymax=band[1], color=colour, alpha=0.25)
        none = "" if prof.segments else " (none)"
        handles += [line, Patch(facecolor=colour, alpha=0.25, label=f"flagged: {label}{none}")]
    ax2.axhline(1.0, ls="--", lw=0.8, color="black")
    ax2.set_xlabel("frame")
    ax2.set_ylabel(CONSISTENCY_SCORE_LABEL)
    ax2.set_xlim(-0.5, n - 0.5)
    ax2.set_ylim(0.0, 1.05 * max(vmax, 1.05))  # the threshold in sight
    ax2.grid(True, alpha=0.3)
    ax2.legend(handles=handles, loc="best", fontsize=8)
    bands = ", a band per estimate" if k_all > 1 else ""
    ax2.set_title(f"per-frame score (dashed: flag threshold; shaded: flagged frames{bands})")
    if title:
        fig.suptitle(title)
    return fig
