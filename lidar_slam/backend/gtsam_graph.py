"""The only module that imports gtsam: factor records -> factor graph -> Levenberg-Marquardt,
graduated non-convexity, global initialisation (chordal / LAGO) and Shonan rotation certificates.

Errors are gtsam's graph.error: 0.5 * sum of squared whitened residuals (geodesic rotation error),
with Huber's robust loss in place of the square on robust edges.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace

import gtsam
import numpy as np

from lidar_slam.backend.factors import BetweenFactor, Dims, PriorFactor
from lidar_slam.backend.sesync import sesync_weights

log = logging.getLogger(__name__)

# GNC's inlier threshold (gtsam's default): a factor is an inlier when its cost
# 0.5 * |r|^2_Omega is below 0.5 * chi2inv(p, dof), i.e. inside the p-confidence ellipsoid.
INLIER_PROBABILITY = 0.99
# Relative tolerance of the LM solves inside GNC (see Problem.gnc).
GNC_INNER_RELATIVE_TOL = 1e-3
# chi2inv(0.99, dof) for Pose2 (3) and Pose3 (6) factors (scipy.stats takes 3 s to import).
CHI2_99 = {3: 11.344866730144373, 6: 16.811893829770927}
# Shonan's Riemannian staircase stops at this rank (gtsam's default is 10; each level is slower,
# and the benchmark graphs certify at p <= 5 when they certify at all).
SHONAN_MAX_P = 6


@dataclass(frozen=True)
class SolveResult:
    """Optimised poses (homogeneous matrices) with gtsam's error before and after; for GNC the
    weight of every between factor (1 inlier, 0 outlier) and errors in GNC's truncated cost."""

    poses: dict[int, np.ndarray]
    initial_error: float
    final_error: float
    iterations: int | None
    seconds: float
    weights: np.ndarray | None = None
    values: object = field(default=None, repr=False)  # the same poses as gtsam.Values


@dataclass(frozen=True)
class InitialGuess:
    """A global initialisation: its poses, which gtsam initialiser made them, and its time (s)."""

    poses: dict[int, np.ndarray]
    method: str  # "chordal" (InitializePose3) or "lago"
    seconds: float


@dataclass(frozen=True)
class RotationCertificate:
    """Shonan averaging of the rotation measurements (SE-Sync's rotation weights): certified when
    the rotation-only problem's global optimum was found and verified (lambda_min >= threshold)."""

    certified: bool
    lambda_min: float | None
    rotation_cost: float | None  # Shonan's cost at its (certified) rotations
    seconds: float
    note: str = ""


def _to_gtsam(T: np.ndarray, dims: Dims):
    if dims == 3:
        return gtsam.Pose3(T)
    return gtsam.Pose2(T[0, 2], T[1, 2], np.arctan2(T[1, 0], T[0, 0]))


def _noise(information: np.ndarray, robust_k: float | None):
    base = gtsam.noiseModel.Gaussian.Information(information)
    if robust_k is None:
        return base
    return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(robust_k), base)


def _values(poses, dims: Dims) -> gtsam.Values:
    if isinstance(poses, gtsam.Values):  # a SolveResult's own: no conversion (15k poses: 0.3 s)
        return poses
    values = gtsam.Values()
    for key, T in poses.items():
        values.insert(key, _to_gtsam(T, dims))
    return values


def _graph(dims: Dims, priors: Iterable[PriorFactor], betweens: Iterable[BetweenFactor],
           robust: bool = True) -> gtsam.NonlinearFactorGraph:
    prior_cls = gtsam.PriorFactorPose3 if dims == 3 else gtsam.PriorFactorPose2
    between_cls = gtsam.BetweenFactorPose3 if dims == 3 else gtsam.BetweenFactorPose2
    graph = gtsam.NonlinearFactorGraph()
    noises: dict = {}  # factors that share one information array share one noise model

    def noise(information: np.ndarray, robust_k: float | None):
        key = (id(information), robust_k)
        if key not in noises:
            noises[key] = _noise(information, robust_k)
        return noises[key]

    for p in priors:
        graph.add(prior_cls(p.key, _to_gtsam(p.T_world_node, dims), noise(p.information, None)))
    for b in betweens:
        graph.add(between_cls(b.i, b.j, _to_gtsam(b.T_i_j, dims),
                              noise(b.information, b.robust_k if robust else None)))
    return graph


def _build(dims: Dims, priors: Iterable[PriorFactor], betweens: Iterable[BetweenFactor],
           poses: Mapping[int, np.ndarray]) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    return _graph(dims, priors, betweens), _values(poses, dims)


