"""Point-to-plane ICP against a fixed cloud (small_gicp, one thread: reproducible).

Used where a scan is registered against keyframe clouds that do not change while it is: the
odometry's refinement of slow scans (lidar_slam.odometry) and localisation's tracking against a
saved map (lidar_slam.localize).
"""

from __future__ import annotations

import numpy as np
import small_gicp


def orthonormal(T: np.ndarray) -> np.ndarray:
    """T with its rotation re-orthonormalised (products of many poses drift off SO(3) in the
    last bits, and small_gicp's Sophus refuses such a rotation)."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    out = T.copy()
    out[:3, :3] = U @ Vt
    return out


def voxel_centroids(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """One point per voxel_m voxel of points (N, 3): the centroid of the points in it."""
    if len(points) == 0:
        return np.zeros((0, 3))
    return small_gicp.voxelgrid_sampling(np.ascontiguousarray(points, np.float64), voxel_m,
                                         num_threads=1).points()[:, :3]


class PlaneTarget:
    """A fixed registration target: points (N, 3) in some frame, one per voxel_m voxel
    (centroids), with normals (10 neighbours) and a KD-tree."""

    def __init__(self, points: np.ndarray, voxel_m: float, max_iterations: int, inlier_m: float):
        self.max_iterations = max_iterations
        self.inlier_m = inlier_m
        self.cloud = small_gicp.voxelgrid_sampling(np.ascontiguousarray(points, np.float64),
                                                   voxel_m, num_threads=1)
        self.tree = small_gicp.KdTree(self.cloud, num_threads=1)
        small_gicp.estimate_normals(self.cloud, self.tree, 10, 1)

    def __len__(self) -> int:
        return self.cloud.size()

    def align(self, source: np.ndarray, T_guess: np.ndarray, max_correspondence_m: float
              ) -> np.ndarray:
        """T_target_source of source (N, 3) by point-to-plane ICP from the guess."""
        result = small_gicp.align(self.cloud, small_gicp.PointCloud(np.ascontiguousarray(source)),
                                  self.tree, init_T_target_source=orthonormal(T_guess),
                                  registration_type="PLANE_ICP",
                                  max_correspondence_distance=max_correspondence_m,
                                  num_threads=1, max_iterations=self.max_iterations)
        return np.asarray(result.T_target_source)

    def fitness(self, points: np.ndarray, T_target_points: np.ndarray) -> float:
        """Share of points (N, 3) within inlier_m of a target point once placed."""
        if len(points) == 0:
            return 0.0
        moved = points @ T_target_points[:3, :3].T + T_target_points[:3, 3]
        _, sq = self.tree.batch_nearest_neighbor_search(moved, num_threads=1)
        return float(np.mean(np.asarray(sq) <= self.inlier_m**2))
