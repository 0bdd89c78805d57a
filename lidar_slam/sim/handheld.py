"""Handheld motion: a person walking laps of a loop with the lidar in the hand, through a built
interior or a street/plaza world, with quick looks, wrist flicks and shakes.

The motion is analytic (a periodic spline path walked at a varying speed, step bobbing and sway,
the hand ahead of the body, smooth C2 bursts of rotation), sampled at KEY_RATE_HZ and splined
by imu_gnss.SmoothTrajectory: that spline is the truth, for the points, the IMU and the GNSS
alike. Bursts that would push the realised body rate past MAX_RATE_DPS or the acceleration past
MAX_ACCEL_MPS2 are slowed until they do not.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from lidar_slam.io.atomic import write_text_atomic
from lidar_slam.sim.imu_gnss import SmoothTrajectory
from lidar_slam.sim.sensor import LidarModel
from lidar_slam.sim.world import World, WorldParams, build_world

log = logging.getLogger(__name__)

MAX_RATE_DPS = 180.0
MAX_ACCEL_MPS2 = 10.0  # kinematic: |d2p/dt2|, gravity not included
CLEARANCE_M = 0.5
KEY_RATE_HZ = 100.0
WORLDS = ("indoor", "outdoor", "office", "warehouse")


def _smoothstep(u: np.ndarray) -> np.ndarray:
    """0 -> 1 with zero first and second derivatives at both ends (C2 when pieced)."""
    u = np.clip(u, 0.0, 1.0)
    return u**3 * (10.0 - 15.0 * u + 6.0 * u**2)


# ----------------------------------------------------------------------------------------------
# The path


@dataclass(frozen=True)
class LoopPath:
    """A closed walking path: xy (m) as a periodic cubic spline of the arc length s (m)."""

    spline: CubicSpline
    length_m: float
    # The polygon's corners in walking order from the start point, closed (first = last = the
    # start): for a motion that walks straight legs and turns on the spot.
    waypoints: np.ndarray | None = None

    @staticmethod
    def rectangle(length_m: float, width_m: float, corner_m: float, clockwise: bool,
                  start_m: float) -> LoopPath:
        """The rectangle (0, 0)-(length_m, width_m), corners rounded over ~corner_m, walked
        from start_m along it (counter-clockwise from the origin unless clockwise)."""
        corners = np.array([[0.0, 0.0], [length_m, 0.0], [length_m, width_m], [0.0, width_m]])
        return LoopPath.polygon(corners, corner_m, clockwise, start_m)

    @staticmethod
    def polygon(corners: np.ndarray, corner_m: float, clockwise: bool, start_m: float
                ) -> LoopPath:
        """The closed polygon through corners (K, 2) (m, in order), corners rounded over
        ~corner_m, walked from start_m along it (in the corners' order unless clockwise)."""
        step = 0.02
        corners = np.r_[corners, corners[:1]]
        seg = np.linalg.norm(np.diff(corners, axis=0), axis=1)
        s = np.arange(0.0, seg.sum(), step)
        arc = np.r_[0.0, np.cumsum(seg)]
        xy = np.c_[np.interp(s, arc, corners[:, 0]), np.interp(s, arc, corners[:, 1])]
        xy = np.roll(xy, -int(round(start_m / step)) % len(xy), axis=0)
        if clockwise:
            xy = xy[::-1]
        xy = gaussian_filter1d(xy, corner_m / step, axis=0, mode="wrap")
        xy = xy[:: int(round(0.25 / step))]
        closed = np.r_[xy, xy[:1]]
        arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))]
        return LoopPath(CubicSpline(arc, closed, bc_type="periodic", extrapolate="periodic"),
                        float(arc[-1]), _waypoints(corners, start_m, clockwise))

    def xy(self, s_m: np.ndarray, nu: int = 0) -> np.ndarray:
        """(N, 2) points (nu=0) or derivatives in s of the path at arc lengths s_m."""
        return self.spline(np.asarray(s_m, dtype=float), nu)

    def samples(self, step_m: float = 0.25) -> np.ndarray:
        """(N, 2) one lap, every step_m."""
        return self.xy(np.arange(0.0, self.length_m, step_m))


