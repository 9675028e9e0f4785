"""What the plots draw (read back from their matplotlib figures, not from PNG bytes): x right and y up with
equal scales in every plot, no empty side view for planar data, estimates and ground truth in one frame,
the epoch plot's metric name, unit, start point, integer epochs and a y-range from 0, visible loop edges."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from scipy.spatial.transform import Rotation

from dm2_backend.evaluation import plots
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.prepared import Topology
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.pipeline import outputs


def tall_loop(n: int = 60, planar: bool = True) -> np.ndarray:
    """Positions (n,3) of a loop 10 m wide (x) and 40 m tall (y); 3D: z rises by 2 m."""
    a = np.linspace(0, 2 * np.pi, n)
    z = np.zeros(n) if planar else np.linspace(0, 2, n)
    return np.column_stack([5 * np.cos(a), 20 * np.sin(a), z])


def poses_at(pos: np.ndarray) -> np.ndarray:
    return se3.make_poses(np.tile(np.eye(3), (len(pos), 1, 1)), pos)


def labels(ax) -> tuple[str, str]:
    return ax.get_xlabel(), ax.get_ylabel()


def test_planar_trajectory_is_one_top_view_x_right_y_up():
    pos = tall_loop()
    fig = plots.trajectory_figure(pos, {"est": pos + 0.1})
    (ax,) = fig.axes  # planar data: no (empty) side view
    assert labels(ax) == ("x [m]", "y [m]")  # although y extends further than x
    gt_line, est_line = ax.lines
    np.testing.assert_array_equal(gt_line.get_xdata(), pos[:, 0])
    np.testing.assert_array_equal(gt_line.get_ydata(), pos[:, 1])
    np.testing.assert_allclose(est_line.get_xdata(), pos[:, 0] + 0.1)
    assert ax.get_aspect() == 1.0


def test_3d_trajectory_has_a_side_view_with_the_flat_axis_up():
    pos = tall_loop(planar=False)
    top, side = plots.trajectory_figure(pos, {"est": pos}).axes
    assert labels(top) == ("x [m]", "y [m]") and labels(side) == ("y [m]", "z [m]")
    np.testing.assert_array_equal(side.lines[0].get_ydata(), pos[:, 2])
    assert top.get_aspect() == side.get_aspect() == 1.0


def test_a_title_of_several_lines_stays_above_the_views():
    pos = tall_loop(planar=False)
    title = "aligned at the first pose\nSE(3) alignment not meaningful for A\nSE(3) alignment not meaningful for B"
    errors = {"APE": (np.ones(len(pos)), "m"), "RPE": (np.ones(len(pos)), "m")}
    figures = [plots.trajectory_figure(pos, {"estimate": pos + 0.1}, title),
               plots.error_map_figure("estimate", pos, errors, pos, title)]
    for fig in figures:
        renderer = FigureCanvasAgg(fig).get_renderer()
        fig.draw(renderer)
        bottom = fig._suptitle.get_window_extent(renderer).y0
        for ax in fig.axes:
            if ax.get_title():  # every view's own title (the colour bars have none) lies wholly under it
                assert ax.title.get_window_extent(renderer).y1 <= bottom


def test_camera_frame_is_seen_from_above_x_right_z_up():
    """KITTI camera frame (y down, flat): x right, z (forward) up."""
    cam = tall_loop()[:, [0, 2, 1]]
    (ax,) = plots.trajectory_figure(None, {"est": cam}).axes
    assert labels(ax) == ("x [m]", "z [m]")


def test_every_plot_of_a_run_has_the_same_orientation():
    pos = tall_loop()
    topo = Topology(np.zeros((len(pos), 1), int), np.array([[5, 40]]), ["loop"], [{"plugin": "loops"}],
                    poses_at(pos))
    axes = [plots.trajectory_figure(pos, {"est": pos}).axes[0],
            plots.error_map_figure("est", pos, {"APE trans": (np.ones(len(pos)), "m")}, pos).axes[0],
            outputs.topology_plot(topo, poses_at(pos)).axes[0]]
    assert {labels(ax) for ax in axes} == {("x [m]", "y [m]")}
    assert {ax.get_aspect() for ax in axes} == {1.0}


def test_loop_edges_are_visible_above_the_trajectory():
    pos = tall_loop()
    topo = Topology(np.zeros((len(pos), 1), int), np.array([[5, 40], [6, 41]]), ["loop", "loop"],
                    [{"plugin": "loops"}], poses_at(pos))
    ax = outputs.topology_plot(topo, poses_at(pos)).axes[0]
    (edges,) = [c for c in ax.collections if isinstance(c, LineCollection) and "loop edges" in c.get_label()]
    assert edges.get_alpha() >= 0.5 and edges.get_linewidths()[0] >= 1.0
    assert edges.get_zorder() > ax.lines[0].get_zorder()  # the trajectory line does not cover them
    np.testing.assert_array_equal(edges.get_segments()[0], pos[[5, 40]][:, :2])


def test_run_plots_draw_estimates_and_ground_truth_in_one_frame(tmp_path):
    """errors.png and trajectory.png: the estimate after its SE(3) alignment, over the ground truth."""
    gt = tall_loop(80, planar=False)
    rng = np.random.default_rng(0)
    R = Rotation.from_euler("z", 70, degrees=True).as_matrix()
    est = (gt + rng.normal(0, 0.01, gt.shape)) @ R.T + [100.0, -50.0, 3.0]  # another frame
    err = np.linalg.norm(outputs.aligned_to(gt, est) - gt, axis=1)
    figs = outputs.write_plots(tmp_path, {"refined": poses_at(est)}, Trajectory(poses_at(gt)),
                               {"translation error": (err, "m")}, None)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["errors.png", "trajectory.png"]
    ax = figs["errors.png"].axes[0]
    assert "aligned" in figs["errors.png"]._suptitle.get_text()
    gt_line = ax.lines[0]
    np.testing.assert_array_equal(gt_line.get_xdata(), gt[:, 0])
    dots = ax.collections[0].get_offsets()
    assert np.abs(dots - gt[:, :2]).max() < 0.05  # the coloured estimate lies on the ground-truth line
    assert figs["errors.png"].axes[1].get_ylabel() == "translation error [m]"  # the colour bar
    top = figs["trajectory.png"].axes[0]
    assert np.abs(np.column_stack([top.lines[1].get_xdata(), top.lines[1].get_ydata()]) - gt[:, :2]).max() < 0.05


def test_ground_truth_of_another_length_is_left_out(tmp_path):
    gt, est = tall_loop(80), tall_loop(60)
    figs = outputs.write_plots(tmp_path, {"refined": poses_at(est)}, Trajectory(poses_at(gt)), None, None)
    (ax,) = figs["trajectory.png"].axes
    assert [ln.get_label() for ln in ax.lines] == ["refined"]


def epochs(metric: str | None, values: list[float]) -> list[dict]:
    return [{"epoch": i, "loss": 1.0, "ate": v, **({"ate_metric": metric} if metric else {})}
            for i, v in enumerate(values)]


@pytest.mark.parametrize(("metric", "label"), [("ape_trans_rmse_m", "APE trans RMSE, SE(3)-aligned [m]"),
                                               ("relations_trans_mean_m", "relations trans mean [m]")])
def test_epoch_plot_names_the_metric_with_its_unit(metric, label):
    ax = plots.epochs_figure(epochs(metric, [0.5, 0.4]), start=0.6).axes[0]
    assert ax.get_ylabel() == label and ax.get_xlabel() == "epochs trained (0 = start)"


def test_epoch_plot_starts_at_the_start_with_integer_epochs_and_zero_based_y():
    values = [0.1040, 0.1038, 0.1036]  # a 0.4 % change
    fig = plots.epochs_figure(epochs("ape_trans_rmse_m", values), start=0.10402)
    FigureCanvasAgg(fig).draw()
    ax = fig.axes[0]
    line = ax.lines[0]
    np.testing.assert_array_equal(line.get_xdata(), [0, 1, 2, 3])
    np.testing.assert_allclose(line.get_ydata(), [0.10402, *values])
    ticks = [t for t in ax.get_xticks() if ax.get_xlim()[0] <= t <= ax.get_xlim()[1]]
    assert ticks == [round(t) for t in ticks] and 0 in ticks
    assert ax.get_ylim()[0] == 0.0 and ax.get_ylim()[1] < 0.2
    assert "-0.4 %" in ax.get_title()


def test_epoch_start_from_a_run_report():
    report = {"start_metrics": {"ape_trans_rmse_m": 0.9, "relations_trans_mean_m": 0.2},
              "epochs": epochs("ape_trans_rmse_m", [0.5])}
    assert plots.run_start(report) == {"ape_trans_rmse_m": 0.9}
    old = {"start_metrics": {"ape_trans_rmse_m": 0.9}, "epochs": epochs(None, [0.5])}  # records without a name
    ax = plots.epochs_figure(old["epochs"], plots.run_start(old)).axes[0]
    np.testing.assert_array_equal(ax.lines[0].get_xdata(), [0, 1])
    assert ax.get_ylabel() == plots.UNNAMED_METRIC

