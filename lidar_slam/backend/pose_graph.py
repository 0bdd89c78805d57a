"""Pose graph with a NumPy interface: priors, odometry and loop edges, then LM (Huber or GNC on
the loops), optionally from a global initialisation as well as from the current estimate.

Poses are homogeneous matrices T_world_node (4x4 in 3D, 3x3 in 2D). Information matrices are in
gtsam's tangent order: 3D rotation first (rx ry rz tx ty tz; 1/rad^2, 1/m^2), 2D (x y theta).
Sigmas are given by name (rot_sigma_deg, trans_sigma_m) and converted only by
factors.sigmas_to_information. gtsam itself stays inside gtsam_graph.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np

from lidar_slam.backend.factors import (
    BetweenFactor,
    Dims,
    PriorFactor,
    check_information,
    check_pose,
    sigmas_to_information,
)
from lidar_slam.errors import SolveError
from lidar_slam.io.g2o import G2oEdge, G2oGraph, write_g2o

log = logging.getLogger(__name__)

Robust = Literal["none", "huber", "gnc"]
Init = Literal["file", "chordal", "auto"]
# A global initialisation's solution replaces the one from the current estimate only when its
# error is lower by more than this (relative): two LM runs into the same minimum stop at errors
# up to ~1e-5 apart (LM's relative tolerance), and a different minimum that close is no better.
TIE_REL = 1e-4


@dataclass(frozen=True)
class OptimizeSummary:
    """The last optimisation: errors before (at the current estimate) and after, iterations and
    wall time in seconds (initialisation included). With solve(): the kept start (init), every
    start tried with its final error (None: skipped), and per edge whether the solution keeps it
    (loop edges: GNC weight, or residual inside GNC's inlier threshold; odometry: always).
    Errors are gtsam's (Huber on robust edges); with GNC, its truncated cost."""

    initial_error: float
    final_error: float
    iterations: int | None
    seconds: float
    robust: str = "none"
    init: str = "file"
    candidates: tuple[tuple[str, float | None], ...] = ()
    inlier: tuple[bool, ...] | None = None
    init_seconds: float = 0.0


class PoseGraph:
    """Nodes keyed by int; optimize() starts from the current estimate and replaces it."""

    def __init__(self, dims: Dims = 3):
        if dims not in (2, 3):
            raise ValueError(f"dims must be 2 or 3, got {dims}")
        self.dims: Dims = dims
        self.priors: list[PriorFactor] = []
        self.edges: list[BetweenFactor] = []
        self._estimate: dict[int, np.ndarray] = {}
        self._sigma_info: dict[tuple[float, float], np.ndarray] = {}
        self.summary: OptimizeSummary | None = None

    def _information(self, information: np.ndarray | None, rot_sigma_deg: float | None,
                     trans_sigma_m: float | None) -> np.ndarray:
        if information is not None:
            if rot_sigma_deg is not None or trans_sigma_m is not None:
                raise ValueError("give either an information matrix or sigmas, not both")
            return check_information(information, self.dims)
        if rot_sigma_deg is None or trans_sigma_m is None:
            raise ValueError("give an information matrix or both rot_sigma_deg and trans_sigma_m")
        # One shared (read-only) matrix per sigma pair: thousands of odometry edges, one array.
        key = (rot_sigma_deg, trans_sigma_m)
        if key not in self._sigma_info:
            info = sigmas_to_information(rot_sigma_deg, trans_sigma_m, self.dims)
            info.setflags(write=False)
            self._sigma_info[key] = info
        return self._sigma_info[key]

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

    def optimize(self, max_iterations: int = 100, relative_error_tol: float | None = None
                 ) -> dict[int, np.ndarray]:
        """Levenberg-Marquardt from the current estimate; returns the new T_world_node per key.
        relative_error_tol: stop when the error falls by less than this fraction (gtsam: 1e-5)."""
        self._check_keys()
        from lidar_slam.backend import gtsam_graph  # gtsam: imported when first needed

        res = gtsam_graph.solve(self.dims, self.priors, self.edges, self._estimate, max_iterations,
                                relative_error_tol)
        self._estimate = res.poses
        self.summary = OptimizeSummary(res.initial_error, res.final_error, res.iterations,
                                       res.seconds)
        log.info("pose graph: %d nodes, %d edges, error %.6g -> %.6g in %d iterations (%.2f s)",
                 len(res.poses), len(self.edges), res.initial_error, res.final_error,
                 res.iterations, res.seconds)
        return self.estimate

    def _edges_for(self, robust: Robust, huber_k: float) -> list[BetweenFactor]:
        """The edges with the kernel of `robust` on loops (GNC brings its own: none here)."""
        k = huber_k if robust == "huber" else None
        return [e if e.robust_k == (k if e.is_loop else None)
                else replace(e, robust_k=k if e.is_loop else None) for e in self.edges]

    def _global_guess(self, edges: list[BetweenFactor], required: bool, given: str):
        """gtsam's global initialisation; when it fails, an error if required, else None."""
        from lidar_slam.backend import gtsam_graph

        try:
            return gtsam_graph.global_initial(self.dims, self.priors, edges)
        except RuntimeError as exc:  # gtsam: e.g. an indeterminate linear system
            if required:
                raise SolveError(f"global initialisation failed: {exc}") from exc
            log.warning("global initialisation failed (%s); optimising from the %s guess only",
                        str(exc).splitlines()[0], given)
            return None

    def solve(self, robust: Robust = "none", init: Init = "file", huber_k: float = 1.345,
              max_iterations: int = 100, given: str = "file",
              relative_error_tol: float | None = None) -> dict[int, np.ndarray]:
        """Optimise with a loop kernel (none, huber, or gnc: odometry edges and priors are known
        inliers) from the current estimate (init="file"; named `given` in the summary), from a
        global initialisation (init="chordal": chordal in 3D, LAGO in 2D), or "auto": both,
        keeping the lower final error. auto compares the two starts by the cost being minimised
        and skips the current estimate when it starts higher (on ais2klinik each LM run costs
        ~5 s); with GNC it runs from the lower start only. Returns and keeps the new
        T_world_node per key; self.summary says what was done. relative_error_tol: LM stops
        when an iteration gains less than this fraction (gtsam's default: 1e-5)."""
        if robust not in ("none", "huber", "gnc"):
            raise ValueError(f"robust must be none, huber or gnc, got {robust!r}")
        if init not in ("file", "chordal", "auto"):
            raise ValueError(f"init must be file, chordal or auto, got {init!r}")
        self._check_keys()
        from lidar_slam.backend import gtsam_graph  # gtsam: imported when first needed

        t0 = time.perf_counter()
        edges = self._edges_for(robust, huber_k)
        known = np.array([not e.is_loop for e in edges], dtype=bool)
        problem = gtsam_graph.Problem(self.dims, self.priors, edges, known)
        cost = problem.truncated_cost if robust == "gnc" else problem.error
        initial_error = cost(self._estimate)
        def run(start, max_iterations):
            if robust == "gnc":
                return problem.gnc(start, max_iterations)
            return problem.lm(start, max_iterations, relative_error_tol)

        results: dict[str, gtsam_graph.SolveResult | None] = {}
        init_seconds = 0.0
        odometry = (robust == "gnc" and init == "auto" and problem.known_span)
        guess = (None if init == "file" or odometry else
                 self._global_guess(edges, init == "chordal", given))
        if odometry:
            # GNC's first solve is the known inliers alone (Problem.gnc), and every later solve
            # restarts from the start given to it: a start bent by wrong loops (the live
            # estimate of a run that admitted them, or a chordal initialisation that averaged
            # them in) leaves LM in a bent minimum even on the true loops (loose-gated
            # simulated s00: ATE 57.7 m with 42 true loops kept; from the odometry 0.180 m).
            # So GNC starts from the odometry: the known edges chained from the prior.
            results["odometry"] = run(self._known_chain(edges, known), max_iterations)
        elif guess is None:
            results[given] = run(self._estimate, max_iterations)
        else:
            init_seconds = guess.seconds
            guess_error = cost(guess.poses)
            given_first = init == "auto" and initial_error <= guess_error
            # GNC re-solves from its start at every step of its schedule: from a poor start it
            # takes minutes and can settle elsewhere (a chordal start bent by 50 wrong loops on
            # sphere2500), so it only runs from the start its own (truncated) cost prefers.
            run_global = init == "chordal" or robust != "gnc" or not given_first
            if init == "auto":
                log.info("init auto: error %.6g at the %s guess, %.6g at the %s one; %s",
                         initial_error, given, guess_error, guess.method,
                         "both optimised" if given_first and run_global else
                         f"only the {given if given_first else guess.method} one optimised")
            results[given] = run(self._estimate, max_iterations) if given_first else None
            results[guess.method] = run(guess.poses, max_iterations) if run_global else None
            if init == "chordal":
                del results[given]
        candidates = tuple((name, None if r is None else r.final_error)
                           for name, r in results.items())
        best = None
        for name, r in results.items():  # the given start first: it wins ties
            if r is not None and (best is None or r.final_error
                                  < best[1].final_error * (1 - TIE_REL)):
                best = (name, r)
        assert best is not None
        name, res = best
        if results.get(given) is None and robust != "gnc":
            # LM stops when an iteration gains < 1e-5 (relative); runs into the same minimum
            # from different starts then end up to ~2e-4 apart (MIT: 385.197 from LAGO, 385.122
            # from the file). When the given start was not optimised, a restart from the kept
            # solution (fresh damping) finishes the job. Not otherwise: at a converged point its
            # steps are at round-off level, and whether LM takes them is a coin toss that made
            # two identical runs differ by 1e-9 m.
            again = problem.lm(res.values, max_iterations, relative_error_tol)
            if again.final_error < res.final_error:
                res = gtsam_graph.SolveResult(again.poses, res.initial_error, again.final_error,
                                              res.iterations + again.iterations,
                                              res.seconds + again.seconds, values=again.values)
        if res.weights is not None:
            inlier = res.weights > 0.5
        else:
            errors = problem.factor_errors(res.values)
            inlier = errors <= gtsam_graph.inlier_thresholds(self.dims, len(edges))
        inlier = tuple(bool(v) for v in (inlier | known))
        self._estimate = res.poses
        self.summary = OptimizeSummary(initial_error, res.final_error, res.iterations,
                                       time.perf_counter() - t0, robust, name, candidates,
                                       inlier, init_seconds)
        log.info("pose graph: %d nodes, %d edges, %s from %s: error %.6g -> %.6g (%.2f s)",
                 len(res.poses), len(self.edges), robust, name, initial_error, res.final_error,
                 self.summary.seconds)
        return self.estimate

    def covariances(self, robust: Robust = "none", huber_k: float = 1.345
                    ) -> dict[int, np.ndarray]:
        """Marginal covariance of every node at the current estimate (gtsam tangent order, in
        the node's frame; see gtsam_graph.marginal_covariances), from the priors, the odometry
        and the loops the last solve kept (with the loop kernel of `robust`): a loop it
        rejected says nothing about where the nodes are."""
        self._check_keys()
        from lidar_slam.backend import gtsam_graph

        return gtsam_graph.marginal_covariances(self.dims, self.priors,
                                                self.covariance_edges(robust, huber_k),
                                                self._estimate)

    def covariance_edges(self, robust: Robust = "none", huber_k: float = 1.345
                         ) -> list[BetweenFactor]:
        """The edges covariances() weighs: the odometry, and the loops the last solve kept with
        the loop kernel of `robust`."""
        edges = self._edges_for(robust, huber_k)
        keep = self.summary.inlier if self.summary is not None else None
        if keep is not None and len(keep) == len(edges):
            edges = [e for e, k in zip(edges, keep, strict=True) if k or not e.is_loop]
        return edges

    def _known_chain(self, edges: list[BetweenFactor], known: np.ndarray
                     ) -> dict[int, np.ndarray]:
        """Poses from the priors chained along the known-inlier edges (breadth first, in key
        order): the solution of the known edges alone where they form a tree. Nodes they do not
        reach keep the current estimate."""
        links: dict[int, list[tuple[int, np.ndarray]]] = {}
        for e, is_known in zip(edges, known, strict=True):
            if is_known:
                links.setdefault(e.i, []).append((e.j, e.T_i_j))
                links.setdefault(e.j, []).append((e.i, np.linalg.inv(e.T_i_j)))
        poses = {p.key: p.T_world_node for p in self.priors}
        queue = deque(sorted(poses))
        while queue:
            i = queue.popleft()
            for j, T_i_j in sorted(links.get(i, []), key=lambda t: t[0]):
                if j not in poses:
                    poses[j] = poses[i] @ T_i_j
                    queue.append(j)
        return {k: poses.get(k, T) for k, T in self._estimate.items()}

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
