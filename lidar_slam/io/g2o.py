"""g2o pose-graph files: 2D (VERTEX_SE2 / EDGE_SE2) and 3D (VERTEX_SE3:QUAT / EDGE_SE3:QUAT).

In memory, poses are homogeneous matrices (3x3 for 2D, 4x4 for 3D) and every information matrix is
in gtsam's tangent order: 2D (x y theta), the same as g2o's; 3D rotation first (rx ry rz tx ty tz),
whereas g2o's EDGE_SE3:QUAT stores [x y z rx ry rz] (translation first). The permutation between the
two happens here and nowhere else. Like gtsam's readG2o, the rotation block is taken as is
(g2o's own rotation residual is the quaternion's vector part, about half the angle; gtsam's is
the full angle).
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidar_slam.errors import InputError
from lidar_slam.geometry import matrix_from_quat, quat_from_matrix
from lidar_slam.io.atomic import write_text_atomic

log = logging.getLogger(__name__)

# Index i of gtsam's rotation-first tangent is index _PERM_3D[i] of g2o's translation-first one.
# The permutation is its own inverse, so the same array converts back.
_PERM_3D = np.array([3, 4, 5, 0, 1, 2])

# tag -> (dims, number of numeric fields after the tag)
_RECORDS = {
    "VERTEX_SE2": (2, 4),
    "EDGE_SE2": (2, 5 + 6),
    "VERTEX_SE3:QUAT": (3, 8),
    "EDGE_SE3:QUAT": (3, 9 + 21),
}


@dataclass(frozen=True)
class G2oEdge:
    """Measurement T_i_j (pose of j in i's frame) with information in gtsam tangent order."""

    i: int
    j: int
    T_i_j: np.ndarray
    information: np.ndarray


@dataclass(frozen=True)
class G2oGraph:
    """A g2o file: initial poses T_world_node (from VERTEX lines or chained edges) and edges;
    n_repaired information matrices were not positive definite and lost their cross terms."""

    dims: int
    poses: dict[int, np.ndarray]
    edges: list[G2oEdge]
    n_vertex_lines: int
    n_repaired: int = 0


def g2o_to_gtsam_information(info_g2o: np.ndarray) -> np.ndarray:
    """3D information [x y z rx ry rz] (g2o) -> [rx ry rz tx ty tz] (gtsam); works both ways."""
    return np.asarray(info_g2o)[..., _PERM_3D[:, None], _PERM_3D[None, :]]


gtsam_to_g2o_information = g2o_to_gtsam_information


def se2_matrix(x: float, y: float, theta_rad: float) -> np.ndarray:
    """3x3 homogeneous SE(2) pose."""
    c, s = np.cos(theta_rad), np.sin(theta_rad)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def se2_params(T: np.ndarray) -> tuple[float, float, float]:
    """(x, y, theta_rad) of a 3x3 homogeneous SE(2) pose."""
    return float(T[0, 2]), float(T[1, 2]), float(np.arctan2(T[1, 0], T[0, 0]))


def _se3_matrix(v: np.ndarray, path: Path, lineno: int) -> np.ndarray:
    q = v[3:7]
    norm = np.linalg.norm(q)
    if not norm > 1e-9:
        raise InputError(path, f"line {lineno}: quaternion has zero norm")
    T = np.eye(4)
    T[:3, :3] = matrix_from_quat(q / norm)
    T[:3, 3] = v[:3]
    return T


def _info_from_upper(values: np.ndarray, n: int) -> np.ndarray:
    info = np.zeros((n, n))
    iu = np.triu_indices(n)
    info[iu] = values
    info.T[iu] = values
    return info


def _parse_line(tokens: list[str], path: Path, lineno: int) -> tuple[np.ndarray, list[int]]:
    tag = tokens[0]
    n_fields = _RECORDS[tag][1]
    if len(tokens) - 1 != n_fields:
        raise InputError(path, f"line {lineno}: {tag} needs {n_fields} fields, "
                               f"got {len(tokens) - 1}")
    n_ids = 2 if tag.startswith("EDGE") else 1
    try:
        ids = [int(t) for t in tokens[1 : 1 + n_ids]]
    except ValueError:
        raise InputError(path, f"line {lineno}: {tag} node ids must be integers") from None
    try:
        values = np.array([float(t) for t in tokens[1 + n_ids :]])
    except ValueError:
        raise InputError(path, f"line {lineno}: {tag} has a field that is not a number") from None
    if not np.all(np.isfinite(values)):
        raise InputError(path, f"line {lineno}: {tag} has a non-finite value")
    return values, ids


def _chain(nodes: set[int], edges: list[G2oEdge], path: Path) -> dict[int, np.ndarray]:
    """Initial poses from consecutive (i, i+1) edges; other edges only for nodes still unreached."""
    inv = np.linalg.inv
    first = min(nodes)
    poses = {first: np.eye(edges[0].T_i_j.shape[0])}
    step: dict[tuple[int, int], np.ndarray] = {}
    for e in edges:
        step.setdefault((e.i, e.j), e.T_i_j)
        step.setdefault((e.j, e.i), inv(e.T_i_j))
    for k in sorted(nodes)[1:]:
        if k - 1 in poses and (k - 1, k) in step:
            poses[k] = poses[k - 1] @ step[(k - 1, k)]
    if len(poses) < len(nodes):
        neighbours: dict[int, list[int]] = {n: [] for n in nodes}
        for a, b in step:
            neighbours[a].append(b)
        queue = deque(poses)
        while queue:
            a = queue.popleft()
            for b in neighbours[a]:
                if b not in poses:
                    poses[b] = poses[a] @ step[(a, b)]
                    queue.append(b)
    missing = nodes - poses.keys()
    if missing:
        raise InputError(path, f"{len(missing)} nodes (e.g. {min(missing)}) are not connected to "
                               f"node {first}; cannot build an initial guess without VERTEX lines")
    return poses


def read_g2o(path: str | Path) -> G2oGraph:
    """Read a 2D or 3D g2o pose graph; without VERTEX lines, chain (i, i+1) edges from identity."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "is a folder, not a g2o file" if path.is_dir()
                         else "g2o file does not exist")
    dims: int | None = None
    poses: dict[int, np.ndarray] = {}
    edges: list[G2oEdge] = []
    edge_lines: list[int] = []
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise InputError(path, "not a text g2o file (not UTF-8)") from None
    for lineno, line in enumerate(text.splitlines(), start=1):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        tag = tokens[0]
        if tag == "FIX":
            log.info("%s: line %d: FIX ignored (the first node gets a prior)", path, lineno)
            continue
        if tag not in _RECORDS:
            raise InputError(path, f"line {lineno}: unsupported record '{tag}' "
                                   f"(expected one of {', '.join(_RECORDS)})")
        if dims is None:
            dims = _RECORDS[tag][0]
        elif _RECORDS[tag][0] != dims:
            raise InputError(path, f"line {lineno}: {tag} mixes {_RECORDS[tag][0]}D with "
                                   f"{dims}D records")
        values, ids = _parse_line(tokens, path, lineno)
        if tag.startswith("VERTEX"):
            if ids[0] in poses:
                raise InputError(path, f"line {lineno}: duplicate vertex {ids[0]}")
            poses[ids[0]] = (se2_matrix(*values) if dims == 2
                             else _se3_matrix(values, path, lineno))
            continue
        i, j = ids
        if i == j:
            raise InputError(path, f"line {lineno}: edge joins node {i} to itself")
        if dims == 2:
            T = se2_matrix(*values[:3])
            info = _info_from_upper(values[3:], 3)
        else:
            T = _se3_matrix(values[:7], path, lineno)
            info = g2o_to_gtsam_information(_info_from_upper(values[7:], 6))
        edges.append(G2oEdge(i, j, T, info))
        edge_lines.append(lineno)
    if not edges:
        raise InputError(path, "no EDGE_SE2 or EDGE_SE3:QUAT records")
    n_repaired = _check_information(edges, edge_lines, path)
    nodes = {e.i for e in edges} | {e.j for e in edges}
    n_vertex_lines = len(poses)
    if poses:
        for e, lineno in zip(edges, edge_lines, strict=True):
            for k in (e.i, e.j):
                if k not in poses:
                    raise InputError(path, f"line {lineno}: edge uses node {k}, which has no "
                                           "VERTEX line")
    else:
        poses = _chain(nodes, edges, path)
    _check_connected(poses, edges, path)
    assert dims is not None
    return G2oGraph(dims, poses, edges, n_vertex_lines, n_repaired)


def _check_connected(poses: dict[int, np.ndarray], edges: list[G2oEdge], path: Path) -> None:
    """One connected graph: only its first node is anchored, so a part without an edge to it
    would float (left where the file put it, or an indeterminate system)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    ids = sorted(poses)
    at = {k: n for n, k in enumerate(ids)}
    rows = [at[e.i] for e in edges]
    cols = [at[e.j] for e in edges]
    adj = coo_matrix((np.ones(len(edges)), (rows, cols)), shape=(len(ids), len(ids)))
    n_parts, label = connected_components(adj, directed=False)
    if n_parts > 1:
        other = ids[int(np.flatnonzero(label != label[0])[0])]
        raise InputError(path, f"the graph is in {n_parts} unconnected parts (no chain of edges "
                               f"joins node {other} to node {ids[0]}); optimize needs one "
                               f"connected pose graph")


def _check_information(edges: list[G2oEdge], edge_lines: list[int], path: Path) -> int:
    """Keep PD information; make an indefinite one block-diagonal (rotation | translation);
    returns how many were repaired.

    Some benchmark files (cubicle.g2o: 5021 of 16869 edges) carry rotation-translation cross terms
    that make the matrix indefinite. SE-Sync only uses the diagonal blocks; gtsam would silently
    factor garbage. Dropping the cross block is the least surprising repair; if the diagonal blocks
    themselves are not PD the file is rejected.
    """
    infos = np.stack([e.information for e in edges])
    bad = np.flatnonzero(~(np.linalg.eigvalsh(infos)[:, 0] > 0))
    if not len(bad):
        return 0
    n = infos.shape[1]
    rot = np.zeros(n, dtype=bool)
    rot[[2] if n == 3 else [0, 1, 2]] = True
    repaired = infos[bad] * (rot[:, None] == rot[None, :])
    lowest = np.linalg.eigvalsh(repaired)[:, 0]
    still_bad = np.flatnonzero(~(lowest > 0))
    if len(still_bad):
        k = bad[still_bad[0]]
        raise InputError(path, f"line {edge_lines[k]}: information matrix is not positive "
                               f"definite (smallest eigenvalue of its diagonal blocks "
                               f"{lowest[still_bad[0]]:.3g})")
    for k, info in zip(bad, repaired, strict=True):
        e = edges[k]
        edges[k] = G2oEdge(e.i, e.j, e.T_i_j, info)
    log.warning("%s: %d of %d information matrices are indefinite (first: line %d); dropped their "
                "rotation-translation cross terms", path, len(bad), len(edges), edge_lines[bad[0]])
    return len(bad)


def _fmt(values) -> str:
    return " ".join(repr(float(v)) for v in values)


def _xyz_quat(poses: list[np.ndarray]) -> np.ndarray:
    """(K, 7) x y z qx qy qz qw of K 4x4 poses (to_xyz_quat, batched)."""
    if not poses:
        return np.zeros((0, 7))
    T = np.stack(poses)
    return np.hstack([T[:, :3, 3], quat_from_matrix(T[:, :3, :3])])


def write_g2o(path: str | Path, graph: G2oGraph) -> None:
    """Write vertices (sorted by id) then edges; 3D information goes back to g2o's order."""
    n = 3 if graph.dims == 2 else 6
    iu = np.triu_indices(n)
    lines = []
    keys = sorted(graph.poses)
    if graph.dims == 2:
        for k in keys:
            lines.append(f"VERTEX_SE2 {k} {_fmt(se2_params(graph.poses[k]))}")
        for e in graph.edges:
            lines.append(f"EDGE_SE2 {e.i} {e.j} {_fmt(se2_params(e.T_i_j))} "
                         f"{_fmt(e.information[iu])}")
    else:
        # Quaternions of every pose at once: one per call costs ~0.1 ms (an eigen-solve), half a
        # second on a 1,500-keyframe graph at the end of every run.
        vertices = _xyz_quat([graph.poses[k] for k in keys])
        measured = _xyz_quat([e.T_i_j for e in graph.edges])
        for k, v in zip(keys, vertices):
            lines.append(f"VERTEX_SE3:QUAT {k} {_fmt(v)}")
        for e, m in zip(graph.edges, measured):
            info = gtsam_to_g2o_information(e.information)
            lines.append(f"EDGE_SE3:QUAT {e.i} {e.j} {_fmt(m)} {_fmt(info[iu])}")
    write_text_atomic(path, "\n".join(lines) + "\n")
