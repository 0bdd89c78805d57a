"""Registration: the only module that imports small_gicp, and ground levelling.

small_gicp does the voxel centroids, normals / covariances, KD-trees and ICP of the package:
the odometry's refinement of slow scans (lidar_slam.frontend.odometry), localisation's tracking
against a
saved map (lidar_slam.localize) and loop verification (lidar_slam.loop.verify). Always on one
thread: its multi-threaded sums are not reproducible bit for bit. Its voxel centroids stay
small_gicp's (not lidar_slam.frontend.downsample's): the poses and loop constraints are its
results bit for bit.

level_ground fits the ground below a sensor, so that descriptors, yaw guesses and occupancy are
taken about gravity rather than about a tilted (e.g. hand-held) sensor's z axis. Plain NumPy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import small_gicp

THREADS = 1  # small_gicp's OpenMP reductions sum in a varying order
NEIGHBOURS = 10  # for normals / covariances


def orthonormal(T: np.ndarray) -> np.ndarray:
    """T with its rotation re-orthonormalised (products of many poses drift off SO(3) in the
    last bits, and small_gicp's Sophus refuses such a rotation)."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    out = T.copy()
    out[:3, :3] = U @ Vt
    return out


def _voxelgrid(points: np.ndarray, voxel_m: float) -> small_gicp.PointCloud:
    return small_gicp.voxelgrid_sampling(np.ascontiguousarray(points, np.float64), voxel_m,
                                         num_threads=THREADS)


def voxel_centroids(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """One point per voxel_m voxel of points (N, 3): the centroid of the points in it
    (small_gicp's voxel grid, in its order)."""
    if len(points) == 0:
        return np.zeros((0, 3))
    return _voxelgrid(points, voxel_m).points()[:, :3]


@dataclass(frozen=True)
class Cloud:
    """A small_gicp cloud with its KD-tree; points (N, 3) in its sensor frame, metres."""

    points: np.ndarray
    cloud: small_gicp.PointCloud
    tree: small_gicp.KdTree

    @property
    def normals(self) -> np.ndarray:
        return self.cloud.normals()[:, :3]

    def nearest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Index (int64, -1: none) and squared distance (m^2) of each point's nearest neighbour
        among this cloud's points (points (N, 3) in the same frame)."""
        idx, sq = self.tree.batch_nearest_neighbor_search(points, num_threads=THREADS)
        return np.asarray(idx, np.int64), np.asarray(sq, np.float64)


def make_cloud(points: np.ndarray, voxel_m: float, normals: bool, covariances: bool,
               max_points: int = 0) -> Cloud:
    """Voxel-downsampled cloud (voxel centroids), at most max_points of them (a fixed random
    subset; 0: no cap), with normals (a point-to-plane target) and / or covariances (GICP)."""
    pts = _voxelgrid(points, voxel_m).points()[:, :3]
    n = len(pts)
    if 0 < max_points < n:
        pts = pts[np.sort(np.random.default_rng(0).choice(n, max_points, replace=False))]
    pts = np.ascontiguousarray(pts)
    cloud = small_gicp.PointCloud(pts)
    tree = small_gicp.KdTree(cloud, num_threads=THREADS)
    if normals and covariances:
        small_gicp.estimate_normals_covariances(cloud, tree, NEIGHBOURS, THREADS)
    elif normals:
        small_gicp.estimate_normals(cloud, tree, NEIGHBOURS, THREADS)
    elif covariances:
        small_gicp.estimate_covariances(cloud, tree, NEIGHBOURS, THREADS)
    return Cloud(pts, cloud, tree)


def align(target: small_gicp.PointCloud, tree: small_gicp.KdTree, source: small_gicp.PointCloud,
          T_target_source: np.ndarray, max_correspondence_m: float, max_iterations: int,
          method: str = "PLANE_ICP") -> np.ndarray:
    """T_target_source of source by small_gicp's ICP (method PLANE_ICP or GICP) from the guess."""
    result = small_gicp.align(target, source, tree, init_T_target_source=T_target_source,
                              registration_type=method,
                              max_correspondence_distance=max_correspondence_m,
                              num_threads=THREADS, max_iterations=max_iterations)
    return np.asarray(result.T_target_source)


class PlaneTarget:
    """A fixed registration target: points (N, 3) in some frame, one per voxel_m voxel
    (centroids), with normals (10 neighbours) and a KD-tree."""

    def __init__(self, points: np.ndarray, voxel_m: float, max_iterations: int, inlier_m: float):
        self.max_iterations = max_iterations
        self.inlier_m = inlier_m
        self.cloud = _voxelgrid(points, voxel_m)
        self.tree = small_gicp.KdTree(self.cloud, num_threads=THREADS)
        small_gicp.estimate_normals(self.cloud, self.tree, NEIGHBOURS, THREADS)

    def __len__(self) -> int:
        return self.cloud.size()

    def align(self, source: np.ndarray, T_guess: np.ndarray, max_correspondence_m: float
              ) -> np.ndarray:
        """T_target_source of source (N, 3) by point-to-plane ICP from the guess."""
        return align(self.cloud, self.tree, small_gicp.PointCloud(np.ascontiguousarray(source)),
                     orthonormal(T_guess), max_correspondence_m, self.max_iterations)

    def fitness(self, points: np.ndarray, T_target_points: np.ndarray) -> float:
        """Share of points (N, 3) within inlier_m of a target point once placed."""
        if len(points) == 0:
            return 0.0
        moved = points @ T_target_points[:3, :3].T + T_target_points[:3, 3]
        _, sq = self.tree.batch_nearest_neighbor_search(moved, num_threads=THREADS)
        return float(np.mean(np.asarray(sq) <= self.inlier_m**2))


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


@dataclass(frozen=True)
class PlaneFit:
    """A point-to-plane alignment's evidence at a given pose: hessian (6x6) = sum J^T J with
    J = [(p x n)^T, n^T] (rotation first, a perturbation on the right in the source frame,
    T_true = T exp(xi): the tangent of gtsam's BetweenFactor error), over the inliers; rms_m
    their point-to-plane residual (m); n their count."""

    hessian: np.ndarray
    rms_m: float
    n: int


def plane_fit(target: PlaneTarget, source: np.ndarray, T_target_source: np.ndarray,
              max_correspondence_m: float, min_sigma_m: float) -> PlaneFit:
    """The point-to-plane Hessian and residual of source (N, 3) placed by T_target_source on
    the target, without moving it. Inliers: nearest target point within max_correspondence_m
    and a residual within 3 robust sigmas (1.4826 MAD, at least min_sigma_m) of the plane."""
    moved = source @ T_target_source[:3, :3].T + T_target_source[:3, 3]
    idx, sq = target.tree.batch_nearest_neighbor_search(moved, num_threads=THREADS)
    idx, sq = np.asarray(idx, np.int64), np.asarray(sq)
    near = (idx >= 0) & (sq <= max_correspondence_m**2)
    if near.sum() < 6:
        return PlaneFit(np.zeros((6, 6)), float("inf"), 0)
    normals = target.cloud.normals()[idx[near], :3]
    r = np.einsum("ij,ij->i", moved[near] - target.cloud.points()[idx[near], :3], normals)
    robust = max(1.4826 * float(np.median(np.abs(r))), min_sigma_m)
    keep = np.abs(r) <= 3.0 * robust
    n = normals[keep] @ T_target_source[:3, :3]  # R^T n, row-wise: the source frame
    J = np.hstack([np.cross(source[near][keep], n), n])
    return PlaneFit(J.T @ J, float(np.sqrt(np.mean(r[keep] ** 2))), int(keep.sum()))
