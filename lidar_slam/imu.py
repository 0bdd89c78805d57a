"""gtsam's IMU preintegration between any two instants: the one home for the front-end (IMU
deskew and prediction) and the back-end (IMU factors between keyframes).

Conventions: the samples are in the IMU frame (angular rate rad/s, specific force m/s^2, gravity
included: ~+9.81 on z at rest with z up), on the scans' clock (io.inertial_input applied the
config's time offset). The world of every IMU state is gravity-aligned with z up, gravity
(0, 0, -GRAVITY_MPS2): gtsam's PreintegrationCombinedParams.MakeSharedU. Between two sample
stamps the measurement is the mean of the two samples (trapezoid), and an interval's ends
between samples are linearly interpolated: the convention the simulator's IMU is checked with
(tests/test_sim_imu.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from lidar_slam.config import ImuConfig
from lidar_slam.geometry import matrix_from_rotvec
from lidar_slam.io.imu_gnss import GAP_PERIODS, ImuSamples

GRAVITY_MPS2 = 9.81
# Covariance of the integration of velocity into position (m^2/s^2 * s), gtsam's own knob for
# the error of the discrete integration; small for 100-400 Hz samples.
INTEGRATION_COVARIANCE = 1e-8
# Covariance of the bias used while preintegrating (gtsam's biasAccOmegaInt), when the params
# have it.
BIAS_ACC_OMEGA_INT = 1e-5


def combined_params(cfg: ImuConfig) -> gtsam.PreintegrationCombinedParams:
    """gtsam's parameters for PreintegratedCombinedMeasurements from the config's noise densities
    and bias random walks (continuous time; gtsam takes their squares as covariances)."""
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(GRAVITY_MPS2)
    p.setGyroscopeCovariance(np.eye(3) * cfg.gyro_noise_density ** 2)
    p.setAccelerometerCovariance(np.eye(3) * cfg.accel_noise_density ** 2)
    p.setIntegrationCovariance(np.eye(3) * INTEGRATION_COVARIANCE)
    p.setBiasOmegaCovariance(np.eye(3) * cfg.gyro_bias_random_walk ** 2)
    p.setBiasAccCovariance(np.eye(3) * cfg.accel_bias_random_walk ** 2)
    if hasattr(p, "setBiasAccOmegaInit"):  # gtsam 4.2 names it so; 4.3 has no setter
        p.setBiasAccOmegaInit(np.eye(6) * BIAS_ACC_OMEGA_INT)
    return p


@dataclass(frozen=True)
class Interval:
    """The measurements over [t0, t1] as gtsam integrates them: per step its duration (s) and
    the mean angular rate and specific force over it (IMU frame). covered: whether the samples
    span the whole interval (ends outside them hold the first / last sample)."""

    dt_s: np.ndarray
    gyro_radps: np.ndarray
    accel_mps2: np.ndarray
    covered: bool


class ImuStream:
    """IMU samples with interpolation at any instant and preintegration between any two."""

    def __init__(self, samples: ImuSamples):
        if len(samples) < 2:
            raise ValueError("an IMU stream needs at least two samples")
        self.samples = samples
        self.t = np.asarray(samples.stamp_s, dtype=np.float64)
        self._values = np.c_[samples.gyro_radps, samples.accel_mps2].astype(np.float64)
        # a step between samples longer than this is a gap (GAP_PERIODS median periods)
        self.gap_s = GAP_PERIODS * float(np.median(np.diff(self.t)))
        # interval()'s last answers: the front-end asks for the interval between two scans,
        # and its IMU check for the same one right after
        self._intervals: dict[tuple[float, float], Interval] = {}

    @property
    def start_s(self) -> float:
        return float(self.t[0])

    @property
    def end_s(self) -> float:
        return float(self.t[-1])

    def at(self, times_s: np.ndarray) -> np.ndarray:
        """(N, 6) angular rate and specific force linearly interpolated at times_s (held past
        the ends)."""
        times_s = np.atleast_1d(np.asarray(times_s, dtype=np.float64))
        # One search for all six columns (np.interp per column cost ~1 ms per scan).
        i = np.clip(np.searchsorted(self.t, times_s, side="right") - 1, 0, len(self.t) - 2)
        w = np.clip((times_s - self.t[i]) / (self.t[i + 1] - self.t[i]), 0.0, 1.0)[:, None]
        return self._values[i] * (1.0 - w) + self._values[i + 1] * w

    def knots(self, t0_s: float, t1_s: float) -> np.ndarray:
        """The step boundaries between t0_s and t1_s (t1_s >= t0_s): both ends and the sample
        stamps inside."""
        if t1_s < t0_s:
            raise ValueError(f"interval ends before it starts: {t0_s} > {t1_s}")
        i0, i1 = np.searchsorted(self.t, [t0_s, t1_s], side="right")
        knots = np.concatenate(([t0_s], self.t[i0:i1], [t1_s]))  # (np.r_: 3x the time)
        knots = knots[np.concatenate(([True], np.diff(knots) > 0))]  # a sample exactly at t0_s
        return knots if len(knots) >= 2 else np.array([t0_s, t1_s])

    def interval(self, t0_s: float, t1_s: float) -> Interval:
        """The steps between t0_s and t1_s (t1_s >= t0_s): the sample stamps inside, with the
        interpolated measurement at both ends (read-only arrays: the last few are kept)."""
        key = (float(t0_s), float(t1_s))
        iv = self._intervals.get(key)
        if iv is None:
            knots = self.knots(t0_s, t1_s)
            values = self.at(knots)
            mean = 0.5 * (values[:-1] + values[1:])
            covered = bool(self.t[0] <= t0_s and t1_s <= self.t[-1])
            iv = Interval(np.diff(knots), mean[:, :3], mean[:, 3:], covered)
            for a in (iv.dt_s, iv.gyro_radps, iv.accel_mps2):
                a.flags.writeable = False
            if len(self._intervals) >= 4:
                del self._intervals[next(iter(self._intervals))]
            self._intervals[key] = iv
        return iv

    def preintegrate(self, t0_s: float, t1_s: float, params: gtsam.PreintegrationCombinedParams,
                     bias: gtsam.imuBias.ConstantBias | None = None
                     ) -> gtsam.PreintegratedCombinedMeasurements:
        """gtsam's preintegrated measurements from t0_s to t1_s about `bias` (zero if None)."""
        pim = gtsam.PreintegratedCombinedMeasurements(
            params, gtsam.imuBias.ConstantBias() if bias is None else bias)
        iv = self.interval(t0_s, t1_s)
        for dt, w, a in zip(iv.dt_s.tolist(), iv.gyro_radps, iv.accel_mps2):
            if dt > 0:
                pim.integrateMeasurement(a, w, dt)
        return pim


