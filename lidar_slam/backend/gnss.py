"""GNSS fixes in the back-end, NumPy only: each fix tied to the keyframe nearest in time (the
antenna at the fix's instant, in that keyframe's frame), a robust alignment of the run to the
fixes that leaves multipath jumps of tens of metres out, and the chi-square gate on each fix's
residual. The factors themselves are built in lidar_slam.backend.inertial_graph.

Residuals are normalised by the fix's own sigmas (sigma_h east and north, sigma_v up): d2 =
(de / sigma_h)^2 + (dn / sigma_h)^2 + (du / sigma_v)^2, chi-square with 3 degrees of freedom for
a fix that is as good as it says.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lidar_slam.geometry import interpolate, inverse, make_pose, yaw_matrix
from lidar_slam.io.imu_gnss import GnssFixes

# chi2inv(0.999, 3): a fix whose normalised squared residual is beyond this is left out (a good
# fix is, 1 in 1000).
CHI2_3_GATE = 16.266
# The alignment (before the solve) sees the run's drift as well as the fixes' noise: its gate
# adds this (m, in quadrature) to every sigma. A 20 m jump of a 1.5 m fix is still 5.9 sigma.
ALIGN_SLACK_M = 3.0
# What the fixes must span for the alignment to fix the map's place on the Earth: this much
# travel (m), and without an IMU (the whole rotation from the fixes) this much across it too.
MIN_TRAVEL_M = 20.0
MIN_WIDTH_M = 10.0
MIN_FIXES = 5
RANSAC_SAMPLES = 400
REFINE_ROUNDS = 5


@dataclass(frozen=True)
class TiedFixes:
    """The usable fixes, each tied to a keyframe: index into the GnssFixes (n,), stamp_s (n,),
    keyframe id (n,), enu_m (n, 3) in the run's local ENU frame, sigma_m (n, 3) (east, north,
    up), arm_kf_m (n, 3): the antenna at the fix's instant in the keyframe's (lidar) frame."""

    index: np.ndarray
    stamp_s: np.ndarray
    keyframe: np.ndarray
    enu_m: np.ndarray
    sigma_m: np.ndarray
    arm_kf_m: np.ndarray

    def __len__(self) -> int:
        return len(self.index)

    def antenna(self, T_frame_kf: dict[int, np.ndarray]) -> np.ndarray:
        """(n, 3) the antenna positions the keyframe poses T_frame_kf put at the fixes."""
        return np.stack([T_frame_kf[int(k)][:3, :3] @ a + T_frame_kf[int(k)][:3, 3]
                         for k, a in zip(self.keyframe, self.arm_kf_m, strict=True)]
                        ) if len(self) else np.empty((0, 3))


def pose_at(stamps_s: np.ndarray, poses: np.ndarray, t_s: float) -> np.ndarray:
    """The pose at t_s between the two stamped poses around it (slerp / lerp); stamps_s must
    span t_s."""
    i = int(np.clip(np.searchsorted(stamps_s, t_s, side="right") - 1, 0, len(stamps_s) - 2))
    span = stamps_s[i + 1] - stamps_s[i]
    s = 0.0 if span <= 0 else float(np.clip((t_s - stamps_s[i]) / span, 0.0, 1.0))
    return interpolate(poses[i], poses[i + 1], s)


def tie_fixes(fixes: GnssFixes, enu_m: np.ndarray, kf_stamps_s: np.ndarray,
              kf_odom: np.ndarray, frame_stamps_s: np.ndarray, frame_odom: np.ndarray,
              lever_arm_m: np.ndarray) -> tuple[TiedFixes, dict[int, str]]:
    """Tie every fix within the scans' time span to the keyframe nearest in time; the antenna
    (lever_arm_m in the lidar frame) at the fix's instant comes from the frames' odometry poses
    (frame_odom at frame_stamps_s) and is expressed in the keyframe's frame (kf_odom, the
    keyframes' odometry poses). Returns the tied fixes and, per fix left out, why."""
    unused: dict[int, str] = {}
    rows = []
    first, last = float(frame_stamps_s[0]), float(frame_stamps_s[-1])
    arm = np.r_[np.asarray(lever_arm_m, dtype=float), 1.0]
    for i, t in enumerate(np.asarray(fixes.stamp_s, dtype=float)):
        if not first <= t <= last:
            unused[i] = f"outside the scans' stamps {first:.3f}..{last:.3f} s"
            continue
        k = int(np.argmin(np.abs(kf_stamps_s - t)))
        T_kf_fix = inverse(kf_odom[k]) @ pose_at(frame_stamps_s, frame_odom, t)
        rows.append((i, t, k, (T_kf_fix @ arm)[:3]))
    index = np.array([r[0] for r in rows], dtype=int)
    sigma = np.c_[fixes.sigma_h_m, fixes.sigma_h_m, fixes.sigma_v_m][index]
    return TiedFixes(index, np.array([r[1] for r in rows]), np.array([r[2] for r in rows],
                                                                      dtype=int),
                     np.asarray(enu_m, dtype=float)[index], sigma,
                     np.array([r[3] for r in rows]).reshape(-1, 3)), unused


