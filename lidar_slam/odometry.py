"""Scan-to-map ICP odometry: the only module that imports kiss_icp.

This is kiss-icp's `KissICP.register_frame` step for step, on kiss-icp's own C++ components, with
two differences: the scan arrives (when it has per-point times) already deskewed by our front-end,
so kiss-icp's preprocessor runs with its deskew off (range crop only) and deskewing happens
exactly once;
and the components are built from our config without kiss-icp's pydantic-settings layer, whose
import alone costs ~50 ms of every run. tests/test_odometry.py checks the poses equal stock
KissICP's on real scans.
"""

from __future__ import annotations

import numpy as np
from kiss_icp.pybind import kiss_icp_pybind as kp

from lidar_slam.config import SlamConfig


def _vec(points: np.ndarray):
    return kp._Vector3dVector(points)


class Odometry:
    """kiss-icp scan-to-map registration; poses are T_world_scan with world = first scan."""

    def __init__(self, cfg: SlamConfig):
        o = cfg.odometry
        self.voxel_size_m = cfg.voxel_size_m()
        self.max_range_m = cfg.data.max_range_m
        self._map = kp._VoxelHashMap(voxel_size=self.voxel_size_m, max_distance=self.max_range_m,
                                     max_points_per_voxel=o.max_points_per_voxel)
        self._registration = kp._Registration(max_num_iterations=o.max_num_iterations,
                                              convergence_criterion=o.convergence_criterion,
                                              max_num_threads=o.max_num_threads)
        self._threshold = kp._AdaptiveThreshold(initial_threshold=o.initial_threshold_m,
                                                min_motion_th=o.min_motion_m,
                                                max_range=self.max_range_m)
        # kiss-icp's range crop (C++, parallel) with its deskew switched off: ours runs before.
        self._crop = kp._Preprocessor(cfg.data.max_range_m, cfg.data.min_range_m, False,
                                      o.max_num_threads)
        self.last_pose = np.eye(4)
        self.last_delta = np.eye(4)  # T_prev_curr, the constant-velocity prediction

    def step(self, points: np.ndarray) -> np.ndarray | None:
        """Register a deskewed scan (N,3), cropped here to the configured range, and return
        T_world_scan; None (and no state change) when no point lies in range."""
        cropped = self._crop._preprocess(_vec(points), np.zeros(0), np.eye(4))
        if len(cropped) == 0:
            return None
        frame_down = kp._voxel_down_sample(cropped, self.voxel_size_m * 0.5)
        source = kp._voxel_down_sample(frame_down, self.voxel_size_m * 1.5)
        sigma = self._threshold._compute_threshold()
        initial_guess = self.last_pose @ self.last_delta
        new_pose = self._registration._align_points_to_map(
            points=source, voxel_map=self._map, initial_guess=initial_guess,
            max_correspondance_distance=3 * sigma, kernel=sigma)
        self._threshold._update_model_deviation(
            model_deviation=np.linalg.inv(initial_guess) @ new_pose)
        self._map._update(frame_down, new_pose)
        self.last_delta = np.linalg.inv(self.last_pose) @ new_pose
        self.last_pose = new_pose
        return new_pose

    def predict(self) -> np.ndarray:
        """Constant-velocity prediction of the next pose; advances the state without a scan."""
        self.last_pose = self.last_pose @ self.last_delta
        return self.last_pose