def _waypoints(closed_corners: np.ndarray, start_m: float, clockwise: bool) -> np.ndarray:
    """The start point (start_m along the closed polygon) and the corners after it in walking
    order, back to the start."""
    seg = np.linalg.norm(np.diff(closed_corners, axis=0), axis=1)
    arc = np.r_[0.0, np.cumsum(seg)]
    s0 = start_m % arc[-1]
    start = np.array([np.interp(s0, arc, closed_corners[:, j]) for j in range(2)])
    k = int(np.searchsorted(arc, s0, side="right"))  # first corner after the start
    ahead = np.r_[closed_corners[k:-1], closed_corners[:k]]
    if clockwise:  # walked backwards: the corners before the start, nearest first
        ahead = np.r_[closed_corners[k - 1::-1], closed_corners[-2:k - 1:-1]]
    keep = np.linalg.norm(ahead - start, axis=1) > 1e-6
    return np.r_[start[None], ahead[keep], start[None]]


# ----------------------------------------------------------------------------------------------
# The motion


@dataclass(frozen=True)
class Burst:
    """One quick move: a "look" swings the arm about the body (yaw: the hand's lever arm
    moves the sensor), a "flick" or a "shake" turns the wrist (about the sensor), a "jolt"
    jerks the hand (a shift there and back). amount: rad about axis 0 roll, 1 pitch, 2 yaw, or
    m along axis 0 ahead, 1 left, 2 up for a jolt; a shake oscillates at freq_hz inside its
    window."""

    kind: str
    axis: int
    t0_s: float
    rise_s: float
    hold_s: float
    fall_s: float
    amount: float
    freq_hz: float = 0.0

    @property
    def t1_s(self) -> float:
        return self.t0_s + self.rise_s + self.hold_s + self.fall_s

    def angle(self, t: np.ndarray) -> np.ndarray:
        up = _smoothstep((t - self.t0_s) / self.rise_s)
        down = _smoothstep((t - self.t0_s - self.rise_s - self.hold_s) / self.fall_s)
        if self.kind == "shake":
            return self.amount * up * (1.0 - down) * np.sin(
                2.0 * np.pi * self.freq_hz * (t - self.t0_s))
        return self.amount * (up - down)

    def slower(self, factor: float) -> Burst:
        """The same burst factor times slower (rates / factor, accelerations / factor^2)."""
        if self.kind == "shake":
            return dataclasses.replace(self, freq_hz=self.freq_hz / factor)
        return dataclasses.replace(self, rise_s=self.rise_s * factor,
                                   fall_s=self.fall_s * factor)


@dataclass(frozen=True)
class Walk:
    """The walker: nominal speed (m/s), step rate (Hz), bobbing and sway (m), the hand's height
    and offset from the body (m: ahead, left), the held pitch (rad) and the hand's tremor (rad,
    Hz, rad: 2 sines per axis, roll, pitch, yaw)."""

    speed_mps: float
    step_hz: float
    bob_m: float
    sway_m: float
    hand_height_m: float
    hand_ahead_m: float
    hand_left_m: float
    pitch_rad: float
    tremor: np.ndarray  # (3, 2, 3): axis, sine, (amplitude, frequency, phase)
    stand_s: float = 1.0  # standing still before setting off
    ramp_s: float = 1.0  # from standing to walking speed

    @staticmethod
    def draw(rng: np.random.Generator) -> Walk:
        tremor = np.stack([rng.uniform(np.radians(0.15), np.radians(0.5), (3, 2)),
                           rng.uniform(0.8, 2.5, (3, 2)), rng.uniform(0, 2 * np.pi, (3, 2))],
                          axis=-1)
        return Walk(float(rng.uniform(1.1, 1.5)), float(rng.uniform(1.8, 2.0)),
                    float(rng.uniform(0.02, 0.035)), float(rng.uniform(0.02, 0.04)),
                    float(rng.uniform(1.2, 1.45)), float(rng.uniform(0.25, 0.4)),
                    float(rng.uniform(-0.2, 0.0)), float(np.radians(rng.uniform(-5.0, 5.0))),
                    tremor)