def _from_values(values: gtsam.Values, dims: Dims) -> dict[int, np.ndarray]:
    at = values.atPose3 if dims == 3 else values.atPose2
    keys = values.keys()  # a gtsam KeyVector, not a dict
    return {int(k): np.asarray(at(k).matrix(), dtype=np.float64) for k in keys}


def graph_error(dims: Dims, priors: Iterable[PriorFactor], betweens: Iterable[BetweenFactor],
                poses: Mapping[int, np.ndarray]) -> float:
    """gtsam's graph.error (0.5 * sum of squared whitened residuals) at the given poses."""
    graph, values = _build(dims, priors, betweens, poses)
    return float(graph.error(values))


def solve(dims: Dims, priors: Sequence[PriorFactor], betweens: Sequence[BetweenFactor],
          initial: Mapping[int, np.ndarray], max_iterations: int,
          relative_error_tol: float | None = None) -> SolveResult:
    """Levenberg-Marquardt from the initial poses (gtsam's default tolerances unless given)."""
    return Problem(dims, priors, betweens).lm(initial, max_iterations, relative_error_tol)


def marginal_covariances(dims: Dims, priors: Sequence[PriorFactor],
                         betweens: Sequence[BetweenFactor], poses: Mapping[int, np.ndarray]
                         ) -> dict[int, np.ndarray]:
    """Marginal covariance of every node at the poses (gtsam Marginals, Cholesky), in gtsam's
    tangent order (Pose3: rotation first, rad and m) and in the node's own frame: the true pose
    is T_world_node @ Exp(xi), xi ~ N(0, cov). Robust edges enter with their kernel's weight at
    the poses, as in the solve's last linearisation."""
    graph, values = _build(dims, priors, betweens, poses)
    marginals = gtsam.Marginals(graph, values)
    return {int(k): np.asarray(marginals.marginalCovariance(k), dtype=np.float64)
            for k in values.keys()}


def linear_step(dims: Dims, priors: Sequence[PriorFactor], betweens: Sequence[BetweenFactor],
                poses: Mapping[int, np.ndarray]) -> dict[int, np.ndarray]:
    """The Gauss-Newton step of the graph linearised at the poses (gtsam's sparse elimination;
    robust edges with their kernel's weight there): each node's tangent vector (Pose3: rotation
    first, in the node's frame)."""
    graph, values = _build(dims, priors, betweens, poses)
    delta = graph.linearize(values).optimize()
    return {int(k): np.asarray(delta.at(k), dtype=np.float64) for k in values.keys()}


def inlier_thresholds(dims: Dims, n: int) -> np.ndarray:
    """GNC's inlier cost threshold for n between factors: 0.5 * chi2inv(INLIER_PROBABILITY, dof)."""
    return np.full(n, 0.5 * CHI2_99[3 if dims == 2 else 6])


