"""Pose-graph factors as plain NumPy records, and the one place sigmas become information.

Poses are homogeneous matrices: 4x4 for 3D graphs, 3x3 for 2D graphs. Information matrices are in
gtsam's tangent order: Pose3 is rotation first (rx ry rz tx ty tz; rad, m), Pose2 is (x y theta).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

Dims = Literal[2, 3]


@dataclass(frozen=True)
class PriorFactor:
    """Anchor T_world_node of one node, with information in gtsam tangent order."""

    key: int
    T_world_node: np.ndarray
    information: np.ndarray


@dataclass(frozen=True)
class BetweenFactor:
    """Relative pose T_i_j = inv(T_world_i) @ T_world_j; Huber-robust when robust_k is set."""

    i: int
    j: int
    T_i_j: np.ndarray
    information: np.ndarray
    robust_k: float | None = None
    is_loop: bool = False


def pose_size(dims: Dims) -> int:
    """Side of the homogeneous pose matrix (3 for SE(2), 4 for SE(3))."""
    return 3 if dims == 2 else 4


def tangent_size(dims: Dims) -> int:
    """Dimension of the tangent space (3 for SE(2), 6 for SE(3))."""
    return 3 if dims == 2 else 6


def sigmas_to_information(rot_sigma_deg: float, trans_sigma_m: float, dims: Dims = 3) -> np.ndarray:
    """Diagonal information in gtsam order: 3D (rx ry rz tx ty tz), 2D (x y th); 1/rad^2, 1/m^2."""
    if rot_sigma_deg <= 0 or trans_sigma_m <= 0:
        raise ValueError(f"sigmas must be positive (rot {rot_sigma_deg} deg, "
                         f"trans {trans_sigma_m} m)")
    rot = np.radians(rot_sigma_deg)
    if dims == 3:
        sigmas = np.array([rot, rot, rot, trans_sigma_m, trans_sigma_m, trans_sigma_m])
    else:
        sigmas = np.array([trans_sigma_m, trans_sigma_m, rot])
    return np.diag(1.0 / sigmas**2)


def with_rotation_floor(info: np.ndarray, floor_deg: float, new_floor_deg: float) -> np.ndarray:
    """The information of an edge measured with rotation floor `floor_deg` as if it had been
    floored at `new_floor_deg` instead: the covariance's rotation diagonal moved by the
    difference of the floors' variances (exact: the floor was added to the measured covariance)."""
    cov = np.linalg.inv(info)
    cov[:3, :3] += np.eye(3) * (np.radians(new_floor_deg) ** 2 - np.radians(floor_deg) ** 2)
    out = np.linalg.inv(cov)
    return 0.5 * (out + out.T)


def check_information(information: np.ndarray, dims: Dims) -> np.ndarray:
    """Validated float64 copy of a symmetric positive-definite information matrix."""
    n = tangent_size(dims)
    info = np.array(information, dtype=np.float64)
    if info.shape != (n, n):
        raise ValueError(f"information must be {n}x{n} for a {dims}D graph, got {info.shape}")
    if not np.all(np.isfinite(info)):
        raise ValueError("information matrix has non-finite entries")
    if np.abs(info - info.T).max() > 1e-6 * max(1e-12, np.abs(info).max()):
        raise ValueError("information matrix is not symmetric")
    info = 0.5 * (info + info.T)  # remove round-off asymmetry (e.g. from an ICP Hessian)
    try:
        np.linalg.cholesky(info)
    except np.linalg.LinAlgError as exc:
        raise ValueError("information matrix is not positive definite") from exc
    return info


def check_pose(T: np.ndarray, dims: Dims) -> np.ndarray:
    """Validated float64 copy of a homogeneous pose of the graph's dimension."""
    n = pose_size(dims)
    pose = np.array(T, dtype=np.float64)
    if pose.shape != (n, n):
        raise ValueError(f"pose must be {n}x{n} for a {dims}D graph, got {pose.shape}")
    R = pose[: n - 1, : n - 1]
    if not np.allclose(R.T @ R, np.eye(n - 1), atol=1e-6) or np.linalg.det(R) <= 0:
        raise ValueError("pose rotation is not a proper rotation matrix")
    return pose
