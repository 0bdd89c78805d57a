"""Drone motion: a multirotor flying laps of a loop at 1.5-6 m, the lidar on its frame.

The loop's xy path is flown at a speed that wanders between ~1.5 and 3.5 m/s; the height above
the ground climbs and descends between 1.5 m and 6 m (under a ceiling: 1 m below it), held for a
while at each level; the yaw follows the path plus yaw spins (a full turn or a half turn at
50-85 deg/s). The attitude is a multirotor's: its thrust axis (body z) points along the
acceleration the rotors must give, a - g plus a drag term against the velocity, so the frame
banks into turns and pitches into accelerations and at cruise. It hovers at its start height
first (at rest: the IMU's initial state is known). Sampled at KEY_RATE_HZ and splined by
imu_gnss.SmoothTrajectory, the truth for the points and the IMU alike.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.ndimage import gaussian_filter1d

from lidar_slam.sim.handheld import KEY_RATE_HZ, LoopPath, MotionStats, _smoothstep, motion_stats
from lidar_slam.sim.imu_gnss import GRAVITY_MPS2, SmoothTrajectory

MAX_RATE_DPS = 150.0
MAX_ACCEL_MPS2 = 6.0  # kinematic: |d2p/dt2|, gravity not included
MIN_HEIGHT_M, MAX_HEIGHT_M = 1.5, 6.0
LATERAL_MPS2 = 2.0  # the corners are taken at most this hard
DRAG_PER_S = 0.35  # rotor drag / mass: the tilt it takes to hold a speed


@dataclass(frozen=True)
class Flight:
    """The flight: cruise speed (m/s) and its swing (m/s, period s); the heights (m) held and
    the times (s) they are reached; yaw spins (start s, duration s, angle rad); hover (s) first,
    then ramp (s) to cruise."""

    speed_mps: float
    speed_swing_mps: float
    speed_period_s: float
    height_times_s: np.ndarray
    heights_m: np.ndarray
    spins: tuple[tuple[float, float, float], ...]
    hover_s: float = 1.5
    ramp_s: float = 2.5

    @staticmethod
    def draw(rng: np.random.Generator, duration_s: float, top_m: float) -> Flight:
        """Heights held 2-5 s, climbs / descents of 2-4 s between them; a spin every 6-12 s."""
        times, heights = [-10.0, 2.0], [MIN_HEIGHT_M + 0.5] * 2
        t = 2.0
        while t < duration_s + 5.0:
            t += float(rng.uniform(2.0, 4.0))  # the climb or descent
            times.append(t)
            heights.append(float(rng.uniform(MIN_HEIGHT_M, top_m)))
            t += float(rng.uniform(2.0, 5.0))  # held
            times.append(t)
            heights.append(heights[-1])
        spins, t = [], float(rng.uniform(4.0, 8.0))
        while t < duration_s:
            angle = float(rng.choice([-1.0, 1.0]) * rng.choice([np.pi, 2 * np.pi]))
            dt = 1.875 * abs(angle) / np.radians(rng.uniform(50.0, 85.0))
            spins.append((t, dt, angle))
            t += dt + float(rng.uniform(6.0, 12.0))
        return Flight(float(rng.uniform(2.2, 2.8)), float(rng.uniform(0.5, 0.8)),
                      float(rng.uniform(8.0, 14.0)), np.array(times), np.array(heights),
                      tuple(spins))


def _held_steps(t: np.ndarray, times: np.ndarray, values: np.ndarray) -> np.ndarray:
    """values at times, smoothstep in between (C2): a height held, then changed, then held."""
    j = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    u = (t - times[j]) / (times[j + 1] - times[j])
    return values[j] + (values[j + 1] - values[j]) * _smoothstep(u)


def thrust_attitude(acc: np.ndarray, vel: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """(N, 3, 3) R_world_body of a multirotor: body z along a + g + drag * v (the specific force
    its rotors give), body x the yaw direction projected off it."""
    z = acc + [0.0, 0.0, GRAVITY_MPS2] + DRAG_PER_S * vel
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    f = np.c_[np.cos(yaw), np.sin(yaw), np.zeros(len(yaw))]
    x = f - np.sum(f * z, axis=1, keepdims=True) * z
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    return np.stack([x, np.cross(z, x), z], axis=2)


def drone_poses(t: np.ndarray, path: LoopPath, ground: Callable[[np.ndarray], np.ndarray],
                flight: Flight) -> np.ndarray:
    """(N, 4, 4) T_world_lidar of the drone at times t (s, evenly spaced)."""
    ramp = _smoothstep((t - flight.hover_s) / flight.ramp_s)
    wanted = ramp * (flight.speed_mps + flight.speed_swing_mps
                     * np.sin(2 * np.pi * (t - flight.hover_s) / flight.speed_period_s))
    # Slow for the corners (lateral acceleration v^2 kappa within LATERAL_MPS2), looking 1 s
    # ahead, the slowed speed smoothed so that braking stays gentle.
    s_grid = np.arange(0.0, path.length_m, 0.1)
    d1, d2 = path.xy(s_grid, 1), path.xy(s_grid, 2)
    kappa = np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
    v_max = np.sqrt(LATERAL_MPS2 / np.maximum(kappa, 1e-6))
    dt = float(t[1] - t[0])
    s = np.r_[0.0, np.cumsum(wanted[1:] * dt)]
    for _ in range(3):
        ahead = (s[:, None] + np.arange(0.0, 3.0, 0.25)[None, :]) % path.length_m
        limit = np.interp(ahead, s_grid, v_max, period=path.length_m).min(axis=1)
        speed = gaussian_filter1d(np.minimum(wanted, limit), 0.6 / dt, mode="nearest")
        speed = np.where(t < flight.hover_s, 0.0, speed) * ramp
        s = np.r_[0.0, np.cumsum(0.5 * (speed[1:] + speed[:-1]) * dt)]
    xy = path.xy(s)
    tangent = path.xy(s, 1)
    yaw = np.unwrap(np.arctan2(tangent[:, 1], tangent[:, 0]))
    for t0, dt, angle in flight.spins:
        yaw += angle * _smoothstep((t - t0) / dt)
    z = ground(xy) + _held_steps(t, flight.height_times_s, flight.heights_m)
    p = np.c_[xy, z]
    spline = CubicSpline(t, p, axis=0)
    T = np.tile(np.eye(4), (len(t), 1, 1))
    T[:, :3, :3] = thrust_attitude(spline(t, 2), spline(t, 1), yaw)
    T[:, :3, 3] = p
    return T


@dataclass(frozen=True)
class DroneMotion:
    trajectory: SmoothTrajectory
    flight: Flight
    stats: MotionStats


def drone_motion(path: LoopPath, ground: Callable[[np.ndarray], np.ndarray], seed: int,
                 duration_s: float, ceiling_m: float | None = None) -> DroneMotion:
    """A seeded flight of duration_s (s, from t = 0, hovering first) round path, at most 1 m
    under ceiling_m (m above the ground, None outdoors); spins slowed until the realised rate
    stays within MAX_RATE_DPS; raises ValueError if it or the acceleration still passes its
    limit."""
    rng = np.random.default_rng([seed, 70])
    top = MAX_HEIGHT_M if ceiling_m is None else min(MAX_HEIGHT_M, ceiling_m - 1.0)
    flight = Flight.draw(rng, duration_s, top)
    keys = np.arange(-1.0, duration_s + 1.0, 1.0 / KEY_RATE_HZ)
    for _ in range(10):  # spins on top of a turn can pass the rate limit: slow them down
        traj = SmoothTrajectory(keys, drone_poses(keys, path, ground, flight))
        stats = motion_stats(traj, 0.0, duration_s, path.length_m, len(flight.spins))[0]
        if stats.max_rate_dps <= MAX_RATE_DPS:
            break
        slower = 1.05 * stats.max_rate_dps / MAX_RATE_DPS
        flight = dataclasses.replace(flight, spins=tuple((t0, dt * slower, a)
                                                         for t0, dt, a in flight.spins))
    if stats.max_rate_dps > MAX_RATE_DPS or stats.max_accel_mps2 > MAX_ACCEL_MPS2:
        raise ValueError(f"drone motion, seed {seed}: {stats.max_rate_dps:.0f} deg/s, "
                         f"{stats.max_accel_mps2:.1f} m/s^2 past the limits ({MAX_RATE_DPS:.0f}, "
                         f"{MAX_ACCEL_MPS2:.0f})")
    return DroneMotion(traj, flight, stats)