class Problem:
    """One pose graph as gtsam factors, built once and solved or evaluated from several starts.

    Between factors carry their Huber kernel where robust_k is set (LM, error); GNC and the
    per-factor costs use the plain Gaussian factors. known_inlier marks the between factors GNC
    never down-weights (odometry); priors always are.
    """

    def __init__(self, dims: Dims, priors: Sequence[PriorFactor],
                 betweens: Sequence[BetweenFactor], known_inlier: np.ndarray | None = None):
        self.dims = dims
        self.n_priors = len(priors)
        self.graph = _graph(dims, priors, betweens)
        robust = any(b.robust_k is not None for b in betweens)
        self.plain = _graph(dims, priors, betweens, robust=False) if robust else self.graph
        self.known_inlier = (np.zeros(len(betweens), dtype=bool) if known_inlier is None
                             else np.asarray(known_inlier, dtype=bool))
        self.known_span = _known_span(priors, betweens, self.known_inlier)

    # Poses: {key: T_world_node} or the gtsam.Values of a SolveResult.
    def error(self, poses) -> float:
        """gtsam's graph.error (Huber on robust edges) at the poses."""
        return float(self.graph.error(_values(poses, self.dims)))

    def factor_errors(self, poses) -> np.ndarray:
        """Plain cost 0.5 * |r|^2_Omega of every between factor at the poses."""
        values = _values(poses, self.dims)
        return np.array([self.plain.at(k).error(values)
                         for k in range(self.n_priors, self.plain.size())])

    def truncated_cost(self, poses) -> float:
        """GNC's objective (truncated least squares): priors and known inliers at their full
        cost, every other between factor at min(cost, inlier threshold)."""
        values = _values(poses, self.dims)
        errors = np.array([self.plain.at(k).error(values) for k in range(self.plain.size())])
        prior, between = errors[: self.n_priors], errors[self.n_priors:]
        capped = np.minimum(between, inlier_thresholds(self.dims, len(between)))
        return float(prior.sum() + np.where(self.known_inlier, between, capped).sum())

    def lm(self, initial, max_iterations: int, relative_error_tol: float | None = None
           ) -> SolveResult:
        """Levenberg-Marquardt from the initial poses (gtsam's default tolerances unless
        relative_error_tol is given)."""
        values = _values(initial, self.dims)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        if relative_error_tol is not None:
            params.setRelativeErrorTol(relative_error_tol)
            params.setAbsoluteErrorTol(0.0)
        t0 = time.perf_counter()
        optimizer = gtsam.LevenbergMarquardtOptimizer(self.graph, values, params)
        initial_error = float(self.graph.error(values))
        result = optimizer.optimize()
        seconds = time.perf_counter() - t0
        final_error = float(self.graph.error(result))
        log.debug("LM: %d iterations, error %.6g -> %.6g in %.2f s", optimizer.iterations(),
                  initial_error, final_error, seconds)
        return SolveResult(_from_values(result, self.dims), initial_error, final_error,
                           int(optimizer.iterations()), seconds, values=result)

    def _gnc_will_iterate(self, values, optimizer) -> bool:
        """False in gtsam's degenerate case: when no factor's cost at the start exceeds half its
        inlier threshold, GNC returns its first solve as it is, with its starting weights (which
        must then not leave the loops at 0)."""
        barc = np.asarray(optimizer.getInlierCostThresholds(), dtype=np.float64)
        return any(2.0 * self.plain.at(k).error(values) > barc[k]
                   for k in range(self.plain.size()))

    def gnc(self, initial, max_iterations: int) -> SolveResult:
        """Graduated non-convexity (gtsam GncLMOptimizer, truncated least squares) from the
        initial poses, then LM on the factors it keeps; errors are truncated_cost, weights
        those of the between factors (1 kept, 0 rejected).

        GNC's first solve uses its starting weights, and its schedule starts from that
        solution's residuals. gtsam starts every unknown factor at weight 1, so the first solve
        is least squares over every loop, wrong ones included: on simulated 07 with 263 wrong
        loops and 6 true ones admitted by loose gates, that solution was bent everywhere and GNC
        then rejected every loop (ATE 3.08 m, the odometry's). When the known inliers (priors
        and odometry) tie every node together, the loops start at weight 0 instead: the first
        solve is the odometry alone, true loops have residuals of the drift (metres) and wrong
        ones of the distance between unrelated places, and GNC's first weights (about
        1/residual) already favour the true ones (the same run: 6 of 6 true loops kept, 263 of
        263 wrong ones rejected, keyframe ATE 0.863 m as without the wrong loops; sphere2500
        with 50 or 200 wrong loops: the same solution as before, in 8 instead of 18-62 s).

        gtsam's GNC re-solves from the initial poses at every step of its schedule; with the
        default (linear, x1.4) schedule and LM's 1e-5 tolerance, 50 wrong loops on sphere2500
        take 200 s. The super-linear schedule and a 1e-3 tolerance for those inner solves take
        13 s to the same weights; the final LM on the kept factors restores full precision."""
        lm = gtsam.LevenbergMarquardtParams()
        lm.setMaxIterations(max_iterations)
        lm.setRelativeErrorTol(GNC_INNER_RELATIVE_TOL)
        params = gtsam.GncLMParams(lm)
        params.setLossType(gtsam.GncLossType.TLS)
        params.setScheduler(gtsam.GncScheduler.SuperLinear)
        known = list(range(self.n_priors)) + [self.n_priors + int(k)
                                              for k in np.flatnonzero(self.known_inlier)]
        params.setKnownInliers(known)
        t0 = time.perf_counter()
        values = _values(initial, self.dims)
        initial_error = self.truncated_cost(values)
        optimizer = gtsam.GncLMOptimizer(self.plain, values, params)
        optimizer.setInlierCostThresholdsAtProbability(INLIER_PROBABILITY)
        if self.known_span and self._gnc_will_iterate(values, optimizer):
            start = np.zeros(self.plain.size())
            start[known] = 1.0
            optimizer.setWeights(start)
        result = optimizer.optimize()
        all_weights = np.asarray(optimizer.getWeights(), dtype=np.float64)
        kept = gtsam.NonlinearFactorGraph()
        for k in np.flatnonzero(all_weights > 0.5):
            kept.push_back(self.plain.at(int(k)))
        polish = gtsam.LevenbergMarquardtParams()
        polish.setMaxIterations(max_iterations)
        result = gtsam.LevenbergMarquardtOptimizer(kept, result, polish).optimize()
        weights = all_weights[self.n_priors:]
        poses = _from_values(result, self.dims)
        final_error = self.truncated_cost(result)
        seconds = time.perf_counter() - t0
        log.debug("GNC: %d of %d factors kept, cost %.6g -> %.6g in %.2f s",
                  int((weights > 0.5).sum()), len(weights), initial_error, final_error, seconds)
        return SolveResult(poses, initial_error, final_error, None, seconds, weights, result)


