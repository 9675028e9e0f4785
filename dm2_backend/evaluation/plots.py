"""Evaluation plots (matplotlib, Agg canvas, no pyplot state), each written atomically.

- trajectories overlaid, top view and side view;
- per-frame translation and rotation APE coloured along the estimate (heat map);
- error versus epoch from a refine run's ``report.json`` ``epochs`` list;
- the place recognition's closures and loop edges over the trajectory (``topology.png``).
The "top" view uses the two axes along which the ground truth extends most, the "side" view the longest
axis against the shortest (so camera-frame KITTI, y down, is drawn from above as well).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure

from dm2_backend.atomic import atomic_write

AXES = "xyz"


def _save(fig: Figure, path: str | Path) -> Path:
    path = Path(path)
    FigureCanvasAgg(fig)
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format=path.suffix.lstrip(".") or "png", dpi=120, bbox_inches="tight")
    return path


def view_axes(positions: np.ndarray) -> tuple[tuple[int, int], tuple[int, int]]:
    """Index pairs of the top view (two longest extents) and the side view (longest vs shortest)."""
    extent = np.ptp(np.asarray(positions).reshape(-1, 3), axis=0)
    order = np.argsort(-extent, kind="stable")
    return (int(order[0]), int(order[1])), (int(order[0]), int(order[2]))


def _setup(ax, axes: tuple[int, int], title: str) -> None:
    ax.set_xlabel(f"{AXES[axes[0]]} [m]")
    ax.set_ylabel(f"{AXES[axes[1]]} [m]")
    ax.set_title(title)
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)


def plot_trajectories(path: str | Path, gt: np.ndarray | None, estimates: dict[str, np.ndarray]) -> Path:
    """Ground-truth (dashed grey) and estimated positions (N,3), top and side views."""
    basis = gt if gt is not None else next(iter(estimates.values()))
    top, side = view_axes(basis)
    fig = Figure(figsize=(12, 5.5))
    for ax, axes, title in ((fig.add_subplot(1, 2, 1), top, "top view"),
                            (fig.add_subplot(1, 2, 2), side, "side view")):
        if gt is not None:
            ax.plot(gt[:, axes[0]], gt[:, axes[1]], "--", color="0.4", lw=1.2, label="ground truth")
        for label, p in estimates.items():
            ax.plot(p[:, axes[0]], p[:, axes[1]], lw=1.0, label=label)
        _setup(ax, axes, title)
        ax.legend(loc="best", fontsize=8)
    return _save(fig, path)


def plot_error_map(
    path: str | Path, label: str, positions: np.ndarray, errors: dict[str, tuple[np.ndarray, str]],
    gt: np.ndarray | None = None,
) -> Path:
    """Per-frame errors (name -> (values, unit)) coloured along the top view of ``positions``."""
    top, _ = view_axes(gt if gt is not None else positions)
    fig = Figure(figsize=(6.5 * len(errors), 5.5))
    for i, (name, (values, unit)) in enumerate(errors.items()):
        ax = fig.add_subplot(1, len(errors), i + 1)
        if gt is not None:
            ax.plot(gt[:, top[0]], gt[:, top[1]], "--", color="0.6", lw=0.8, label="ground truth")
        size = float(np.clip(4000.0 / max(len(values), 1), 4, 30))
        x, y = positions[:, top[0]], positions[:, top[1]]
        sc = ax.scatter(x, y, c=values, s=size, cmap="jet", linewidths=0)
        fig.colorbar(sc, ax=ax, label=f"{name} [{unit}]")
        _setup(ax, top, f"{label}: {name}")
    return _save(fig, path)


def epoch_series(epochs: list) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``name -> (epoch, value)`` from a run report's ``epochs``; entries without ``ate`` are skipped."""
    series: dict[str, tuple[list, list]] = {}
    for i, entry in enumerate(epochs):
        if not isinstance(entry, dict) or "ate" not in entry:
            continue
        ep = entry.get("epoch", i + 1)
        ate = entry["ate"]
        values = ate if isinstance(ate, dict) else {"ate": ate}
        for name, v in values.items():
            if isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v):
                xs, ys = series.setdefault(name, ([], []))
                xs.append(ep)
                ys.append(float(v))
    return {k: (np.asarray(x, dtype=float), np.asarray(y)) for k, (x, y) in series.items()}


