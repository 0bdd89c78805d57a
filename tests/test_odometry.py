"""Odometry: our kiss-icp wrapper gives stock KissICP's poses on real scans."""

import numpy as np
from kiss_icp.config import load_config as kiss_load_config
from kiss_icp.kiss_icp import KissICP

from lidar_slam.config import load_config
from lidar_slam.io.sources import open_source
from lidar_slam.odometry import Odometry


def test_odometry_equals_stock_kiss_icp_on_kitti(kitti16):
    src = open_source(kitti16)
    stock = KissICP(kiss_load_config(None))
    ours = Odometry(load_config())
    for scan in src.scans(0, 8):
        stock.register_frame(scan.points, np.array([]))
        T = ours.register(scan.points)
        np.testing.assert_allclose(T, stock.last_pose, atol=1e-6)
    assert np.linalg.norm(T[:3, 3]) > 5.0  # the car moved ~6 m


def test_predict_extrapolates_constant_velocity():
    odo = Odometry(load_config())
    odo.last_delta = np.eye(4)
    odo.last_delta[0, 3] = 1.5
    assert odo.predict()[0, 3] == 1.5 and odo.predict()[0, 3] == 3.0
