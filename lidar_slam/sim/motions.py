"""`simulate --motion`: a handheld walk, a legged robot's trot or a drone's flight round a loop
of a built world, written as a KITTI-layout sequence with its IMU / GNSS on the same trajectory.

Which worlds each motion goes through (MOTION_WORLDS): a walker and a legged robot anywhere; a
drone where there is room to fly (the plaza, the warehouse hall), never in corridors.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidar_slam.sim.handheld import (
    CLEARANCE_M,
    Burst,
    MotionStats,
    Site,
    build_site,
    clearance_m,
    handheld_motion,
    write_bursts,
)
from lidar_slam.sim.imu_gnss import GnssOptions, ImuOptions, SmoothTrajectory
from lidar_slam.sim.sensor import LidarModel, get_sensor

log = logging.getLogger(__name__)

MOTIONS = ("handheld", "legged", "drone")
MOTION_WORLDS = {"handheld": ("indoor", "outdoor", "office", "warehouse"),
                 "legged": ("indoor", "outdoor", "office", "warehouse"),
                 "drone": ("outdoor", "warehouse")}
# A drone takes corners at speed: its loop is rounded wider than a walker's.
CORNER_M = {"drone": 2.0}

_SPLINE = ("  The sensor moves along a cubic spline / RotationSpline through the motion's key\n"
           "  poses (100 Hz), the same trajectory the IMU and the GNSS are measured on.\n")


@dataclass(frozen=True)
class Motion:
    """A motion as simulate_motion writes it: the truth, its realised maxima, the README's
    account (without the clearance line) and, for a walk, its bursts."""

    trajectory: SmoothTrajectory
    stats: MotionStats
    text: str
    bursts: list[Burst] | None = None


def _maxima(st: MotionStats) -> str:
    return (f"realised maxima: body rate {st.max_rate_dps:.0f} deg/s, acceleration "
            f"{st.max_accel_mps2:.1f} m/s^2 (gravity not included),\n  specific force "
            f"{st.max_specific_force_mps2:.1f} m/s^2, speed {st.max_speed_mps:.2f} m/s.")


def make_motion(kind: str, site: Site, seed: int, duration_s: float) -> Motion:
    """The seeded motion of this kind round site's loop, duration_s (s) from t = 0."""
    if kind == "handheld":
        m = handheld_motion(site.path, site.ground, seed, duration_s)
        st = m.stats
        text = (f"These poses are the truth of a handheld walk ({site.kind}, seed {seed}):\n"
                f"  {st.distance_m:.0f} m walked, {st.laps:.2f} laps of a "
                f"{site.path.length_m:.0f} m loop, {st.n_bursts} quick looks / flicks / shakes;\n"
                f"  {_maxima(st)}\n" + _SPLINE +
                "bursts.csv: each quick move, kind (look: the arm swings about the body; flick,\n"
                "  shake: the wrist turns; jolt: the hand shifts and back), axis (0 roll / ahead,\n"
                "  1 pitch / left, 2 yaw / up), start and end (s), amount (deg, or m for a jolt),\n"
                "  freq_hz (a shake's).\n")
        return Motion(m.trajectory, st, text, m.bursts)
    if kind == "legged":
        from lidar_slam.sim.legged import BODY_HEIGHT_M, legged_motion

        m = legged_motion(site.path, site.ground, seed, duration_s)
        st, tr = m.stats, m.trot
        text = (f"These poses are the truth of a legged robot's trot ({site.kind}, seed {seed}):"
                f"\n  {st.distance_m:.0f} m walked, {st.laps:.2f} laps of a "
                f"{site.path.length_m:.0f} m loop in straight legs, {st.n_bursts} starts from\n"
                f"  standing, turns on the spot at {tr.turn_dps:.0f} deg/s; the lidar "
                f"{BODY_HEIGHT_M:.2f} m up, trot at {tr.step_hz:.1f} Hz: bounce "
                f"{100 * tr.bounce_m:.1f} cm,\n  roll / pitch {tr.roll_rad * 57.2958:.1f} / "
                f"{tr.pitch_rad * 57.2958:.1f} deg;\n  {_maxima(st)}\n" + _SPLINE)
        return Motion(m.trajectory, st, text)
    if kind == "drone":
        from lidar_slam.sim.drone import drone_motion

        m = drone_motion(site.path, site.ground, seed, duration_s, site.ceiling_m)
        st, fl = m.stats, m.flight
        text = (f"These poses are the truth of a multirotor's flight ({site.kind}, seed {seed}):\n"
                f"  {st.distance_m:.0f} m flown, {st.laps:.2f} laps of a "
                f"{site.path.length_m:.0f} m loop at {fl.heights_m.min():.1f}-"
                f"{fl.heights_m.max():.1f} m above the ground, {st.n_bursts} yaw spins;\n"
                f"  tilted along its thrust (acceleration + gravity + drag);\n  {_maxima(st)}\n"
                + _SPLINE)
        return Motion(m.trajectory, st, text)
    raise ValueError(f"unknown motion {kind!r}; choose one of {MOTIONS}")