def plot_error_vs_epoch(path: str | Path, epochs: list) -> Path | None:
    """Error versus epoch; None (nothing written) when no epoch has an ``ate`` entry."""
    series = epoch_series(epochs)
    if not series:
        return None
    fig = Figure(figsize=(7, 4.5))
    ax = fig.add_subplot(1, 1, 1)
    for name, (x, y) in series.items():
        ax.plot(x, y, marker="o", ms=3, label=name)
    ax.set_xlabel("epoch")
    ax.set_ylabel("ATE")
    ax.set_title("error vs epoch")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best")
    return _save(fig, path)


#: how each closure status is drawn on the topology plot: colour, line width, line style, opacity, label
CLOSURE_STYLE = {
    "rejected": ("0.55", 0.5, "solid", 0.25, "rejected candidates"),
    "verified": ("tab:red", 1.0, "dashed", 0.8, "verified, not accepted"),
    "dropped": ("tab:red", 1.2, "solid", 0.9, "dropped by the final solve"),
    "accepted": ("tab:green", 1.4, "solid", 0.9, "accepted closures"),
}


def _segments(pos: np.ndarray, pairs: np.ndarray, limit: int) -> np.ndarray:
    """(M,2,2) line segments between the frames of each pair, evenly subsampled to at most ``limit``."""
    pairs = np.asarray(pairs, dtype=int).reshape(-1, 2)
    if len(pairs) > limit:
        pairs = pairs[np.linspace(0, len(pairs) - 1, limit).astype(int)]
    return np.stack([pos[pairs[:, 0]], pos[pairs[:, 1]]], axis=1)


def plot_topology(path: str | Path, positions: np.ndarray, closures: dict[str, np.ndarray],
                  loop_edges: np.ndarray, title: str = "topology", limit: int = 3000) -> Path:
    """Top view of the trajectory with the topology's loop edges (light) and the loop-closure candidates
    (``status -> (M,2)`` frame pairs) drawn as lines between the two frames' positions."""
    positions = np.asarray(positions)
    top = (0, 1) if np.ptp(positions[:, 2]) < 1e-6 else view_axes(positions)[0]  # planar: x right, y up
    pos = positions[:, list(top)]
    fig = Figure(figsize=(9, 8))
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(pos[:, 0], pos[:, 1], color="tab:blue", lw=0.8, label="trajectory")
    if len(loop_edges):
        drawn = f", {limit} drawn" if len(loop_edges) > limit else ""
        ax.add_collection(LineCollection(_segments(pos, loop_edges, limit), colors="tab:purple", linewidths=0.4,
                                         alpha=0.25, label=f"loop edges ({len(loop_edges)}{drawn})"))
    for status, (colour, width, style, alpha, label) in CLOSURE_STYLE.items():
        pairs = np.asarray(closures.get(status, np.zeros((0, 2))), dtype=int).reshape(-1, 2)
        if len(pairs):
            shown = f", {limit} drawn" if len(pairs) > limit else ""
            seg = _segments(pos, pairs, limit)
            ax.add_collection(LineCollection(seg, colors=colour, linewidths=width, linestyles=style, alpha=alpha,
                                             label=f"{label} ({len(pairs)}{shown})"))
            if status != "rejected":  # closures along a corridor lie on the trajectory: mark their ends
                ax.scatter(seg[:, :, 0].ravel(), seg[:, :, 1].ravel(), s=8, color=colour, alpha=alpha, zorder=3)
    ax.plot(pos[0, 0], pos[0, 1], "k^", ms=6, label="start")
    _setup(ax, top, title)
    ax.legend(loc="best", fontsize=8)
    return _save(fig, path)
