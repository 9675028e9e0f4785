"""Pairwise registration plugins ``icp`` (open3d GICP in 3D, 2D point-to-line for planar scans, by default) and
``gicp`` (Generalized ICP always); the machinery, options and gates are in :mod:`dm2_backend.algorithms.pairwise`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from dm2_backend.algorithms.pairwise import PairwiseRegistration


@dataclass
class IcpRegistration(PairwiseRegistration):
    """The default registration: ICP of each neighbour onto its anchor, gated (see the options)."""

    name: ClassVar[str] = "icp"


@dataclass
class GicpRegistration(PairwiseRegistration):
    """The ``icp`` registration with open3d's Generalized ICP."""

    name: ClassVar[str] = "gicp"

    method: str = "gicp"
