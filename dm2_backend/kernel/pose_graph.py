"""A pose graph: nodes with initial poses and relative-pose edges with information matrices (what the g2o
format holds, what the pose-graph baselines solve)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

import numpy as np

from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory

#: g2o SE3 ordering [x y z qx qy qz] -> rotation-first [qx qy qz x y z] (GTSAM Pose3 tangent order)
ROTATION_FIRST = np.array([3, 4, 5, 0, 1, 2])
#: where a planar graph's [x y theta] sit in the SE(3) tangent [x y z rx ry rz] (rad, as GTSAM reads g2o's
#: information), and the axes a planar pose leaves at 0 (z, roll, pitch)
PLANAR_AXES = np.array([0, 1, 5])
HELD_AXES = np.array([2, 3, 4])


def lift_planar_information(information: np.ndarray, hold: float) -> np.ndarray:
    """Planar informations (E, 3, 3) on [x y theta] as SE(3) ones (E, 6, 6): on x, y and yaw
    (:data:`PLANAR_AXES`), and ``hold`` on z, roll and pitch (:data:`HELD_AXES`)."""
    information = np.asarray(information, dtype=np.float64).reshape(-1, 3, 3)
    info = np.zeros((len(information), 6, 6))
    info[:, PLANAR_AXES[:, None], PLANAR_AXES[None, :]] = information
    info[:, HELD_AXES, HELD_AXES] = hold
    return info


@dataclass(frozen=True)
class GraphBuild:
    """How dm2 built a graph from registrations: its odometry edges (how many from the warm start's own steps,
    where no registration held), its loop edges, the registrations' rmse floor (m), the information model in
    words and how many edges carry a registration's Hessian."""

    odometry_edges: int
    odometry_from_warm_start: int
    loop_edges: int
    rmse_floor: float
    information_model: str
    hessian_edges: int

    def summary(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class HeldAxes:
    """The tangent axes a planar graph lifted to SE(3) holds still (z, roll, pitch) and their information."""

    axes: tuple[int, ...]
    information: float


@dataclass
class PoseGraph:
    """Nodes (ascending ids) with initial poses, and relative-pose edges with information matrices; ``source``:
    the file it was read from; ``built``: how dm2 built it; ``held``: the axes a lifted planar graph holds;
    ``meta``: what the g2o reader noted (skipped lines, nodes placed from edges, informations not PSD)."""

    ids: np.ndarray  # (N,) int node ids, ascending
    poses: np.ndarray  # (N, 4, 4) initial poses
    edges: np.ndarray  # (E, 2) int node ids (i, j)
    relative: np.ndarray  # (E, 4, 4) pose of j in the frame of i
    information: np.ndarray  # (E, 6, 6) g2o order [x y z qx qy qz], or (E, 3, 3) [x y theta] when planar
    planar: bool = False
    fixed: list[int] = field(default_factory=list)
    meta: dict = field(default_factory=dict)
    source: str | None = None
    built: GraphBuild | None = None
    held: HeldAxes | None = None
    #: (E,) bool: edges solved as given, without a robust kernel (steps the step guard holds); None: none
    exact: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.ids)

    def index_of(self) -> dict[int, int]:
        """Node id -> row in :attr:`poses`."""
        return {int(n): k for k, n in enumerate(self.ids)}

    def edge_rows(self) -> np.ndarray:
        """Edges as rows of :attr:`poses` (E, 2)."""
        index = self.index_of()
        return np.vectorize(index.__getitem__, otypes=[int])(self.edges).reshape(-1, 2)

    def information_rotation_first(self) -> np.ndarray:
        """Information matrices in GTSAM's tangent order (rotation first for 3D; unchanged for 2D)."""
        if self.planar:
            return self.information.copy()
        return self.information[:, ROTATION_FIRST][:, :, ROTATION_FIRST]

    def holding(self, steps: np.ndarray, relative: np.ndarray, information: np.ndarray) -> PoseGraph:
        """This graph with one exact edge per step ``steps[k]`` (node row ``k`` to the next) at ``relative[k]`` with
        ``information[k]`` (this graph's order and size): those steps held where the information pins them."""
        steps = np.asarray(steps, dtype=int)
        relative = np.asarray(relative, dtype=np.float64).reshape(-1, 4, 4)
        if self.planar:
            relative = se3.from_xy_yaw(se3.to_xy_yaw(relative)).reshape(-1, 4, 4)
        dim = 3 if self.planar else 6
        exact = self.exact if self.exact is not None else np.zeros(len(self.edges), bool)
        return replace(self, edges=np.concatenate([self.edges, np.stack([self.ids[steps], self.ids[steps + 1]], 1)]),
                       relative=np.concatenate([self.relative, relative]),
                       information=np.concatenate([self.information,
                                                   np.asarray(information, dtype=np.float64).reshape(-1, dim, dim)]),
                       exact=np.concatenate([exact, np.ones(len(steps), bool)]))

    def lifted_to_se3(self, hold: float) -> PoseGraph:
        """This graph as an SE(3) one: a planar graph's [x y theta] information on x, y and yaw
        (:data:`PLANAR_AXES`), and ``hold`` (1/m^2, 1/rad^2) on z, roll and pitch, so they stay where the poses have
        them (:attr:`held` records it); a 3D graph as it is."""
        if not self.planar:
            return self
        info = lift_planar_information(self.information, hold)
        held = HeldAxes(tuple(HELD_AXES.tolist()), float(hold))
        return replace(self, information=info, planar=False, held=held)

    def summary(self) -> dict:
        """Where the graph came from and how it was built, for ``report.json``."""
        out = {} if self.source is None else {"source": self.source}
        if self.built is not None:
            out.update(self.built.summary())
        if self.held is not None:
            out["held"] = {"axes": list(self.held.axes), "information": self.held.information}
        return {**out, **self.meta}

    def to_trajectory(self) -> Trajectory:
        meta = {"edges": len(self.edges), **self.summary()}
        return Trajectory(poses=self.poses, frame_ids=[str(int(n)) for n in self.ids], planar=self.planar,
                          meta=meta)

    @classmethod
    def from_trajectory(cls, traj: Trajectory) -> PoseGraph:
        """Vertices of ``traj`` and odometry edges between consecutive poses with identity information."""
        ids = _ids_of(traj)
        n = len(traj)
        dim = 3 if traj.planar else 6
        return cls(
            ids=ids, poses=traj.poses.copy(),
            edges=np.stack([ids[:-1], ids[1:]], axis=1).reshape(-1, 2),
            relative=se3.relative(traj.poses[:-1], traj.poses[1:]).reshape(-1, 4, 4),
            information=np.tile(np.eye(dim), (max(n - 1, 0), 1, 1)),
            planar=traj.planar,
        )


def _ids_of(traj: Trajectory) -> np.ndarray:
    ids = traj.frame_ids
    if ids is not None and all(i.isdigit() for i in ids):
        values = np.array([int(i) for i in ids])
        if np.all(np.diff(values) > 0):
            return values
    return np.arange(len(traj))


def indefinite(info: np.ndarray) -> np.ndarray:
    """Which of the (E, d, d) information matrices are not positive semi-definite (beyond rounding)."""
    if len(info) == 0:
        return np.zeros(0, bool)
    w = np.linalg.eigvalsh(info)
    return w[:, 0] < -1e-9 * np.maximum(np.abs(w).max(axis=1), 1.0)
