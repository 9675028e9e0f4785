"""A depth camera's noise measured on its own images, and the smoothing it sets (formats/depth_image_noise.py)."""

from __future__ import annotations

import logging

import numpy as np
import open3d as o3d
import pytest

from dm2_backend.formats import ReadOptions, open_scans
from dm2_backend.formats.depth import back_project
from dm2_backend.formats.depth_image_noise import DepthImageNoise, measure, smooth
from dm2_backend.kernel.geometry import se3
from dm2_backend.pipeline.inputs import depth_sensor, log_sensor
from dm2_backend.pipeline.run_writer import sensor_comment
from dm2_backend.prepare.cache_keys import source_key
from dm2_backend.runtime.errors import InputError

INTRINSICS = (585.0, 585.0, 320.0, 240.0)
#: a Kinect v1's disparity: depth = K / n for whole n (1/8 pixel over 7.5 cm at fx 585)
K_DISPARITY = 585.0 * 0.075 / 0.125


def quantised(z: np.ndarray) -> np.ndarray:
    return K_DISPARITY / np.rint(K_DISPARITY / z)


def tilted_wall(noise: float = 0.0, seed: int = 0, shape=(240, 320)) -> tuple[np.ndarray, np.ndarray]:
    """Millimetre depth of a wall 2-5 m away tilted across the image, quantised as a Kinect's, and the exact depth."""
    v, u = np.mgrid[0:shape[0], 0:shape[1]]
    z = 2.0 + 3.0 * u / shape[1] + 0.3 * v / shape[0]
    noisy = z + np.random.default_rng(seed).normal(0.0, noise * z**2, z.shape)
    return np.rint(quantised(noisy) * 1000).astype(np.uint16), z


def test_measured_step_and_scatter_follow_the_camera():
    """The step measured per range bin is the disparity quantisation's z^2 / 348 (within 20 %); noise added with a
    known sigma is measured within a third of it."""
    images = [tilted_wall(0.004, seed)[0] for seed in range(3)]
    noise = measure(images, 1000.0)
    assert noise is not None and noise.images == 3 and len(noise.ranges_m) == 10
    z = np.array(noise.ranges_m)
    assert np.allclose(noise.steps_m, z**2 / K_DISPARITY, rtol=0.2)
    # noise 4 mm x z^2 dithers the steps: the scatter measured is at least the noise and below the step plus it
    sigma = np.array(noise.sigmas_m)
    assert np.all(sigma > 0.67 * 0.004 * z**2) and np.all(sigma < 0.004 * z**2 + z**2 / K_DISPARITY)
    assert measure([np.zeros((50, 50), np.uint16)], 1000.0) is None  # nothing valid: nothing measured


def test_smoothing_removes_the_staircase_and_keeps_edges():
    """A quantised wall sits on its plane three times closer once smoothed; a 30 cm depth step between two walls
    stays a step (no pixel takes a depth between them)."""
    raw, exact = tilted_wall(0.002)
    noise = measure([raw], 1000.0)
    smoothed = smooth(raw, 1000.0, noise)
    inner = (slice(5, -5), slice(5, -5))
    before = np.sqrt(np.mean((raw[inner] / 1000.0 - exact[inner]) ** 2))
    after = np.sqrt(np.mean((smoothed[inner] - exact[inner]) ** 2))
    assert after < before / 3.0
    near, near_exact = tilted_wall(0.002, seed=1)
    edge = np.where(np.arange(320)[None, :] < 160, near, near + 300).astype(np.uint16)  # a 30 cm step at u = 160
    out = smooth(edge, 1000.0, noise)
    rows = slice(5, -5)
    # each side within a step (35-45 mm at 3.5-4 m) of its own wall, 30 cm from the other one
    assert np.all(np.abs(out[rows, 150:160] - near_exact[rows, 150:160]) < 0.05)
    assert np.all(np.abs(out[rows, 160:170] - near_exact[rows, 160:170] - 0.3) < 0.05)
    stride = smooth(raw, 1000.0, noise, stride=2)
    assert stride.shape == (120, 160) and np.allclose(stride, smoothed[::2, ::2])
    invalid = raw.copy()
    invalid[:, :40] = 0
    invalid[:, 40:50] = 65535
    out = smooth(invalid, 1000.0, noise)
    assert np.all(out[:, :50] == 0.0) and np.all(out[5:-5, 50:] > 0)  # an invalid pixel stays invalid, none spreads


def _cloud(points: np.ndarray) -> o3d.geometry.PointCloud:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64))).voxel_down_sample(0.02)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.1, max_nn=30))
    return pcd