def simulate_motion(out_dir: str | Path, motion: str, world_kind: str, seed: int,
                    duration_s: float, sensor: str | LidarModel = "os1-64",
                    imu: ImuOptions | None = None, gnss: GnssOptions | None = None,
                    on_scan: Callable[[int], None] | None = None, stamp: str = "start"
                    ) -> tuple[object, MotionStats]:
    """A motion of duration_s (s) through a seeded world, written as a KITTI-layout sequence
    (as simulate_sequence; sweep k from k / rate_hz, stamped at its start or end as stamp
    says, the truth in poses.txt) with imu.csv / gnss.csv from the same trajectory. Raises
    ValueError when the sensor comes within CLEARANCE_M of a surface. Returns (SimSummary,
    MotionStats)."""
    from lidar_slam.sim.sequence import write_sequence

    if motion not in MOTIONS:
        raise ValueError(f"unknown motion {motion!r}; choose one of {MOTIONS}")
    if world_kind not in MOTION_WORLDS[motion]:
        raise ValueError(f"--motion {motion} goes through {', '.join(MOTION_WORLDS[motion])}, "
                         f"not {world_kind}")
    sensor = get_sensor(sensor)
    t0 = time.perf_counter()
    site = build_site(world_kind, seed, sensor, CORNER_M.get(motion))
    m = make_motion(motion, site, seed, duration_s)
    n = int(round(duration_s * sensor.rate_hz))
    stamps = np.arange(n) / sensor.rate_hz
    gap = clearance_m(site.world, m.trajectory, 0.0, n / sensor.rate_hz)
    if gap.min() < CLEARANCE_M:
        raise ValueError(f"{motion} {world_kind} seed {seed}: the sensor comes within "
                         f"{gap.min():.2f} m of a surface (< {CLEARANCE_M} m)")
    world_s = time.perf_counter() - t0
    text = m.text.replace("\n  The sensor moves", f" Closest surface {gap.min():.2f} m.\n"
                          "  The sensor moves", 1)
    summary = write_sequence(out_dir, site.world, sensor, m.trajectory, stamps,
                             m.trajectory(stamps), seed, np.eye(4), world_s, on_scan, imu,
                             gnss, motion=text, stamp=stamp)
    if m.bursts is not None:
        write_bursts(Path(out_dir) / "bursts.csv", m.bursts)
    log.info("%s %s seed %d: %s", motion, world_kind, seed, m.stats)
    return summary, m.stats


def simulate_handheld(out_dir: str | Path, world_kind: str, seed: int, duration_s: float,
                      sensor: str | LidarModel = "os1-64", imu: ImuOptions | None = None,
                      gnss: GnssOptions | None = None,
                      on_scan: Callable[[int], None] | None = None, stamp: str = "start"
                      ) -> tuple[object, MotionStats]:
    """simulate_motion of a handheld walk."""
    return simulate_motion(out_dir, "handheld", world_kind, seed, duration_s, sensor, imu, gnss,
                           on_scan, stamp)
