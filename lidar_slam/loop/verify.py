"""Geometric verification of a loop candidate: ICP from several yaw hypotheses, then gates on
fitness, RMSE, the margin over the best different pose, and how far ICP turned from its start.
A wrong loop accepted is worse than a loop missed.

Descriptor yaw guesses in rectangular rooms are often off by a multiple of 90 deg (180 deg on
reverse revisits), and ICP started there settles on a wrong pose whose fitness still looks
plausible. So every start yaw_guess + k * 90 deg is aligned on coarse clouds (large
correspondence distances pull in the metres between revisits), the hypotheses are ranked by
coarse fitness, the winner's basin is probed by restarts pushed a few metres sideways (halls and
corridors repeat every bay), the winner must beat the best *different* solution by a margin, and
only the winner is refined on the fine clouds. small_gicp (behind lidar_slam.registration)
does the downsampling, normals, KD-trees and ICP, single-threaded.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from lidar_slam.config import VerifyConfig
from lidar_slam.geometry import inverse, make_pose, rotation_angle_deg, yaw_matrix, yaw_rad
from lidar_slam.registration import Cloud, align, level_ground, make_cloud
from lidar_slam.types import LoopCandidate, LoopConstraint

log = logging.getLogger(__name__)


# Two converged poses closer than this are the same solution (for the margin gate).
_SAME_ROT_DEG = 10.0
_SAME_TRANS_M = 1.0


@dataclass(frozen=True)
class Hypothesis:
    """One coarse alignment: its start (yaw offset from the initial guess in deg, and for basin
    probes the sideways push in metres, levelled match frame), result and coarse fitness; yaws
    are of T_match_query about the match's ground normal (rad)."""

    offset_deg: float
    T_match_query: np.ndarray
    coarse_fitness: float
    yaw_start_rad: float
    yaw_icp_rad: float
    push_m: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True)
class VerificationResult:
    """Outcome of verify(): fitness / rmse_m of the refined winner on the fine clouds, margin in
    coarse fitness, yaws of T_match_query about the levelled z axis (rad)."""

    accepted: bool
    reason: str
    fitness: float
    rmse_m: float
    yaw_guess_rad: float
    yaw_icp_rad: float
    margin: float
    constraint: LoopConstraint | None
    T_match_query: np.ndarray | None = None  # the refined winner, accepted or not
    hypotheses: tuple[Hypothesis, ...] = ()


@dataclass(frozen=True)
class Fit:
    """Share of query points with a match point within the inlier distance, their RMSE (m),
    and the (K, 2) query/match indices of those pairs."""

    fitness: float
    rmse_m: float
    correspondences: np.ndarray


def _icp(src: Cloud, tgt: Cloud, T0: np.ndarray, max_corr_m: float,
         cfg: VerifyConfig) -> np.ndarray:
    """One ICP run query -> match from T0; returns T_match_query. small_gicp's PLANE_ICP
    weighs each axis of the residual by the normal's component, so unlike open3d's
    point-to-plane it resists sliding along oblique walls and needs more iterations to pull in
    metres (tools/loop_tuning.py sweep --every-scan: 77 loops accepted vs open3d's 88, none
    wrong)."""
    return align(tgt.cloud, tgt.tree, src.cloud, T0, max_corr_m, cfg.max_iterations,
                 "GICP" if cfg.method == "gicp" else "PLANE_ICP")


def evaluate_fit(src: Cloud, tgt: Cloud, T_match_query: np.ndarray, inlier_m: float) -> Fit:
    """Fitness and inlier RMSE of T_match_query: each query point's nearest match point."""
    moved = src.points @ T_match_query[:3, :3].T + T_match_query[:3, 3]
    idx, sq = tgt.nearest(moved)
    inlier = (idx >= 0) & (sq <= inlier_m**2)
    fitness = float(inlier.sum()) / max(len(moved), 1)
    rmse = float(np.sqrt(sq[inlier].mean())) if inlier.any() else np.inf
    return Fit(fitness, rmse, np.c_[np.flatnonzero(inlier), idx[inlier]])


def _coarse_align(src_c: Cloud, tgt_c: Cloud, T0: np.ndarray,
                  cfg: VerifyConfig) -> tuple[np.ndarray, float]:
    """Coarse ICP from T0 (full, then half the coarse correspondence distance); (T, fitness)."""
    T = _icp(src_c, tgt_c, T0, cfg.coarse_correspondence_m, cfg)
    T = _icp(src_c, tgt_c, T, 0.5 * cfg.coarse_correspondence_m, cfg)
    return T, evaluate_fit(src_c, tgt_c, T, cfg.coarse_inlier_m).fitness