@pytest.mark.parametrize("step", [30, 240])
def test_a_simulated_kinect_step_is_held_once_smoothed(step):
    """Two consecutive frames of the simulated hall (a Kinect v1's noise and disparity steps, 3-8 m away):
    registered from the true step, the frames as recorded slide towards standing still (more than 2 cm off);
    smoothed, they hold the step within 5 mm."""
    from dm2_backend.simulate import depth_room as dr

    poses = dr.camera_path("hall", 450, 0.75, 0)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(dr.room_mesh(0, hall=True)))
    camera = dr.DepthCamera(max_depth=8.0, disparity_step=0.125)
    images = [dr.depth_image(scene, camera, camera.rays(), poses[i], np.random.default_rng([0, 33, i]))
              for i in (step, step + 1)]
    noise = measure(images, 1000.0)
    true = se3.relative(poses[step], poses[step + 1])
    reg = o3d.pipelines.registration
    errors = []
    for model in (None, noise):
        a, b = (_cloud(back_project(img, INTRINSICS, 1000.0, 2, model)) for img in images[::-1])
        found = reg.registration_icp(a, b, 0.16, true, reg.TransformationEstimationPointToPlane(),
                                     reg.ICPConvergenceCriteria(max_iteration=50)).transformation
        errors.append(float(np.linalg.norm(se3.relative(true, found)[:3, 3])))
    assert errors[0] > 0.02 and errors[1] < 0.005


def test_depth_is_read_as_recorded_unless_smoothing_is_asked(tmp_path, caplog):
    """By default the points are the recorded depth and the noise is measured and stated in the sequence's meta;
    --smooth-depth (ReadOptions.smooth_depth) smooths them by it."""
    from PIL import Image

    raw, _ = tilted_wall(0.002)
    folder = tmp_path / "seq"
    folder.mkdir()
    for i in range(2):
        Image.fromarray(raw).save(folder / f"frame-{i:06d}.depth.png")
        np.savetxt(folder / f"frame-{i:06d}.pose.txt", np.eye(4))
    as_recorded = open_scans(folder)
    assert as_recorded.meta["image_noise"]["images"] == 2 and not as_recorded.meta["smoothed"]
    assert "depth noise measured on 2 images" in as_recorded.meta["image_noise_line"]
    assert np.array_equal(as_recorded[0].points, back_project(raw, INTRINSICS, 1000.0, 2))
    smoothed = open_scans(folder, options=ReadOptions(smooth_depth=True))
    assert smoothed.meta["smoothed"] and source_key(smoothed) != source_key(as_recorded)  # cached apart
    assert not np.array_equal(smoothed[0].points, as_recorded[0].points)
    with caplog.at_level(logging.INFO, logger="dm2_backend.pipeline.inputs"):
        log_sensor(depth_sensor(as_recorded))
        log_sensor(depth_sensor(smoothed))
    noise_lines = [r.getMessage() for r in caplog.records if "depth noise measured on 2 images" in r.getMessage()]
    assert len(noise_lines) == 2 and noise_lines[0].endswith("depth as recorded")
    assert noise_lines[1].endswith("(--smooth-depth)")
    comment = sensor_comment(depth_sensor(smoothed))
    assert "# depth noise measured on 2 images" in comment and "# depth smoothed" in comment
    assert "smoothed" not in sensor_comment(depth_sensor(as_recorded))


def test_tolerance_interpolates_and_clamps():
    noise = DepthImageNoise((1.0, 3.0), (0.002, 0.03), (0.001, 0.01), 1)
    assert noise.tolerance(np.array([1.0]))[0] == pytest.approx(3.0 * np.hypot(0.002, 0.001))
    assert noise.tolerance(np.array([10.0]))[0] == pytest.approx(3.0 * np.hypot(0.03, 0.01))
    assert "step 2.0 mm, scatter 1.0 mm at 1.0 m" in noise.describe()


def test_float_depth_and_bins_without_steps():
    """A float image (metres) has no unit to floor its steps at; a range holding one depth value measures no step
    (it is left out, not given the unit)."""
    _, exact = tilted_wall()
    noise = measure([exact.astype(np.float32)], 1.0)
    assert noise is not None and max(noise.steps_m) < 1e-3  # no metre-sized floor
    image = np.full((240, 320), 3000, np.uint16)  # half the image one value: 3 m in every pixel
    image[:, :160] = np.rint(quantised(1.0 + np.arange(160) / 320.0) * 1000)[None, :]  # a wall at 1-1.5 m
    measured = measure([image], 1000.0)
    assert measured is not None and max(measured.ranges_m) < 2.0  # the 3 m bin has no step to measure
    assert min(measured.steps_m) > 0.002  # the wall's steps (3-6 mm), not the unit


def test_smoothing_asked_on_frames_too_sparse_to_measure_is_refused(tmp_path):
    """--smooth-depth on images with too few valid pixels: one line naming the folder, not a silent raw read."""
    from PIL import Image

    folder = tmp_path / "seq"
    folder.mkdir()
    sparse = np.zeros((40, 40), np.uint16)
    sparse[10:20, 10:20] = 1500
    Image.fromarray(sparse).save(folder / "frame-000000.depth.png")
    np.savetxt(folder / "frame-000000.pose.txt", np.eye(4))
    assert open_scans(folder).meta["image_noise"] is None  # read as recorded, nothing to state
    with pytest.raises(InputError, match="too few valid depth pixels"):
        open_scans(folder, options=ReadOptions(smooth_depth=True))
