"""Legged motion: a quadruped trotting laps of a loop with the lidar on its back, ~0.5 m up.

The robot walks the loop's straight legs (LoopPath.waypoints) at 1.2-1.5 m/s, stopping at each
corner to turn on the spot (70-100 deg/s), and now and then in the middle of a leg; it starts and
stops abruptly (0.35-0.5 s from standing to walking speed). While its legs move (walking or
turning) the trot shakes the body: a 2-3 Hz vertical bounce of 1.5-2.5 cm, a roll at half the
step rate and a pitch at the step rate of 1.5-3 deg, with a stride-to-stride jitter. Sampled at
KEY_RATE_HZ and splined by imu_gnss.SmoothTrajectory, the truth for the points and the IMU alike.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from lidar_slam.sim.handheld import KEY_RATE_HZ, LoopPath, MotionStats, _smoothstep, motion_stats
from lidar_slam.sim.imu_gnss import SmoothTrajectory

MAX_RATE_DPS = 120.0
MAX_ACCEL_MPS2 = 15.0  # kinematic: |d2p/dt2|, gravity not included
BODY_HEIGHT_M = 0.55  # the lidar above the floor (on a ~0.5 m body)


@dataclass(frozen=True)
class Trot:
    """The robot: walking speed (m/s), start / stop ramp (s), turn rate (deg/s), step rate (Hz),
    bounce (m), roll and pitch amplitudes (rad), chance of a stop mid-leg, standing (s) first."""

    speed_mps: float
    ramp_s: float
    turn_dps: float
    step_hz: float
    bounce_m: float
    roll_rad: float
    pitch_rad: float
    pause_chance: float
    stand_s: float = 1.0

    @staticmethod
    def draw(rng: np.random.Generator) -> Trot:
        return Trot(float(rng.uniform(1.2, 1.5)), float(rng.uniform(0.35, 0.5)),
                    float(rng.uniform(70.0, 100.0)), float(rng.uniform(2.0, 3.0)),
                    float(rng.uniform(0.015, 0.025)), float(np.radians(rng.uniform(1.5, 3.0))),
                    float(np.radians(rng.uniform(1.5, 3.0))), 0.3)


@dataclass(frozen=True)
class Phase:
    """One piece of the plan: "stand", "walk" (from a to b, xy) or "turn" (heading a to b)."""

    kind: str
    t0_s: float
    t1_s: float
    a: np.ndarray
    b: np.ndarray


def plan(path: LoopPath, trot: Trot, duration_s: float, rng: np.random.Generator) -> list[Phase]:
    """Stand, then walk leg after leg of the loop (laps until duration_s), turning on the spot
    at each corner, pausing mid-leg now and then."""
    wp = path.waypoints
    heading = float(np.arctan2(*(wp[1] - wp[0])[::-1]))
    t = trot.stand_s
    phases = [Phase("stand", -np.inf, t, wp[0], wp[0])]
    k = 0
    while t < duration_s + 1.0:
        a, b = wp[k % (len(wp) - 1)], wp[k % (len(wp) - 1) + 1]
        want = float(np.arctan2(*(b - a)[::-1]))
        turn = (want - heading + np.pi) % (2 * np.pi) - np.pi
        if abs(turn) > 1e-3:
            dt = 1.875 * abs(turn) / np.radians(trot.turn_dps)  # smoothstep's peak rate
            phases.append(Phase("turn", t, t + dt, np.array([heading]),
                                np.array([heading + turn])))
            heading, t = heading + turn, t + dt
        stops = [a]
        if rng.random() < trot.pause_chance and np.linalg.norm(b - a) > 4.0:
            stops.append(a + (b - a) * float(rng.uniform(0.3, 0.7)))
        stops.append(b)
        for p, q in zip(stops[:-1], stops[1:]):
            dt = float(np.linalg.norm(q - p)) / trot.speed_mps + trot.ramp_s
            phases.append(Phase("walk", t, t + dt, p, q))
            t += dt
            pause = float(rng.uniform(0.3, 1.2)) if q is not b else float(rng.uniform(0.1, 0.3))
            phases.append(Phase("stand", t, t + pause, q, q))
            t += pause
        k += 1
    return phases


def _walked(u: np.ndarray, ramp: float) -> np.ndarray:
    """Fraction of a leg walked at normalised time u in [0, 1] when the speed rises and falls
    as smoothsteps over ramp (a fraction of the leg's time): the integral of the speed."""
    grid = np.linspace(0.0, 1.0, 2001)
    v = _smoothstep(grid / ramp) * _smoothstep((1.0 - grid) / ramp)
    s = np.r_[0.0, np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(grid))]
    return np.interp(u, grid, s / s[-1])


