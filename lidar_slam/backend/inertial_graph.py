"""The full keyframe graph with IMU and GNSS factors, in gtsam: pose X(k), velocity V(k) and bias
B(k) per keyframe; the pose graph's odometry (a chain of edges, or a drift state F(k) per
keyframe: odometry_as_drift) and loop edges, gtsam CombinedImuFactor between
consecutive keyframes (PreintegratedCombinedMeasurements from lidar_slam.imu), GPSFactorArm per
GNSS fix (Huber-robust), a prior on the first pose and bias. Levenberg-Marquardt, then the
poses' marginal covariances.

Everything here is in one frame S (gravity-aligned z up; ENU with GNSS) and the nodes are IMU
frames: the preintegrated measurements then need no lever-arm correction (gtsam's body_P_sensor
leaves out the angular acceleration term), and the caller moves lidar-frame edges and lever arms
into the IMU frame (lidar_slam.backend.imu_gnss_solve).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, F, R, V, X

from lidar_slam.backend.factors import BetweenFactor

MOUNT = R(0)  # the correction of R_lidar_imu, when the solve refines it (mount_sigma_rad)


@dataclass(frozen=True)
class ImuLink:
    """IMU measurements preintegrated from keyframe i's stamp to keyframe j's."""

    i: int
    j: int
    pim: gtsam.PreintegratedCombinedMeasurements


@dataclass(frozen=True)
class GnssFactor:
    """One fix: the antenna at enu_m (S frame) is at arm_m in node `key`'s frame; sigma_m (3,)."""

    key: int
    enu_m: np.ndarray
    arm_m: np.ndarray
    sigma_m: np.ndarray


@dataclass(frozen=True)
class InertialSolution:
    """T_S_node (4x4), velocity (3,) and bias (6,: accelerometer then gyro) per keyframe with
    IMU states, the error before / after, LM iterations and seconds; covariances (6x6, rotation
    first, node frame) when asked for."""

    poses: dict[int, np.ndarray]
    velocities: dict[int, np.ndarray]
    biases: dict[int, np.ndarray]
    initial_error: float
    final_error: float
    iterations: int
    seconds: float
    covariances: dict[int, np.ndarray] = field(default_factory=dict)
    # T_imu_imu' (4x4, a rotation): the nodes are the frames of the IMU mounted at T_lidar_imu
    # T_imu_imu' when the solve refined the mounting (mount_sigma_rad), else None
    mount_correction: np.ndarray | None = None
    # the graph and its solution (gtsam), for covariances asked for later (with_covariances)
    graph: object = field(default=None, repr=False)
    estimate: object = field(default=None, repr=False)

    def with_covariances(self, anchor: int | None = None) -> InertialSolution:
        """Itself with the poses' covariances (computed now if the solve did not); with an
        anchor, of each pose relative to that one (relative_covariances)."""
        if self.graph is None or (self.covariances and anchor is None):
            return self
        return dataclasses.replace(self, covariances=pose_covariances(
            self.graph, self.estimate, list(self.poses), anchor))


def _noise(information: np.ndarray, robust_k: float | None):
    base = gtsam.noiseModel.Gaussian.Information(information)
    if robust_k is None:
        return base
    return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(robust_k), base)


