"""IMU and GNSS simulated from the same smooth trajectory that places the lidar points.

Frames: the world is the simulator's frame, gravity-aligned (z up, gravity (0, 0, -GRAVITY)),
and read as a local ENU frame (x east, y north, z up) whose origin is the GNSS datum. The IMU
frame is T_lidar_imu from the lidar frame; the GNSS lever arm is in the lidar frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, RotationSpline

from lidar_slam.geo import enu_to_wgs84
from lidar_slam.io.atomic import atomic_path

log = logging.getLogger(__name__)

GRAVITY_MPS2 = 9.81  # as gtsam's PreintegrationParams.MakeSharedU(9.81)
_DEG = np.pi / 180.0
_G0 = 9.80665  # the datasheet's g


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time noise of an IMU: white-noise densities, bias random walks, and the spread
    of the bias at the start (what a static calibration leaves)."""

    gyro_noise_density: float  # rad/s/sqrt(Hz)
    accel_noise_density: float  # m/s^2/sqrt(Hz)
    gyro_bias_random_walk: float  # rad/s^2/sqrt(Hz)
    accel_bias_random_walk: float  # m/s^3/sqrt(Hz)
    gyro_bias_sigma: float  # rad/s, initial bias
    accel_bias_sigma: float  # m/s^2, initial bias