def _known_span(priors: Sequence[PriorFactor], betweens: Sequence[BetweenFactor],
                known: np.ndarray) -> bool:
    """True when the priors and the known-inlier between factors alone fix every node: the
    known edges connect all nodes into one tree-or-more and a prior anchors it."""
    keys = {p.key for p in priors} | {k for b in betweens for k in (b.i, b.j)}
    if not priors or not keys:
        return False
    parent = {k: k for k in keys}

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    for b, is_known in zip(betweens, known, strict=True):
        if is_known:
            parent[root(b.i)] = root(b.j)
    return len({root(k) for k in keys}) == 1


def _diagonal_noise(information: np.ndarray):
    # The linear initialisers need diagonal noise (LAGO casts to Diagonal; InitializePose3 reads
    # one rotation precision): keep the information's diagonal, drop its cross terms.
    return gtsam.noiseModel.Diagonal.Precisions(np.diag(information).copy())


def _has_odometry_chain(betweens: Sequence[BetweenFactor], keys: Iterable[int]) -> bool:
    """LAGO's fast path needs an edge (k, k+1) for every pair of consecutive keys."""
    keys = sorted(keys)
    if keys != list(range(keys[0], keys[0] + len(keys))):
        return False
    linked = {min(b.i, b.j) for b in betweens if abs(b.i - b.j) == 1}
    return all(k in linked for k in keys[:-1])


def _lift(T: np.ndarray):
    x, y, th = T[0, 2], T[1, 2], np.arctan2(T[1, 0], T[0, 0])
    return gtsam.Pose3(gtsam.Rot3.Rz(th), np.array([x, y, 0.0]))


def _lift_information(info: np.ndarray) -> np.ndarray:
    # (x y theta) -> (rx ry rz tx ty tz): theta's precision on every rotation axis, and the
    # mean planar precision on z, so the lifted graph stays planar.
    d = np.diag(info)
    return np.diag([d[2], d[2], d[2], d[0], d[1], 0.5 * (d[0] + d[1])])


def global_initial(dims: Dims, priors: Sequence[PriorFactor], betweens: Sequence[BetweenFactor]
                   ) -> InitialGuess:
    """A global initial guess that ignores the current poses: 3D gtsam InitializePose3 (chordal
    relaxation of the rotations, then one Gauss-Newton step on the poses); 2D gtsam LAGO along
    the odometry chain. A 2D graph without a complete (k, k+1) chain gets InitializePose3 on the
    graph lifted into 3D, because LAGO's own spanning-tree search takes 7 s on ais2klinik
    (15k nodes) against 2 s for the chordal one. Robust kernels are ignored; information
    matrices are diagonalised. Needs a prior (the anchor)."""
    if not priors:
        raise ValueError("a global initialisation needs a prior on one node")
    keys = {p.key for p in priors} | {b.i for b in betweens} | {b.j for b in betweens}
    t0 = time.perf_counter()
    # A prior only fixes the gauge, but the pipeline's (1e-3 deg: 3e9 / rad^2) leaves the
    # linear orientation system indeterminate to gtsam's Cholesky: cap its precisions at those
    # of the most certain edge.
    cap = np.max([np.diag(b.information) for b in betweens], axis=0)
    priors = [replace(p, information=np.diag(np.minimum(np.diag(p.information), cap)))
              for p in priors]
    graph = gtsam.NonlinearFactorGraph()
    if dims == 2 and _has_odometry_chain(betweens, keys):
        for p in priors:
            graph.add(gtsam.PriorFactorPose2(p.key, _to_gtsam(p.T_world_node, 2),
                                             _diagonal_noise(p.information)))
        for b in betweens:
            graph.add(gtsam.BetweenFactorPose2(b.i, b.j, _to_gtsam(b.T_i_j, 2),
                                               _diagonal_noise(b.information)))
        values, method = gtsam.lago.initialize(graph, True), "lago"
        poses = _from_values(values, 2)
    else:
        lift = _lift if dims == 2 else (lambda T: gtsam.Pose3(T))
        info3 = _lift_information if dims == 2 else (lambda info: info)
        for p in priors:
            graph.add(gtsam.PriorFactorPose3(p.key, lift(p.T_world_node),
                                             _diagonal_noise(info3(p.information))))
        for b in betweens:
            graph.add(gtsam.BetweenFactorPose3(b.i, b.j, lift(b.T_i_j),
                                               _diagonal_noise(info3(b.information))))
        values, method = gtsam.InitializePose3.initialize(graph), "chordal"
        poses = {int(k): np.asarray(values.atPose3(k).matrix()) for k in values.keys()
                 if int(k) in keys}  # without InitializePose3's anchor key
        if dims == 2:
            poses = {k: _planar(T) for k, T in poses.items()}
    seconds = time.perf_counter() - t0
    log.debug("global initialisation (%s): %d poses in %.2f s", method, len(poses), seconds)
    return InitialGuess(poses, method, seconds)


