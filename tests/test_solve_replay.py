"""tools/solve_replay.py: its overrides reach the config with the config's own types, and its
keyframe ATE is the rigid-aligned RMSE (zero for a rigidly moved copy)."""

from __future__ import annotations

import importlib

import numpy as np

from lidar_slam.config import SlamConfig
from lidar_slam.geometry import make_pose, matrix_from_rotvec


def replay():
    return importlib.import_module("tools.solve_replay")


def test_overrides_keep_the_configs_types_and_touch_nothing_else():
    cfg = replay().override(SlamConfig(), ["backend.inertial_odom_min_rot_sigma_deg=0.005",
                                            "backend.max_iterations=7"])
    assert cfg.backend.inertial_odom_min_rot_sigma_deg == 0.005
    assert cfg.backend.max_iterations == 7 and isinstance(cfg.backend.max_iterations, int)
    assert cfg.loop == SlamConfig().loop


def test_keyframe_ate_is_zero_for_a_rigid_copy_and_the_rmse_otherwise():
    rng = np.random.default_rng(0)
    gt = np.stack([make_pose(np.eye(3), p) for p in rng.uniform(-20, 20, (50, 3))])
    T = make_pose(matrix_from_rotvec([0.1, -0.2, 0.7]), [3.0, -1.0, 2.0])
    assert replay()._ate(T @ gt, gt) < 1e-9
    noisy = gt.copy()
    noisy[:, :3, 3] += np.where(np.arange(50)[:, None] % 2 == 0, 0.1, -0.1) * np.array([0, 0, 1])
    assert abs(replay()._ate(noisy, gt) - 0.1) < 1e-3


def test_settings_are_read_as_yaml_and_validated():
    from lidar_slam.config import SlamConfig
    from tools.solve_replay import override

    cfg = override(SlamConfig(), ["backend.odometry_drift_state=false",
                                   "imu.T_lidar_imu_sigma_deg=0.5", "backend.huber_k=2"])
    assert cfg.backend.odometry_drift_state is False and cfg.imu.T_lidar_imu_sigma_deg == 0.5
    assert cfg.backend.huber_k == 2.0
    import pytest
    from pydantic import ValidationError

    with pytest.raises(ValidationError):
        override(SlamConfig(), ["backend.huber_k=-1"])
