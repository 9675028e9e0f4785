"""EuRoC MAV ground-truth CSV (read only).

``timestamp [ns], p_x, p_y, p_z, q_w, q_x, q_y, q_z`` followed by velocity and bias columns (17 in all,
``state_groundtruth_estimate0/data.csv``) or without them (8 columns). The header is a ``#`` line (a first
line of column names without ``#`` is accepted too). Quaternions are w-first. Nanosecond stamps are parsed
as integers and turned into seconds with one correctly rounded division.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dm2_backend.formats import _text
from dm2_backend.formats.registry import ReadOptions, TrajectoryFormat, trajectory_format
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.runtime.errors import InputError

COLUMNS = (17, 8)
WHAT = "EuRoC: timestamp[ns] px py pz qw qx qy qz [+ 9 velocity/bias columns]"


def _stamp_ns(path: Path, number: int, text: str) -> int:
    try:
        ns = int(text)
    except ValueError:
        value = _text.parse_floats(path, number, [text])[0]
        if value != int(value):
            raise InputError(path, f"timestamp {text!r} is not whole nanoseconds", line=number) from None
        ns = int(value)
    if not -(2**63) <= ns < 2**63:  # ROS / EuRoC stamps are int64 nanoseconds
        raise InputError(path, f"timestamp {text[:40]!r} is beyond the int64 nanosecond range", line=number)
    return ns


def read_euroc(path: str | Path, options: ReadOptions | None = None) -> Trajectory:
    """Read a EuRoC ground-truth CSV (see ``ReadOptions.duplicate_times``)."""
    path = Path(path)
    options = options or ReadOptions()
    stamps_ns: list[int] = []
    rows: list[list[str]] = []
    numbers: list[int] = []
    width = None
    for number, fields in _text.data_lines(_text.open_text(path)):
        if width is None and not rows and not _text.is_float(fields[0]) and fields[0].isidentifier():
            continue  # a header line without '#'
        if width is None:
            if len(fields) not in COLUMNS:
                raise InputError(path, _text.count_problem(len(fields), COLUMNS, WHAT), line=number)
            width = len(fields)
        elif len(fields) != width:
            raise InputError(path, _text.count_problem(len(fields), (width,), WHAT), line=number)
        stamps_ns.append(_stamp_ns(path, number, fields[0]))
        rows.append(fields[1:8])
        numbers.append(number)
    if not rows:
        raise InputError(path, "no pose lines (empty file?)")
    data = _text.to_floats(path, rows, numbers)
    lines = np.asarray(numbers)
    stamps = np.asarray([n / 1_000_000_000 for n in stamps_ns], dtype=np.float64)
    meta: dict = {"columns": width}
    stamps, data, lines, repeats_ok = _text.duplicate_times(path, stamps, data, lines, options, meta)
    _text.check_quaternions(path, data[:, 3:7], lines)
    poses = se3.from_xyz_quat(data[:, 0:3], data[:, 3:7], "wxyz")
    return _text.validate(Trajectory(poses=poses, timestamps=stamps, meta=meta), path, lines, repeats_ok)


def sniff(path: Path) -> bool:
    """First data line (after an optional header) has 17 or 8 numeric comma-separated fields."""
    with open(path, encoding="utf-8") as fh:
        lines = [fh.readline(), fh.readline()]
    for _, fields in _text.data_lines([line for line in lines if "," in line]):
        if all(_text.is_float(f) for f in fields):
            return len(fields) in COLUMNS
    return False


FORMAT = trajectory_format(
    TrajectoryFormat(
        name="euroc",
        description="EuRoC ground-truth CSV: ns timestamps, position, w-first quaternion (read only)",
        read=read_euroc,
        write=None,
        suffixes=(".csv",),
        sniff=sniff,
    )
)
