"""2D maps of a simulated room: the ray-cast occupancy grid (walls at the right cells, free inside), its
map_server files read back, and the M-Net's grid from a field trained in a frame other than the world's."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from maps_cases import HALF, PILLAR, distance, room, train_field, wall_samples
from optim_cases import one_thread

from dm2_backend.kernel.geometry import se3
from dm2_backend.maps import occupancy_grid, run_maps
from dm2_backend.optim import mnet_file


@pytest.fixture(autouse=True, scope="module")
def _single_thread():
    yield from one_thread()


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A folder with an M-Net trained on the room (field frame = world moved by G) and the maps written."""
    out = tmp_path_factory.mktemp("room2d")
    r = room(planar=True)
    G = se3.from_xy_yaw(np.array([[1.0, -2.0, 0.7]]))[0]
    mnet_file.save_mnet(out / mnet_file.MNET, train_field(r, G, cell=0.05, steps=200), G)
    files = run_maps.write_run_maps(out, r.sequence(), r.poses, strict=True, progress=False)
    return out, files


def centres(m: occupancy_grid.MapServerMap, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    h = m.image.shape[0]
    return np.column_stack([m.origin[0] + (cols + 0.5) * m.resolution, m.origin[1] + (h - rows - 0.5) * m.resolution])


def found(classes: np.ndarray, rows: np.ndarray, cols: np.ndarray, value: int) -> np.ndarray:
    """Per (row, col): a cell of ``value`` within one cell of it."""
    h, w = classes.shape
    hit = np.zeros(len(rows), bool)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            r, c = np.clip(rows + dr, 0, h - 1), np.clip(cols + dc, 0, w - 1)
            hit |= classes[r, c] == value
    return hit


def test_files_and_resolution_from_the_data(run_dir):
    out, files = run_dir
    assert files == ["map.pgm", "map.yaml", "mnet_map.pgm", "mnet_map.yaml", "maps.json"]
    summary = run_maps.read_summary(out)
    spacing = summary["scale"]["spacing_raw"]
    assert summary["resolution"] == pytest.approx(spacing, rel=1e-2)  # 1 degree beams at a few metres: ~6 cm
    assert 0.02 < summary["resolution"] < 0.15
    doc = yaml.safe_load((out / "map.yaml").read_text())
    assert doc["image"] == "map.pgm" and doc["negate"] == 0 and doc["mode"] == "trinary"
    assert doc["occupied_thresh"] == 0.65 and doc["free_thresh"] == 0.196
    assert doc["resolution"] == summary["resolution"] and len(doc["origin"]) == 3 and doc["origin"][2] == 0.0


def test_walls_at_the_right_cells(run_dir):
    out, _ = run_dir
    m = occupancy_grid.read_map_server(out / "map.yaml")
    classes = m.classes()
    rows, cols = m.pixel(wall_samples(step=m.resolution / 2))
    assert found(classes, rows, cols, 1).all()  # every wall and pillar face is occupied within one cell
    occ_r, occ_c = np.nonzero(classes == 1)
    xy = centres(m, occ_r, occ_c)
    beyond = np.maximum(np.abs(xy[:, 0]) - HALF[0], np.abs(xy[:, 1]) - HALF[1])
    d = np.where(beyond > 0, beyond, distance(xy, planar=True))
    assert d.max() <= m.resolution  # every occupied cell centre within one cell of a surface


def test_free_inside(run_dir):
    out, _ = run_dir
    m = occupancy_grid.read_map_server(out / "map.yaml")
    classes = m.classes()
    rng = np.random.default_rng(0)
    xy = rng.uniform(-np.array(HALF), np.array(HALF), (4000, 2))
    xy = xy[distance(xy, planar=True) > 3 * m.resolution]
    rows, cols = m.pixel(xy)
    inside = classes[rows, cols]
    assert (inside != 1).all()
    assert (inside == 0).mean() > 0.97  # the rest: a pillar's shadow, never seen


def test_grid_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    prob = rng.uniform(0, 1, (7, 11))
    prob[2, 3] = np.nan
    pixels = occupancy_grid.trinary_pixels(prob)
    files = occupancy_grid.write_map_server(tmp_path / "g.yaml", pixels, 0.125, (-1.5, 2.25))
    assert files == ["g.pgm", "g.yaml"]
    m = occupancy_grid.read_map_server(tmp_path / "g.yaml")
    assert m.resolution == 0.125 and m.origin == (-1.5, 2.25, 0.0) and m.negate == 0
    assert m.image.shape == (7, 11)
    np.testing.assert_array_equal(m.image, pixels[::-1])  # row 0 of the image is the top (largest y)
    assert m.image[-1 - 2, 3] == occupancy_grid.UNKNOWN
    expected = np.where(np.isnan(prob), -1, np.where(prob > 0.65, 1, np.where(prob < 0.196, 0, -1)))
    np.testing.assert_array_equal(m.classes(), expected[::-1])
    # world (x, y) -> the pixel of its cell: lower-left cell (0, 0) is the image's last row
    assert m.pixel(np.array([-1.5 + 0.01, 2.25 + 0.01])) == (6, 0)
    assert m.pixel(np.array([-1.5 + 10.9 * 0.125, 2.25 + 6.9 * 0.125])) == (0, 10)
    scaled = occupancy_grid.scale_pixels(np.array([[0.0, 1.0, 0.5, np.nan]]))
    np.testing.assert_array_equal(scaled, [[255, 0, 128, occupancy_grid.UNKNOWN]])


def test_mnet_map_on_the_same_cells(run_dir):
    out, _ = run_dir
    grid = occupancy_grid.read_map_server(out / "map.yaml")
    m = occupancy_grid.read_map_server(out / "mnet_map.yaml")
    assert m.image.shape == grid.image.shape and m.origin == grid.origin and m.resolution == grid.resolution
    assert m.mode == "scale"
    classes = m.classes()
    rows, cols = m.pixel(wall_samples(step=m.resolution / 2))
    assert found(classes, rows, cols, 1).mean() > 0.97  # the field's walls, in world coordinates via G
    xy = np.random.default_rng(2).uniform(-np.array(HALF), np.array(HALF), (4000, 2))
    xy = xy[distance(xy, planar=True) > 3 * m.resolution]
    inside = classes[m.pixel(xy)]
    assert (inside == 0).mean() > 0.9 and (inside == 1).mean() < 0.02
    # cells inside the pillar, which no beam reached: unknown in both maps
    h, w = m.image.shape
    rows, cols = np.mgrid[0:h, 0:w]
    xy = centres(m, rows.ravel(), cols.ravel())
    behind = np.maximum(np.abs(xy[:, 0] - PILLAR[0]), np.abs(xy[:, 1] - PILLAR[1])) < PILLAR[2] - 1.5 * m.resolution
    assert behind.sum() >= 9
    assert (grid.image.ravel()[behind] == occupancy_grid.UNKNOWN).all()
    assert (m.image.ravel()[behind] == occupancy_grid.UNKNOWN).all()


def test_mnet_file_loads_weights_only(run_dir):
    out, _ = run_dir
    import torch

    state = torch.load(out / mnet_file.MNET, weights_only=True)
    assert state["format"] == mnet_file.FORMAT and state["dim"] == 2 and state["trained"] is True
    mnet = mnet_file.load_mnet(out / mnet_file.MNET)
    G = np.asarray(state["world_from_field"])
    np.testing.assert_allclose(mnet.world_from_field, G)
    p = np.array([[0.3, -0.2], [4.0, 1.0]])  # the same logits through the transform and directly
    local = np.linalg.inv(G)[:2, :2] @ p.T + np.linalg.inv(G)[:2, 3:4]
    with torch.no_grad():
        direct = mnet.field(torch.from_numpy(local.T).float()).numpy()
    np.testing.assert_allclose(mnet.logits(p), direct, rtol=1e-5, atol=1e-5)
