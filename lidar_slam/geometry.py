"""SE(3) helpers on 4x4 float64 arrays (NumPy only: scipy's import alone costs ~0.3 s)."""

from __future__ import annotations

import numpy as np


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) as (qx, qy, qz, qw) with qw >= 0 from rotation matrices (..., 3,
    3).

    Uses the symmetric 4x4 (Bar-Itzhack) eigenvector, so slightly non-orthonormal input gives the
    nearest rotation's quaternion.
    """
    R = np.asarray(R, dtype=np.float64)
    m = R.reshape(-1, 3, 3)
    xx, xy, xz = m[:, 0, 0], m[:, 0, 1], m[:, 0, 2]
    yx, yy, yz = m[:, 1, 0], m[:, 1, 1], m[:, 1, 2]
    zx, zy, zz = m[:, 2, 0], m[:, 2, 1], m[:, 2, 2]
    K = np.stack([
        np.stack([xx - yy - zz, yx + xy, zx + xz, zy - yz], -1),
        np.stack([yx + xy, yy - xx - zz, zy + yz, xz - zx], -1),
        np.stack([zx + xz, zy + yz, zz - xx - yy, yx - xy], -1),
        np.stack([zy - yz, xz - zx, yx - xy, xx + yy + zz], -1),
    ], -2) / 3.0
    _, vecs = np.linalg.eigh(K)
    q = vecs[:, :, -1]
    q = q * np.where(q[:, 3:4] < 0, -1.0, 1.0)
    return q.reshape(R.shape[:-2] + (4,))


def matrix_from_quat(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from quaternions (..., 4) ordered (qx, qy, qz, qw)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def _skew_and_angle(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Of rotation matrices (n, 3, 3): w = vee(R - R^T) (2 sin(angle) axis), sin(angle) and the
    angle (rad), atan2(sin, cos) from the skew part and the trace (exact also for small angles,
    where arccos((trace - 1) / 2) loses precision)."""
    w = np.stack([m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0],
                  m[:, 1, 0] - m[:, 0, 1]], -1)
    s = 0.5 * np.linalg.norm(w, axis=-1)
    return w, s, np.arctan2(s, 0.5 * (m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2] - 1.0))


# Above this angle (rad) the skew part says too little of the axis: the quaternion route there.
_NEAR_PI_RAD = 3.0


def rotvec_from_matrix(R: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle, rad) of a rotation matrix (..., 3, 3): the angle
    atan2(sin, cos) from the skew part and the trace (exact for small angles too), the axis
    from the skew part, or from the quaternion (quat_from_matrix) near pi. ~5x faster than the
    quaternion route alone, the same to ~1e-16 rad."""
    R = np.asarray(R, dtype=np.float64)
    m = R.reshape(-1, 3, 3)
    w, s, angle = _skew_and_angle(m)
    # angle / (2 sin(angle)), -> 1/2 at 0 (its series: 1/2 + angle^2 / 12)
    f = np.where(s > 1e-8, angle / np.maximum(2.0 * s, 1e-300), 0.5 + angle**2 / 12.0)
    out = w * f[:, None]
    far = angle > _NEAR_PI_RAD
    if far.any():
        q = quat_from_matrix(m[far])
        v = q[:, :3]
        n = np.linalg.norm(v, axis=-1, keepdims=True)
        out[far] = v * (2.0 * np.arctan2(n, q[:, 3:4]) / np.maximum(n, 1e-300))
    return out.reshape(R.shape[:-2] + (3,))


def matrix_from_rotvec(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) from a rotation vector (rad), Rodrigues' formula."""
    rv = np.asarray(rotvec, dtype=np.float64)
    theta = float(np.linalg.norm(rv))
    if theta < 1e-12:
        return np.eye(3)
    k = rv / theta
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * Kx + (1 - np.cos(theta)) * Kx @ Kx


