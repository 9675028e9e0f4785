"""3D maps of a simulated room (walls, pillar, floor, ceiling): the OctoMap written and read back, and the mesh of
an M-Net trained in a frame other than the world's."""

from __future__ import annotations

import os

import numpy as np
import pytest
from maps_cases import HALF, HEIGHT, distance, room, train_field
from optim_cases import one_thread
from scipy.spatial import cKDTree

from dm2_backend.kernel.geometry import se3
from dm2_backend.maps import octomap_export, run_maps
from dm2_backend.optim import mnet_file
from dm2_backend.runtime.memory import release_freed_memory

WALL = 0.2  # thickness of the simulated walls, floor and ceiling


@pytest.fixture(autouse=True, scope="module")
def _single_thread():
    yield from one_thread()


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    pytest.importorskip("skimage", reason="the M-Net mesh needs scikit-image (pip install 'dm2[maps]')")
    out = tmp_path_factory.mktemp("room3d")
    r = room(planar=False)
    G = se3.from_xyz_euler(np.array([[0.5, -1.0, 0.2, 0.0, 0.0, 0.4]]))[0]
    field = train_field(r, G, cell=0.15, steps=150, levels=5, max_cells=2**16, lr=3e-2)
    mnet_file.save_mnet(out / mnet_file.MNET, field, G)
    files = run_maps.write_run_maps(out, r.sequence(), r.poses, strict=True, progress=False)
    return out, files, r


def test_mesh_on_the_surfaces(run_dir):
    out, files, r = run_dir
    assert "mnet_mesh.ply" in files
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(out / "mnet_mesh.ply"))
    v, faces = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    assert len(faces) > 1000 and mesh.has_vertex_normals()
    step = mnet_file.load_mnet(out / mnet_file.MNET).finest_cell  # the marching-cubes lattice step
    assert run_maps.read_summary(out)["skipped"] == {}
    inside = (np.abs(v[:, 0]) < HALF[0]) & (np.abs(v[:, 1]) < HALF[1]) & (v[:, 2] > 0) & (v[:, 2] < HEIGHT)
    assert inside.mean() > 0.6
    assert distance(v[inside], planar=False).max() <= 2 * step  # world coordinates (through G), on the surfaces
    outside = np.maximum.reduce([np.abs(v[:, 0]) - HALF[0], np.abs(v[:, 1]) - HALF[1], -v[:, 2], v[:, 2] - HEIGHT])
    assert outside.max() <= WALL + 2 * step  # the unobserved back of a wall: at most two cells behind it
    scanned = np.concatenate(r.world())
    gap, _ = cKDTree(v).query(scanned)
    assert np.percentile(gap, 99) <= 2 * step  # and it covers what was scanned


def test_octomap_round_trip(run_dir):
    pytest.importorskip("pyoctomap", reason="OctoMap export needs pyoctomap (pip install 'dm2[maps]')")
    out, files, r = run_dir
    assert "octomap.bt" in files
    tree = octomap_export.read_octomap(out / "octomap.bt")
    res = run_maps.read_summary(out)["resolution"]
    assert tree.getResolution() == pytest.approx(res)
    scanned = np.concatenate(r.world())[::25]
    assert (octomap_export.occupancy_at(tree, scanned) == 1).mean() > 0.97  # occupied at the wall points
    sensors = np.repeat(r.poses[:, :3, 3], [len(s) for s in r.scans], axis=0)[::25]
    middle = 0.5 * (sensors + scanned)
    middle = middle[distance(middle, planar=False) > 3 * res]
    assert (octomap_export.occupancy_at(tree, middle) == 0).mean() > 0.97  # free along the beams
    rng = np.random.default_rng(0)
    p = np.column_stack([rng.uniform(-HALF[0], HALF[0], 600), rng.uniform(-HALF[1], HALF[1], 600),
                         rng.uniform(0, HEIGHT, 600)])
    p = p[distance(p, planar=False) > 3 * res]
    assert (octomap_export.occupancy_at(tree, p) != 1).all()  # never occupied inside (free or unknown)


def test_octomap_missing_is_skipped_with_a_hint(tmp_path, monkeypatch):
    import builtins

    real = builtins.__import__

    def no_pyoctomap(name, *args, **kw):
        if name == "pyoctomap":
            raise ImportError("No module named 'pyoctomap'")
        return real(name, *args, **kw)

    monkeypatch.setattr(builtins, "__import__", no_pyoctomap)
    r = room(planar=False)
    files = run_maps.write_run_maps(tmp_path, r.sequence(), r.poses, strict=True, progress=False)
    assert files == ["maps.json"]
    skipped = run_maps.read_summary(tmp_path)["skipped"]
    assert "pip install 'dm2[maps]'" in skipped["octomap"] and "mnet" in skipped


def _rss_mib() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


@pytest.mark.skipif(not release_freed_memory(), reason="no malloc_trim in this C library")
def test_octomap_gives_its_memory_back(tmp_path):
    """An OcTree of half a million leaves takes about 60 MiB of small nodes; once written and freed, the process
    keeps none of it (without handing the freed pages back it kept all of it, under the run's next stages)."""
    pytest.importorskip("pyoctomap", reason="OctoMap export needs pyoctomap (pip install 'dm2[maps]')")
    rng = np.random.default_rng(0)
    scans = []
    for k in range(20):
        sensor = np.array([0.5 * k, 0.0, 1.0])
        angle, reach = rng.uniform(0, 2 * np.pi, 2000), rng.uniform(5, 20, 2000)
        scans.append((sensor, np.c_[sensor[0] + reach * np.cos(angle), reach * np.sin(angle),
                                    rng.uniform(-1, 3, 2000)]))
    before = _rss_mib()
    summary = octomap_export.write_octomap(tmp_path / "t.bt", scans, 0.15)
    assert summary["leaf_nodes"] > 400_000
    assert _rss_mib() - before < 20