# Bosch BMI088 data sheet (BST-BMI088-DS001): gyro rate noise density 0.014 deg/s/sqrt(Hz)
# (typical, as Bosch's forum quotes the sheet). UNVERIFIED against the sheet's own table (not
# found): gyro bias stability 2 deg/h, accelerometer noise density 175 ug/sqrt(Hz) (third-party
# code quotes it), zero-rate offset +-1 deg/s and zero-g offset +-20 mg before calibration. The
# sheet gives no random walk: it is taken as bias stability / sqrt(100 s) (gyro), and 0.04 mg /
# sqrt(100 s) (accelerometer). The initial biases are what a static calibration leaves, 0.1
# deg/s and 5 mg (1-sigma).
BMI088 = ImuNoise(
    gyro_noise_density=0.014 * _DEG,
    accel_noise_density=175e-6 * _G0,
    gyro_bias_random_walk=2.0 * _DEG / 3600.0 / 10.0,
    accel_bias_random_walk=0.04e-3 * _G0 / 10.0,
    gyro_bias_sigma=0.1 * _DEG,
    accel_bias_sigma=5e-3 * _G0,
)
NOISELESS = ImuNoise(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

# Near Karlsruhe, where KITTI was recorded: lat (deg), lon (deg), ellipsoidal height (m).
KARLSRUHE = (49.0110, 8.4240, 112.0)


@dataclass(frozen=True)
class ImuOptions:
    """The simulated IMU: rate (Hz), noise, T_lidar_imu (4x4, the IMU frame in the lidar's) and
    time_offset_s: the IMU's clock reads the lidar's minus this (s), so a run adds it back to
    every imu.csv stamp, as the config's imu.time_offset_s."""

    rate_hz: float = 200.0
    noise: ImuNoise = BMI088
    T_lidar_imu: np.ndarray = field(default_factory=lambda: np.eye(4))
    time_offset_s: float = 0.0


@dataclass(frozen=True)
class GnssOptions:
    """The simulated GNSS receiver: rate (Hz), 1-sigma white noise (m), the share of epochs
    lost and of multipath jumps (a 20-50 m horizontal offset on one epoch), the antenna lever
    arm (m, lidar frame) and the datum (lat deg, lon deg, height m) of the world's origin."""

    rate_hz: float = 1.0
    sigma_h_m: float = 1.5
    sigma_v_m: float = 3.0
    dropout: float = 0.05
    jump_fraction: float = 0.02
    jump_range_m: tuple[float, float] = (20.0, 50.0)
    lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    datum: tuple[float, float, float] = KARLSRUHE


# ----------------------------------------------------------------------------------------------
# The trajectory


class SmoothTrajectory:
    """T_world_lidar at any time, twice differentiable: a cubic spline through the key positions
    and scipy's RotationSpline through the key attitudes (both pass through every key pose, and
    extrapolate their end pieces). Called like PoseInterpolator: times (s) -> (N, 4, 4)."""

    def __init__(self, stamps_s: np.ndarray, poses: np.ndarray):
        t = np.asarray(stamps_s, dtype=float)
        poses = np.asarray(poses, dtype=float)
        if len(t) != len(poses) or len(t) < 2:
            raise ValueError("need as many stamps as poses, at least two")
        if np.any(np.diff(t) <= 0):
            raise ValueError("stamps must increase strictly")
        self.position = CubicSpline(t, poses[:, :3, 3], axis=0)
        self.attitude = RotationSpline(t, Rotation.from_matrix(poses[:, :3, :3]))

    def __call__(self, times_s: np.ndarray) -> np.ndarray:
        """(N, 4, 4) T_world_lidar at times_s (s)."""
        times_s = np.atleast_1d(np.asarray(times_s, dtype=float))
        out = np.tile(np.eye(4), (len(times_s), 1, 1))
        out[:, :3, :3] = self.attitude(times_s).as_matrix()
        out[:, :3, 3] = self.position(times_s)
        return out

    def imu_truth(self, times_s: np.ndarray, T_lidar_imu: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Noise-free gyro (rad/s) and specific force (m/s^2), both in the IMU frame, and the
        IMU's world velocity (m/s), each (N, 3), at times_s."""
        t = np.atleast_1d(np.asarray(times_s, dtype=float))
        R = self.attitude(t).as_matrix()
        w = self.attitude(t, 1)  # body (lidar) frame, as R^T dR/dt
        dw = self.attitude(t, 2)
        r = np.asarray(T_lidar_imu, dtype=float)[:3, 3]
        R_li = np.asarray(T_lidar_imu, dtype=float)[:3, :3]
        # The IMU sits at r in the lidar frame: its velocity and acceleration gain the rotation's.
        w_x_r = np.cross(w, r)
        v = self.position(t, 1) + np.einsum("nij,nj->ni", R, w_x_r)
        a_body = np.cross(dw, r) + np.cross(w, w_x_r)
        a = self.position(t, 2) + np.einsum("nij,nj->ni", R, a_body)
        f_world = a - np.array([0.0, 0.0, -GRAVITY_MPS2])
        R_wi = R @ R_li
        f_imu = np.einsum("nji,nj->ni", R_wi, f_world)
        gyro = w @ R_li  # R_li^T w
        return gyro, f_imu, v


# ----------------------------------------------------------------------------------------------
# IMU


@dataclass(frozen=True)
class ImuData:
    """Samples at stamps_s (n,): measured gyro/accel, their noise-free values, the biases in
    them and the IMU's world velocity, each (n, 3)."""

    stamps_s: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    gyro_true: np.ndarray
    accel_true: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray
    velocity_world: np.ndarray


def simulate_imu(traj: SmoothTrajectory, t0_s: float, t1_s: float, options: ImuOptions,
                 rng: np.random.Generator) -> ImuData:
    """Samples every 1/rate_hz from t0_s to t1_s: truth + bias (random walk) + white noise,
    discretised as sigma_d = density * sqrt(rate) and walk step = walk * sqrt(dt)."""
    n = int(np.floor((t1_s - t0_s) * options.rate_hz + 1e-9)) + 1
    t = t0_s + np.arange(n) / options.rate_hz
    gyro_true, accel_true, v = traj.imu_truth(t, options.T_lidar_imu)
    nz, dt = options.noise, 1.0 / options.rate_hz

    def biased(sigma0: float, walk: float, density: float, truth: np.ndarray):
        start = rng.normal(0.0, sigma0, 3) if sigma0 > 0 else np.zeros(3)
        steps = rng.normal(0.0, walk * np.sqrt(dt), (n, 3))
        steps[0] = 0.0
        bias = start + np.cumsum(steps, axis=0)
        white = rng.normal(0.0, density / np.sqrt(dt), (n, 3))
        return truth + bias + white, bias

    gyro, bg = biased(nz.gyro_bias_sigma, nz.gyro_bias_random_walk, nz.gyro_noise_density,
                      gyro_true)
    accel, ba = biased(nz.accel_bias_sigma, nz.accel_bias_random_walk, nz.accel_noise_density,
                       accel_true)
    return ImuData(t, gyro, accel, gyro_true, accel_true, bg, ba, v)


def write_imu(out: Path, imu: ImuData, time_offset_s: float = 0.0) -> None:
    """imu.csv (stamp_s,wx,wy,wz,ax,ay,az) on the IMU's clock, time_offset_s (s) behind the
    lidar's, and imu_truth.csv (noise-free values, biases and the world velocity of the IMU) on
    the lidar's."""
    with atomic_path(out / "imu.csv") as tmp:
        np.savetxt(tmp, np.c_[imu.stamps_s - time_offset_s, imu.gyro, imu.accel], delimiter=",",
                   fmt=["%.6f"] + ["%.9g"] * 6, header="stamp_s,wx,wy,wz,ax,ay,az", comments="")
    with atomic_path(out / "imu_truth.csv") as tmp:
        np.savetxt(tmp, np.c_[imu.stamps_s, imu.gyro_true, imu.accel_true, imu.gyro_bias,
                              imu.accel_bias, imu.velocity_world],
                   delimiter=",", fmt=["%.6f"] + ["%.12g"] * 15, comments="",
                   header="stamp_s,wx,wy,wz,ax,ay,az,bwx,bwy,bwz,bax,bay,baz,vx,vy,vz")


# ----------------------------------------------------------------------------------------------
# GNSS


@dataclass(frozen=True)
class GnssData:
    """Every epoch (n,): true antenna ENU (m) and WGS84, the fix reported (lat, lon, h), whether
    it was dropped, and the multipath jump (m, 0 if none)."""

    stamps_s: np.ndarray
    enu_true: np.ndarray
    wgs84_true: np.ndarray
    wgs84_fix: np.ndarray
    dropped: np.ndarray
    jump_m: np.ndarray
    options: GnssOptions


def simulate_gnss(traj: SmoothTrajectory, t0_s: float, t1_s: float, options: GnssOptions,
                  rng: np.random.Generator) -> GnssData:
    """Fixes on whole multiples of 1/rate_hz within [t0_s, t1_s]: the antenna's ENU position
    plus white noise (sigma_h each horizontal axis, sigma_v up), some dropped, some jumped."""
    k = np.arange(np.ceil(t0_s * options.rate_hz - 1e-9), np.floor(t1_s * options.rate_hz) + 1)
    t = k / options.rate_hz + 0.0  # no -0.0
    T = traj(t)
    enu = T[:, :3, 3] + T[:, :3, :3] @ np.asarray(options.lever_arm_m, dtype=float)
    n = len(t)
    noise = rng.normal(0.0, 1.0, (n, 3)) * [options.sigma_h_m, options.sigma_h_m,
                                            options.sigma_v_m]
    dropped = rng.random(n) < options.dropout
    jumped = (rng.random(n) < options.jump_fraction) & ~dropped
    size = rng.uniform(*options.jump_range_m, n)
    heading = rng.uniform(0.0, 2.0 * np.pi, n)
    offset = np.c_[size * np.cos(heading), size * np.sin(heading), np.zeros(n)]
    jump_m = np.where(jumped, size, 0.0)
    measured = enu + noise + offset * jumped[:, None]
    return GnssData(t, enu, enu_to_wgs84(enu, options.datum),
                    enu_to_wgs84(measured, options.datum), dropped, jump_m, options)


def write_gnss(out: Path, gnss: GnssData) -> None:
    """gnss.csv (stamp_s,lat_deg,lon_deg,alt_m,sigma_h_m,sigma_v_m; dropped epochs left out)
    and gnss_truth.csv (every epoch: true ENU and WGS84 of the antenna, dropped, jump_m)."""
    keep = ~gnss.dropped
    o = gnss.options
    sig = np.tile([o.sigma_h_m, o.sigma_v_m], (int(keep.sum()), 1))
    with atomic_path(out / "gnss.csv") as tmp:
        np.savetxt(tmp, np.c_[gnss.stamps_s[keep], gnss.wgs84_fix[keep], sig], delimiter=",",
                   fmt=["%.6f", "%.10f", "%.10f", "%.4f", "%.3f", "%.3f"], comments="",
                   header="stamp_s,lat_deg,lon_deg,alt_m,sigma_h_m,sigma_v_m")
    with atomic_path(out / "gnss_truth.csv") as tmp:
        np.savetxt(tmp, np.c_[gnss.stamps_s, gnss.enu_true, gnss.wgs84_true, gnss.dropped,
                              gnss.jump_m], delimiter=",", comments="",
                   fmt=["%.6f"] + ["%.6f"] * 3 + ["%.10f", "%.10f", "%.4f", "%d", "%.3f"],
                   header="stamp_s,east_m,north_m,up_m,lat_deg,lon_deg,alt_m,dropped,jump_m")
