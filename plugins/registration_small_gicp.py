"""Pairwise registration ``small-gicp``: the ``icp`` registration's pairs, initial guesses and gates with
small_gicp's registration (Koide 2024); optional dependency (``pip install dm2[gicp]``)."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from dm2_backend.algorithms.common import Cloud, Match, lengths, project_planar
from dm2_backend.algorithms.gates import coverage
from dm2_backend.algorithms.pairwise import PairwiseRegistration
from dm2_backend.kernel.prepared import Frames
from dm2_backend.runtime.errors import InputError

TYPES = ("GICP", "VGICP", "ICP", "PLANE_ICP")


@dataclass
class SmallGicpRegistration(PairwiseRegistration):
    """Options as ``icp``; ``method`` is a small_gicp registration type (GICP, VGICP, ICP, PLANE_ICP)."""

    name: ClassVar[str] = "small-gicp"
    #: the optional package this plugin needs and the extra that installs it (``dm2 plugins`` reports it)
    requires: ClassVar[tuple[str, str]] = ("small_gicp", "dm2[gicp]")

    method: str = "GICP"

    def _check(self, frames: Frames) -> None:
        try:
            import small_gicp
        except ImportError:
            raise InputError(None, "registration 'small-gicp' needs small_gicp: install dm2[gicp]") from None
        if self.method not in TYPES:
            raise InputError(None, f"small-gicp: unknown method {self.method!r}; choices: {', '.join(TYPES)}")
        self._sg = small_gicp

    def _build(self, frames: Frames, used: list[int], fine: float, pool: ThreadPoolExecutor) -> list:
        """Per frame: a KD-tree for the gates and, except for VGICP (whose voxel maps depend on the pass),
        small_gicp's down-sampled cloud with covariances and its KD-tree, made once per frame instead of
        once per pair (each frame is in about eight pairs)."""
        scale = lengths(frames)
        self._resolution = 0.5 * max(scale.voxel, scale.spacing)

        def build(f: int) -> Cloud:
            cloud = Cloud(frames.points[f], frames.planar, fine).ensure("point-to-point")
            if self.method != "VGICP":
                cloud.small_gicp = self._sg.preprocess_points(np.asarray(frames.points[f], dtype=np.float64),
                                                             downsampling_resolution=self._resolution,
                                                             num_neighbors=10, num_threads=1)
            return cloud

        return list(pool.map(build, used))

    def _register_pair(self, frames: Frames, a: int, b: int, init: np.ndarray, fine: float) -> Match:
        T = init
        for d in (4.0 * fine, fine):
            if self.method == "VGICP":
                result = self._sg.align(
                    np.asarray(frames.points[a], dtype=np.float64),
                    np.asarray(frames.points[b], dtype=np.float64),
                    init_T_target_source=T,
                    registration_type=self.method,
                    downsampling_resolution=self._resolution,
                    voxel_resolution=d,
                    max_correspondence_distance=d,
                    num_threads=1,
                )
            else:
                (target, tree), (source, _) = self._clouds[a].small_gicp, self._clouds[b].small_gicp
                result = self._sg.align(target, source, tree, init_T_target_source=T, registration_type=self.method,
                                        max_correspondence_distance=d, num_threads=1)
            T = np.asarray(result.T_target_source, dtype=np.float64)
            if frames.planar:
                T = project_planar(T)
        return Match(T, *coverage(self._clouds[b], self._clouds[a], T, fine))