def draw_bursts(rng: np.random.Generator, start_s: float, end_s: float) -> list[Burst]:
    """Bursts one after another from start_s to end_s, 0.5-2 s apart. Shakes are the hardest
    for a constant-velocity model: 3-5 Hz, so the rate turns over within a sweep."""
    out, t = [], start_s + float(rng.uniform(0.3, 0.8))
    deg = np.radians
    while t < end_s:
        kind = rng.choice(["look", "flick", "shake", "jolt"], p=[0.25, 0.3, 0.3, 0.15])
        sign = rng.choice([-1.0, 1.0])
        if kind == "look":
            a = deg(rng.uniform(45.0, 110.0))
            b = Burst("look", 2, t, 1.875 * a / deg(rng.uniform(120.0, 175.0)),
                      rng.uniform(0.3, 1.2), 1.875 * a / deg(rng.uniform(90.0, 175.0)), sign * a)
        elif kind == "flick":
            a = deg(rng.uniform(15.0, 40.0))
            b = Burst("flick", int(rng.choice(3, p=[0.35, 0.4, 0.25])), t,
                      1.875 * a / deg(rng.uniform(100.0, 178.0)), rng.uniform(0.05, 0.5),
                      1.875 * a / deg(rng.uniform(80.0, 178.0)), sign * a)
        elif kind == "jolt":
            b = Burst("jolt", int(rng.integers(3)), t, rng.uniform(0.18, 0.3),
                      rng.uniform(0.0, 0.3), rng.uniform(0.18, 0.3),
                      sign * rng.uniform(0.03, 0.08))
        else:
            freq = rng.uniform(3.0, 5.0)
            b = Burst("shake", int(rng.integers(3)), t, rng.uniform(0.15, 0.3),
                      rng.uniform(0.5, 1.5), rng.uniform(0.15, 0.3),
                      sign * deg(rng.uniform(120.0, 170.0)) / (2 * np.pi * freq), freq)
        out.append(b)
        t = b.t1_s + float(rng.uniform(0.5, 2.0))
    return out


def walk_poses(t: np.ndarray, path: LoopPath, ground: Callable[[np.ndarray], np.ndarray],
               walk: Walk, bursts: list[Burst]) -> np.ndarray:
    """(N, 4, 4) T_world_lidar of the hand-held sensor at times t (s, increasing, evenly
    spaced: the distance walked is integrated on them)."""
    ramp = _smoothstep((t - walk.stand_s) / walk.ramp_s)
    speed = walk.speed_mps * ramp * (1.0 + 0.08 * np.sin(2 * np.pi * t / 9.0))
    s = np.r_[0.0, np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(t))]
    stride = 2.0 * np.pi * s * walk.step_hz / walk.speed_mps  # step phase
    tangent = path.xy(s, 1)
    heading = np.unwrap(np.arctan2(tangent[:, 1], tangent[:, 0]))
    left = np.c_[-np.sin(heading), np.cos(heading)]
    body = path.xy(s) + (walk.sway_m * ramp * np.sin(stride / 2))[:, None] * left
    angles = np.zeros((len(t), 3))  # wrist roll, pitch, yaw
    look = np.zeros(len(t))
    jolt = np.zeros((len(t), 3))  # hand shift ahead, left, up
    for b in bursts:
        if b.kind == "look":
            look += b.angle(t)
        elif b.kind == "jolt":
            jolt[:, b.axis] += b.angle(t)
        else:
            angles[:, b.axis] += b.angle(t)
    for axis in range(3):
        for amp, freq, phase in walk.tremor[axis]:
            angles[:, axis] += amp * np.sin(2 * np.pi * freq * t + phase)
    arm = heading + look
    ahead, left = walk.hand_ahead_m + jolt[:, 0], walk.hand_left_m + jolt[:, 1]
    hand = np.c_[ahead * np.cos(arm) - left * np.sin(arm), ahead * np.sin(arm) + left * np.cos(arm)]
    T = np.tile(np.eye(4), (len(t), 1, 1))
    T[:, :2, 3] = body + hand
    T[:, 2, 3] = (ground(body) + walk.hand_height_m - walk.bob_m * ramp * np.cos(stride)
                  + jolt[:, 2])
    T[:, :3, :3] = Rotation.from_euler(
        "ZYX", np.c_[arm + angles[:, 2], walk.pitch_rad + angles[:, 1], angles[:, 0]]
    ).as_matrix()
    return T