def build(poses: dict[int, np.ndarray], velocities: dict[int, np.ndarray],
          edges: list[BetweenFactor], links: list[ImuLink], gnss: list[GnssFactor],
          prior_pose: np.ndarray, prior_covariance: np.ndarray, bias_sigma: np.ndarray,
          gnss_huber_k: float, mount_sigma_rad: float | None = None,
          drift: tuple[float, float] | None = None
          ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """The graph solve() optimises (see there) and its initial values."""
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    first = min(poses)
    for k, T in poses.items():
        values.insert(X(k), gtsam.Pose3(T))
    graph.add(gtsam.PriorFactorPose3(X(first), gtsam.Pose3(prior_pose),
                                     gtsam.noiseModel.Gaussian.Covariance(prior_covariance)))
    noises: dict = {}
    if drift is not None:
        odometry = [e for e in edges if not e.is_loop]
        edges = [e for e in edges if e.is_loop]
        for factor in odometry_as_drift(odometry, poses, values, drift,
                                        mount=mount_sigma_rad is not None):
            graph.add(factor)
    for e in edges:
        key = (id(e.information), e.robust_k)
        if key not in noises:
            noises[key] = _noise(e.information, e.robust_k)
        if mount_sigma_rad is None:
            graph.add(gtsam.BetweenFactorPose3(X(e.i), X(e.j), gtsam.Pose3(e.T_i_j),
                                               noises[key]))
        else:
            graph.add(mount_edge(e, noises[key]))
    if mount_sigma_rad is not None:
        values.insert(MOUNT, gtsam.Rot3())
        graph.add(gtsam.PriorFactorRot3(MOUNT, gtsam.Rot3(),
                                        gtsam.noiseModel.Isotropic.Sigma(3, mount_sigma_rad)))
    bias_noise = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(bias_sigma, dtype=float))
    starts = {link.i for link in links} - {link.j for link in links}
    for k in sorted({link.i for link in links} | {link.j for link in links}):
        values.insert(V(k), np.asarray(velocities[k], dtype=float))
        values.insert(B(k), gtsam.imuBias.ConstantBias())
        if k in starts:
            graph.add(gtsam.PriorFactorConstantBias(B(k), gtsam.imuBias.ConstantBias(),
                                                    bias_noise))
    for link in links:
        graph.add(gtsam.CombinedImuFactor(X(link.i), V(link.i), X(link.j), V(link.j), B(link.i),
                                          B(link.j), link.pim))
    huber = gtsam.noiseModel.mEstimator.Huber.Create(gnss_huber_k)
    for g in gnss:
        model = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Diagonal.Sigmas(
            np.asarray(g.sigma_m, dtype=float)))
        graph.add(gtsam.GPSFactorArm(X(g.key), np.asarray(g.enu_m, dtype=float),
                                     np.asarray(g.arm_m, dtype=float), model))
    return graph, values


def solve(poses: dict[int, np.ndarray], velocities: dict[int, np.ndarray],
          edges: list[BetweenFactor], links: list[ImuLink], gnss: list[GnssFactor],
          prior_pose: np.ndarray, prior_covariance: np.ndarray, bias_sigma: np.ndarray,
          gnss_huber_k: float, max_iterations: int, relative_error_tol: float,
          covariances: bool = True, mount_sigma_rad: float | None = None,
          drift: tuple[float, float] | None = None) -> InertialSolution:
    """LM from the initial poses (T_S_node) and velocities (keyframes with IMU states), biases
    zero; the first keyframe's pose has a prior (mean, 6x6 covariance in its frame) and the first
    bias of every chain of IMU links a zero-mean prior (bias_sigma, 6: accelerometer then gyro).
    mount_sigma_rad: the IMU's mounting rotation is refined too (a rotation of the IMU frame
    the edges were moved into, zero-mean prior of this sigma per axis; see mount_edge).
    drift: the odometry edges as a drift state instead of a chain (odometry_as_drift), with
    these white fractions (rotation, translation) of each edge's covariance.
    """
    graph, values = build(poses, velocities, edges, links, gnss, prior_pose, prior_covariance,
                          bias_sigma, gnss_huber_k, mount_sigma_rad, drift)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(relative_error_tol)
    params.setAbsoluteErrorTol(0.0)
    t0 = time.perf_counter()
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    initial_error = float(graph.error(values))
    result = optimizer.optimize()
    out_poses = {k: np.asarray(result.atPose3(X(k)).matrix(), dtype=np.float64) for k in poses}
    with_imu = [k for k in velocities if values.exists(V(k))]
    cov = pose_covariances(graph, result, list(poses)) if covariances else {}
    mount = None
    if mount_sigma_rad is not None:
        mount = np.eye(4)
        mount[:3, :3] = result.atRot3(MOUNT).matrix()
    return InertialSolution(
        out_poses, {k: np.asarray(result.atVector(V(k))) for k in with_imu},
        {k: np.asarray(result.atConstantBias(B(k)).vector()) for k in with_imu}, initial_error,
        float(graph.error(result)), int(optimizer.iterations()), time.perf_counter() - t0, cov,
        mount, graph, result)


_SELECT_ROTATION = np.vstack([np.eye(3), np.zeros((3, 3))])  # d Pose3(R, 0) / d R (6x3)