def predict_pose(pim: gtsam.PreintegratedCombinedMeasurements, T_world_imu: np.ndarray,
                 v_world: np.ndarray, bias6: np.ndarray) -> np.ndarray:
    """T_world_imu (4x4) at the end of `pim` from the state at its start and the bias it is
    corrected about (6 values in gtsam's ConstantBias.vector() order: accel, then gyro)."""
    bias = bias_from_vector(bias6)
    start = gtsam.NavState(gtsam.Pose3(np.asarray(T_world_imu, dtype=float)),
                           np.asarray(v_world, dtype=float))
    return pim.predict(start, bias).pose().matrix()


def predict_poses_along(stream: ImuStream, t0_s: float, times_s: list[float],
                        params: gtsam.PreintegrationCombinedParams, T_world_imu: np.ndarray,
                        v_world: np.ndarray, bias6: np.ndarray) -> list[np.ndarray]:
    """T_world_imu (4x4) at each of times_s (increasing, after t0_s) from the state at t0_s,
    the IMU integrated once through them about the bias (6 values, accel then gyro). A sample
    step that a time cuts is integrated in its two parts (its mean rate over each), also for the
    later times, so they differ from predict_pose on stream.preintegrate(t0_s, t) for each t
    alone by ~1e-6 m (0.1 s of a shaky hand-held walk)."""
    bias = bias_from_vector(bias6)
    start = gtsam.NavState(gtsam.Pose3(np.asarray(T_world_imu, dtype=float)),
                           np.asarray(v_world, dtype=float))
    pim, t_at, out = gtsam.PreintegratedCombinedMeasurements(params, bias), t0_s, []
    for t in times_s:
        if t > t_at:
            iv = stream.interval(t_at, t)
            for dt, w, a in zip(iv.dt_s.tolist(), iv.gyro_radps, iv.accel_mps2):
                if dt > 0:
                    pim.integrateMeasurement(a, w, dt)
            t_at = t
        out.append(pim.predict(start, bias).pose().matrix())
    return out


def bias_from_vector(bias6: np.ndarray) -> gtsam.imuBias.ConstantBias:
    """gtsam's bias from 6 values in its vector() order: accel, then gyro."""
    b = np.asarray(bias6, dtype=float)
    return gtsam.imuBias.ConstantBias(b[:3], b[3:])


def closest_rotation(H: np.ndarray) -> np.ndarray:
    """The rotation R maximising tr(R^T H) (gtsam's Rot3.ClosestTo: the Kabsch solution)."""
    return np.asarray(gtsam.Rot3.ClosestTo(np.asarray(H, dtype=float)).matrix(), dtype=np.float64)


def gravity_rotation(specific_force: np.ndarray) -> np.ndarray:
    """R_world_imu (3x3), the smallest rotation taking the direction of specific_force (IMU frame)
    to +z of a z-up world."""
    f = np.asarray(specific_force, dtype=np.float64)
    norm = float(np.linalg.norm(f))
    if not np.isfinite(norm) or norm < 1e-6:
        raise ValueError("no specific force to align with gravity")
    # NumPy (geometry), not scipy.spatial: its import costs a run ~28 MB of RSS and 0.3 s
    f = f / norm
    axis = np.cross(f, [0.0, 0.0, 1.0])
    s, c = float(np.linalg.norm(axis)), float(f[2])
    if s < 1e-12:  # along z already, or upside down: half a turn about x
        return np.eye(3) if c > 0 else matrix_from_rotvec([np.pi, 0.0, 0.0])
    return matrix_from_rotvec(axis / s * np.arctan2(s, c))