def legged_poses(t: np.ndarray, phases: list[Phase], trot: Trot,
                 ground: Callable[[np.ndarray], np.ndarray], rng: np.random.Generator
                 ) -> np.ndarray:
    """(N, 4, 4) T_world_lidar of the robot's back at times t (s, evenly spaced, within the
    plan)."""
    xy = np.zeros((len(t), 2))
    yaw = np.zeros(len(t))
    moving = np.zeros(len(t))
    first = next(p for p in phases if p.kind == "walk")
    heading = float(np.arctan2(*(first.b - first.a)[::-1]))
    here = phases[0].a
    for ph in phases:
        i = (t >= ph.t0_s) & (t < ph.t1_s)
        u = (t[i] - ph.t0_s) / (ph.t1_s - ph.t0_s) if ph.kind != "stand" else None
        if ph.kind == "turn":
            xy[i], moving[i] = here, 1.0
            yaw[i] = ph.a[0] + (ph.b[0] - ph.a[0]) * _smoothstep(u)
            heading = float(ph.b[0])
            continue
        yaw[i] = heading
        if ph.kind == "walk":
            ramp = trot.ramp_s / (ph.t1_s - ph.t0_s)
            xy[i], moving[i] = ph.a + np.outer(_walked(u, ramp), ph.b - ph.a), 1.0
        else:
            xy[i] = ph.a
        here = ph.b
    # Legs settle and start within ~0.15 s: the trot's amplitude follows `moving`, smoothed.
    gait = np.clip(gaussian_filter1d(moving, 0.08 * KEY_RATE_HZ), 0.0, 1.0)
    jitter = gaussian_filter1d(rng.normal(0.0, 1.0, len(t)), 0.3 * KEY_RATE_HZ)
    jitter *= 0.6 / max(float(np.std(jitter)), 1e-9)  # rad of step phase, slowly wandering
    phase = 2 * np.pi * trot.step_hz * t + jitter
    z = ground(xy) + BODY_HEIGHT_M + gait * trot.bounce_m * np.cos(phase)
    roll = gait * trot.roll_rad * np.sin(phase / 2)
    pitch = gait * trot.pitch_rad * np.sin(phase + 0.7)
    T = np.tile(np.eye(4), (len(t), 1, 1))
    T[:, :2, 3], T[:, 2, 3] = xy, z
    T[:, :3, :3] = Rotation.from_euler("ZYX", np.c_[yaw, pitch, roll]).as_matrix()
    return T


@dataclass(frozen=True)
class LeggedMotion:
    trajectory: SmoothTrajectory
    trot: Trot
    phases: list[Phase]
    stats: MotionStats


def legged_motion(path: LoopPath, ground: Callable[[np.ndarray], np.ndarray], seed: int,
                  duration_s: float) -> LeggedMotion:
    """A seeded trot of duration_s (s, from t = 0, standing first) round path; raises
    ValueError if the realised rate or acceleration passes MAX_RATE_DPS / MAX_ACCEL_MPS2."""
    rng = np.random.default_rng([seed, 60])
    trot = Trot.draw(rng)
    phases = plan(path, trot, duration_s, rng)
    keys = np.arange(-1.0, duration_s + 1.0, 1.0 / KEY_RATE_HZ)
    traj = SmoothTrajectory(keys, legged_poses(keys, phases, trot, ground, rng))
    starts = sum(p.kind == "walk" for p in phases if p.t0_s < duration_s)
    stats = motion_stats(traj, 0.0, duration_s, path.length_m, starts)[0]
    if stats.max_rate_dps > MAX_RATE_DPS or stats.max_accel_mps2 > MAX_ACCEL_MPS2:
        raise ValueError(f"legged motion, seed {seed}: {stats.max_rate_dps:.0f} deg/s, "
                         f"{stats.max_accel_mps2:.1f} m/s^2 past the limits ({MAX_RATE_DPS:.0f}, "
                         f"{MAX_ACCEL_MPS2:.0f})")
    return LeggedMotion(traj, trot, phases, stats)