def rotate_by_rotvec(rotvecs: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Each vector of v (N, 3) turned by the rotation of its rotation vector (N, 3, rad):
    Rodrigues' formula on the vectors, no matrices."""
    rv = np.asarray(rotvecs, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    theta = np.linalg.norm(rv, axis=-1, keepdims=True)
    k = rv / np.where(theta > 1e-300, theta, 1.0)
    kxv = np.cross(k, v)
    return v + np.sin(theta) * kxv + (1.0 - np.cos(theta)) * np.cross(k, kxv)


class Slerp:
    """scipy.spatial.transform.Slerp in NumPy (scipy.spatial's import costs ~0.3 s of a run):
    rotations R (K, 3, 3) at increasing times (K,); between two, a turn about the fixed axis
    of their relative rotation at a constant rate."""

    def __init__(self, times: np.ndarray, R: np.ndarray):
        self.times = np.asarray(times, dtype=np.float64)
        self.R = np.asarray(R, dtype=np.float64)
        if len(self.times) < 2 or np.any(np.diff(self.times) <= 0):
            raise ValueError("Slerp needs at least two rotations at increasing times")
        # each interval's rotation vector, in the frame of its start
        self._turn = rotvec_from_matrix(np.swapaxes(self.R[:-1], 1, 2) @ self.R[1:])

    def _at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Interval index and rotation vector from its start to each time (within the times:
        scipy's convention, a time on a knot ends the interval before it)."""
        t = np.asarray(t, dtype=np.float64)
        if np.any(t < self.times[0]) or np.any(t > self.times[-1]):
            raise ValueError(f"Slerp: times must be within [{self.times[0]}, {self.times[-1]}]")
        i = np.clip(np.searchsorted(self.times, t, side="left") - 1, 0, len(self.times) - 2)
        s = (t - self.times[i]) / (self.times[i + 1] - self.times[i])
        return i, self._turn[i] * s[:, None]

    def matrices(self, t: np.ndarray) -> np.ndarray:
        """The rotations (N, 3, 3) at times t (N,)."""
        i, rv = self._at(t)
        return self.R[i] @ matrices_from_rotvecs(rv)

    def apply(self, t: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Each vector of v (N, 3) turned by the rotation at its time t (N,), without forming
        the matrices' products."""
        i, rv = self._at(t)
        return np.einsum("nij,nj->ni", self.R[i], rotate_by_rotvec(rv, v))


def matrices_from_rotvecs(rotvecs: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) from rotation vectors (N, 3, rad), Rodrigues' formula."""
    rv = np.asarray(rotvecs, dtype=np.float64).reshape(-1, 3)
    theta = np.linalg.norm(rv, axis=-1)
    k = rv / np.where(theta > 1e-300, theta, 1.0)[:, None]
    K = np.zeros((len(rv), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    sin, cos = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    return np.eye(3) + sin * K + (1.0 - cos) * (K @ K)


def se3_log(T: np.ndarray) -> np.ndarray:
    """gtsam's Pose3::Logmap of a 4x4 pose: (rotation vector, u), rotation first, with u the
    translation taken through the inverse of SE(3)'s left Jacobian (Agrawal 2006, eq. 14, as
    gtsam writes it)."""
    w = rotvec_from_matrix(T[:3, :3])
    t = np.asarray(T[:3, 3], dtype=np.float64)
    angle = float(np.linalg.norm(w))
    if angle < 1e-10:
        return np.concatenate([w, t])
    k = w / angle
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    Kt = K @ t
    u = t - (0.5 * angle) * Kt + (1.0 - angle / (2.0 * np.tan(0.5 * angle))) * (K @ Kt)
    return np.concatenate([w, u])


def between_error(T_i_j: np.ndarray, T_w_i: np.ndarray, T_w_j: np.ndarray) -> np.ndarray:
    """gtsam's BetweenFactorPose3 error (6, rotation first, in j's frame) of the measurement
    T_i_j at poses T_w_i, T_w_j: Logmap(T_i_j^-1 T_w_i^-1 T_w_j), as
    backend.gtsam_graph.between_error computes it with gtsam (the same to ~1e-14,
    tests/test_geometry.py). For the loop worker process, which imported gtsam for this alone:
    0.28 s of its CPU, and the run waits for the worker's last keyframes at its end (a 40 s
    hand-held walk's wall 4.38 -> 4.16 s)."""
    return se3_log(inverse(T_i_j) @ (inverse(T_w_i) @ T_w_j))


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
    """Rotation angle of a transform (or a stack) in degrees, from the skew part and the trace
    (_skew_and_angle). For rotations orthonormal to machine precision (the pipeline's own);
    rotations read from files (orthonormal to ~1e-7) need the nearest rotation's angle
    (eval.metrics._angle_deg)."""
    T = np.asarray(T, dtype=np.float64)
    angle = _skew_and_angle(T[..., :3, :3].reshape(-1, 3, 3))[2]
    return np.degrees(angle).reshape(T.shape[:-2])[()]


def yaw_rad(T: np.ndarray) -> float:
    """Heading (rotation about z) of a pose in radians."""
    return float(np.arctan2(T[1, 0], T[0, 0]))


def to_xyz_quat(T: np.ndarray) -> np.ndarray:
    """(x, y, z, qx, qy, qz, qw) of a pose."""
    return np.r_[T[:3, 3], quat_from_matrix(T[:3, :3])]


def from_xyz_quat(v: np.ndarray) -> np.ndarray:
    """4x4 pose from (x, y, z, qx, qy, qz, qw)."""
    return make_pose(matrix_from_quat(v[3:7]), v[:3])


def interpolate(T_a: np.ndarray, T_b: np.ndarray, s: float) -> np.ndarray:
    """Pose at fraction s between T_a and T_b (slerp on rotation, lerp on translation)."""
    dR = rotvec_from_matrix(T_a[:3, :3].T @ T_b[:3, :3])
    R = T_a[:3, :3] @ matrix_from_rotvec(s * dR)
    return make_pose(R, (1 - s) * T_a[:3, 3] + s * T_b[:3, 3])


def yaw_matrix(yaw: float) -> np.ndarray:
    """4x4 rotation about z by yaw radians."""
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    return T