def normalised_d2(residual_m: np.ndarray, sigma_m: np.ndarray, slack_m: float = 0.0
                  ) -> np.ndarray:
    """(n,) squared residuals (n, 3) over the sigmas (n, 3), slack_m added in quadrature."""
    return (residual_m ** 2 / (sigma_m ** 2 + slack_m ** 2)).sum(axis=1)


@dataclass(frozen=True)
class Alignment:
    """T_enu_world (4x4) that puts the run's world frame on the fixes, and which fixes agree with
    it (inlier, (n,)); T_enu_world None when the fixes cannot place the run (why says so)."""

    T_enu_world: np.ndarray | None
    inlier: np.ndarray
    why: str = ""


def _fit(a: np.ndarray, e: np.ndarray, w: np.ndarray, yaw_only: bool) -> np.ndarray:
    """The rigid transform (4x4) minimising sum w |e - (R a + t)|^2: R a rotation about z when
    yaw_only (a already gravity-aligned), else any rotation (weighted Kabsch)."""
    w = w / w.sum()
    ca, ce = w @ a, w @ e
    A, E = a - ca, e - ce
    if yaw_only:
        s = (w * (A[:, 0] * E[:, 1] - A[:, 1] * E[:, 0])).sum()
        c = (w * (A[:, 0] * E[:, 0] + A[:, 1] * E[:, 1])).sum()
        R = yaw_matrix(float(np.arctan2(s, c)))[:3, :3]
    else:
        U, _, Vt = np.linalg.svd((E * w[:, None]).T @ A)
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
        R = U @ D @ Vt
    return make_pose(R, ce - R @ ca)


def _spread_problem(a: np.ndarray, yaw_only: bool) -> str | None:
    """Why the positions a (n, 3; gravity-aligned when yaw_only) cannot fix the alignment."""
    pts = a[:, :2] if yaw_only else a
    centred = pts - pts.mean(axis=0)
    _, _, Vt = np.linalg.svd(centred, full_matrices=False)
    extent = np.ptp(centred @ Vt.T, axis=0)
    if extent[0] < MIN_TRAVEL_M:
        return f"the fixes span {extent[0]:.1f} m of travel (need {MIN_TRAVEL_M:g} m)"
    if not yaw_only and extent[1] < MIN_WIDTH_M:
        return (f"without an IMU the path must not be a line: the fixes span {extent[0]:.0f} m "
                f"along it but {extent[1]:.1f} m across (need {MIN_WIDTH_M:g} m)")
    return None


def align(antenna_world: np.ndarray, enu_m: np.ndarray, sigma_m: np.ndarray,
          R_up_world: np.ndarray | None = None, seed: int = 0) -> Alignment:
    """Robust alignment of the antenna positions the run puts at the fixes (antenna_world, world
    frame) to the fixes (enu_m): RANSAC over pairs (yaw and translation, when R_up_world, the
    rotation from the world to a gravity-aligned z-up frame, is known from an IMU) or triplets
    (the whole rotation), scored by the truncated normalised residuals, then refined by least
    squares on the fixes inside the alignment gate (CHI2_3_GATE with ALIGN_SLACK_M)."""
    n = len(enu_m)
    yaw_only = R_up_world is not None
    a = antenna_world @ R_up_world.T if yaw_only else np.asarray(antenna_world, dtype=float)
    none = np.zeros(n, dtype=bool)
    if n < MIN_FIXES:
        return Alignment(None, none, f"{n} usable fixes (need {MIN_FIXES})")
    problem = _spread_problem(a, yaw_only)
    if problem is not None:
        return Alignment(None, none, problem)
    rng = np.random.default_rng(seed)
    m = 2 if yaw_only else 3
    w = 1.0 / (sigma_m ** 2).mean(axis=1)
    best, best_cost = None, np.inf
    for _ in range(RANSAC_SAMPLES):
        pick = rng.choice(n, m, replace=False)
        if np.linalg.norm(np.ptp(a[pick, :2], axis=0)) < 0.5 * MIN_TRAVEL_M:
            continue  # too close together to fix a direction
        T = _fit(a[pick], enu_m[pick], w[pick], yaw_only)
        d2 = normalised_d2(enu_m - (a @ T[:3, :3].T + T[:3, 3]), sigma_m, ALIGN_SLACK_M)
        cost = np.minimum(d2, CHI2_3_GATE).sum()
        if cost < best_cost:
            best, best_cost = T, cost
    if best is None:
        return Alignment(None, none, "no pair of fixes far enough apart")
    inlier = none
    for _ in range(REFINE_ROUNDS):
        d2 = normalised_d2(enu_m - (a @ best[:3, :3].T + best[:3, 3]), sigma_m, ALIGN_SLACK_M)
        new = d2 < CHI2_3_GATE
        if new.sum() < MIN_FIXES:
            return Alignment(None, none, f"only {int(new.sum())} fixes agree with one another")
        if np.array_equal(new, inlier):
            break
        inlier = new
        best = _fit(a[inlier], enu_m[inlier], w[inlier], yaw_only)
    T_enu_world = best.copy()
    if yaw_only:
        T_enu_world[:3, :3] = best[:3, :3] @ R_up_world
    return Alignment(T_enu_world, inlier)
