"""Lidar models (beam elevations, azimuth steps, noise) and poses between stamps."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------------------------
# Sensors


@dataclass(frozen=True)
class SensorModel:
    """A spinning multi-beam lidar: beam elevations (deg), azimuth steps per sweep, sweep rate."""

    name: str
    elevations_deg: tuple[float, ...]
    n_azimuth: int
    rate_hz: float
    max_range_m: float
    min_range_m: float = 1.0
    range_noise_m: float = 0.015
    dropout: float = 0.02
    mount_height_m: float = 1.73
    # Intrinsic calibration error: the lasers really point this much higher than the nominal
    # elevations the points are computed with (KITTI's HDL-64E has ~0.2 deg: kiss-icp's
    # `correct_kitti_scan` undoes 0.205 deg). Makes drift as real as the sensor's.
    elevation_error_deg: float = 0.0

    @property
    def period_s(self) -> float:
        """Duration of one sweep (s)."""
        return 1.0 / self.rate_hz

    def column_times_s(self) -> np.ndarray:
        """(A,) capture time of each azimuth column, seconds after the sweep start."""
        return np.arange(self.n_azimuth) * (self.period_s / self.n_azimuth)

    def directions(self, elevation_offset_deg: float = 0.0) -> np.ndarray:
        """(A, B, 3) unit beam directions in the sensor frame, column by column in firing order."""
        az = np.pi - 2.0 * np.pi * np.arange(self.n_azimuth) / self.n_azimuth
        el = np.radians(np.asarray(self.elevations_deg) + elevation_offset_deg)
        ce = np.cos(el)[None, :]
        return np.stack(
            [ce * np.cos(az)[:, None], ce * np.sin(az)[:, None], np.broadcast_to(
                np.sin(el)[None, :], (len(az), len(el)))], axis=-1)


def _hdl64_elevations() -> tuple[float, ...]:
    # Upper block 32 lasers at ~1/3 deg spacing, lower block 32 at ~1/2 deg, as the HDL-64E.
    upper = np.linspace(2.0, -8.33, 32)
    lower = np.linspace(-8.83, -24.8, 32)
    return tuple(np.r_[upper, lower].round(4))


SENSORS: dict[str, SensorModel] = {
    "hdl64": SensorModel("hdl64", _hdl64_elevations(), n_azimuth=2000, rate_hz=10.0,
                         max_range_m=120.0, range_noise_m=0.015, mount_height_m=1.73,
                         elevation_error_deg=0.2),
    "vlp16": SensorModel("vlp16", tuple(np.linspace(-15.0, 15.0, 16)), n_azimuth=1800,
                         rate_hz=10.0, max_range_m=100.0, range_noise_m=0.02,
                         mount_height_m=1.8),
    "os1-64": SensorModel("os1-64", tuple(np.linspace(16.6, -16.6, 64).round(4)), n_azimuth=1024,
                          rate_hz=10.0, max_range_m=120.0, min_range_m=0.5,
                          range_noise_m=0.015, mount_height_m=1.8),
}


def get_sensor(sensor: str | SensorModel) -> SensorModel:
    """A sensor model by name (hdl64, vlp16, os1-64) or the model itself."""
    if isinstance(sensor, SensorModel):
        return sensor
    if sensor not in SENSORS:
        raise ValueError(f"unknown sensor {sensor!r}; choose one of {sorted(SENSORS)}")
    return SENSORS[sensor]


# ----------------------------------------------------------------------------------------------
# Trajectory helpers


class PoseInterpolator:
    """T_world_lidar at any time: slerp/lerp between key poses, linear extrapolation past the
    ends."""

    def __init__(self, stamps_s: np.ndarray, poses: np.ndarray):
        self.t = np.asarray(stamps_s, dtype=float)
        self.poses = np.asarray(poses, dtype=float)
        if len(self.t) != len(self.poses) or len(self.t) == 0:
            raise ValueError("need as many stamps as poses, at least one")
        if np.any(np.diff(self.t) <= 0):
            raise ValueError("stamps must increase strictly")
        self.R = Rotation.from_matrix(self.poses[:, :3, :3])
        if len(self.t) > 1:
            self.dr = (self.R[:-1].inv() * self.R[1:]).as_rotvec()

    def __call__(self, times_s: np.ndarray) -> np.ndarray:
        """(N, 4, 4) poses at times_s (s)."""
        times_s = np.atleast_1d(np.asarray(times_s, dtype=float))
        out = np.tile(np.eye(4), (len(times_s), 1, 1))
        if len(self.t) == 1:
            out[:] = self.poses[0]
            return out
        i = np.clip(np.searchsorted(self.t, times_s, side="right") - 1, 0, len(self.t) - 2)
        s = (times_s - self.t[i]) / (self.t[i + 1] - self.t[i])
        out[:, :3, :3] = (self.R[i] * Rotation.from_rotvec(s[:, None] * self.dr[i])).as_matrix()
        p = self.poses[:, :3, 3]
        out[:, :3, 3] = p[i] + s[:, None] * (p[i + 1] - p[i])
        return out
