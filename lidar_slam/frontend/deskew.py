"""Motion compensation under a constant-velocity model.

Convention: a scan's pose refers to the instant of its stamp (`Scan.stamp_s`), and per-point
times are seconds relative to that stamp. A point captured at time t is moved into the sensor
frame at the stamp with the pose T_stamp_t = interpolate(I, T_prev_curr, t / period_s), where
T_prev_curr is the last frame-to-frame motion (over period_s seconds). Rotation is interpolated on
SO(3) about the fixed axis of the motion, translation linearly.
"""

from __future__ import annotations

import numpy as np

from lidar_slam.geometry import rotvec_from_matrix


def deskew(points: np.ndarray, point_times_s: np.ndarray, T_prev_curr: np.ndarray,
           period_s: float) -> np.ndarray:
    """Points (N,3) captured at point_times_s, expressed in the sensor frame at the scan stamp."""
    if period_s <= 0:
        return points
    s = point_times_s * (1.0 / period_s)
    rotvec = rotvec_from_matrix(T_prev_curr[:3, :3])
    theta = float(np.linalg.norm(rotvec))
    out = s[:, None] * T_prev_curr[:3, 3]
    out += points
    if theta > 1e-12:
        # Rodrigues about the motion's fixed axis k: R(a) p = p + sin(a) K p + (1 - cos(a)) K^2 p,
        # as (N,3) x (3,3) products into one reused buffer (fresh temporaries cost page faults).
        k = rotvec / theta
        K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
        ang = s * theta
        tmp = np.empty_like(out)
        np.matmul(points, K.T, out=tmp)
        tmp *= np.sin(ang)[:, None]
        out += tmp
        np.matmul(points, (K @ K).T, out=tmp)
        tmp *= (1.0 - np.cos(ang))[:, None]
        out += tmp
    return out