def _failed_gates(fitness: float, rmse: float, margin: float | None, turned_deg: float,
                  T: np.ndarray, cfg: VerifyConfig) -> list[str]:
    """Why a refined alignment is not trusted (empty: accepted); margin None = not measured."""
    fails = []
    if fitness < cfg.min_fitness:
        fails.append(f"fitness {fitness:.2f} < {cfg.min_fitness:.2f}")
    if rmse > cfg.max_rmse_m:
        fails.append(f"rmse {rmse:.3f} m > {cfg.max_rmse_m:.3f} m")
    if margin is not None and margin < cfg.min_margin:
        fails.append(f"ambiguous: margin {margin:.2f} < {cfg.min_margin:.2f}")
    if turned_deg > cfg.max_yaw_disagreement_deg:
        fails.append(f"ICP turned {turned_deg:.0f} deg from its start")
    t_m = float(np.linalg.norm(T[:3, 3]))
    if t_m > cfg.max_translation_m:
        fails.append(f"translation {t_m:.1f} m > {cfg.max_translation_m} m")
    return fails


def information_matrix(src_pts: np.ndarray, tgt_pts: np.ndarray, tgt_normals: np.ndarray,
                       corr: np.ndarray, T_match_query: np.ndarray, sigma_m: float,
                       cfg: VerifyConfig) -> np.ndarray:
    """6x6 information of T_match_query, rotation first (rx ry rz tx ty tz), for a perturbation
    applied on the right, in the query frame: T_true = T exp(xi). That is the tangent space in
    which gtsam's BetweenFactorPose3(match, query, T) measures its error, Logmap(T^-1 T_mq).

    The point-to-plane Hessian sum(J^T J) / sigma^2 with J = [(p x n)^T, n^T], p the query point
    and n the match normal both in the query frame, keeps the shape (a corridor stays weak along
    its axis). Thousands of neighbouring residuals are not independent, so each block (rotation,
    translation) is scaled down until no axis of it is more certain than
    cfg.info_min_rot_sigma_deg / cfg.info_min_trans_sigma_m: D H D, D diagonal, which scales the
    covariance's diagonal by exactly those factors. One factor for both blocks (the larger)
    left the other block 2-8x looser than its floor: long-range points pin rotation, so the
    translation of a warehouse or plaza loop came out at 5-15 cm for errors of 1-2 cm
    (docs/bank.md, "The loops' information per block"). A direction the scans cannot observe
    at all keeps a weak information of (10 deg, 1 m)^-2, so the matrix stays positive definite.
    corr: (K, 2) query/match indices.

    Not small_gicp's RegistrationResult.H: its tangent is the same (rotation first, T exp(xi)),
    but its PLANE_ICP residual is per axis, n * (q - T p) elementwise, so its Hessian weights by
    diag(n^2) instead of n n^T and calls a corridor at 45 deg to the axes well constrained along
    its length (test_small_gicp_hessian_invents_information_along_a_diagonal_corridor).
    """
    R = T_match_query[:3, :3]
    p = src_pts[corr[:, 0]]
    n = tgt_normals[corr[:, 1]] @ R  # R^T n, row-wise
    J = np.hstack([np.cross(p, n), n])
    H = J.T @ J / max(sigma_m, 1e-3) ** 2
    H = 0.5 * (H + H.T) + np.diag([np.radians(10.0) ** -2] * 3 + [1.0] * 3)
    var = np.diag(np.linalg.inv(H))
    floor_r = np.radians(cfg.info_min_rot_sigma_deg) ** 2
    floor_t = cfg.info_min_trans_sigma_m**2
    d = np.repeat([1.0 / np.sqrt(max(1.0, floor_r / var[:3].min())),
                   1.0 / np.sqrt(max(1.0, floor_t / var[3:].min()))], 3)
    return H * np.outer(d, d)


def _wrap(a: float) -> float:
    return float(np.arctan2(np.sin(a), np.cos(a)))


def _distinct(T_a: np.ndarray, T_b: np.ndarray) -> bool:
    """True when two poses are different solutions (not the same one found twice)."""
    d = inverse(T_a) @ T_b
    return bool(rotation_angle_deg(d) > _SAME_ROT_DEG or np.linalg.norm(d[:3, 3]) > _SAME_TRANS_M)


@dataclass(frozen=True)
class Side:
    """One side of a verification, built once and reusable for every candidate it takes part
    in (the query keyframe's against each of its candidates, a match keyframe's for several
    queries): fine and coarse clouds, and the rotation levelling its ground (4x4)."""

    fine: Cloud
    coarse: Cloud
    L_level: np.ndarray


def query_side(points: np.ndarray, cfg: VerifyConfig) -> Side:
    """The query's clouds (the ICP source: capped subsets) from its points (its frame, m)."""
    gicp = cfg.method == "gicp"
    fine = make_cloud(points, cfg.voxel_m, False, gicp, cfg.fine_max_points)
    coarse = make_cloud(points, cfg.coarse_voxel_m, False, gicp, cfg.coarse_max_points)
    return Side(fine, coarse, _level(fine.points, cfg))