WALK_MIN = 0.05  # of an edge's variance (per whitened direction) stays in the walk


def odometry_as_drift(edges: list[BetweenFactor], poses: dict[int, np.ndarray],
                      values: gtsam.Values, white: tuple[float, float], mount: bool = False
                      ) -> list:
    """The odometry edges (a chain i -> j, sorted by i) as a drift state: per keyframe k a pose
    F(k) = T_S_odom, where the odometry's own world lies, and the odometry's pose O_k (the
    edges composed from the start of their chain) measured from it, X_k = F_k O_k Exp(w_k),
    with white pose noise w_k (BetweenFactorPose3(F_k, X_k, O_k)), while F is a random walk
    (BetweenFactorPose3(F_i, F_j, identity)). w -> 0 is the chain; a scan-to-map odometry's
    error, bounded while its local map lasts, is mostly white, and a chain that makes it a
    random walk lets the IMU bend it (docs/bank.md, "A drift state").

    Each edge's covariance C_ij (in X_j's frame) is split so that the edge keeps it: the edge's
    error is -Ad(T_ji) w_i + w_j + Ad(O_j^-1) d (d the walk's step in F's frame), so keyframe
    k's white noise W_k = S C_k S / 2 (S = diag(sqrt(white)): rotation, translation), C_k the
    surer (smaller log-determinant) of the two edges at k moved into X_k's frame, and the walk
    takes the rest, C_ij - Ad(T_ji) W_i Ad(T_ji)^T - W_j (at least WALK_MIN of C_ij in every
    direction), moved into F's frame by Ad(O_j). So an edge across an odometry reset (kiss-icp's
    threshold added to its covariance) is a jump of the drift, not white noise of the keyframe
    after it. Both Huber (the edge's robust_k). Inserts F's initial values (X_k O_k^-1) into
    values. mount: the nodes' IMU is turned by MOUNT (see mount_edge), so is each O_k."""
    S = np.diag(np.sqrt([white[0]] * 3 + [white[1]] * 3))
    chain = sorted(edges, key=lambda e: e.i)
    seen: set[int] = set()
    for e in chain:
        if e.j <= e.i or e.j in seen:
            raise ValueError(f"odometry edge {e.i} -> {e.j}: not a chain (each keyframe reached "
                             "once, forwards)")
        seen.add(e.j)
    cov = [np.linalg.inv(e.information) for e in chain]
    surest: dict[int, tuple[float, np.ndarray]] = {}
    for e, C in zip(chain, cov):
        logdet = float(np.linalg.slogdet(C)[1])
        Ad = adjoint(e.T_i_j)  # C in X_i's frame, for keyframe i
        for k, C_k in ((e.i, Ad @ C @ Ad.T), (e.j, C)):
            if k not in surest or logdet < surest[k][0]:
                surest[k] = (logdet, C_k)
    W = {k: S @ C @ S / 2.0 for k, (_, C) in surest.items()}
    odom: dict[int, np.ndarray] = {}
    out: list = []

    def white_factor(k: int, robust_k: float | None):
        noise = _noise(np.linalg.inv(0.5 * (W[k] + W[k].T)), robust_k)
        if mount:
            return mount_edge(BetweenFactor(k, k, odom[k], np.eye(6)), noise, (F(k), X(k)))
        return gtsam.BetweenFactorPose3(F(k), X(k), gtsam.Pose3(odom[k]), noise)

    for e, C in zip(chain, cov):
        if e.i not in odom:  # the start of a chain: its own drift state
            odom[e.i] = np.eye(4)
            values.insert(F(e.i), gtsam.Pose3(poses[e.i]))
            out.append(white_factor(e.i, e.robust_k))
        odom[e.j] = odom[e.i] @ e.T_i_j
        values.insert(F(e.j), gtsam.Pose3(poses[e.j] @ np.linalg.inv(odom[e.j])))
        out.append(white_factor(e.j, e.robust_k))
        Ad_ji = adjoint(np.linalg.inv(e.T_i_j))
        L = np.linalg.cholesky(C)
        L_inv = np.linalg.inv(L)
        rest = L_inv @ (C - Ad_ji @ W[e.i] @ Ad_ji.T - W[e.j]) @ L_inv.T  # C's whitened frame
        lam, U = np.linalg.eigh(0.5 * (rest + rest.T))
        walk_c = L @ (U * np.maximum(lam, WALK_MIN)) @ U.T @ L.T
        Ad = adjoint(odom[e.j])
        walk = Ad @ walk_c @ Ad.T
        out.append(gtsam.BetweenFactorPose3(F(e.i), F(e.j), gtsam.Pose3(),
                                            _noise(np.linalg.inv(0.5 * (walk + walk.T)),
                                                   e.robust_k)))
    return out


