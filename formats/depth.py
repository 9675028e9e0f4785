"""Depth-image sequences as scans: each 16-bit depth PNG is back-projected to a point cloud.

Points are in the camera frame (x right, y down, z forward; pinhole ``X = (u - cx) Z / fx``,
``Y = (v - cy) Z / fy``); depth 0 and 65535 are invalid. ``ReadOptions.stride`` keeps every
n-th pixel in u and v (default 2: at most 320 x 240 points from a 640 x 480 image; 1 keeps all). The camera's
noise is measured on its own images and stated (``meta["image_noise"]``, :mod:`.depth_image_noise`);
``ReadOptions.smooth_depth`` smooths each pixel's depth by it over its neighbours on the same surface.

Layouts:

- 7-Scenes: ``frame-NNNNNN.depth.png`` (millimetres), ``frame-NNNNNN.pose.txt`` (4 x 4 camera-to-world,
  the ``reference`` poses), optional ``camera-intrinsics.txt`` (3 x 3 K; else fx = fy = 585,
  cx = 320, cy = 240, the dataset's published values). Timestamps are frame index / 30 Hz.
- TUM RGB-D: ``depth.txt`` (``timestamp filename`` a line), ``depth/*.png`` (5000 units per metre),
  optional ``groundtruth.txt`` (TUM trajectory): the ``reference`` poses are the ground-truth poses
  nearest in time to the depth frames, within 0.02 s, stamped with the depth frames' times (frames
  without such a pose are left out of it). Intrinsics from ``ReadOptions.intrinsics``, else TUM's
  recommended defaults for the registered depth images, fx = fy = 525, cx = 319.5, cy = 239.5.

``ReadOptions.depth_scale`` (depth units per metre), when given, overrides the layout's default.
"""

from __future__ import annotations

import functools
import io
import os
import re
import struct
import warnings
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image

from dm2_backend.formats import depth_image_noise
from dm2_backend.formats.depth_image_noise import DepthImageNoise
from dm2_backend.formats.registry import (
    ReadOptions,
    ScanSource,
    TrajectoryFormat,
    scan_source,
    trajectory_format,
)
from dm2_backend.kernel.scans import DEPTH_CAMERA, Scan, ScanSequence
from dm2_backend.kernel.trajectory import Trajectory, associate_by_time, validate_poses
from dm2_backend.runtime.errors import InputError

SEVEN_SCENES_INTRINSICS = (585.0, 585.0, 320.0, 240.0)
TUM_INTRINSICS = (525.0, 525.0, 319.5, 239.5)
DEPTH_SCALE = {"7-scenes": 1000.0, "tum": 5000.0}
SEVEN_SCENES_RATE = 30.0
SEVEN_SCENES_DEFAULT, TUM_DEFAULT = "7-Scenes default", "TUM RGB-D default"
#: where intrinsics or a depth scale came from when nothing was given for them: the layout's defaults
ASSUMED = (SEVEN_SCENES_DEFAULT, TUM_DEFAULT)
TUM_MAX_DIFF = 0.02
DEFAULT_STRIDE = 2
#: images the depth noise is measured on
NOISE_SAMPLE = 10
_FRAME = re.compile(r"frame-(\d+)\.depth\.png")


@dataclass
class DepthFolder:
    """What a depth sequence folder holds (images are read lazily)."""

    layout: str
    images: list[Path]
    timestamps: np.ndarray
    intrinsics: tuple[float, float, float, float]
    intrinsics_from: str
    scale: float
    scale_from: str
    reference: Trajectory | None = None
    notes: dict = field(default_factory=dict)


def layout_of(path: Path) -> str | None:
    """``"7-scenes"``, ``"tum"`` or None."""
    if not path.is_dir():
        return None
    if (path / "depth.txt").is_file():
        return "tum"
    with os.scandir(path) as it:
        if any(_FRAME.fullmatch(e.name) for e in it):
            return "7-scenes"
    return None


def _numbers(path: Path, count: int, what: str) -> np.ndarray:
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except FileNotFoundError:
        raise InputError(path, "no such file") from None
    try:
        values = np.array([float(v) for v in text.split()], dtype=np.float64)
    except ValueError as exc:
        raise InputError(path, f"expected {count} numbers ({what}): {exc}") from None
    if len(values) != count:
        raise InputError(path, f"expected {count} numbers ({what}), found {len(values)}")
    if not np.isfinite(values).all():
        raise InputError(path, f"{what} has NaN or infinite values")
    return values


