"""HBA data folders (hku-mars/HBA, used with BALM): ``<folder>/pcd/<i>.pcd`` scans numbered from 0 and
``<folder>/pose.json``, one pose a line per scan: ``tx ty tz qw qx qy qz`` (quaternion scalar first; plain text
despite the name), the pose of the scan in the world frame.

HBA reads the file with ``mypcl::read_pose`` (``file >> tx >> ty >> tz >> w >> x >> y >> z`` until the first
failure, ``Eigen::Quaterniond(w, x, y, z)``) and the scans as ``pcd/`` + the index, zero-padded to
``pcd_name_fill_num`` digits (0: none; 5 for its KITTI examples) + ``.pcd``; it writes its result back over
``pose.json`` in the same form (6 significant digits, re-anchored at the first pose).

dm2 reads the pose file strictly: 7 finite numbers a line (blank and ``#`` lines skipped), a quaternion whose
norm is within ``_text.QUAT_NORM_TOL`` of 1 (normalised), else one line naming the file and line. The folder
(``--scans FOLDER``) is a scan source whose ``pose.json`` is the trajectory to refine unless ``--poses`` is
given; its scans must be ``.pcd`` named by the numbers 0 to N-1 (one padding for all) and as many as the poses.
There are no timestamps (the pose index serves), unless a ``times.txt`` lies in the folder (as for any scan
folder). dm2 writes poses at full precision (shortest exact text) in the frame it was given, and a run on an HBA
folder writes its result as ``hba/pose.json`` in the run folder (see :func:`write_hba_folder`), never over the
input's ``pose.json``.
"""

from __future__ import annotations

from pathlib import Path

from dm2_backend.formats import _text, scan_folder
from dm2_backend.formats.registry import ReadOptions, ScanSource, TrajectoryFormat, scan_source, trajectory_format
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.scans import ScanSequence
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.runtime.errors import InputError

POSE_FILE = "pose.json"
SCANS_DIR = "pcd"
WHAT = "HBA pose: tx ty tz qw qx qy qz"


def read_hba(path: str | Path, options: ReadOptions | None = None) -> Trajectory:
    """Read an HBA ``pose.json`` (see the module docstring); no timestamps."""
    path = Path(path)
    rows, lines = _text.read_table(path, (7,), WHAT)
    _text.check_quaternions(path, rows[:, 3:7], lines)
    traj = Trajectory(poses=se3.from_xyz_quat(rows[:, :3], rows[:, 3:7], "wxyz"))
    return _text.validate(traj, path, lines)


def write_hba(traj: Trajectory, path: str | Path, options: ReadOptions | None = None) -> None:
    """Write ``traj`` as an HBA ``pose.json``: ``tx ty tz qw qx qy qz`` a line (exact float text, ``qw >= 0``);
    timestamps are not stored."""
    xyz, q = se3.to_xyz_quat(traj.poses, "wxyz")
    with atomic_write(Path(path)) as fh:
        for p, r in zip(xyz, q, strict=True):
            fh.write(f"{_text.fmt_row(p)} {_text.fmt_row(r)}\n")


def sniff(path: Path) -> bool:
    """7 numeric columns whose last four are unit quaternions."""
    return _text.sniff_poses(path, 7, 3)


FORMAT = trajectory_format(
    TrajectoryFormat(
        name="hba",
        description="HBA / BALM pose.json (plain text): tx ty tz qw qx qy qz a line, one per scan pcd/<i>.pcd",
        read=read_hba,
        write=write_hba,
        suffixes=(".json",),
        sniff=sniff,
        stamped=False,
    )
)


def is_hba_folder(path: Path) -> bool:
    """A folder holding ``pose.json`` and a ``pcd/`` folder."""
    path = Path(path)
    return path.is_dir() and (path / POSE_FILE).is_file() and (path / SCANS_DIR).is_dir()


