"""lidar_slam.imu: gtsam's preintegration between any two instants, from samples on their own
clock (interval ends between samples interpolated), and gravity alignment."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lidar_slam.config import ImuConfig
from lidar_slam.imu import (
    ImuStream,
    bias_from_vector,
    combined_params,
    gravity_rotation,
    predict_pose,
    predict_poses_along,
)
from lidar_slam.io.imu_gnss import ImuSamples
from lidar_slam.sim.imu_gnss import NOISELESS, ImuOptions, SmoothTrajectory, simulate_imu


def shaky_walk(seconds: float = 4.0) -> SmoothTrajectory:
    """A hand-held sensor: walking, bobbing, turning fast (up to ~150 deg/s)."""
    t = np.linspace(0.0, seconds, int(seconds * 20) + 1)
    poses = np.tile(np.eye(4), (len(t), 1, 1))
    bob = 0.03 * np.sin(2 * np.pi * 1.9 * t)
    poses[:, :3, 3] = np.c_[1.3 * t, 0.4 * np.sin(1.1 * t), 1.4 + bob]
    euler = np.c_[1.2 * np.sin(2.0 * t), 0.3 * np.sin(3.1 * t), 0.2 * np.sin(2.3 * t + 1.0)]
    poses[:, :3, :3] = Rotation.from_euler("zyx", euler).as_matrix()
    return SmoothTrajectory(t, poses)


def T_lidar_imu() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [180.0, 0.0, 90.0], degrees=True).as_matrix()
    T[:3, 3] = [0.05, -0.02, -0.04]
    return T


def stream(traj: SmoothTrajectory, rate_hz: float, T_li: np.ndarray) -> ImuSamples:
    imu = simulate_imu(traj, 0.0, 4.0, ImuOptions(rate_hz=rate_hz, noise=NOISELESS,
                                                    T_lidar_imu=T_li), np.random.default_rng(0))
    return ImuSamples(imu.stamps_s, imu.gyro, imu.accel, "test")


@pytest.mark.parametrize("t0, t1", [(0.5, 0.6), (1.2345, 1.3391), (2.0, 2.5), (3.001, 3.002)])
def test_preintegration_between_instants_off_the_samples_carries_one_pose_to_the_next(t0, t1):
    traj, T_li = shaky_walk(), T_lidar_imu()
    imu = ImuStream(stream(traj, 200.0, T_li))
    _, _, v = traj.imu_truth(np.array([t0]), T_li)
    T0, T1 = traj(np.array([t0, t1])) @ T_li
    pim = imu.preintegrate(t0, t1, combined_params(ImuConfig()))
    assert pim.deltaTij() == pytest.approx(t1 - t0)
    pred = pim.predict(gtsam.NavState(gtsam.Pose3(T0), v[0]), gtsam.imuBias.ConstantBias())
    d = np.linalg.inv(T1) @ pred.pose().matrix()
    assert np.linalg.norm(d[:3, 3]) < 1e-3 * max(1.0, (t1 - t0) / 0.1) ** 2
    assert np.degrees(Rotation.from_matrix(d[:3, :3]).magnitude()) < 0.01


def test_poses_along_one_integration_are_each_instants_own_prediction():
    """The frames between two keyframes (backend.imu_gnss_solve.imu_frame_poses): one
    integration through their stamps gives each the pose an integration to it alone gives, to
    the steps their stamps cut (~1e-6 m); stamps between samples, on a sample, and two in one
    sample step included."""
    traj, T_li = shaky_walk(), T_lidar_imu()
    imu = ImuStream(stream(traj, 200.0, T_li))
    params = combined_params(ImuConfig())
    t0 = 1.2345
    times = [1.2371, 1.24, 1.2402, 1.2667, 1.3391]
    _, _, v = traj.imu_truth(np.array([t0]), T_li)
    T0 = traj(np.array([t0]))[0] @ T_li
    bias6 = np.array([0.02, -0.01, 0.03, 0.001, -0.002, 0.0005])
    along = predict_poses_along(imu, t0, times, params, T0, v[0], bias6)
    for t, T in zip(times, along, strict=True):
        alone = predict_pose(imu.preintegrate(t0, t, params, bias_from_vector(bias6)), T0, v[0],
                             bias6)
        np.testing.assert_allclose(T, alone, atol=1e-5)


def test_an_interval_outside_the_samples_is_reported_as_not_covered():
    imu = ImuStream(stream(shaky_walk(), 100.0, np.eye(4)))
    assert imu.interval(1.0, 1.1).covered
    assert not imu.interval(3.95, 4.2).covered
    assert not imu.interval(-0.1, 0.1).covered


def test_gravity_rotation_takes_the_specific_force_at_rest_to_up():
    R_true = Rotation.from_euler("xyz", [12.0, -7.0, 0.0], degrees=True).as_matrix()
    f_imu = R_true.T @ np.array([0.0, 0.0, 9.81])
    R = gravity_rotation(f_imu)
    np.testing.assert_allclose(R @ f_imu, [0.0, 0.0, 9.81], atol=1e-9)
    with pytest.raises(ValueError):
        gravity_rotation(np.zeros(3))


def test_enu_and_wgs84_round_trip_at_a_datum():
    from lidar_slam.geo import LocalEnu

    frame = LocalEnu(49.011, 8.424, 112.0)
    enu = np.array([[0.0, 0.0, 0.0], [1500.0, -800.0, 25.0], [-3.0, 7.0, -2.0]])
    llh = frame.to_wgs84(enu)
    np.testing.assert_allclose(llh[0], frame.datum, atol=1e-9)
    np.testing.assert_allclose(frame.from_wgs84(llh), enu, atol=1e-6)


def test_a_datum_given_as_numpy_scalars_converts_like_one_of_floats():
    from lidar_slam.geo import LocalEnu

    datum = (49.011, 8.424, 112.0)
    llh = np.array([[49.0111, 8.4245, 115.0]])
    exact = LocalEnu(*datum).from_wgs84(llh)
    np.testing.assert_allclose(LocalEnu(*np.array(datum)).from_wgs84(llh), exact, atol=1e-9)