def mount_edge(e: BetweenFactor, noise, keys: tuple[int, int] | None = None
               ) -> gtsam.CustomFactor:
    """The edge e (T_i_j between IMU frames at the mounting assumed) between nodes whose IMU is
    turned by D (the key MOUNT, T_imu_imu'): it measures D^-1 T_i_j D. Error as gtsam's
    BetweenFactorPose3 (Logmap of measured^-1 X_i^-1 X_j), Jacobians by gtsam's own.
    keys: the two gtsam keys (default X(e.i), X(e.j))."""
    Z = gtsam.Pose3(e.T_i_j)
    ki, kj = keys if keys is not None else (X(e.i), X(e.j))

    def error(this, values, H):
        Hi, Hj, Ha, Hb, Hz, Hm1, Hm2, He1, He2, Hl = (np.zeros((6, 6), order="F")
                                                       for _ in range(10))
        hx = values.atPose3(ki).between(values.atPose3(kj), Hi, Hj)
        D = gtsam.Pose3(values.atRot3(MOUNT), np.zeros(3))
        M = D.inverse(Ha).compose(Z, Hb, Hz).compose(D, Hm1, Hm2)
        err = gtsam.Pose3.Logmap(M.between(hx, He1, He2), Hl)
        if H is not None:
            H[0] = Hl @ He2 @ Hi
            H[1] = Hl @ He2 @ Hj
            H[2] = Hl @ He1 @ (Hm1 @ Hb @ Ha + Hm2) @ _SELECT_ROTATION
        return err

    return gtsam.CustomFactor(noise, [ki, kj, MOUNT], error)


def pose_covariances(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                     keys: list[int], anchor: int | None = None) -> dict[int, np.ndarray]:
    """Marginal covariance (6x6, rotation first, node frame) of every pose X(k) at the solution;
    with an anchor, of every pose relative to X(anchor) (relative_covariances).

    gtsam's Marginals (COLAMD ordering) calls these graphs indeterminate near the last
    velocities (00 and synthetic drives, with or without GNSS), while the same Hessian is
    positive definite to NumPy's Cholesky (its smallest pivot 1.4): so the Bayes tree is
    eliminated in METIS order (which succeeds; the same covariances as a sparse LU, to 5e-7),
    COLAMD next, and the diagonal blocks of the inverse Hessian by a sparse LU (scipy) last."""
    gfg = graph.linearize(values)
    out = None
    for ordering in (gtsam.Ordering.MetisGaussianFactorGraph,
                     gtsam.Ordering.ColamdGaussianFactorGraph):
        try:
            tree = gfg.eliminateMultifrontal(ordering(gfg))
            out = {k: _symmetric(tree.marginalCovariance(X(k))) for k in keys}
            break
        except RuntimeError:  # gtsam's IndeterminantLinearSystemException
            continue
    if out is None:
        out = _lu_covariances(gfg, keys)
    if anchor is None:
        return out
    return relative_covariances(out, _anchor_columns(gfg, keys, anchor), values, anchor)