def read_pose_file(path: Path) -> np.ndarray:
    """A 7-Scenes pose file: 4 x 4 camera-to-world matrix."""
    T = _numbers(path, 16, "a 4 x 4 pose").reshape(4, 4)
    if np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-6:
        raise InputError(path, f"last row of the 4 x 4 pose is {T[3].tolist()}, not [0, 0, 0, 1]")
    validate_poses(T[None], path)
    return T


def read_intrinsics_file(path: Path) -> tuple[float, float, float, float]:
    """``camera-intrinsics.txt``: the 3 x 3 matrix K."""
    K = _numbers(path, 9, "a 3 x 3 camera matrix").reshape(3, 3)
    if K[0, 0] <= 0 or K[1, 1] <= 0 or np.abs(K[2] - [0, 0, 1]).max() > 1e-9 or K[1, 0] != 0:
        raise InputError(path, "not a pinhole camera matrix [[fx 0 cx] [0 fy cy] [0 0 1]]")
    return float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])


def read_depth_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """TUM ``depth.txt``: ``timestamp filename`` a line, ``#`` comments; strictly increasing times."""
    stamps: list[float] = []
    names: list[str] = []
    lines: list[int] = []
    with open(path, encoding="utf-8", errors="replace") as fh:
        for no, line in enumerate(fh, 1):
            tokens = line.split()
            if not tokens or tokens[0].startswith("#"):
                continue
            try:
                stamp = float(tokens[0])
            except ValueError:
                stamp = float("nan")
            if len(tokens) != 2 or not np.isfinite(stamp):
                raise InputError(path, f"expected 'timestamp filename', got {line.strip()[:60]!r}", line=no)
            if "\x00" in tokens[1]:
                raise InputError(path, f"image file name {tokens[1][:60]!r} holds a NUL byte", line=no)
            if stamps and stamp <= stamps[-1]:
                kind = "duplicate" if stamp == stamps[-1] else "unsorted"
                raise InputError(path, f"{kind} timestamp {stamp!r} after {stamps[-1]!r}", line=no)
            stamps.append(stamp)
            names.append(tokens[1])
            lines.append(no)
    if not names:
        raise InputError(path, "lists no depth images")
    return np.array(stamps, dtype=np.float64), names


def _seven_scenes(path: Path, options: ReadOptions) -> DepthFolder:
    matches = [m for m in map(_FRAME.fullmatch, os.listdir(path)) if m]
    frames = sorted((int(m.group(1)), path / m.group(0)) for m in matches)
    index = np.array([i for i, _ in frames])
    images = [p for _, p in frames]
    if options.intrinsics is not None:
        intrinsics, origin = tuple(options.intrinsics), "--intrinsics"
    elif (path / "camera-intrinsics.txt").is_file():
        intrinsics, origin = read_intrinsics_file(path / "camera-intrinsics.txt"), "camera-intrinsics.txt"
    else:
        intrinsics, origin = SEVEN_SCENES_INTRINSICS, SEVEN_SCENES_DEFAULT
    pose_files = [p.with_name(p.name.replace(".depth.png", ".pose.txt")) for p in images]
    stamps = index / SEVEN_SCENES_RATE
    reference = None
    present = [p.is_file() for p in pose_files]
    if any(present):
        if not all(present):
            raise InputError(pose_files[present.index(False)], "pose file missing (other frames have one)")
        reference = Trajectory(np.stack([read_pose_file(p) for p in pose_files]), stamps,
                               meta={"source": str(path), "frame": "camera-to-world"})
    scale = DEPTH_SCALE["7-scenes"] if options.depth_scale is None else float(options.depth_scale)
    scale_from = SEVEN_SCENES_DEFAULT if options.depth_scale is None else "--depth-scale"
    return DepthFolder("7-scenes", images, stamps, intrinsics, origin, scale, scale_from, reference)


def _tum(path: Path, options: ReadOptions) -> DepthFolder:
    from dm2_backend.formats.tum import read_tum

    stamps, names = read_depth_list(path / "depth.txt")
    images = [path / n for n in names]
    if options.intrinsics is not None:
        intrinsics, origin = tuple(options.intrinsics), "--intrinsics"
    else:
        intrinsics, origin = TUM_INTRINSICS, TUM_DEFAULT
    scale = DEPTH_SCALE["tum"] if options.depth_scale is None else float(options.depth_scale)
    scale_from = TUM_DEFAULT if options.depth_scale is None else "--depth-scale"
    folder = DepthFolder("tum", images, stamps, intrinsics, origin, scale, scale_from)
    gt_path = path / "groundtruth.txt"
    if gt_path.is_file():
        gt = read_tum(gt_path)
        i_depth, i_gt = associate_by_time(stamps, gt.timestamps, TUM_MAX_DIFF)
        if len(i_depth):
            folder.reference = Trajectory(
                gt.poses[i_gt], stamps[i_depth],
                meta={"source": str(gt_path), "scan_index": i_depth, "gt_timestamps": gt.timestamps[i_gt]},
            )
        folder.notes["reference"] = (
            f"{len(i_depth)} of {len(stamps)} frames have a groundtruth pose within {TUM_MAX_DIFF} s")
    return folder