def scan_numbers(folder: Path) -> tuple[list[Path], int]:
    """The ``.pcd`` files of an HBA ``pcd/`` folder in index order and HBA's ``pcd_name_fill_num`` for their
    names (0: not padded); :class:`InputError` unless they are named by the numbers 0 to N-1 with one padding."""
    files = scan_folder.scan_files(folder)
    kind = files[0].suffix.lower()
    if kind != ".pcd":
        raise InputError(folder, f"holds {kind} scans; HBA reads pcd/<i>.pcd (give --scans {folder} and --poses "
                                 f"{folder.parent / POSE_FILE} --poses-format hba to read these)")
    stems = [f.stem for f in files]
    bad = next((f for f, s in zip(files, stems, strict=True) if not (s.isascii() and s.isdigit())), None)
    if bad is not None:
        raise InputError(bad, "is not named by its index (HBA reads pcd/0.pcd, pcd/1.pcd, ...)")
    numbers = [int(s) for s in stems]
    missing = next((i for i, n in enumerate(numbers) if n != i), None)
    if missing is not None:
        raise InputError(folder, f"has no scan {missing} (HBA numbers the scans 0 to N-1 with no gap; found "
                                 f"{files[missing].name} in its place)")
    fill = len(stems[0])  # scan 0's name: as many digits as HBA pads to (setw(fill), setfill('0'))
    odd = next((f for f, s, n in zip(files, stems, numbers, strict=True) if s != str(n).zfill(fill)), None)
    if odd is not None:
        raise InputError(odd, f"is not padded as {files[0].name} is (HBA pads every name to one width, "
                              "pcd_name_fill_num)")
    return files, 0 if fill == 1 else fill


def open_hba(path: Path, options: ReadOptions) -> ScanSequence:
    """The scans of an HBA folder; ``meta["poses_file"]`` names its ``pose.json`` (read as ``--poses`` when none
    is given, ``pipeline.inputs``)."""
    folder = Path(path)
    if not is_hba_folder(folder):
        raise InputError(folder, f"not an HBA folder (expected {POSE_FILE} and a {SCANS_DIR}/ folder in it)")
    scans = folder / SCANS_DIR
    files, fill = scan_numbers(scans)
    stamps, origin = scan_folder.find_timestamps(scans, files, options)
    return ScanSequence(
        loader=lambda i: scan_folder.read_scan_file(files[i]),
        count=len(files),
        timestamps=stamps,
        source=str(folder),
        meta={"files": files, "times_from": origin, "kind": ".pcd", "layout": "hba", "scans_folder": str(scans),
              "poses_file": str(folder / POSE_FILE), "poses_format": FORMAT.name, "pcd_name_fill_num": fill},
    )


def sniff_folder(path: Path) -> bool:
    return is_hba_folder(path) and scan_folder.sniff(path / SCANS_DIR)


def describe(path: Path) -> list[tuple[str, str]]:
    files, fill = scan_numbers(Path(path) / SCANS_DIR)
    return [
        ("HBA folder", str(path)),
        ("scan files", f"{len(files)} x .pcd ({files[0].name} .. {files[-1].name}), pcd_name_fill_num {fill}"),
        ("poses", f"{Path(path) / POSE_FILE} (the trajectory refined unless --poses is given)"),
    ]


scan_source(ScanSource(
    name="hba",
    description="HBA / BALM folder: pcd/<i>.pcd scans and pose.json (tx ty tz qw qx qy qz), read as scans and "
                "poses; a run writes its result as hba/pose.json",
    open=open_hba,
    suffixes=("/",),
    sniff=sniff_folder,
    describe=describe,
))


def write_hba_folder(folder: Path, traj: Trajectory) -> list[str]:
    """``folder/pose.json``: the poses as HBA reads them, to go with the input's ``pcd/`` folder (HBA's
    ``data_path`` is a folder holding both; dm2 never writes into the input's folder). Returns the files
    written, relative to ``folder``'s parent."""
    folder = Path(folder)
    write_hba(traj, folder / POSE_FILE)
    return [f"{folder.name}/{POSE_FILE}"]