def relative_covariances(marginals: dict[int, np.ndarray],
                         cross: dict[int, np.ndarray], values: gtsam.Values, anchor: int
                         ) -> dict[int, np.ndarray]:
    """Covariance (node frame) of each pose relative to the anchor's, T_0k = X_0^-1 X_k: with
    X_k = X_k^ Exp(xi_k), T_0k = T_0k^ Exp(xi_k - Ad(T_k0) xi_0) to first order, so
    C_rel = C_kk + A C_00 A' - C_k0 A' - A C_0k with A = Ad(X_k^-1 X_0). The run's poses are
    written relative to its first keyframe (poses_kitti.txt: frame 0 at its stamp is the
    identity), while the solve with the IMU places that keyframe in the gravity frame only as
    surely as gravity says (its tilt): a tilt error of it turns every written position about
    it, which the marginals alone do not carry. The anchor keeps its own marginal (how surely
    gravity places the written frame). cross: {k: cov(xi_k, xi_0)}."""
    X0 = values.atPose3(X(anchor))
    out = {}
    for k, c in marginals.items():
        if k == anchor:  # its own marginal: how surely gravity places the written frame
            out[k] = c
            continue
        A = np.asarray(values.atPose3(X(k)).between(X0).AdjointMap(), dtype=np.float64)
        ck0 = cross[k]
        rel = _symmetric(c + A @ marginals[anchor] @ A.T - ck0 @ A.T - A @ ck0.T)
        # the terms cancel where X_k is near X_0, and the marginals (Bayes tree) and the cross
        # terms (LU) are two factorisations: keep it positive definite
        w, v = np.linalg.eigh(rel)
        floor = 1e-12 * max(float(w.max()), 1e-300)
        out[k] = rel if w.min() > floor else _symmetric((v * np.maximum(w, floor)) @ v.T)
    return out


def joint_pose_covariance(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                          keys: list[int], anchor: int | None = None) -> np.ndarray:
    """The joint covariance (6N x 6N, rotation first per pose, node frames, keys' order) of the
    poses X(k) at the solution, from the inverse Hessian's pose columns (sparse LU); with an
    anchor, of each pose relative to it as relative_covariances (the anchor's own rows as its
    marginal): its diagonal blocks are pose_covariances'. For tools (the spread of a run's
    NEES), not the run: 6N right-hand sides, 64 poses' at a time, and a dense 6N x 6N result
    (a bank sequence's few hundred keyframes; 0.6 GB at 1500)."""
    gfg = graph.linearize(values)
    offsets, lu, Jtb = _normal_equations(gfg, "COLAMD")
    cols = np.concatenate([np.arange(offsets[X(k)], offsets[X(k)] + 6) for k in keys])
    S = np.empty((len(cols), len(cols)))
    for c0 in range(0, len(cols), 6 * 64):
        part = cols[c0:c0 + 6 * 64]
        E = np.zeros((len(Jtb), len(part)))
        E[part, np.arange(len(part))] = 1.0
        S[:, c0:c0 + len(part)] = lu.solve(E)[cols]
    if anchor is None:
        return _symmetric(S)
    T = np.eye(len(cols))
    X0 = values.atPose3(X(anchor))
    a = keys.index(anchor)
    for i, k in enumerate(keys):
        if k != anchor:
            T[6 * i:6 * i + 6, 6 * a:6 * a + 6] = -np.asarray(
                values.atPose3(X(k)).between(X0).AdjointMap(), dtype=np.float64)
    return _symmetric(T @ S @ T.T)


def _anchor_columns(gfg: gtsam.GaussianFactorGraph, keys: list[int], anchor: int
                    ) -> dict[int, np.ndarray]:
    """cov(xi_k, xi_anchor) (6x6 each): the inverse Hessian's anchor columns H^-1 e_i, each the
    solution of the graph with a linear term e_i on the anchor (a HessianFactor, G = 0, g = e_i)
    less the graph's own solution; eliminated as pose_covariances (METIS, then COLAMD), a sparse
    LU last (scipy: its import alone is 0.15 s of a 4.5 s hand-held walk, against ~30 ms for
    the seven eliminations; the same columns to 1e-9)."""
    for ordering in (gtsam.Ordering.MetisGaussianFactorGraph,
                     gtsam.Ordering.ColamdGaussianFactorGraph):
        try:
            order = ordering(gfg)
            own = gfg.optimize(order)
            cols = []
            for i in range(6):
                with_g = gtsam.GaussianFactorGraph()
                with_g.push_back(gfg)
                with_g.push_back(gtsam.HessianFactor(X(anchor), np.zeros((6, 6)),
                                                     np.eye(6)[i], 0.0))
                cols.append(with_g.optimize(order))
        except RuntimeError:  # gtsam's IndeterminantLinearSystemException
            continue
        return {k: np.stack([c.at(X(k)) - own.at(X(k)) for c in cols], axis=1) for k in keys}
    offsets, lu, Jtb = _normal_equations(gfg, "COLAMD")
    E = np.zeros((len(Jtb), 6))
    E[offsets[X(anchor)]:offsets[X(anchor)] + 6] = np.eye(6)
    Z = lu.solve(E)
    return {k: Z[offsets[X(k)]:offsets[X(k)] + 6] for k in keys}


