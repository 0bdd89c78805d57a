"""SE(3) helpers on 4x4 float64 arrays."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 pose from a 3x3 rotation and a translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (or a stack of them, (..., 4, 4))."""
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Ti = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    Ti[..., :3, :3] = Rt
    Ti[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    Ti[..., 3, 3] = 1.0
    return Ti


def relative(T_world_a: np.ndarray, T_world_b: np.ndarray) -> np.ndarray:
    """T_a_b = inv(T_world_a) @ T_world_b."""
    return inverse(T_world_a) @ T_world_b


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to (N, 3) points."""
    return points @ T[:3, :3].T + T[:3, 3]


def rotation_angle_deg(T: np.ndarray) -> np.ndarray:
    """Rotation angle of a transform (or a stack) in degrees."""
    R = T[..., :3, :3]
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def yaw_rad(T: np.ndarray) -> float:
    """Heading (rotation about z) of a pose in radians."""
    return float(np.arctan2(T[1, 0], T[0, 0]))


def to_xyz_quat(T: np.ndarray) -> np.ndarray:
    """(x, y, z, qx, qy, qz, qw) of a pose."""
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    return np.r_[T[:3, 3], q]


def from_xyz_quat(v: np.ndarray) -> np.ndarray:
    """4x4 pose from (x, y, z, qx, qy, qz, qw)."""
    return make_pose(Rotation.from_quat(v[3:7]).as_matrix(), v[:3])


def log_se3(T: np.ndarray) -> np.ndarray:
    """Twist (rho, phi) of a pose: translation part first, rotation vector second (decoupled)."""
    return np.r_[T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_rotvec()]


def interpolate(T_a: np.ndarray, T_b: np.ndarray, s: float) -> np.ndarray:
    """Pose at fraction s between T_a and T_b (slerp on rotation, lerp on translation)."""
    dR = Rotation.from_matrix(T_a[:3, :3].T @ T_b[:3, :3]).as_rotvec()
    R = T_a[:3, :3] @ Rotation.from_rotvec(s * dR).as_matrix()
    return make_pose(R, (1 - s) * T_a[:3, 3] + s * T_b[:3, 3])


def yaw_matrix(yaw: float) -> np.ndarray:
    """4x4 rotation about z by yaw radians."""
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    return T