def _planar(T: np.ndarray) -> np.ndarray:
    th = np.arctan2(T[1, 0], T[0, 0])
    c, s = np.cos(th), np.sin(th)
    return np.array([[c, -s, T[0, 3]], [s, c, T[1, 3]], [0.0, 0.0, 1.0]])


def certify_rotations(dims: Dims, betweens: Sequence[BetweenFactor],
                      poses: Mapping[int, np.ndarray]) -> RotationCertificate:
    """Shonan averaging (gtsam ShonanAveraging2/3) of the edges' rotations with SE-Sync's
    rotation weights kappa (scaled to mean 1), started at the rotations of poses; certified when
    its Riemannian staircase verifies global optimality of the rotation-only problem by
    SHONAN_MAX_P (lambda_min: the certificate matrix's smallest eigenvalue, at that scale)."""
    kappa, _ = sesync_weights(np.stack([b.information for b in betweens]), dims)
    # Scaling every weight scales the certificate matrix and changes nothing else; at kitti_05's
    # kappa (1.5e6) gtsam's eigensolver fails and its absolute threshold (-1e-4) means nothing.
    kappa = kappa / kappa.mean()
    t0 = time.perf_counter()
    lm = gtsam.LevenbergMarquardtParams()
    initial = gtsam.Values()
    if dims == 3:
        measurements = [gtsam.BinaryMeasurementRot3(
            b.i, b.j, gtsam.Rot3(b.T_i_j[:3, :3]),
            gtsam.noiseModel.Isotropic.Sigma(3, 1 / np.sqrt(k)))
            for b, k in zip(betweens, kappa, strict=True)]
        params = gtsam.ShonanAveragingParameters3(lm)
        shonan = gtsam.ShonanAveraging3(measurements, params)
        for key, T in poses.items():
            initial.insert(key, gtsam.Rot3(T[:3, :3]))
    else:  # ShonanAveraging2 takes Pose2 factors and keeps their theta variance only
        factors = [gtsam.BetweenFactorPose2(
            b.i, b.j, _to_gtsam(b.T_i_j, 2), gtsam.noiseModel.Gaussian.Covariance(
                np.diag([1.0, 1.0, 1.0 / k]))) for b, k in zip(betweens, kappa, strict=True)]
        params = gtsam.ShonanAveragingParameters2(lm)
        shonan = gtsam.ShonanAveraging2(factors, params)
        for key, T in poses.items():
            initial.insert(key, gtsam.Rot2(np.arctan2(T[1, 0], T[0, 0])))
    threshold = params.getOptimalityThreshold()
    try:
        rotations, lambda_min = shonan.run(initial, dims, SHONAN_MAX_P)
    except RuntimeError as exc:  # "Shonan::run did not converge for given max_p"
        return RotationCertificate(False, None, None, time.perf_counter() - t0, str(exc))
    certified = bool(lambda_min >= threshold)
    return RotationCertificate(certified, float(lambda_min), float(shonan.cost(rotations)),
                               time.perf_counter() - t0)


def between_error(T_i_j: np.ndarray, T_w_i: np.ndarray, T_w_j: np.ndarray) -> np.ndarray:
    """gtsam's BetweenFactorPose3 error (6, rotation first, in j's frame) of the measurement
    T_i_j at poses T_w_i, T_w_j."""
    return np.asarray(gtsam.Pose3(T_i_j).localCoordinates(
        gtsam.Pose3(T_w_i).between(gtsam.Pose3(T_w_j))))