def pose_steps(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
               keys: list[int], anchor: int | None = None) -> dict[int, np.ndarray]:
    """One Gauss-Newton step of graph from values: its 6-vector (rotation first, node frame) for
    every pose X(k); with an anchor, of every pose relative to X(anchor) (xi_k - Ad(X_k^-1 X_0)
    xi_0, as relative_covariances). Eliminated as pose_covariances does (METIS, COLAMD, then a
    sparse LU)."""
    gfg = graph.linearize(values)
    out = None
    for ordering in (gtsam.Ordering.MetisGaussianFactorGraph,
                     gtsam.Ordering.ColamdGaussianFactorGraph):
        try:
            step = gfg.optimize(ordering(gfg))
            out = {k: np.asarray(step.at(X(k)), dtype=np.float64) for k in keys}
            break
        except RuntimeError:  # gtsam's IndeterminantLinearSystemException
            continue
    if out is None:
        offsets, lu, Jtb = _normal_equations(gfg)
        x = lu.solve(Jtb)
        out = {k: x[offsets[X(k)]:offsets[X(k)] + 6] for k in keys}
    if anchor is None:
        return out
    X0 = values.atPose3(X(anchor))
    return {k: v - np.asarray(values.atPose3(X(k)).between(X0).AdjointMap()) @ out[anchor]
            for k, v in out.items()}


def _normal_equations(gfg: gtsam.GaussianFactorGraph, permc_spec: str = "MMD_AT_PLUS_A"):
    """gtsam's linear system (min |J x - b|) as sparse normal equations: the column offset of
    every key (sparseJacobian_'s order: keys sorted, then b), the sparse LU of J^T J (SuperLU's
    column ordering permc_spec), J^T b."""
    from scipy.sparse import csc_matrix
    from scipy.sparse.linalg import splu

    offsets, n = {}, 0
    for key in sorted(gfg.keys()):
        offsets[key] = n
        n += 3 if gtsam.Symbol(key).chr() in (ord("v"), ord("r")) else 6  # pose, bias: 6
    rows, cols, vals = gfg.sparseJacobian_()
    r, c = rows.astype(int) - 1, cols.astype(int) - 1  # 1-based
    inside = c < n  # the last column is b
    J = csc_matrix((vals[inside], (r[inside], c[inside])), shape=(int(r.max()) + 1, n))
    b = np.zeros(J.shape[0])
    np.add.at(b, r[~inside], vals[~inside])
    return offsets, splu(csc_matrix(J.T @ J), permc_spec=permc_spec), J.T @ b


def _symmetric(cov) -> np.ndarray:
    cov = np.asarray(cov, dtype=np.float64)
    return 0.5 * (cov + cov.T)


def _lu_covariances(gfg: gtsam.GaussianFactorGraph, keys: list[int]) -> dict[int, np.ndarray]:
    """The pose blocks of the inverse Hessian by a sparse LU (slow: ~1 ms per pose)."""
    offsets, lu, Jtb = _normal_equations(gfg)
    n = len(Jtb)
    out = {}
    for chunk in range(0, len(keys), 64):  # 64 poses' columns at a time: bounded memory
        part = keys[chunk:chunk + 64]
        E = np.zeros((n, 6 * len(part)))
        for c, k in enumerate(part):
            E[offsets[X(k)]:offsets[X(k)] + 6, 6 * c:6 * c + 6] = np.eye(6)
        Z = lu.solve(E)
        for c, k in enumerate(part):
            out[k] = _symmetric(Z[offsets[X(k)]:offsets[X(k)] + 6, 6 * c:6 * c + 6])
    return out


def adjoint(T: np.ndarray) -> np.ndarray:
    """gtsam's 6x6 adjoint of T (rotation first): T Exp(xi) T^-1 = Exp(Ad(T) xi)."""
    return np.asarray(gtsam.Pose3(T).AdjointMap(), dtype=np.float64)

