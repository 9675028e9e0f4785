"""A depth camera's range noise measured on its own frames (``dm2_backend.optim.depth_noise``)."""

from __future__ import annotations

import numpy as np
import pytest

from dm2_backend.formats import open_scans
from dm2_backend.kernel import planes
from dm2_backend.optim import depth_noise
from dm2_backend.simulate.depth_room import write_depth_room


@pytest.fixture(scope="module")
def across(tmp_path_factory):
    """The simulated Kinect looking across the room (0.4-4 m; 1.2 mm + 1.9 mm (z - 0.4)^2 of noise)."""
    out = tmp_path_factory.mktemp("across")
    write_depth_room(out, 12, "across", 0.05, seed=2, progress=False)
    return open_scans(out)


def test_the_noise_grows_with_the_range_as_the_camera_makes_it(across):
    noise = depth_noise.measure(across, 0.02, 2048)
    assert noise is not None and noise.frames == 12 and noise.cells > 300
    near, far = noise.sigma(1.0), noise.sigma(3.0)
    # the simulator's sigma: 1.6 mm at 1 m and 9.6 mm at 3 m; the flat cells it is measured on are biased thin
    # far out (a cell thicker than a quarter of its width is not flat), so at least half that growth
    assert 0.5e-3 < near < 4e-3 and far / near > 3.0
    w = noise.weights(np.array([0.5, 1.0, noise.reference_m, 3.0, 8.0]))
    assert np.all(np.diff(w) <= 0) and w[2] == pytest.approx(1.0)
    assert w[-1] == depth_noise.MIN_WEIGHT
    pure = depth_noise.RangeNoise(0.0, 1e-6, 1.0, 100, 3)  # sigma = 1 mm z^2: twice as far, a sixteenth
    np.testing.assert_allclose(pure.weights(np.array([0.5, 1.0, 2.0])), [10.0, 1.0, 1.0 / 16.0])


def test_weighed_cells_keep_their_shape(across):
    cells = planes.cells_from_scans(across.subset(np.arange(3)), 0.02, 2048, 10**6)
    noise = depth_noise.RangeNoise(1e-6, 1e-6, 2.0, 100, 3)
    out = depth_noise.weighed(cells, noise)
    w = noise.weights(np.linalg.norm(cells.mean.astype(np.float64), axis=1))
    np.testing.assert_allclose(out.count, cells.count * w, rtol=1e-6)
    np.testing.assert_allclose(out.scatter / out.count[:, None], cells.scatter / cells.count[:, None], rtol=1e-4,
                               atol=1e-12)
    assert np.array_equal(out.mean, cells.mean) and np.array_equal(out.frame, cells.frame)


def test_too_few_flat_cells_measure_nothing(across):
    assert depth_noise.measure(across.subset(np.arange(1)), 0.5, 8) is None