@dataclass(frozen=True)
class MotionStats:
    """Realised maxima on the truth (the spline) over the simulated span: body rate (deg/s),
    kinematic acceleration |d2p/dt2| (m/s^2, gravity not included), specific force |a - g|
    (m/s^2), speed (m/s); distance walked (m), laps of the loop, bursts."""

    max_rate_dps: float
    max_accel_mps2: float
    max_specific_force_mps2: float
    max_speed_mps: float
    distance_m: float
    laps: float
    n_bursts: int


@dataclass(frozen=True)
class HandheldMotion:
    trajectory: SmoothTrajectory
    walk: Walk
    bursts: list[Burst]
    stats: MotionStats


def motion_stats(traj: SmoothTrajectory, t0_s: float, t1_s: float, path_length_m: float,
                 n_bursts: int, step_s: float = 1e-3) -> tuple[MotionStats, np.ndarray,
                                                               np.ndarray]:
    """MotionStats of traj over [t0_s, t1_s], and |omega| (rad/s), |a| (m/s^2) every step_s."""
    t = np.arange(t0_s, t1_s + step_s / 2, step_s)
    w = np.linalg.norm(traj.attitude(t, 1), axis=1)
    a = traj.position(t, 2)
    v = np.linalg.norm(traj.position(t, 1), axis=1)
    an = np.linalg.norm(a, axis=1)
    f = np.linalg.norm(a + [0.0, 0.0, 9.81], axis=1)
    dist = float(np.sum(v) * step_s)
    stats = MotionStats(float(np.degrees(w.max())), float(an.max()), float(f.max()),
                        float(v.max()), dist, dist / path_length_m, n_bursts)
    return stats, w, an


def handheld_motion(path: LoopPath, ground: Callable[[np.ndarray], np.ndarray], seed: int,
                    duration_s: float) -> HandheldMotion:
    """A seeded walk of duration_s (s, from t = 0) along path, bursts slowed until the realised
    rate and acceleration stay within MAX_RATE_DPS and MAX_ACCEL_MPS2."""
    rng = np.random.default_rng([seed, 20])
    walk = Walk.draw(rng)
    bursts = draw_bursts(rng, walk.stand_s, duration_s)
    keys = np.arange(-1.0, duration_s + 1.0, 1.0 / KEY_RATE_HZ)
    limits = np.array([np.radians(MAX_RATE_DPS), MAX_ACCEL_MPS2]) * 0.995
    for _ in range(60):
        traj = SmoothTrajectory(keys, walk_poses(keys, path, ground, walk, bursts))
        stats, w, a = motion_stats(traj, 0.0, duration_s, path.length_m, len(bursts))
        ratios = np.c_[w, a] / limits
        worst = np.unravel_index(np.argmax(ratios), ratios.shape)
        ratio = float(ratios[worst])
        if ratio <= 1.0:
            return HandheldMotion(traj, walk, bursts, stats)
        t_worst = worst[0] * 1e-3
        hit = [i for i, b in enumerate(bursts) if b.t0_s - 0.1 <= t_worst <= b.t1_s + 0.1]
        if not hit:
            raise ValueError(f"handheld motion, seed {seed}: the walk alone reaches "
                             f"{'rate' if worst[1] == 0 else 'acceleration'} {ratio:.2f}x "
                             f"the limit at t = {t_worst:.2f} s")
        factor = 1.02 * (ratio if worst[1] == 0 else np.sqrt(ratio))
        for i in hit:
            bursts[i] = bursts[i].slower(factor)
    raise ValueError(f"handheld motion, seed {seed}: bursts could not be kept within limits")


# ----------------------------------------------------------------------------------------------
# Sites and sequences


@dataclass(frozen=True)
class Site:
    """Where the walk happens: the world, the loop walked and the ground height under it."""

    kind: str
    world: World
    path: LoopPath
    ground: Callable[[np.ndarray], np.ndarray]
    ceiling_m: float | None = None  # indoors: the ceiling's height above the floor
    # The loop's polygon (K, 2) (m, in order) before rounding: another walk of the same loop
    # (simulate --sessions: another start, the other way round) is LoopPath.polygon of it.
    corners: np.ndarray | None = None