def load_folder(path: str | Path, options: ReadOptions | None = None) -> DepthFolder:
    path = Path(path)
    options = options or ReadOptions()
    layout = layout_of(path)
    if layout is None:
        raise InputError(path, "not a depth sequence folder (7-Scenes frame-*.depth.png or TUM depth.txt)")
    folder = _seven_scenes(path, options) if layout == "7-scenes" else _tum(path, options)
    fx, fy, _, _ = folder.intrinsics
    if len(folder.intrinsics) != 4 or fx <= 0 or fy <= 0:
        raise InputError(path, f"bad intrinsics {folder.intrinsics} (need fx fy cx cy with fx, fy > 0)")
    if not folder.scale > 0:
        raise InputError(path, f"depth scale must be positive, got {folder.scale}")
    return folder


#: largest depth image accepted (pixels), checked from the header before decoding (PIL's own bomb limit is
#: 179 megapixels; depth cameras give 0.3 to 1 megapixel)
MAX_DEPTH_PIXELS = 16_777_216  # 4096 x 4096
#: what PIL raises for broken or hostile images (its decoders raise SyntaxError for broken PNG chunks)
_IMAGE_ERRORS = (OSError, SyntaxError, ValueError, EOFError, struct.error, zlib.error, Image.DecompressionBombError)


def _check_png_chunks(path: Path, data: bytes) -> None:
    """Every PNG chunk's declared length fits in the file (PIL reads a chunk's declared length at once)."""
    if not data.startswith(b"\x89PNG\r\n\x1a\n"):
        return
    pos = 8
    while pos + 8 <= len(data):
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        if pos + 12 + length > len(data):
            raise InputError(path, f"truncated or corrupt PNG: chunk {kind!r} declares {length} bytes, "
                                   f"{max(len(data) - pos - 12, 0)} remain")
        if kind == b"IEND":
            return
        pos += 12 + length


def read_depth_image(path: Path) -> np.ndarray:
    """A 16-bit depth PNG as a uint16 array (H, W)."""
    try:
        data = path.read_bytes()
        _check_png_chunks(path, data)
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            with Image.open(io.BytesIO(data)) as img:
                if img.mode not in ("I;16", "I;16B", "I;16L", "I"):
                    raise InputError(path, f"not a 16-bit depth image (PIL mode {img.mode})")
                if img.width * img.height > MAX_DEPTH_PIXELS:
                    raise InputError(path, f"image of {img.width} x {img.height} pixels (limit {MAX_DEPTH_PIXELS})")
                depth = np.asarray(img)
    except FileNotFoundError:
        raise InputError(path, "no such file") from None
    except Image.DecompressionBombWarning as exc:
        raise InputError(path, f"cannot read the image: {exc}") from None
    except _IMAGE_ERRORS as exc:
        raise InputError(path, f"cannot read the image: {exc or type(exc).__name__}") from None
    if depth.ndim != 2 or depth.size == 0:
        raise InputError(path, f"not a single-channel depth image (shape {depth.shape})")
    if depth.dtype != np.uint16:
        depth = depth.clip(0, 65535).astype(np.uint16)
    return depth


@functools.lru_cache(maxsize=8)
def _rays(shape: tuple[int, int], intrinsics: tuple[float, ...], stride: int) -> tuple[np.ndarray, ...]:
    fx, fy, cx, cy = intrinsics
    u = np.arange(0, shape[1], stride, dtype=np.float64)
    v = np.arange(0, shape[0], stride, dtype=np.float64)
    rx = ((u - cx) / fx)[None, :].repeat(len(v), 0).astype(np.float32)
    ry = ((v - cy) / fy)[:, None].repeat(len(u), 1).astype(np.float32)
    return rx, ry


