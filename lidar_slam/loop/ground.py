"""Ground-plane levelling of a keyframe cloud, so that descriptors and yaw guesses are taken about
gravity rather than about a tilted (e.g. hand-held) sensor's z axis. Plain NumPy (no open3d)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class GroundLevel:
    """R_level_sensor: rotation (no yaw) taking sensor-frame points to a frame whose z is the
    ground normal; height_m: sensor height above that ground plane, or None when none was found."""

    R_level_sensor: np.ndarray
    height_m: float | None


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation taking unit vector a onto unit vector b (Rodrigues)."""
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3)
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + K + K @ K / (1.0 + c)


def level_ground(points: np.ndarray, max_tilt_deg: float = 30.0, max_range_m: float = 10.0,
                 inlier_m: float = 0.1, min_height_m: float = 0.3, iterations: int = 64,
                 seed: int = 0) -> GroundLevel:
    """Fit the ground plane below the sensor (RANSAC over near points, normal within max_tilt_deg
    of sensor z, plane at least min_height_m below the origin) and return the levelling rotation.

    points: (N, 3) in the sensor (keyframe) frame, metres. Falls back to identity / None height
    when no plausible plane supports at least 10 % of the candidate points.
    """
    pts = np.asarray(points, dtype=np.float64)
    r = np.hypot(pts[:, 0], pts[:, 1])
    # At 30 deg of tilt the floor 10 m away on the raised side is ~3 m above a 2 m-high sensor's
    # horizon only beyond ~3.5 m; keeping z < 0 and r < 10 m leaves most floor points in.
    cand = pts[(r < max_range_m) & (pts[:, 2] < -min_height_m)]
    identity = GroundLevel(np.eye(3), None)
    if len(cand) < 50:
        return identity
    rng = np.random.default_rng(seed)
    if len(cand) > 4000:
        cand = cand[rng.choice(len(cand), 4000, replace=False)]
    tri = cand[rng.integers(0, len(cand), size=(iterations, 3))]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(normals, axis=1)
    ok = norm > 1e-6
    normals = normals[ok] / norm[ok, None]
    normals *= np.sign(normals[:, 2:3]) + (normals[:, 2:3] == 0)
    d = -np.einsum("ij,ij->i", normals, tri[ok, 0])  # plane n.x + d = 0; d > 0 below the origin
    cos_max = np.cos(np.radians(max_tilt_deg))
    good = (normals[:, 2] >= cos_max) & (d >= min_height_m)
    if not good.any():
        return identity
    normals, d = normals[good], d[good]
    inliers = np.abs(cand @ normals.T + d) < inlier_m
    best = int(np.argmax(inliers.sum(axis=0)))
    mask = inliers[:, best]
    if mask.sum() < max(30, 0.1 * len(cand)):
        return identity
    # Least-squares refit on the inliers: the normal is the smallest principal axis.
    sel = cand[mask]
    centre = sel.mean(axis=0)
    n = np.linalg.svd(sel - centre, full_matrices=False)[2][2]
    n = n if n[2] > 0 else -n
    if n[2] < cos_max:
        return identity
    height = float(np.dot(n, centre) * -1.0)
    if height < min_height_m:
        return identity
    return GroundLevel(_rotation_between(n, np.array([0.0, 0.0, 1.0])), height)
