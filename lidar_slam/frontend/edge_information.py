"""How sure each odometry edge is, from its own data: the information matrix of the motion
between consecutive keyframes.

kiss-icp does not expose its registration's Hessian, so each keyframe's cloud is placed on the
previous keyframe's cloud by the odometry's relative pose (no ICP is run: the odometry's pose is
the estimate being weighed) and the point-to-plane Hessian of that fit is taken there,
J = [(p x n)^T, n^T] per residual, scaled by the residual's own measured variance:

    information = sum(J^T J) / rms^2

The shape of the Hessian says which directions the scene constrains (a corridor leaves its axis
weak; an open field leaves yaw weak); the residual says how well the two clouds agree. Two
corrections keep it honest:

- neighbouring residuals on one surface are not independent (the same wall, the same voxel
  quantisation): the source cloud is thinned to one point per `cell_m` cell first, so the count
  of residuals is roughly the count of distinct surface patches;
- floors: a covariance of `min_rot_sigma_deg` / `min_trans_sigma_m` per axis is added to the
  measured one (what a registration on a dense scene cannot see: calibration, deskew and
  quantisation errors), so no direction is more certain than that while a weak direction stays
  as weak as measured (a uniform down-scaling, as the loop verification does, would make a
  car's weak forward axis ten times too loose because its ground pins z); and a direction the
  clouds cannot observe keeps a weak information of (10 deg, 1 m)^-2 so that the matrix stays
  positive definite.

Everything here is a function of the stored keyframe clouds and odometry poses, so a resumed run
recomputes the same matrices.
"""

from __future__ import annotations

import numpy as np

from lidar_slam.config import OdometryInformationConfig
from lidar_slam.geometry import relative, rotation_angle_deg
from lidar_slam.registration import PlaneTarget, plane_fit, voxel_centroids

WEAK_INFORMATION = np.diag([np.radians(10.0) ** -2] * 3 + [1.0] * 3)
MIN_RESIDUALS = 30  # fewer inliers than this: the configured sigmas instead
# A flick's deskew error stays in the odometry for a few scans (the keyframe's and 2 before).
DESKEW_WINDOW = 2


def information(fit_hessian: np.ndarray, rms_m: float, cfg: OdometryInformationConfig
                ) -> np.ndarray:
    """6x6 information (rotation first) from a point-to-plane Hessian sum(J^T J) and the RMS
    residual (m) of its inliers, floored as the module says."""
    H = fit_hessian / max(rms_m, cfg.min_residual_m) ** 2
    cov = np.linalg.inv(0.5 * (H + H.T) + WEAK_INFORMATION)
    cov += np.diag([np.radians(cfg.min_rot_sigma_deg) ** 2] * 3 + [cfg.min_trans_sigma_m ** 2] * 3)
    info = np.linalg.inv(cov)
    return 0.5 * (info + info.T)


class EdgeInformation:
    """add(T_world_kf, points) for each keyframe in order -> the information of the edge from the
    previous keyframe to it (None for the first, or when either cloud is empty or too thin:
    the caller then uses the configured sigmas); between() for any two consecutive ones, stored()
    for two in a keyframe store."""

    def __init__(self, cfg: OdometryInformationConfig, cloud_voxel_m: float):
        self.cfg = cfg
        self.cloud_voxel_m = cloud_voxel_m
        self._prev: tuple[np.ndarray, np.ndarray] | None = None  # T_world_kf, points

    def add(self, T_world_kf: np.ndarray, points: np.ndarray) -> np.ndarray | None:
        """points: (N, 3) the keyframe's cloud in its own frame (m)."""
        prev, self._prev = self._prev, (T_world_kf, np.asarray(points, np.float64))
        if prev is None:
            return None
        return self.between(prev[0], prev[1], T_world_kf, self._prev[1])

    def stored(self, store, kf_id: int) -> np.ndarray | None:
        """The information of the edge into keyframe kf_id from a keyframe store's clouds and
        odometry poses (map.keyframes.KeyframeStore or KeyframeReader; None for the first)."""
        if kf_id == 0:
            return None
        prev, kf = store.get(kf_id - 1), store.get(kf_id)
        return self.between(prev.T_world_kf_odom, prev.points, kf.T_world_kf_odom, kf.points)

    def between(self, T_world_prev: np.ndarray, prev_points: np.ndarray, T_world_kf: np.ndarray,
                points: np.ndarray) -> np.ndarray | None:
        """The information of the edge from a keyframe (pose, cloud in its frame) to the next,
        whatever came before (add() in keyframe order gives the same)."""
        prev_points = np.asarray(prev_points, np.float64)
        points = np.asarray(points, np.float64)
        if len(prev_points) < MIN_RESIDUALS or len(points) < MIN_RESIDUALS:
            return None
        c = self.cfg
        target = PlaneTarget(prev_points, self.cloud_voxel_m, 0, c.max_correspondence_m)
        source = voxel_centroids(points, c.cell_m)  # this keyframe's cloud
        fit = plane_fit(target, source, relative(T_world_prev, T_world_kf),
                        c.max_correspondence_m, c.min_residual_m)
        if fit.n < MIN_RESIDUALS:
            return None
        return information(fit.hessian, fit.rms_m, c)


def deskew_white(odom_poses: np.ndarray, kf_positions: dict[int, int],
                 kf_ranges: dict[int, float], scale: float, window: int = DESKEW_WINDOW
                 ) -> dict[int, float]:
    """The variance (m^2, per axis) of each keyframe's position error that a deskew at constant
    velocity leaves and no lidar constraint can see: (scale x miss x range)^2, miss the largest
    rotation (rad) by which a scan's pose missed the constant-velocity prediction from the two
    before it, over the keyframe's scan and the `window` before it, and range the keyframe
    cloud's median range (m). Through a hand-held flick the sweep is deskewed along a motion it
    did not have; its cloud, and the pose fitted to it, are then a few decimetres off for the
    next scans while every registration of that cloud agrees with it (docs/bank.md, Decisions,
    "a keyframe's covariance carries its deskew's white error"). odom_poses: (K, 4, 4) the
    run's odometry poses at the scans' stamps, in order (odometry_kitti.txt: with per-point
    times each lies between two registrations, so a flick's miss shows there about halved and
    over two scans; the bank's scale was set on these poses); kf_positions: {keyframe: its
    scan's position in odom_poses}; kf_ranges: {keyframe: m}."""
    T = np.asarray(odom_poses, dtype=float)
    miss = np.zeros(len(T))
    if len(T) >= 3:
        # the constant-velocity prediction of scan p: T[p-1] moved again by T[p-2] -> T[p-1]
        pred = T[1:-1] @ np.linalg.inv(T[:-2]) @ T[1:-1]
        miss[2:] = np.radians(rotation_angle_deg(np.linalg.inv(pred) @ T[2:]))
    out = {}
    for kf, p in kf_positions.items():
        m = float(miss[max(0, p - window):p + 1].max()) if 0 <= p < len(T) else 0.0
        out[kf] = (scale * m * float(kf_ranges.get(kf, 0.0))) ** 2
    return out
