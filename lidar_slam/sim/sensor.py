"""Lidar models (what each fires in a sweep, when; range limits, noise) and poses between
stamps."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------------------------
# Sensors


@dataclass(frozen=True)
class Sweep:
    """What a sensor fires in one sweep: times_s (G,) seconds after the sweep start, one sensor
    pose each; directions (G, B, 3) unit vectors in the sensor frame, the B beams fired at each
    of those instants: the nominal ones the points are computed with, and directions_true, the
    ones really fired (an intrinsic calibration error). A spinning lidar fires one column of
    B beams at a time; a non-repetitive one fires single beams (B = 1), each at its own time."""

    times_s: np.ndarray
    directions: np.ndarray
    directions_true: np.ndarray


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

    def sweep(self, frame: int = 0, seed: int = 0) -> Sweep:
        """The columns of every sweep (the same each frame: frame and seed are not used)."""
        d = self.directions()
        d_true = self.directions(self.elevation_error_deg) if self.elevation_error_deg else d
        return Sweep(self.column_times_s(), d, d_true)

    @property
    def pattern_text(self) -> str:
        """The firing pattern in words (a sequence's README)."""
        return f"{len(self.elevations_deg)} beams, {self.n_azimuth} azimuth steps"


_GOLDEN = (np.sqrt(5.0) - 1.0) / 2.0  # 0.618...: the most irrational step (Weyl sequence)
_SILVER = np.sqrt(2.0) - 1.0


@dataclass(frozen=True)
class NonRepetitiveModel:
    """A non-repetitive scanner (Livox Mid-360-like): points_per_s single beams, each fired at
    its own time, evenly through the sweep. The head turns once a sweep (clockwise seen from
    above, as the spinning models), starting each sweep at an azimuth that moves on by an
    irrational fraction of a turn (the motor is not locked to the frame boundaries), while the
    beam nods up and down the vertical FOV (a triangle wave) nods_per_sweep times a sweep, a
    number with an irrational fraction too. No two sweeps fire the same directions and the
    pattern fills the FOV over time; the points are on no rings and no columns. The real scan
    pattern is proprietary: this keeps its rate, FOV and those properties, not its shape.
    Deterministic from the seed (the phases) and the sweep's index."""

    name: str
    points_per_s: float
    rate_hz: float
    min_elevation_deg: float
    max_elevation_deg: float
    max_range_m: float
    min_range_m: float
    range_noise_m: float
    dropout: float = 0.02
    mount_height_m: float = 1.8
    # ~175 nods a sweep make the passes about as far apart in azimuth (360 / 2n deg) as the
    # points along a pass (2 n fov / N deg) with N = 20000, fov = 59 deg: ~1 deg either way.
    nods_per_sweep: float = 175.0 + _GOLDEN

    @property
    def period_s(self) -> float:
        """Duration of one sweep (s)."""
        return 1.0 / self.rate_hz

    @property
    def points_per_sweep(self) -> int:
        return int(round(self.points_per_s / self.rate_hz))

    def sweep(self, frame: int = 0, seed: int = 0) -> Sweep:
        """The single beams of sweep number frame (the sweep's index in the sensor's life),
        with phases from seed: (N,) times and (N, 1, 3) directions."""
        n = self.points_per_sweep
        az_phase, nod_phase = np.random.default_rng([seed, 40]).random(2)
        u = np.arange(n) / n  # fraction of the sweep
        az = np.pi - 2.0 * np.pi * (((frame * _SILVER + az_phase) % 1.0) + u)
        nod = ((frame * self.nods_per_sweep + nod_phase) % 1.0) + self.nods_per_sweep * u
        tri = 1.0 - np.abs(2.0 * (nod % 1.0) - 1.0)  # 0 -> 1 -> 0 once a nod
        el = np.radians(self.min_elevation_deg
                        + (self.max_elevation_deg - self.min_elevation_deg) * tri)
        d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)],
                     axis=-1)[:, None, :]
        return Sweep(u * self.period_s, d, d)

    @property
    def pattern_text(self) -> str:
        """The firing pattern in words (a sequence's README)."""
        return (f"non-repetitive, {self.points_per_sweep} points a sweep over elevations "
                f"{self.min_elevation_deg:g}..{self.max_elevation_deg:g} deg")


# The lidar models the simulator knows: a spinning multi-beam one or a non-repetitive one.
LidarModel = SensorModel | NonRepetitiveModel


def _hdl64_elevations() -> tuple[float, ...]:
    # Upper block 32 lasers at ~1/3 deg spacing, lower block 32 at ~1/2 deg, as the HDL-64E.
    upper = np.linspace(2.0, -8.33, 32)
    lower = np.linspace(-8.83, -24.8, 32)
    return tuple(np.r_[upper, lower].round(4))


# Figures are approximate, after the vendors' public datasheets (not re-checked against the
# sheets here): ranges at ~80 % reflectivity unless said, noise the 1-sigma range precision.
SENSORS: dict[str, LidarModel] = {
    "hdl64": SensorModel("hdl64", _hdl64_elevations(), n_azimuth=2000, rate_hz=10.0,
                         max_range_m=120.0, range_noise_m=0.015, mount_height_m=1.73,
                         elevation_error_deg=0.2),
    "vlp16": SensorModel("vlp16", tuple(np.linspace(-15.0, 15.0, 16)), n_azimuth=1800,
                         rate_hz=10.0, max_range_m=100.0, range_noise_m=0.02,
                         mount_height_m=1.8),
    "os1-64": SensorModel("os1-64", tuple(np.linspace(16.6, -16.6, 64).round(4)), n_azimuth=1024,
                          rate_hz=10.0, max_range_m=120.0, min_range_m=0.5,
                          range_noise_m=0.015, mount_height_m=1.8),
    # Hesai PandarXT32: 32 channels at 1 deg from -16 to +15 deg, 0.18 deg azimuth at 10 Hz
    # (2000 columns), range 0.05-120 m, accuracy ~1 cm (approximate).
    "xt32": SensorModel("xt32", tuple(float(e) for e in np.arange(15.0, -17.0, -1.0)),
                        n_azimuth=2000, rate_hz=10.0, max_range_m=120.0, min_range_m=0.05,
                        range_noise_m=0.01, mount_height_m=1.8),
    # Ouster OS0-128: 128 beams evenly over a 90 deg vertical FOV (+45..-45 deg, ~0.7 deg
    # apart), 1024 columns at 10 Hz; short range: ~50 m, from 0.3 m; precision ~1.5-5 cm
    # (approximate: 2 cm taken).
    "os0-128": SensorModel("os0-128", tuple(np.linspace(45.0, -45.0, 128).round(4)),
                           n_azimuth=1024, rate_hz=10.0, max_range_m=50.0, min_range_m=0.3,
                           range_noise_m=0.02, mount_height_m=1.8),
    # Livox Mid-360: non-repetitive, 360 deg x -7..+52 deg, 200,000 points/s (20,000 a 10 Hz
    # frame), 0.1-40 m (40 m at 10 % reflectivity), range precision ~2 cm (approximate).
    "mid360": NonRepetitiveModel("mid360", points_per_s=200_000.0, rate_hz=10.0,
                                 min_elevation_deg=-7.0, max_elevation_deg=52.0,
                                 max_range_m=40.0, min_range_m=0.1, range_noise_m=0.02),
}


def get_sensor(sensor: str | LidarModel) -> LidarModel:
    """A sensor model by name (a key of SENSORS) or the model itself."""
    if isinstance(sensor, (SensorModel, NonRepetitiveModel)):
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