def back_project(
    depth: np.ndarray, intrinsics: tuple[float, float, float, float], scale: float, stride: int = 1,
    noise: DepthImageNoise | None = None,
) -> np.ndarray:
    """Camera-frame points (M, 3) float32 of the valid pixels (not 0, not 65535) of a depth image; with ``noise``,
    each pixel's depth smoothed over its neighbours on the same surface (:mod:`.depth_image_noise`)."""
    if noise is not None:
        d, scale = depth_image_noise.smooth(depth, scale, noise, stride), 1.0
    else:
        d = np.asarray(depth)[::stride, ::stride]
    valid = depth_image_noise.valid_depth(d)
    rx, ry = _rays(tuple(depth.shape), tuple(float(v) for v in intrinsics), stride)
    z = d[valid].astype(np.float32) / np.float32(scale)
    out = np.empty((len(z), 3), dtype=np.float32)
    np.multiply(rx[valid], z, out=out[:, 0])
    np.multiply(ry[valid], z, out=out[:, 1])
    out[:, 2] = z
    return out


def _stride(options: ReadOptions) -> int:
    stride = DEFAULT_STRIDE if options.stride is None else options.stride
    if not isinstance(stride, int) or isinstance(stride, bool) or stride < 1:
        raise InputError(None, f"stride must be a whole number >= 1, got {stride!r}")
    return stride


def measure_noise(folder: DepthFolder) -> DepthImageNoise | None:
    """The folder's depth noise, measured on :data:`NOISE_SAMPLE` images spread over the sequence."""
    picks = np.unique(np.linspace(0, len(folder.images) - 1, min(NOISE_SAMPLE, len(folder.images))).astype(int))
    return depth_image_noise.measure((read_depth_image(folder.images[i]) for i in picks), folder.scale)


def open_depth(path: Path, options: ReadOptions) -> ScanSequence:
    folder = load_folder(path, options)
    stride = _stride(options)
    noise = measure_noise(folder)
    if options.smooth_depth and noise is None:
        raise InputError(path, f"--smooth-depth: too few valid depth pixels to measure the noise on (at least "
                               f"{depth_image_noise.MIN_PIXELS} over {NOISE_SAMPLE} images)")
    smoothing = noise if options.smooth_depth else None

    def load(i: int) -> Scan:
        image = folder.images[i]
        points = back_project(read_depth_image(image), folder.intrinsics, folder.scale, stride, smoothing)
        if len(points) == 0:
            raise InputError(image, "empty scan (no valid depth)")
        return Scan(points=points, timestamp=float(folder.timestamps[i]))

    refs = {"reference": folder.reference} if folder.reference is not None else {}
    return ScanSequence(
        loader=load, count=len(folder.images), timestamps=folder.timestamps, source=str(path),
        trajectories=refs,
        meta={"layout": folder.layout, "intrinsics": folder.intrinsics, "depth_scale": folder.scale,
              "intrinsics_from": folder.intrinsics_from, "depth_scale_from": folder.scale_from,
              "assumed": [name for name, given in (("intrinsics", folder.intrinsics_from), ("depth_scale",
                                                   folder.scale_from)) if given in ASSUMED],
              "stride": stride, "image_noise": noise.summary() if noise is not None else None,
              "smoothed": smoothing is not None,
              "smoothing": smoothing.summary() if smoothing is not None else None,
              "image_noise_line": noise.describe() if noise is not None else None,
              "files": folder.images, **folder.notes},
    )


def read_reference(path: Path, options: ReadOptions) -> Trajectory:
    folder = load_folder(path, options)
    if folder.reference is None:
        where = "pose files" if folder.layout == "7-scenes" else "groundtruth.txt within 0.02 s of the frames"
        raise InputError(path, f"no reference poses ({where})")
    return folder.reference


def sniff(path: Path) -> bool:
    return layout_of(path) is not None


def describe(path: Path) -> list[tuple[str, str]]:
    folder = load_folder(path)
    fx, fy, cx, cy = folder.intrinsics
    rows = [
        ("layout", f"{folder.layout}, {len(folder.images)} depth images"),
        ("intrinsics", f"fx {fx:g} fy {fy:g} cx {cx:g} cy {cy:g} ({folder.intrinsics_from})"),
        ("depth scale", f"{folder.scale:g} units per metre ({folder.scale_from})"),
    ]
    return rows + [(k, v) for k, v in folder.notes.items()]


_DESCRIPTION = "depth image sequence (7-Scenes or TUM RGB-D layout), back-projected to camera-frame points"
scan_source(ScanSource("depth", _DESCRIPTION, open_depth, ("/",), sniff, describe, sensor=DEPTH_CAMERA))
trajectory_format(TrajectoryFormat(
    "depth", "reference poses of a depth image sequence folder (7-Scenes pose files / TUM groundtruth.txt)",
    read_reference, None, ("/",), sniff, describe,
))
