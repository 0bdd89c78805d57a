"""IMU and GNSS in the final solve of the back-end (issue 22, item 3).

After the pose graph's final solve (loops kept or rejected as before), the keyframes are moved
into a gravity-aligned z-up frame S (with GNSS: the local ENU frame of the first usable fix) and
solved again with every factor: the pose graph's odometry and kept loops, a CombinedImuFactor
between consecutive keyframes (velocity and bias states) and a Huber-robust GPSFactorArm per
fix. The windows of the live estimate stay pose-only; only this final solve sees the IMU and
GNSS. The result comes back in the run's world frame (the first keyframe where the pose graph
put it) with T_S_world, where that world lies in S.

Initial values: the gravity direction from the IMU over the whole run (the mean specific force
rotated by the poses, less the change of velocity of the odometry), velocities from the
odometry, biases zero. With GNSS, T_enu_world from a robust alignment of the run's antenna
positions to the fixes (lidar_slam.backend.gnss), then solve and gate again until the fixes
kept stop changing: a multipath jump is left out, not followed.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field

import numpy as np

from lidar_slam.backend import gnss as gnss_align
from lidar_slam.backend import gtsam_graph, inertial_graph
from lidar_slam.backend.factors import BetweenFactor, sigmas_to_information, with_rotation_floor
from lidar_slam.config import SlamConfig
from lidar_slam.frontend import imu_check
from lidar_slam.geo import LocalEnu
from lidar_slam.geometry import interpolate, inverse, make_pose
from lidar_slam.imu import (
    ImuStream,
    combined_params,
    gravity_rotation,
    predict_pose,
    predict_poses_along,
)
from lidar_slam.io.imu_gnss import GnssFixes, ImuSamples
from lidar_slam.io.imu_units import STANDARD_GRAVITY_MPS2

log = logging.getLogger(__name__)

# Prior of the first bias (accelerometer m/s^2, gyro rad/s): loose, a consumer MEMS unit's
# offsets after a static calibration are ~0.05 m/s^2 and ~0.002 rad/s.
BIAS_SIGMA = np.array([0.2, 0.2, 0.2, 0.02, 0.02, 0.02])
# Without GNSS the first keyframe keeps its place and heading (the pose graph's prior) but its
# roll and pitch are the IMU's to say: their prior is this loose (rad).
FREE_TILT_SIGMA_RAD = 0.5
# With GNSS the fixes place the run: the first keyframe's prior only keeps the problem well
# posed (m, rad).
GNSS_PRIOR_TRANS_SIGMA_M, GNSS_PRIOR_ROT_SIGMA_RAD = 100.0, 1.0
GNSS_HUBER_K = 3.0  # whitened units: a fix within 3 sigma counts fully
GATE_ROUNDS = 4
# Fewer fixes than this share kept by the gate: the fixes do not follow the lidar's path (a
# multipath jump is a few of them): said in one warning (summary.json gnss.warning).
MIN_KEPT_SHARE = 0.5
# LM stops when an iteration gains less than this (relative): on sim s08 without GNSS, LM creeps
# along a flat valley (not yet understood) for 100 iterations at 1e-9, 46 at 1e-6,
# the same poses (ATE 0.1124 m both); elsewhere it converges in 3-10 either way.
RELATIVE_TOL = 1e-6
MIN_IMU_SPAN_S = 1.0  # IMU links must cover this much to tell gravity


@dataclass(frozen=True)
class RunTrajectory:
    """What the run knows of its path: keyframe stamps (s) and odometry poses (n, 4, 4: the
    back-end's nodes), the odometry at each keyframe's stamp (n, 4, 4: the first keyframe's node
    is at the middle of its sweep, lidar_slam.frontend.odometry T_world_first, and so is every
    keyframe's with point times in a run without an IMU, Pipeline._node_at_ref), every frame's
    stamp and odometry pose (m, 4, 4); all in the odometry's world frame."""

    kf_stamps_s: np.ndarray
    kf_odom: np.ndarray
    kf_stamp_odom: np.ndarray
    frame_stamps_s: np.ndarray
    frame_odom: np.ndarray


@dataclass(frozen=True)
class FixReport:
    """One GNSS fix as the back-end used it (a row of gnss_fixes.csv): its keyframe (-1 when
    not tied), its ENU position (m), the residual (m) and normalised squared residual after
    the solve, and used / rejected / unused with why."""

    stamp_s: float
    keyframe: int
    enu_m: tuple[float, float, float]
    residual_m: float
    d2: float
    status: str
    why: str = ""


@dataclass
class InertialResult:
    """The final solve with IMU and/or GNSS: kf_poses (T_world_kf, same world as given, the first
    keyframe where it was given), their covariances (6x6, rotation first, keyframe frame),
    T_S_world (S: gravity-aligned z up; the ENU frame `enu` when geo-referenced), per-fix
    reports, and what summary.json says (imu, gnss)."""

    kf_poses: dict[int, np.ndarray]
    covariances: dict[int, np.ndarray]
    T_S_world: np.ndarray | None  # None: nothing was solved (the fixes could not place the run)
    enu: LocalEnu | None
    fixes: list[FixReport] = field(default_factory=list)
    summary: dict = field(default_factory=dict)
    seconds: float = 0.0
    # T_world_lidar at the stamps of the frames between two keyframes linked by the IMU (keyed
    # by the frame's position in the run): see imu_frame_poses
    frame_poses: dict[int, np.ndarray] = field(default_factory=dict)
    # solve(joint=True) only (tools/nees_spread.py): the joint covariance (6N x 6N, rotation first
    # per pose) of the keyframes in sorted order, as `covariances` are, cross terms included
    joint_covariance: np.ndarray | None = None


def _velocities(T_world_kf: dict[int, np.ndarray], tr: RunTrajectory, C: np.ndarray
                ) -> dict[int, np.ndarray]:
    """Each keyframe's IMU velocity (world frame, m/s): the central difference of the
    odometry's IMU positions over the frames on either side of its stamp, turned with the
    keyframe's correction (pose graph vs odometry)."""
    t = tr.frame_stamps_s
    p = tr.frame_odom[:, :3, :3] @ C[:3, 3] + tr.frame_odom[:, :3, 3]
    out = {}
    for k, T in T_world_kf.items():
        i = int(np.searchsorted(t, tr.kf_stamps_s[k]))
        a, b = max(i - 1, 0), min(i + 1, len(t) - 1)
        if not t[b] > t[a]:
            out[k] = np.zeros(3)
            continue
        R_corr = T[:3, :3] @ tr.kf_odom[k][:3, :3].T
        out[k] = R_corr @ (p[b] - p[a]) / (t[b] - t[a])
    return out


def _imu_links(stream: ImuStream, cfg: SlamConfig, stamps: np.ndarray, keys: list[int]):
    """Preintegrated IMU between consecutive keyframes whose interval the samples cover without
    a gap (ImuStream.gap_s: the odometry alone bridges one; integrated across, a
    0.5 s gap in a walk cost 0.36 m)."""
    params = combined_params(cfg.imu)
    gap = np.diff(stream.t) > stream.gap_s
    gaps, gap_ends = stream.t[:-1][gap], stream.t[1:][gap]  # the samples either side of each
    links = []
    for i, j in zip(keys[:-1], keys[1:], strict=True):
        t0, t1 = float(stamps[i]), float(stamps[j])
        if not (np.isfinite(t0) and np.isfinite(t1) and stream.start_s <= t0 < t1 <= stream.end_s):
            continue
        if ((gaps < t1) & (gap_ends > t0)).any():
            continue
        links.append(inertial_graph.ImuLink(i, j, stream.preintegrate(t0, t1, params)))
    return links


def imu_frame_poses(links: list[inertial_graph.ImuLink], sol: inertial_graph.InertialSolution,
                    stream: ImuStream, params, kf_stamps_s: np.ndarray,
                    frame_stamps_s: np.ndarray) -> dict[int, np.ndarray]:
    """T_S_imu at the stamp of every frame strictly between two keyframes linked by the IMU:
    the IMU integrated forward from the first keyframe's solved state (velocity, bias), its
    mismatch with the second keyframe's solved pose spread linearly over the interval. Frames
    between keyframes are not in the solve; moved with their keyframes' corrections they keep
    the odometry's scan-to-scan jitter (sim 07-os0: 2 cm per frame along track) plus the
    keyframes' own, where the IMU over a fraction of a second is good to a millimetre."""
    out: dict[int, np.ndarray] = {}
    for ln in links:
        if ln.i not in sol.poses or ln.j not in sol.poses:
            continue
        t0, t1 = float(kf_stamps_s[ln.i]), float(kf_stamps_s[ln.j])
        inside = np.flatnonzero((frame_stamps_s > t0) & (frame_stamps_s < t1))
        if not len(inside):
            continue
        bias6, v0 = sol.biases[ln.i], sol.velocities[ln.i]
        T_end = predict_pose(ln.pim, sol.poses[ln.i], v0, bias6)
        mismatch = sol.poses[ln.j] @ inverse(T_end)
        times = [float(frame_stamps_s[f]) for f in inside.tolist()]
        # one integration through the link, predicting at each frame's stamp on the way
        for f, t, T in zip(inside.tolist(), times, predict_poses_along(
                stream, t0, times, params, sol.poses[ln.i], v0, bias6)):
            out[f] = interpolate(T, mismatch @ T, (t - t0) / (t1 - t0))
    return out


def _imu_part(cfg: SlamConfig, imu: ImuSamples, tr: RunTrajectory, keys: list[int],
              T_world_imu: dict[int, np.ndarray], v_world: dict[int, np.ndarray],
              C: np.ndarray):
    """The IMU links between keyframes, R_up_world (None without links), and the summary. None
    either when the accelerometer disagrees with the odometry (frontend.imu_check: its sign or
    axes wrong), with one warning."""
    stream = ImuStream(imu)
    check = imu_check.acceleration_disagreement(stream, tr.frame_stamps_s, tr.frame_odom, C)
    accel = {} if check is None else {"acceleration_disagreement": round(check.disagreement, 4),
                                      "acceleration_windows": check.windows,
                                      "acceleration_variation_mps2":
                                          round(check.variation_mps2, 4),
                                      "acceleration_gravity_mps2": round(check.gravity_mps2, 4)}
    why = None
    if check is not None and check.disagreement > imu_check.MAX_ACCEL_DISAGREEMENT:
        why = (f"left out of the final solve (its poses are lidar-only): its accelerations "
               f"differ from the lidar odometry's {check.disagreement:.3g}x as much as those "
               f"vary, over {check.windows} windows of {2 * imu_check.ACCEL_WINDOW_S:g} s (ax, "
               f"ay, az with a wrong sign, axes, unit or delay?)")
    elif check is not None and abs(check.gravity_mps2 - STANDARD_GRAVITY_MPS2) > \
            imu_check.MAX_GRAVITY_ERROR_MPS2:
        why = (f"left out of the final solve (its poses are lidar-only): the gravity its "
               f"accelerations imply is {check.gravity_mps2:.2f} m/s^2, not Earth's 9.81 (ax, "
               f"ay, az with a scale error?)")
    if why is not None:
        log.warning("%s: IMU %s", imu.source, why)
        return [], None, {"factors": 0, "reason": why, **accel}
    links = _imu_links(stream, cfg, tr.kf_stamps_s, keys)
    span = sum(ln.pim.deltaTij() for ln in links)
    if span < MIN_IMU_SPAN_S:
        return [], None, {"factors": 0, "reason": f"IMU covers {span:.2f} s between keyframes "
                                                  f"(need {MIN_IMU_SPAN_S} s)", **accel}
    R_up_world = _up_rotation(links, T_world_imu, v_world)
    tilt = np.degrees(np.arccos(np.clip(R_up_world[2, 2], -1.0, 1.0)))
    return links, R_up_world, {"factors": len(links), "seconds_covered": round(span, 3),
                               "world_tilt_deg": round(float(tilt), 4), **accel}


def _up_rotation(links, T_world_imu: dict[int, np.ndarray], v_world: dict[int, np.ndarray]
                 ) -> np.ndarray:
    """R_up_world: the smallest rotation from the world to a z-up frame. Gravity in the world:
    over every link, the change of velocity = the integrated specific force (rotated by the
    poses) + gravity x time, so g = (sum dv - sum R_i dV_ij) / sum dt."""
    dv = sum(v_world[ln.j] - v_world[ln.i] for ln in links)
    f = sum(T_world_imu[ln.i][:3, :3] @ np.asarray(ln.pim.deltaVij()) for ln in links)
    g = (dv - f) / sum(ln.pim.deltaTij() for ln in links)
    return gravity_rotation(-g)


def _node_to_imu(tr: RunTrajectory, keys: list[int], C: np.ndarray) -> dict[int, np.ndarray]:
    """Per keyframe, T_node_imu: from the back-end's node to the IMU at the keyframe's stamp
    (the same array C wherever the node is at the stamp, so that edges share noise models)."""
    out = {}
    for k in keys:
        D = inverse(tr.kf_odom[k]) @ tr.kf_stamp_odom[k]
        out[k] = C if np.allclose(D, np.eye(4), rtol=0.0, atol=1e-12) else D @ C
    return out


def _edges_between_imus(edges: list[BetweenFactor], Cn: dict[int, np.ndarray]
                        ) -> list[BetweenFactor]:
    """Node edges as edges between the IMU frames: T_i_j -> Cn_i^-1 T_i_j Cn_j, information
    Ad(Cn_j)^T I Ad(Cn_j) (the edge's error e becomes Ad(Cn_j^-1) e)."""
    infos: dict[tuple[int, int], np.ndarray] = {}
    out = []
    for e in edges:
        Ci, Cj = Cn[e.i], Cn[e.j]
        key = (id(e.information), id(Cj))
        if key not in infos:  # shared matrices stay shared (one noise model)
            Ad = inertial_graph.adjoint(Cj)
            infos[key] = Ad.T @ e.information @ Ad
        out.append(BetweenFactor(e.i, e.j, inverse(Ci) @ e.T_i_j @ Cj, infos[key], e.robust_k,
                                 e.is_loop))
    return out


def _inertial_odometry(cfg: SlamConfig, edges: list[BetweenFactor],
                       measured: dict[int, np.ndarray]) -> list[BetweenFactor]:
    """The odometry edges with the kernel of a solve with the IMU (huber_k) and their own
    information where it was measured (measured: keyed by the edge's second keyframe; its rotation
    floor moved to backend.inertial_odom_min_rot_sigma_deg), else the config's
    backend.inertial_odom_*; loops as they are."""
    b = cfg.backend
    info = sigmas_to_information(b.inertial_odom_rot_sigma_deg, b.inertial_odom_trans_sigma_m)
    floor, new_floor = b.odom_information.min_rot_sigma_deg, b.inertial_odom_min_rot_sigma_deg
    own = {j: info_j if floor == new_floor else with_rotation_floor(info_j, floor, new_floor)
           for j, info_j in measured.items()}
    return [e if e.is_loop else dataclasses.replace(e, information=own.get(e.j, info),
                                                    robust_k=b.huber_k)
            for e in edges]


def _mounted(edges: list[BetweenFactor], D: np.ndarray | None) -> list[BetweenFactor]:
    """Edges between IMU frames as between the frames of the IMU turned by D (T_imu_imu'):
    T_i_j -> D^-1 T_i_j D, what inertial_graph.mount_edge measures."""
    if D is None:
        return edges
    D_inv = inverse(D)
    return [dataclasses.replace(e, T_i_j=D_inv @ e.T_i_j @ D) for e in edges]


def _scaled(edges: list[BetweenFactor], scale: float) -> list[BetweenFactor]:
    """The odometry edges with their translations times scale; loops as they are."""
    out = []
    for e in edges:
        if not e.is_loop:
            T = e.T_i_j.copy()
            T[:3, 3] *= scale
            e = dataclasses.replace(e, T_i_j=T)
        out.append(e)
    return out


def _refined(cfg: SlamConfig, C: np.ndarray) -> dict:
    """summary.json's record of the mounting the final solve refined (T_lidar_imu 4x4 row by
    row) and how far it turned from the one the run started with (deg)."""
    from lidar_slam.geometry import rotvec_from_matrix

    turn = rotvec_from_matrix(cfg.imu.T_lidar_imu_matrix()[:3, :3].T @ C[:3, :3])
    return {"T_lidar_imu": [round(float(v), 9) + 0.0 for v in C.ravel()],
            "prior_sigma_deg": cfg.imu.T_lidar_imu_sigma_deg,
            "turned_deg": round(float(np.degrees(np.linalg.norm(turn))), 4)}


CHI2_3_MEDIAN = 2.366  # median of the chi-square distribution with 3 degrees of freedom


VARIANCE_FACTOR_MIN = 1.0 / 16.0  # a guard (residuals that vanish); two bank walks reach it


def _odometry_residuals(edges: list[BetweenFactor], poses: dict[int, np.ndarray]
                        ) -> tuple[list[tuple[int, int]], np.ndarray, np.ndarray, np.ndarray]:
    """Per odometry edge (i, j) at a solution (poses: T_S_node, S gravity-aligned, z up), its
    rotation, horizontal and vertical translation residual squared, each normalised by that part
    of the edge's own covariance (see odometry_variance)."""
    keys, r_rot, r_h, r_v = [], [], [], []
    for e in edges:
        if e.is_loop:
            continue
        err = gtsam_graph.between_error(e.T_i_j, poses[e.i], poses[e.j])
        cov = np.linalg.inv(e.information)
        r_rot.append(err[:3] @ np.linalg.solve(cov[:3, :3], err[:3]))
        R = poses[e.j][:3, :3]  # the residual's frame (X_j's) in S
        e_s, C_s = R @ err[3:], R @ cov[3:, 3:] @ R.T
        r_h.append(e_s[:2] @ np.linalg.solve(C_s[:2, :2], e_s[:2]))
        r_v.append(e_s[2] ** 2 / C_s[2, 2])
        keys.append((e.i, e.j))
    return keys, np.array(r_rot), np.array(r_h), np.array(r_v)


def _mean_factors(r_rot: np.ndarray, r_h: np.ndarray, r_v: np.ndarray
                  ) -> tuple[float, float, float]:
    lo = VARIANCE_FACTOR_MIN
    return (max(lo, float(np.mean(r_rot)) / 3.0), max(lo, float(np.mean(r_h)) / 2.0),
            max(lo, float(np.mean(r_v))))


def odometry_variance(edges: list[BetweenFactor], poses: dict[int, np.ndarray]
                      ) -> tuple[float, float, float]:
    """Variance factors (rotation, horizontal translation, vertical translation; each at least
    VARIANCE_FACTOR_MIN) of the odometry edges at a solution with the IMU (poses: T_S_node, S
    gravity-aligned, z up): the mean over edges of each part's squared residual normalised by that
    part of the edge's own covariance, over its chi-square mean (3 for rotation, 2 horizontal, 1
    vertical; the median instead was tried on the bank and not taken: docs/bank.md, Decisions). The
    IMU, far surer of rotation over a keyframe's fraction of a second than the gyro-free
    registration, shows the odometry's real rotation error in its residual; an edge information from
    the clouds alone sees the registration's noise but not the deskew or calibration errors of a
    shaken sensor (a hand-held walk: 2.5x the predicted rotation error). Translation is split by
    gravity: a lidar's height error is not its horizontal one (a 16-beam car: 3x its sigma
    vertically while the horizontal fits; docs/bank.md). Tightened as well as loosened since the
    refinement's 0.3 m matches with the IMU (da02498) made the odometry surer than its registrations
    say: on the bank every row the same or better, NEES in 1..9 on 13 -> 14 of 16 (docs/bank.md,
    Decisions, 2026-12-05). Before that change only loosening was taken: tightening lost the median
    then."""
    _, r_rot, r_h, r_v = _odometry_residuals(edges, poses)
    if not len(r_rot):
        return 1.0, 1.0, 1.0
    return _mean_factors(r_rot, r_h, r_v)


# An edge beyond the 99.99 % chi-square quantile (6 dof) of its scaled covariance is a flick:
# scipy.stats.chi2.ppf(0.9999, 6) (tests/test_edge_information.py; scipy.stats takes 0.7 s to
# import)
ODOMETRY_OUTLIER_CHI2 = 27.856
MIN_INLIER_EDGES = 10


def odometry_variance_robust(edges: list[BetweenFactor], poses: dict[int, np.ndarray]
                             ) -> tuple[tuple[float, float, float], dict[tuple[int, int], float]]:
    """odometry_variance for an odometry whose errors are white (the drift state's white
    fractions both above 0): a hand-held walk's few flicks (a scan deskewed along the wrong
    motion) carry most of the edges' residual, and a mean over every edge loosened all of them
    for a few (office-handheld-os1: rotation chi2 per dof mean 2.3, median 0.33; NEES 0.79).
    The factors are the mean over the edges within ODOMETRY_OUTLIER_CHI2 (the 99.99 % quantile,
    6 dof) of the covariance they give, iterated until that set holds; each edge beyond it gets
    its own factor (its chi2 over 6, on top of the three). Returns the factors and
    {(i, j): own factor}. Where the errors persist from edge to edge (the chain, a car's slow
    bias) a large residual is part of the path's drift, not a flick: odometry_variance there
    (docs/bank.md, Decisions, 2026-12-05)."""
    keys, r_rot, r_h, r_v = _odometry_residuals(edges, poses)
    if not len(r_rot):
        return (1.0, 1.0, 1.0), {}
    inlier = np.ones(len(keys), dtype=bool)
    for _ in range(10):
        f = _mean_factors(r_rot[inlier], r_h[inlier], r_v[inlier])
        q = r_rot / f[0] + r_h / f[1] + r_v / f[2]
        now = q <= ODOMETRY_OUTLIER_CHI2
        if np.array_equal(now, inlier) or int(now.sum()) < MIN_INLIER_EDGES:
            break
        inlier = now
    f = _mean_factors(r_rot[inlier], r_h[inlier], r_v[inlier])
    q = r_rot / f[0] + r_h / f[1] + r_v / f[2]
    return f, {k: max(1.0, float(qk) / 6.0) for k, qk, ok in zip(keys, q, inlier) if not ok}


WHITE_FRACTION_MAX = 0.95  # of an edge's covariance: some walk always stays (the local map moves)
WHITE_FRACTION_MIN = 0.01  # a drift state with less is the chain (and ill-conditioned)
MIN_WHITE_PAIRS = 10  # consecutive edges needed to tell white noise from drift


def odometry_white_fractions(edges: list[BetweenFactor], poses: dict[int, np.ndarray]
                             ) -> tuple[float, float]:
    """How much of the odometry edges' error is white pose noise rather than drift (rotation,
    translation; 0..WHITE_FRACTION_MAX), estimated from their residuals at a solution with the
    IMU: a white pose error w_j of keyframe j (X_j = F O_j Exp(w_j)) enters the edge i -> j as
    +w_j and the edge j -> k as -Ad(T_jk^-1) w_j, so with the second edge's residual moved into
    X_j's frame (Ad(T_jk)) consecutive residuals correlate at -w/2 for a white fraction w of the
    edge's variance, while drift leaves them independent. So w = -2 rho, rho pooled over the
    pairs, each axis normalised by the first edge's sigma; rho >= 0 (an odometry that drifts)
    gives 0, and so do fewer than MIN_WHITE_PAIRS pairs. The residuals are those of a fitted
    solution: the IMU takes out some of a drift's low frequencies, which leans rho negative
    (docs/bank.md compares the estimate with the truth's on the bank)."""
    chain = sorted((e for e in edges if not e.is_loop), key=lambda e: e.i)
    pairs = [(a, b) for a, b in zip(chain, chain[1:]) if a.j == b.i]
    if len(pairs) < MIN_WHITE_PAIRS:
        return 0.0, 0.0
    err = {id(e): gtsam_graph.between_error(e.T_i_j, poses[e.i], poses[e.j]) for e in chain}
    r, r_next = [], []
    for a, b in pairs:
        sigma = np.sqrt(np.diag(np.linalg.inv(a.information)))
        r.append(err[id(a)] / sigma)
        r_next.append(inertial_graph.adjoint(b.T_i_j) @ err[id(b)] / sigma)
    r, r_next = np.array(r), np.array(r_next)
    out = []
    for block in (slice(0, 3), slice(3, 6)):
        den = float((r[:, block] ** 2).sum() + (r_next[:, block] ** 2).sum()) / 2.0
        rho = float((r[:, block] * r_next[:, block]).sum()) / den if den > 0 else 0.0
        out.append(float(np.clip(-2.0 * rho, 0.0, WHITE_FRACTION_MAX)))
    return out[0], out[1]


def _scaled_odometry(edges: list[BetweenFactor], factors: tuple[float, float, float],
                     poses: dict[int, np.ndarray],
                     own: dict[tuple[int, int], float] | None = None) -> list[BetweenFactor]:
    """The odometry edges with their covariance loosened by the variance factors (rotation,
    horizontal, vertical translation: odometry_variance): C -> S C S^T, S = diag(sqrt(f_rot) I,
    R_j^T diag(sqrt(f_h), sqrt(f_h), sqrt(f_v)) R_j), R_j the rotation of the edge's end node in
    the gravity-aligned S (poses: T_S_node), and an edge in own by its own factor too
    (odometry_variance_robust); loops as they are. Factors all 1, none own: the same edges."""
    f_rot, f_h, f_v = (float(f) for f in factors)
    own = own or {}
    if f_rot == f_h == f_v == 1.0 and not own:
        return list(edges)
    out = []
    for e in edges:
        if not e.is_loop:
            R = poses[e.j][:3, :3]
            S = np.zeros((6, 6))
            S[:3, :3] = np.sqrt(f_rot) * np.eye(3)
            S[3:, 3:] = R.T @ np.diag(np.sqrt([f_h, f_h, f_v])) @ R
            C = S @ np.linalg.inv(e.information) @ S.T * own.get((e.i, e.j), 1.0)
            info = np.linalg.inv(0.5 * (C + C.T))
            e = dataclasses.replace(e, information=0.5 * (info + info.T))
        out.append(e)
    return out


def _prior_covariance(R_S_node: np.ndarray, rot_sigma: np.ndarray, trans_sigma: float
                      ) -> np.ndarray:
    """6x6 covariance (node frame, rotation first) of rotation sigmas given about the S axes
    (rad) and an isotropic position sigma (m)."""
    cov = np.zeros((6, 6))
    cov[:3, :3] = R_S_node.T @ np.diag(np.asarray(rot_sigma, dtype=float) ** 2) @ R_S_node
    cov[3:, 3:] = np.eye(3) * trans_sigma ** 2
    return cov


def solve(cfg: SlamConfig, T_world_kf: dict[int, np.ndarray], edges: list[BetweenFactor],
          tr: RunTrajectory, imu: ImuSamples | None, fixes: GnssFixes | None,
          odom_information: dict[int, np.ndarray] | None = None, joint: bool = False
          ) -> InertialResult | None:
    """The final solve with every factor (see the module docstring); None without IMU and GNSS.
    joint: also the joint covariance of all keyframe poses (InertialResult.joint_covariance).
    When neither can be used, the poses given, with the reasons in the summary and reports."""
    if imu is None and fixes is None:
        return None
    t_start = time.perf_counter()
    keys = sorted(T_world_kf)
    summary: dict = {}
    links, R_up_world = [], None
    C = cfg.imu.T_lidar_imu_matrix() if imu is not None else np.eye(4)
    Cn = _node_to_imu(tr, keys, C)
    v_world = _velocities(T_world_kf, tr, C)
    T_world_imu = {k: T @ Cn[k] for k, T in T_world_kf.items()}
    if imu is not None:
        links, R_up_world, summary["imu"] = _imu_part(cfg, imu, tr, keys, T_world_imu, v_world,
                                                        C)
    tied, alignment, enu, unused = None, None, None, {}
    if fixes is not None:
        tied, alignment, enu, unused = _tie_and_align(cfg, fixes, T_world_kf, tr, R_up_world)
        if alignment.T_enu_world is None:
            log.warning("GNSS not used: %s", alignment.why)
            # read, but not in the solve: summary.json's gnss.used says so, as imu.used does
            summary["gnss"] = {"used": False, "geo_referenced": False, "reason": alignment.why}
            tied = None
    if tied is None and not links:  # nothing to solve: the pose graph's poses stay
        result = InertialResult(dict(T_world_kf), {}, None, None, summary=summary)
        if fixes is not None:
            result.fixes = _reports(fixes, None, None, None, None, unused, alignment)
            summary["gnss"].update(_counts(result.fixes))
        return result
    if tied is not None:
        T_S_world = alignment.T_enu_world
        rot_sigma, trans_sigma = np.full(3, GNSS_PRIOR_ROT_SIGMA_RAD), GNSS_PRIOR_TRANS_SIGMA_M
    else:
        T_S_world = make_pose(R_up_world, np.zeros(3))
        b = cfg.backend
        rot_sigma = np.array([FREE_TILT_SIGMA_RAD, FREE_TILT_SIGMA_RAD,
                              np.radians(b.prior_rot_sigma_deg)])
        trans_sigma = b.prior_trans_sigma_m
    poses = {k: T_S_world @ T for k, T in T_world_imu.items()}
    velocities = {k: T_S_world[:3, :3] @ v for k, v in v_world.items()}
    prior_mean = poses[keys[0]]
    prior_cov = _prior_covariance(prior_mean[:3, :3], rot_sigma, trans_sigma)
    if links:
        edges = _inertial_odometry(cfg, edges, odom_information or {})
    imu_edges = _edges_between_imus(edges, Cn)
    Cn_inv = {k: inverse(T) for k, T in Cn.items()}
    sigma_deg = cfg.imu.T_lidar_imu_sigma_deg
    mount_sigma = None if not links or sigma_deg is None else float(np.radians(sigma_deg))

    drift = None  # white fractions of the odometry's drift state, once known

    def gnss_factors(used: np.ndarray) -> list[inertial_graph.GnssFactor]:
        return [] if tied is None else [
            inertial_graph.GnssFactor(k, tied.enu_m[f], Cn_inv[k][:3, :3] @ tied.arm_kf_m[f]
                                      + Cn_inv[k][:3, 3], tied.sigma_m[f])
            for f in np.flatnonzero(used) for k in [int(tied.keyframe[f])]]

    def run(used: np.ndarray) -> inertial_graph.InertialSolution:
        factors = gnss_factors(used)
        return inertial_graph.solve(poses, velocities, imu_edges, links, factors,
                                    prior_mean, prior_cov, BIAS_SIGMA, GNSS_HUBER_K,
                                    cfg.backend.max_iterations, RELATIVE_TOL,
                                    covariances=False, mount_sigma_rad=mount_sigma, drift=drift)

    def lidar_poses(sol: inertial_graph.InertialSolution) -> dict[int, np.ndarray]:
        D_inv = np.eye(4) if sol.mount_correction is None else inverse(sol.mount_correction)
        return {k: T @ D_inv @ Cn_inv[k] for k, T in sol.poses.items()}

    used = alignment.inlier.copy() if tied is not None else np.zeros(0, dtype=bool)
    sol = run(used)
    if links:  # the odometry's own weights, checked against the IMU (see odometry_variance)
        mounted = _mounted(imu_edges, sol.mount_correction)
        white, own = (0.0, 0.0), {}
        if cfg.backend.odometry_drift_state:
            white = odometry_white_fractions(mounted, sol.poses)
            summary["imu"]["odometry_white_fraction"] = [round(w, 3) for w in white]
            if max(white) > 0.0:
                drift = tuple(max(w, WHITE_FRACTION_MIN) for w in white)
        if min(white) > 0.0:  # white errors: a large residual is a flick of its own
            factors, own = odometry_variance_robust(mounted, sol.poses)
        else:
            factors = odometry_variance(mounted, sol.poses)
        summary["imu"]["odometry_variance_factor"] = [round(f, 3) for f in factors]
        summary["imu"]["odometry_outlier_edges"] = len(own)
        if factors != (1.0, 1.0, 1.0) or drift is not None or own:
            D_inv = (np.eye(4) if sol.mount_correction is None
                     else inverse(sol.mount_correction))  # imu_edges: the IMU as assumed
            imu_edges = _scaled_odometry(imu_edges, factors,
                                         {k: T @ D_inv for k, T in sol.poses.items()}, own)
            poses = sol.poses
            velocities = {k: sol.velocities.get(k, v) for k, v in velocities.items()}
            sol = run(used)
    d2 = residual = np.zeros(0)
    for round_ in range(GATE_ROUNDS + 1 if tied is not None else 0):
        diff = tied.enu_m - tied.antenna(lidar_poses(sol))
        residual, d2 = np.linalg.norm(diff, axis=1), gnss_align.normalised_d2(diff, tied.sigma_m)
        gate = d2 < gnss_align.CHI2_3_GATE
        if np.array_equal(gate, used) or round_ == GATE_ROUNDS:
            break
        used, poses = gate, sol.poses  # solve again from here without the fixes gated out
        velocities = {k: sol.velocities.get(k, v) for k, v in velocities.items()}
        sol = run(used)
    if tied is not None and int(used.sum()) < MIN_KEPT_SHARE * len(used):
        log.warning("GNSS: %d of %d fixes rejected by the final solve's gate: the geo-reference "
                    "rests on the %d kept (fixes that do not follow the lidar's path: latitude "
                    "and longitude swapped, a sign, unit or clock wrong?)", len(used) -
                    int(used.sum()), len(used), int(used.sum()))
        summary.setdefault("gnss", {})["warning"] = (
            f"{len(used) - int(used.sum())} of {len(used)} fixes rejected: the geo-reference "
            f"rests on the {int(used.sum())} kept")
    # of the last solve only, each pose's relative to the first keyframe's: the written poses
    # are (the output anchors there), and gravity places its tilt only so surely
    anchor = keys[0]
    sol = sol.with_covariances(anchor)
    scale_sigma = cfg.backend.odometry_scale_sigma
    if links and scale_sigma is not None and sol.covariances:
        # The odometry's scale as a consider parameter: how far the solution moves when every
        # odometry translation is scale_sigma longer (one Gauss-Newton step from it, the same
        # graph otherwise, linearised at the solution), added to each pose's covariance
        graph, _ = inertial_graph.build(sol.poses, velocities,
                                        _scaled(imu_edges, 1.0 + scale_sigma),
                                        links, gnss_factors(used), prior_mean, prior_cov,
                                        BIAS_SIGMA, GNSS_HUBER_K, mount_sigma, drift)
        step = inertial_graph.pose_steps(graph, sol.estimate, list(sol.covariances), anchor)
        covs = {k: c + np.outer(step[k], step[k]) for k, c in sol.covariances.items()}
        sol = dataclasses.replace(sol, covariances=covs)
    else:
        step = None
    T_S_lidar = lidar_poses(sol)
    if sol.mount_correction is not None:  # the nodes are the IMU turned by it
        C = C @ sol.mount_correction
        Cn = {k: T @ sol.mount_correction for k, T in Cn.items()}
        summary["imu"]["T_lidar_imu_refined"] = _refined(cfg, C)
    T_S_world_out = T_S_lidar[keys[0]] @ inverse(T_world_kf[keys[0]])
    T_world_S = inverse(T_S_world_out)
    Ad = {k: inertial_graph.adjoint(T) for k, T in Cn.items()}
    result = InertialResult({k: T_world_S @ T for k, T in T_S_lidar.items()},
                            {k: Ad[k] @ c @ Ad[k].T for k, c in sol.covariances.items()},
                            T_S_world_out, enu if tied is not None else None)
    if joint and sol.graph is not None:
        J = inertial_graph.joint_pose_covariance(sol.graph, sol.estimate, keys, anchor)
        if step is not None:
            s_all = np.concatenate([step[k] for k in keys])
            J = J + np.outer(s_all, s_all)
        D = np.zeros_like(J)
        for i, k in enumerate(keys):
            D[6 * i:6 * i + 6, 6 * i:6 * i + 6] = Ad[k]
        result.joint_covariance = D @ J @ D.T
    if links:
        C_inv = inverse(C)
        frames = imu_frame_poses(links, sol, ImuStream(imu), combined_params(cfg.imu),
                                 tr.kf_stamps_s, tr.frame_stamps_s)
        result.frame_poses = {f: T_world_S @ T @ C_inv for f, T in frames.items()}
        bias = np.mean([sol.biases[k] for k in sol.biases], axis=0)
        summary["imu"]["mean_bias_accel_mps2"] = [round(float(v), 5) for v in bias[:3]]
        summary["imu"]["mean_bias_gyro_radps"] = [round(float(v), 6) for v in bias[3:]]
    if fixes is not None:
        result.fixes = _reports(fixes, tied, used, residual, d2, unused, alignment)
        summary["gnss"] = {**summary.get("gnss", {}), **_counts(result.fixes)}
        if tied is not None:
            summary["gnss"]["geo_referenced"] = True  # where: summary.json geo (run.outputs)
    result.seconds = time.perf_counter() - t_start
    summary["inertial_solve"] = {"seconds": round(result.seconds, 3),
                                 "error": [round(sol.initial_error, 6),
                                           round(sol.final_error, 6)],
                                 "iterations": sol.iterations}
    result.summary = summary
    log.info("final solve with %d IMU factors and %d GNSS fixes: error %.6g -> %.6g, %.2f s",
             len(links), int(used.sum()), sol.initial_error, sol.final_error, result.seconds)
    return result


def _tie_and_align(cfg: SlamConfig, fixes: GnssFixes, T_world_kf: dict[int, np.ndarray],
                   tr: RunTrajectory, R_up_world: np.ndarray | None):
    """The fixes tied to keyframes in the ENU frame of the first fix within the scans' span,
    and the robust alignment of the run to them."""
    inside = np.flatnonzero((fixes.stamp_s >= tr.frame_stamps_s[0])
                            & (fixes.stamp_s <= tr.frame_stamps_s[-1]))
    first = int(inside[0]) if len(inside) else 0
    enu = LocalEnu(float(fixes.lat_deg[first]), float(fixes.lon_deg[first]),
                   float(fixes.alt_m[first]))
    enu_m = enu.from_wgs84(np.c_[fixes.lat_deg, fixes.lon_deg, fixes.alt_m])
    tied, unused = gnss_align.tie_fixes(fixes, enu_m, tr.kf_stamps_s, tr.kf_odom,
                                        tr.frame_stamps_s, tr.frame_odom,
                                        np.asarray(cfg.gnss.lever_arm_m, dtype=float))
    alignment = gnss_align.align(tied.antenna(T_world_kf), tied.enu_m, tied.sigma_m, R_up_world)
    return tied, alignment, enu, unused


def _counts(fixes: list[FixReport]) -> dict[str, int]:
    return {f"fixes_{s}": sum(f.status == s for f in fixes) for s in ("used", "rejected", "unused")}


def _reports(fixes: GnssFixes, tied, used, residual, d2, unused, alignment) -> list[FixReport]:
    """One FixReport per fix of the input, in its order."""
    out: dict[int, FixReport] = {}
    gate = gnss_align.CHI2_3_GATE
    for f in range(0 if tied is None else len(tied)):
        i = int(tied.index[f])
        enu_f = tuple(float(v) for v in tied.enu_m[f])
        if used[f]:
            status, why = "used", ""
        else:
            status = "rejected"
            why = f"normalised residual {d2[f]:.1f} > {gate:g} (chi-square 3, 99.9 %)"
        out[i] = FixReport(float(fixes.stamp_s[i]), int(tied.keyframe[f]), enu_f,
                           float(residual[f]), float(d2[f]), status, why)
    for i in range(len(fixes)):
        if i not in out:
            why = unused.get(i) or f"no geo-reference: {alignment.why}"
            out[i] = FixReport(float(fixes.stamp_s[i]), -1, (np.nan,) * 3, np.nan, np.nan,
                               "unused", why)
    return [out[i] for i in range(len(fixes))]
