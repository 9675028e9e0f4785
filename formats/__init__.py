"""Input/output adapters. Importing this package registers every built-in format, then the formats other
packages add through the ``dm2.formats`` entry-point group (see ``registry.load_third_party``)."""

from dm2_backend.formats import (  # noqa: F401  (each module registers itself)
    bag,
    balm,
    carmen,
    depth,
    dm2_priors,
    euroc,
    g2o,
    hba,
    kitti,
    kitti_raw,
    nclt,
    poses_npy,
    scan_folder,
    tum,
)
from dm2_backend.formats.registry import (
    SCAN_SOURCES,
    TRAJECTORY_FORMATS,
    ReadOptions,
    detect_scan_source,
    detect_trajectory_format,
    format_for_output,
    load_third_party,
    open_scans,
    read_trajectory,
    write_trajectory,
)

load_third_party()

__all__ = [
    "SCAN_SOURCES",
    "TRAJECTORY_FORMATS",
    "ReadOptions",
    "detect_scan_source",
    "detect_trajectory_format",
    "format_for_output",
    "open_scans",
    "read_trajectory",
    "write_trajectory",
]
