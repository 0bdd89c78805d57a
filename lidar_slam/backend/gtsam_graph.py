"""The only module that imports gtsam: factor records -> factor graph -> Levenberg-Marquardt.

Errors are gtsam's graph.error: 0.5 * sum of squared whitened residuals (geodesic rotation error),
with Huber's robust loss in place of the square on robust edges.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import gtsam
import numpy as np

from lidar_slam.backend.factors import BetweenFactor, Dims, PriorFactor

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SolveResult:
    """Optimised poses (homogeneous matrices) with gtsam's error before and after."""

    poses: dict[int, np.ndarray]
    initial_error: float
    final_error: float
    iterations: int
    seconds: float


def _to_gtsam(T: np.ndarray, dims: Dims):
    if dims == 3:
        return gtsam.Pose3(T)
    return gtsam.Pose2(T[0, 2], T[1, 2], np.arctan2(T[1, 0], T[0, 0]))


def _noise(information: np.ndarray, robust_k: float | None):
    base = gtsam.noiseModel.Gaussian.Information(information)
    if robust_k is None:
        return base
    return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(robust_k), base)


def _build(dims: Dims, priors: Iterable[PriorFactor], betweens: Iterable[BetweenFactor],
           poses: Mapping[int, np.ndarray]) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    prior_cls = gtsam.PriorFactorPose3 if dims == 3 else gtsam.PriorFactorPose2
    between_cls = gtsam.BetweenFactorPose3 if dims == 3 else gtsam.BetweenFactorPose2
    graph = gtsam.NonlinearFactorGraph()
    for p in priors:
        graph.add(prior_cls(p.key, _to_gtsam(p.T_world_node, dims), _noise(p.information, None)))
    for b in betweens:
        noise = _noise(b.information, b.robust_k)
        graph.add(between_cls(b.i, b.j, _to_gtsam(b.T_i_j, dims), noise))
    values = gtsam.Values()
    for key, T in poses.items():
        values.insert(key, _to_gtsam(T, dims))
    return graph, values


def _from_values(values: gtsam.Values, dims: Dims) -> dict[int, np.ndarray]:
    at = values.atPose3 if dims == 3 else values.atPose2
    keys = values.keys()  # a gtsam KeyVector, not a dict
    return {int(k): np.asarray(at(k).matrix(), dtype=np.float64) for k in keys}


def graph_error(dims: Dims, priors: Iterable[PriorFactor], betweens: Iterable[BetweenFactor],
                poses: Mapping[int, np.ndarray]) -> float:
    """gtsam's graph.error (0.5 * sum of squared whitened residuals) at the given poses."""
    graph, values = _build(dims, priors, betweens, poses)
    return float(graph.error(values))


def solve(dims: Dims, priors: Iterable[PriorFactor], betweens: Iterable[BetweenFactor],
          initial: Mapping[int, np.ndarray], max_iterations: int) -> SolveResult:
    """Levenberg-Marquardt (gtsam default tolerances) from the initial poses."""
    graph, values = _build(dims, priors, betweens, initial)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    t0 = time.perf_counter()
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    initial_error = float(graph.error(values))
    result = optimizer.optimize()
    seconds = time.perf_counter() - t0
    final_error = float(graph.error(result))
    log.debug("LM: %d iterations, error %.6g -> %.6g in %.2f s", optimizer.iterations(),
              initial_error, final_error, seconds)
    return SolveResult(_from_values(result, dims), initial_error, final_error,
                       int(optimizer.iterations()), seconds)


class Incremental:
    """gtsam ISAM2 over a growing graph: factors and initial values go in as they arrive, one
    update() re-solves only the part of the Bayes tree a new factor touches (a loop: the cliques
    along it), so the cost of a keyframe or a loop does not grow with the graph."""

    def __init__(self, dims: Dims, relinearize_threshold: float = 0.01, relinearize_skip: int = 1):
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(relinearize_threshold)
        params.relinearizeSkip = relinearize_skip
        self.dims = dims
        self.isam = gtsam.ISAM2(params)
        self._graph = gtsam.NonlinearFactorGraph()
        self._values = gtsam.Values()

    def add(self, priors: Iterable[PriorFactor], betweens: Iterable[BetweenFactor],
            initial: Mapping[int, np.ndarray]) -> None:
        """Queue new factors and the initial poses of new nodes for the next update()."""
        graph, values = _build(self.dims, priors, betweens, initial)
        self._graph.push_back(graph)
        self._values.insert(values)

    def update(self, extra_iterations: int = 0) -> None:
        """Fold the queued factors in; extra_iterations more ISAM2 steps (after a loop)."""
        self.isam.update(self._graph, self._values)
        for _ in range(extra_iterations):
            self.isam.update()
        self._graph = gtsam.NonlinearFactorGraph()
        self._values = gtsam.Values()

    def estimate(self) -> dict[int, np.ndarray]:
        """Current estimate of every node."""
        return _from_values(self.isam.calculateEstimate(), self.dims)

    def pose(self, key: int) -> np.ndarray:
        """Current estimate of one node (cost independent of the graph size)."""
        at = self.isam.calculateEstimatePose3 if self.dims == 3 else self.isam.calculateEstimatePose2
        return np.asarray(at(key).matrix(), dtype=np.float64)