def match_side(points: np.ndarray, cfg: VerifyConfig) -> Side:
    """The match's clouds (the ICP target, with normals for the information matrix)."""
    gicp = cfg.method == "gicp"
    fine = make_cloud(points, cfg.voxel_m, True, gicp)
    coarse = make_cloud(fine.points, cfg.coarse_voxel_m, not gicp, gicp)
    return Side(fine, coarse, _level(fine.points, cfg))


def _level(points: np.ndarray, cfg: VerifyConfig) -> np.ndarray:
    if not cfg.level_to_ground:
        return np.eye(4)
    return make_pose(level_ground(points).R_level_sensor, np.zeros(3))


def verify(candidate: LoopCandidate, query: np.ndarray | Side, match: np.ndarray | Side,
           cfg: VerifyConfig, T_match_query_init: np.ndarray | None = None) -> VerificationResult:
    """Verify a candidate; query: points in the query keyframe frame, match: points (a keyframe
    or a small submap) in the match keyframe frame, metres, or either side already built by
    query_side / match_side with the same cfg (same result). Without T_match_query_init the
    start is the candidate's yaw guess about both clouds' ground normals (see scan_context's
    convention).
    """
    q = query if isinstance(query, Side) else query_side(query, cfg)
    m = match if isinstance(match, Side) else match_side(match, cfg)
    src, src_c, L_q = q.fine, q.coarse, q.L_level
    tgt, tgt_c, L_m = m.fine, m.coarse, m.L_level
    if min(len(src_c.points), len(tgt_c.points)) < 10:
        return VerificationResult(False, "too few points", 0.0, np.inf, candidate.yaw_guess_rad,
                                  np.nan, 0.0, None)
    if T_match_query_init is None:
        T_match_query_init = inverse(L_m) @ yaw_matrix(candidate.yaw_guess_rad) @ L_q

    def levelled_yaw(T: np.ndarray) -> float:
        return yaw_rad(L_m @ T @ inverse(L_q))

    # 1. Coarse alignment of every yaw hypothesis, ranked by coarse fitness.
    hyps = []
    for off in (0.0, 90.0, 180.0, 270.0) if cfg.try_yaw_offsets else (0.0,):
        T0 = inverse(L_m) @ yaw_matrix(np.radians(off)) @ L_m @ T_match_query_init
        T, fit = _coarse_align(src_c, tgt_c, T0, cfg)
        hyps.append(Hypothesis(off, T, fit, levelled_yaw(T0), levelled_yaw(T)))
    # 2. Probe the winner's basin: restarts pushed a few metres sideways (repetitive halls and
    # corridors have a second minimum one bay along) compete with it like other hypotheses.
    top = max(hyps, key=lambda h: h.coarse_fitness)
    for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)) if cfg.probe_shift_m > 0 else ():
        push = (cfg.probe_shift_m * dx, cfg.probe_shift_m * dy)
        T0 = inverse(L_m) @ make_pose(np.eye(3), [*push, 0.0]) @ L_m @ top.T_match_query
        T, fit = _coarse_align(src_c, tgt_c, T0, cfg)
        hyps.append(Hypothesis(top.offset_deg, T, fit, top.yaw_start_rad, levelled_yaw(T), push))
    best = max(hyps, key=lambda h: h.coarse_fitness)
    rivals = [h.coarse_fitness for h in hyps if _distinct(h.T_match_query, best.T_match_query)]
    margin = best.coarse_fitness - max(rivals, default=0.0)

    # 3. Refine the winner on the fine clouds, score it there, and gate.
    T = _icp(src, tgt, best.T_match_query, cfg.max_correspondence_m, cfg)
    ev = evaluate_fit(src, tgt, T, cfg.inlier_m)
    fitness, rmse = ev.fitness, ev.rmse_m
    yaw_icp = levelled_yaw(T)
    turned = abs(np.degrees(_wrap(yaw_icp - best.yaw_start_rad)))
    fails = _failed_gates(fitness, rmse, margin if len(hyps) > 1 else None, turned, T, cfg)
    reason = "; ".join(fails)

    constraint = None
    if not fails:
        info = information_matrix(src.points, tgt.points, tgt.normals, ev.correspondences, T,
                                  rmse, cfg)
        constraint = LoopConstraint(candidate.query, candidate.match, T, info, fitness, rmse)
    log.debug("loop %d->%d: fitness %.2f rmse %.3f margin %.2f yaw %+.0f -> %+.0f deg: %s",
              candidate.query, candidate.match, fitness, rmse, margin,
              np.degrees(candidate.yaw_guess_rad), np.degrees(yaw_icp), reason or "accepted")
    return VerificationResult(not fails, reason, fitness, rmse, candidate.yaw_guess_rad, yaw_icp,
                              margin, constraint, T, tuple(hyps))
