"""Scan-to-map ICP odometry: the only module that imports kiss_icp.

The scan arrives cropped and (when it has per-point times) already deskewed by our front-end, so
kiss-icp's own preprocessing/deskew is not used: deskewing happens exactly once.
"""

from __future__ import annotations

import numpy as np
from kiss_icp.config import KISSConfig
from kiss_icp.kiss_icp import KissICP

from lidar_slam.config import SlamConfig


def kiss_config(cfg: SlamConfig) -> KISSConfig:
    """Our config sections mapped onto kiss-icp's (deskew off: our front-end does it)."""
    kc = KISSConfig()
    kc.data.max_range = cfg.data.max_range_m
    kc.data.min_range = cfg.data.min_range_m
    kc.data.deskew = False
    kc.mapping.voxel_size = cfg.voxel_size_m()
    kc.mapping.max_points_per_voxel = cfg.odometry.max_points_per_voxel
    kc.adaptive_threshold.initial_threshold = cfg.odometry.initial_threshold_m
    kc.adaptive_threshold.min_motion_th = cfg.odometry.min_motion_m
    kc.registration.max_num_iterations = cfg.odometry.max_num_iterations
    kc.registration.convergence_criterion = cfg.odometry.convergence_criterion
    kc.registration.max_num_threads = cfg.odometry.max_num_threads
    return kc


class Odometry:
    """kiss-icp scan-to-map registration; poses are T_world_scan with world = first scan."""

    def __init__(self, cfg: SlamConfig):
        self._icp = KissICP(kiss_config(cfg))

    @property
    def last_delta(self) -> np.ndarray:
        """Last frame-to-frame motion T_prev_curr (the constant-velocity prediction)."""
        return self._icp.last_delta

    def step(self, points: np.ndarray) -> np.ndarray:
        """Register a cropped, deskewed scan (N,3) and return T_world_scan."""
        icp = self._icp
        source, frame_downsample = icp.voxelize(points)
        sigma = icp.adaptive_threshold.get_threshold()
        initial_guess = icp.last_pose @ icp.last_delta
        new_pose = icp.registration.align_points_to_map(
            points=source,
            voxel_map=icp.local_map,
            initial_guess=initial_guess,
            max_correspondance_distance=3 * sigma,
            kernel=sigma,
        )
        icp.adaptive_threshold.update_model_deviation(np.linalg.inv(initial_guess) @ new_pose)
        icp.local_map.update(frame_downsample, new_pose)
        icp.last_delta = np.linalg.inv(icp.last_pose) @ new_pose
        icp.last_pose = new_pose
        return new_pose

    def predict(self) -> np.ndarray:
        """Constant-velocity prediction of the next pose; advances the state without a scan."""
        icp = self._icp
        icp.last_pose = icp.last_pose @ icp.last_delta
        return icp.last_pose
