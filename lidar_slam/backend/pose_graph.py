"""Pose graph with a NumPy interface: priors, odometry and (Huber-robust) loop edges, then LM.

Poses are homogeneous matrices T_world_node (4x4 in 3D, 3x3 in 2D). Information matrices are in
gtsam's tangent order: 3D rotation first (rx ry rz tx ty tz; 1/rad^2, 1/m^2), 2D (x y theta).
Sigmas are given by name (rot_sigma_deg, trans_sigma_m) and converted only by
factors.sigmas_to_information. gtsam itself stays inside gtsam_graph.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidar_slam.backend.factors import (
    BetweenFactor,
    Dims,
    PriorFactor,
    check_information,
    check_pose,
    sigmas_to_information,
)
from lidar_slam.io.g2o import G2oEdge, G2oGraph, write_g2o

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class OptimizeSummary:
    """The last optimisation: gtsam errors before/after, LM iterations and wall time in seconds."""

    initial_error: float
    final_error: float
    iterations: int
    seconds: float


class PoseGraph:
    """Nodes keyed by int; optimize() starts from the current estimate and replaces it."""

    def __init__(self, dims: Dims = 3):
        if dims not in (2, 3):
            raise ValueError(f"dims must be 2 or 3, got {dims}")
        self.dims: Dims = dims
        self.priors: list[PriorFactor] = []
        self.edges: list[BetweenFactor] = []
        self._estimate: dict[int, np.ndarray] = {}
        self.summary: OptimizeSummary | None = None

    def _information(self, information: np.ndarray | None, rot_sigma_deg: float | None,
                     trans_sigma_m: float | None) -> np.ndarray:
        if information is not None:
            if rot_sigma_deg is not None or trans_sigma_m is not None:
                raise ValueError("give either an information matrix or sigmas, not both")
            return check_information(information, self.dims)
        if rot_sigma_deg is None or trans_sigma_m is None:
            raise ValueError("give an information matrix or both rot_sigma_deg and trans_sigma_m")
        return sigmas_to_information(rot_sigma_deg, trans_sigma_m, self.dims)

    def add_prior(self, key: int, T_world_node: np.ndarray, rot_sigma_deg: float,
                  trans_sigma_m: float) -> None:
        """Anchor node key at T_world_node with the given sigmas (deg, m)."""
        info = sigmas_to_information(rot_sigma_deg, trans_sigma_m, self.dims)
        self.priors.append(PriorFactor(int(key), check_pose(T_world_node, self.dims), info))

    def add_odometry(self, i: int, j: int, T_i_j: np.ndarray, information: np.ndarray | None = None,
                     *, rot_sigma_deg: float | None = None, trans_sigma_m: float | None = None
                     ) -> None:
        """Odometry edge T_i_j (pose of j in i's frame): information matrix or sigmas (deg, m)."""
        info = self._information(information, rot_sigma_deg, trans_sigma_m)
        self.edges.append(BetweenFactor(int(i), int(j), check_pose(T_i_j, self.dims), info))

    def add_loop(self, i: int, j: int, T_i_j: np.ndarray, information: np.ndarray,
                 robust_k: float | None = None) -> None:
        """Loop edge T_i_j; Huber with threshold robust_k (whitened units) when given."""
        if robust_k is not None and not robust_k > 0:
            raise ValueError(f"robust_k must be positive, got {robust_k}")
        info = check_information(information, self.dims)
        self.edges.append(BetweenFactor(int(i), int(j), check_pose(T_i_j, self.dims), info,
                                        None if robust_k is None else float(robust_k), True))

    def set_initial(self, key: int, T_world_node: np.ndarray) -> None:
        """Initial guess (or new current estimate) of node key."""
        self._estimate[int(key)] = check_pose(T_world_node, self.dims)

    @property
    def estimate(self) -> dict[int, np.ndarray]:
        """Current T_world_node of every node (initial guesses until optimize() runs)."""
        return dict(self._estimate)

    def _check_keys(self) -> None:
        used = {p.key for p in self.priors} | {e.i for e in self.edges} | {e.j for e in self.edges}
        missing = used - self._estimate.keys()
        if missing:
            raise ValueError(f"{len(missing)} nodes have no initial pose, e.g. {min(missing)}")

    def optimize(self, max_iterations: int = 100) -> dict[int, np.ndarray]:
        """Levenberg-Marquardt from the current estimate; returns the new T_world_node per key."""
        self._check_keys()
        from lidar_slam.backend import gtsam_graph  # gtsam: imported when first needed

        res = gtsam_graph.solve(self.dims, self.priors, self.edges, self._estimate, max_iterations)
        self._estimate = res.poses
        self.summary = OptimizeSummary(res.initial_error, res.final_error, res.iterations,
                                       res.seconds)
        log.info("pose graph: %d nodes, %d edges, error %.6g -> %.6g in %d iterations (%.2f s)",
                 len(res.poses), len(self.edges), res.initial_error, res.final_error,
                 res.iterations, res.seconds)
        return self.estimate

    def error(self, poses: dict[int, np.ndarray] | None = None) -> float:
        """gtsam graph error (0.5 * sum of whitened squares, Huber on robust edges) at the poses."""
        if poses is None:
            self._check_keys()
            poses = self._estimate
        from lidar_slam.backend import gtsam_graph

        return gtsam_graph.graph_error(self.dims, self.priors, self.edges, poses)

    def to_g2o(self) -> G2oGraph:
        """The graph as g2o records: current estimate as vertices, edges with their information."""
        edges = [G2oEdge(e.i, e.j, e.T_i_j, e.information) for e in self.edges]
        return G2oGraph(self.dims, self.estimate, edges, len(self._estimate))

    def write_g2o(self, path: str | Path) -> None:
        """Write a g2o file (without priors and robust kernels, which the format lacks)."""
        write_g2o(path, self.to_g2o())

    @classmethod
    def from_g2o(cls, g2o: G2oGraph, robust_k: float | None = None) -> PoseGraph:
        """g2o edges: (i, i+1) as odometry, others as loops (Huber when robust_k is set)."""
        graph = cls(g2o.dims)
        for key, T in g2o.poses.items():
            graph._estimate[key] = T
        for e in g2o.edges:
            is_loop = abs(e.j - e.i) != 1
            graph.edges.append(BetweenFactor(e.i, e.j, e.T_i_j, e.information,
                                             robust_k if is_loop else None, is_loop))
        return graph
