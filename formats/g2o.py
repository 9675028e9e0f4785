"""g2o pose graphs: ``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT`` (3D) and ``VERTEX_SE2`` / ``EDGE_SE2`` (2D).

* ``VERTEX_SE3:QUAT id x y z qx qy qz qw`` and ``EDGE_SE3:QUAT i j x y z qx qy qz qw`` + the 21 upper-triangle
  entries (row-major) of the 6x6 information matrix, ordered ``[x y z qx qy qz]`` (translation first; GTSAM's
  Pose3 noise is rotation first, see :meth:`PoseGraph.information_rotation_first`).
* ``VERTEX_SE2 id x y theta`` and ``EDGE_SE2 i j x y theta`` + 6 upper-triangle entries ``[x y theta]``.
* An edge ``i j`` holds the pose of node ``j`` in the frame of node ``i``. ``FIX id...`` lines mark fixed
  nodes. Other lines (``VERTEX_XY``, ``EDGE_SE2_XY``, ...) are skipped and counted in ``meta["skipped"]``.

Quaternions are normalised as ``gtsam.readG2o`` does. Nodes without a vertex line (an edges-only file) get
initial poses by chaining the odometry edges ``i -> i+1`` from identity, then any other edge in file
order, which is what ``gtsam.readG2o`` gives for the usual edges-only file. Information matrices that are
not positive semi-definite get one warning and are kept as the file writes them, so that a solver optimises
what the file says (``information="nearest-psd"``: read as the nearest positive-definite ones, see
:func:`_project_information`).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from dm2_backend.formats import _text
from dm2_backend.formats.registry import ReadOptions, TrajectoryFormat, trajectory_format
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.pose_graph import PoseGraph
from dm2_backend.kernel.trajectory import Trajectory, validate_poses
from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.runtime.errors import InputError

log = logging.getLogger(__name__)

#: tag -> (fields after the tag, 3D?)
TAGS = {"VERTEX_SE2": (4, False), "EDGE_SE2": (11, False), "VERTEX_SE3:QUAT": (8, True),
        "EDGE_SE3:QUAT": (30, True)}


#: information entries beyond this overflow the eigen-decomposition (squares of 1e154 are inf)
MAX_INFORMATION = 1e150


def _check_magnitudes(info: np.ndarray, lines: np.ndarray, path: Path) -> None:
    big = np.abs(info).max(axis=(1, 2), initial=0.0) > MAX_INFORMATION
    if big.any():
        k = int(np.argmax(big))
        raise InputError(path, f"information matrix entry beyond {MAX_INFORMATION:.0e}", line=int(lines[k]))


def _upper_to_full(values: np.ndarray, dim: int) -> np.ndarray:
    M = np.zeros((len(values), dim, dim))
    iu = np.triu_indices(dim)
    M[:, iu[0], iu[1]] = values
    M[:, iu[1], iu[0]] = values
    return M


class _Parser:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.is3d: bool | None = None
        self.vertices: dict[int, tuple[int, list[str]]] = {}
        self.edges: list[tuple[int, int, list[str], int]] = []
        self.fixed: list[tuple[int, int]] = []
        self.skipped: dict[str, int] = {}

    def fail(self, problem: str, line: int) -> InputError:
        return InputError(self.path, problem, line=line)

    def node_id(self, text: str, line: int) -> int:
        try:
            node = int(text)
        except ValueError:
            raise self.fail(f"node id {text!r} is not an integer", line) from None
        if not -(2**63) <= node < 2**63:
            raise self.fail(f"node id {text[:40]!r} is beyond the int64 range", line)
        return node

    def line(self, number: int, fields: list[str]) -> None:
        tag = fields[0]
        if tag == "FIX":
            if len(fields) < 2:
                raise self.fail("FIX without a node id", number)
            self.fixed += [(self.node_id(f, number), number) for f in fields[1:]]
            return
        if tag not in TAGS:
            self.skipped[tag] = self.skipped.get(tag, 0) + 1
            return
        count, is3d = TAGS[tag]
        if len(fields) - 1 != count:
            raise self.fail(f"{tag} has {len(fields) - 1} fields, expected {count}", number)
        if self.is3d is None:
            self.is3d = is3d
        elif self.is3d != is3d:
            raise self.fail(f"{tag} in a {'3D' if self.is3d else '2D'} graph (2D and 3D mixed)", number)
        if tag.startswith("VERTEX"):
            node = self.node_id(fields[1], number)
            if node in self.vertices:
                first = self.vertices[node][0]
                raise self.fail(f"vertex {node} defined twice (first on line {first})", number)
            self.vertices[node] = (number, fields[2:])
        else:
            i, j = self.node_id(fields[1], number), self.node_id(fields[2], number)
            if i == j:
                raise self.fail(f"edge from node {i} to itself", number)
            self.edges.append((i, j, fields[3:], number))


def _table(path: Path, rows: list[list[str]], lines: np.ndarray, width: int) -> np.ndarray:
    if not rows:
        return np.zeros((0, width))
    return _text.to_floats(path, rows, lines.tolist())


def _poses_from(values: np.ndarray, lines: np.ndarray, is3d: bool, path: Path) -> np.ndarray:
    if len(values) == 0:
        return se3.identity(0)
    if is3d:
        _text.check_quaternions(path, values[:, 3:7], lines)
        return se3.from_xyz_quat(values[:, :3], values[:, 3:7], "xyzw")
    return se3.from_xy_yaw(values[:, :3])


#: eigenvalues of a projected information matrix are at least this fraction of its largest (invertible)
PSD_FLOOR = 1e-9
#: how information matrices that are not positive semi-definite are read: as the file writes them, or the
#: nearest positive-definite ones
INFORMATION_MODES = ("file", "nearest-psd")


def _project_information(info: np.ndarray, lines: np.ndarray, path: Path, project: bool = True,
                         warn: bool = True) -> int:
    """Replace (in place) information matrices that are not positive semi-definite by the nearest ones that
    are, with negative eigenvalues raised to :data:`PSD_FLOOR` of the largest (kept invertible, so that
    gtsam's and g2o's Cholesky factorisations work); one warning says how many and the first line. Returns
    how many were not positive semi-definite; ``project=False`` warns (unless ``warn=False``: the caller
    says how its solver weighs them) and keeps them as they are.

    Real graphs hold such matrices (SE-Sync's ``cubicle.g2o``). ``gtsam.readG2o`` keeps them as they are and
    its noise model then factorises them wrongly without a word (an LLT of an indefinite matrix; NaN sigmas
    for a diagonal one), so a solver would weigh those edges arbitrarily."""
    if len(info) == 0:
        return 0
    w, V = np.linalg.eigh(info)
    top = np.maximum(np.abs(w).max(axis=1), 1.0)
    bad = w[:, 0] < -1e-9 * top
    if bad.any() and not project:
        if warn:
            log.warning("%s: %d of %d information matrices are not positive semi-definite (first on line %d); "
                        "optimised as the file writes them (--information nearest-psd: the nearest "
                        "positive-definite ones)", path, int(bad.sum()), len(info), int(lines[int(np.argmax(bad))]))
    elif bad.any():
        floor = PSD_FLOOR * np.abs(w[bad]).max(axis=1, keepdims=True)
        wb = np.maximum(w[bad], floor)
        info[bad] = (V[bad] * wb[:, None, :]) @ np.swapaxes(V[bad], 1, 2)
        info[bad] = (info[bad] + np.swapaxes(info[bad], 1, 2)) / 2
        log.warning("%s: %d of %d information matrices are not positive semi-definite (first on line %d); "
                    "using the nearest positive-definite ones (--information nearest-psd)", path, int(bad.sum()),
                    len(info),
                    int(lines[int(np.argmax(bad))]))
    return int(bad.sum())


def _fill_missing(ids: np.ndarray, known: dict[int, np.ndarray], edges: np.ndarray, rel: np.ndarray) -> int:
    """Initial poses of nodes without a vertex, from odometry edges i -> i+1 first, then any edge.

    Returns how many nodes got a pose."""
    before = len(known)
    odometry = np.flatnonzero(edges[:, 1] == edges[:, 0] + 1)
    order = [odometry[np.argsort(edges[odometry, 0], kind="stable")], np.arange(len(edges))]
    while True:
        changed = True
        while changed:
            changed = False
            for group in order:
                for e in group:
                    i, j = int(edges[e, 0]), int(edges[e, 1])
                    if i in known and j not in known:
                        known[j] = known[i] @ rel[e]
                        changed = True
                    elif j in known and i not in known:
                        known[i] = known[j] @ se3.inverse(rel[e])
                        changed = True
        missing = set(ids.tolist()) - known.keys()
        if not missing:
            break
        known[min(missing)] = np.eye(4)  # a component without any vertex starts at identity
    return len(known) - before


def read_g2o(path: str | Path, information: str = "file", warn: bool = True) -> PoseGraph:
    """Parse a g2o file; :class:`InputError` naming the line for anything malformed. ``information``: how
    matrices that are not positive semi-definite are read (:data:`INFORMATION_MODES`); ``warn=False``: no
    warning for those kept as written (the solver's own says how it weighs them)."""
    if information not in INFORMATION_MODES:
        raise ValueError(f"information must be one of {', '.join(INFORMATION_MODES)}, not {information!r}")
    path = Path(path)
    parser = _Parser(path)
    for number, fields in _text.data_lines(_text.open_text(path)):
        parser.line(number, fields)
    if parser.is3d is None:
        raise InputError(path, "no VERTEX_SE2/EDGE_SE2/VERTEX_SE3:QUAT/EDGE_SE3:QUAT lines")
    is3d = parser.is3d
    v_ids = np.array(sorted(parser.vertices), dtype=int)
    v_lines = np.array([parser.vertices[n][0] for n in v_ids], dtype=int)
    v_values = _table(path, [parser.vertices[n][1] for n in v_ids], v_lines, 7 if is3d else 3)
    v_poses = _poses_from(v_values, v_lines, is3d, path)
    edges = np.array([(i, j) for i, j, _, _ in parser.edges], dtype=int).reshape(-1, 2)
    e_lines = np.array([n for *_, n in parser.edges], dtype=int)
    e_values = _table(path, [v for _, _, v, _ in parser.edges], e_lines, 28 if is3d else 9)
    k = 7 if is3d else 3
    relative = _poses_from(e_values[:, :k], e_lines, is3d, path).reshape(-1, 4, 4)
    matrices = _upper_to_full(e_values[:, k:], 6 if is3d else 3)
    _check_magnitudes(matrices, e_lines, path)
    not_psd = _project_information(matrices, e_lines, path, project=information == "nearest-psd", warn=warn)
    ids = np.union1d(v_ids, edges.reshape(-1)).astype(int)
    known = {int(n): T for n, T in zip(v_ids, v_poses, strict=True)}
    with np.errstate(over="ignore", invalid="ignore"):  # chained huge numbers: refused just below, no warnings
        filled = _fill_missing(ids, known, edges, relative) if len(known) < len(ids) else 0
    for node, number in parser.fixed:
        if node not in known:
            raise InputError(path, f"FIX of unknown node {node}", line=number)
    poses = np.stack([known[int(n)] for n in ids]).reshape(-1, 4, 4)
    validate_poses(poses, path)  # before any solver: chained edges can carry a position past any map
    meta: dict = {}
    if filled:
        meta["initialised_from_edges"] = filled
    if parser.skipped:
        meta["skipped"] = dict(parser.skipped)
    if not_psd:
        meta["information_not_psd"] = not_psd
        if information == "nearest-psd":
            meta["information_projected"] = not_psd
    return PoseGraph(
        ids=ids, poses=poses, edges=edges,
        relative=relative, information=matrices, planar=not is3d,
        fixed=sorted({n for n, _ in parser.fixed}), meta=meta, source=str(path),
    )


def _pose_table(T: np.ndarray, planar: bool) -> np.ndarray:
    """Rows ``x y theta`` (planar) or ``x y z qx qy qz qw``."""
    if planar:
        return se3.to_xy_yaw(T).reshape(-1, 3)
    xyz, q = se3.to_xyz_quat(T.reshape(-1, 4, 4), "xyzw")
    return np.concatenate([xyz, q], axis=1)


def write_g2o(graph: PoseGraph, path: str | Path) -> None:
    """Write ``graph`` (exact float text); every node gets a vertex line."""
    path = Path(path)
    if graph.planar and not se3.is_planar(np.concatenate([graph.poses, graph.relative])):
        raise InputError(path, "graph is marked planar (2D) but its poses leave the z = 0 plane")
    vertex, edge = ("VERTEX_SE2", "EDGE_SE2") if graph.planar else ("VERTEX_SE3:QUAT", "EDGE_SE3:QUAT")
    iu = np.triu_indices(3 if graph.planar else 6)
    vertices = _pose_table(graph.poses, graph.planar).tolist()
    measured = _pose_table(graph.relative, graph.planar).tolist()
    information = graph.information[:, iu[0], iu[1]].reshape(len(graph.edges), len(iu[0])).tolist()
    with atomic_write(path) as fh:
        for n, row in zip(graph.ids.tolist(), vertices, strict=True):
            fh.write(f"{vertex} {n} {' '.join(map(repr, row))}\n")
        if graph.fixed:
            fh.write("FIX " + " ".join(str(int(n)) for n in graph.fixed) + "\n")
        for (i, j), row, info in zip(graph.edges.tolist(), measured, information, strict=True):
            fh.write(f"{edge} {i} {j} {' '.join(map(repr, row + info))}\n")


def _read(path: Path, options: ReadOptions) -> Trajectory:
    return read_g2o(path).to_trajectory()  # its poses validated


def _write(traj: Trajectory, path: Path, options: ReadOptions) -> None:
    write_g2o(PoseGraph.from_trajectory(traj), path)


FORMAT = trajectory_format(
    TrajectoryFormat(
        name="g2o",
        description="g2o pose graph (VERTEX/EDGE_SE3:QUAT or VERTEX/EDGE_SE2); vertices as the trajectory",
        read=_read,
        write=_write,
        suffixes=(".g2o",),
        stamped=False,
    )
)