def _flat(xy: np.ndarray) -> np.ndarray:
    return np.zeros(len(xy))


def build_site(kind: str, seed: int, sensor: LidarModel, corner_m: float | None = None
               ) -> Site:
    """An interior around a ring corridor, a plaza ringed by streets and buildings, an office
    floor of identical rooms (floors.py) or a warehouse hall; the loop's corners rounded over
    corner_m (default: 0.6 m indoors, 1.5 m outdoors: a walker's)."""
    from lidar_slam.sim import floors
    from lidar_slam.sim.indoor import IndoorLayout, build_indoor_world

    rng = np.random.default_rng([seed, 30])
    if kind == "indoor":
        lay = IndoorLayout.draw(rng)
        path = LoopPath.rectangle(lay.length_m, lay.width_m, corner_m or 0.6,
                                  bool(rng.random() < 0.5),
                                  float(rng.uniform(0.0, 2 * (lay.length_m + lay.width_m))))
        world = build_indoor_world(lay, path.samples(), seed)
        return Site(kind, world, path, _flat, lay.ceiling_m,
                    _rectangle(lay.length_m, lay.width_m))
    if kind in ("office", "warehouse"):
        if kind == "office":
            lay = floors.OfficeLayout.draw(rng)
            corners = lay.loop_corners(int(rng.integers(lay.n_corridors - 1)))
        else:
            lay = floors.WarehouseLayout.draw(rng)
            corners = lay.loop_corners()
        lap = float(np.sum(np.linalg.norm(np.diff(np.r_[corners, corners[:1]], axis=0), axis=1)))
        path = LoopPath.polygon(corners, corner_m or 0.6, bool(rng.random() < 0.5),
                                float(rng.uniform(0.0, lap)))
        build = floors.build_office_world if kind == "office" else floors.build_warehouse_world
        world = build(lay, path.samples(), seed)
        return Site(kind, world, path, _flat, lay.ceiling_m, np.asarray(corners, float))
    if kind != "outdoor":
        raise ValueError(f"unknown world {kind!r}; choose one of {WORLDS}")
    length, width = float(rng.uniform(20.0, 28.0)), float(rng.uniform(11.0, 15.0))
    path = LoopPath.rectangle(length, width, corner_m or 1.5, bool(rng.random() < 0.5),
                              float(rng.uniform(0.0, 2 * (length + width))))
    xy = path.samples(0.5)
    tangent = path.xy(np.arange(0.0, path.length_m, 0.5), 1)
    yaw = np.arctan2(tangent[:, 1], tangent[:, 0])
    poses = np.tile(np.eye(4), (len(xy), 1, 1))
    poses[:, :3, :3] = Rotation.from_euler("z", yaw[:, None]).as_matrix()
    slope = rng.uniform(-0.03, 0.03, 2)
    poses[:, :3, 3] = np.c_[xy, sensor.mount_height_m + xy @ slope]
    world = build_world(poses, sensor, seed, WorldParams(extend_m=30.0))
    return Site(kind, world, path, world.terrain.height, None, _rectangle(length, width))


def _rectangle(length_m: float, width_m: float) -> np.ndarray:
    return np.array([[0.0, 0.0], [length_m, 0.0], [length_m, width_m], [0.0, width_m]])


def write_bursts(path: Path, bursts: list[Burst]) -> None:
    """bursts.csv: kind,axis,t0_s,t1_s,amount (deg, m for a jolt),freq_hz, one line each."""
    rows = "".join(
        f"{b.kind},{b.axis},{b.t0_s:.4f},{b.t1_s:.4f},"
        f"{b.amount if b.kind == 'jolt' else np.degrees(b.amount):.4f},{b.freq_hz:.4f}\n"
        for b in bursts)
    write_text_atomic(path, "kind,axis,t0_s,t1_s,amount,freq_hz\n" + rows)


def clearance_m(world: World, traj: SmoothTrajectory, t0_s: float, t1_s: float,
                step_s: float = 0.02) -> np.ndarray:
    """Distance (m) from the sensor to the nearest surface every step_s over [t0_s, t1_s]."""
    t = np.arange(t0_s, t1_s + step_s / 2, step_s)
    return world.closest(traj(t)[:, :3, 3])[0]
