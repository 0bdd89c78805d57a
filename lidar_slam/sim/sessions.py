"""`simulate --sessions N`: N recordings of one world made at different times, for `merge`.

Every session goes round the same loop of the same seeded world (lidar_slam.sim.handheld's
sites: indoor or outdoor) from its own start point, odd sessions the other way round, and is
written as its own KITTI-layout sequence in its own frame (its first pose is its origin, as a
separate recording): OUT/session_<i>/. Beside each, truth_world.txt holds its poses in the
common world frame (KITTI rows, one per scan, T_world_lidar), which the merge never sees.

Between sessions the world changes: objects (furniture indoors, parked cars outdoors) are moved,
added or removed. Each change happens before one session and holds for the later ones;
OUT/changes.json is its truth: the object, what happened, from which session on, and its box
before and after (centre x, y, yaw, length, width, z0, z1 in the world frame, m and rad).

Motions: "handheld" (handheld.handheld_motion: a walk with looks, flicks and shakes) and "car"
(a drive at 4-6 m/s, the lidar on the roof: the outdoor world only).
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from lidar_slam.io.atomic import write_text_atomic
from lidar_slam.io.trajectory import write_kitti_poses
from lidar_slam.o3d import o3d
from lidar_slam.sim.handheld import (
    CLEARANCE_M,
    KEY_RATE_HZ,
    LoopPath,
    Site,
    _smoothstep,
    build_site,
    clearance_m,
    handheld_motion,
)
from lidar_slam.sim.imu_gnss import GnssOptions, ImuOptions, SmoothTrajectory
from lidar_slam.sim.sensor import LidarModel, get_sensor
from lidar_slam.sim.world import CLASSES, World, _box, place_on_terrain

log = logging.getLogger(__name__)

SESSION_MOTIONS = {"handheld": ("indoor", "outdoor"), "car": ("outdoor",)}
CHANGE_KINDS = ("moved", "added", "removed")
CHANGES_FILE = "changes.json"
TRUTH_FILE = "truth_world.txt"
# How close (m) a changed object may come to the loop walked or driven, and to other surfaces.
_PATH_GAP_M = {"handheld": 1.0, "car": 2.5}
_SURFACE_GAP_M = 0.15


@dataclass(frozen=True)
class Box:
    """An upright box in the world frame: centre (m), yaw (rad), footprint and height range."""

    x: float
    y: float
    yaw: float
    length: float
    width: float
    z0: float
    z1: float

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        return _box(self.x, self.y, self.yaw, self.length, self.width, self.z0, self.z1)

    def outline(self, step_m: float = 0.2) -> np.ndarray:
        """Points (N, 2) on the footprint's outline."""
        from lidar_slam.sim.world import _box_footprint

        return _box_footprint(self.x, self.y, self.yaw, self.length, self.width, step_m)


@dataclass(frozen=True)
class Change:
    """One object changed before session `session` (and so in every later one): kind moved
    (before and after), added (after only) or removed (before only); cls is its CLASSES
    name."""

    object_id: int
    kind: str
    session: int
    cls: str
    before: Box | None
    after: Box | None

    def box_in(self, session: int) -> Box | None:
        """Where the object is in that session (None: not there)."""
        return self.before if session < self.session else self.after


def _draw_box(rng: np.random.Generator, path: LoopPath, motion: str, ground) -> Box:
    """A piece of furniture (handheld) or a parked car beside the loop, at a random place."""
    s = float(rng.uniform(0.0, path.length_m))
    xy, tangent = path.xy(s), path.xy(s, 1)
    yaw = float(np.arctan2(tangent[1], tangent[0]))
    normal = np.array([-np.sin(yaw), np.cos(yaw)]) * rng.choice([-1.0, 1.0])
    if motion == "car":
        length, width, height = rng.uniform(3.8, 4.8), rng.uniform(1.7, 1.9), rng.uniform(1.4, 1.6)
        offset = rng.uniform(3.6, 9.0)
    else:
        length, width, height = rng.uniform(0.5, 1.2), rng.uniform(0.4, 0.7), rng.uniform(0.7, 1.6)
        offset = rng.uniform(1.2, 1.5)
        yaw += float(rng.normal(0.0, 0.2))
    c = xy + offset * normal
    z0 = float(ground(c[None])[0])
    return Box(float(c[0]), float(c[1]), yaw, float(length), float(width), z0, z0 + float(height))


def draw_changes(site: Site, motion: str, n_sessions: int, n_changes: int, seed: int
                 ) -> list[Change]:
    """n_changes objects changed between sessions (each before a session 1..n-1), kept clear of
    the loop, of the world's surfaces and of each other."""
    if n_sessions < 2 or n_changes == 0:
        return []
    rng = np.random.default_rng([seed, 40])
    path_tree = cKDTree(site.path.samples(0.1))
    taken: list[Box] = []

    def free(box: Box) -> bool:
        outline = box.outline()
        if path_tree.query(outline)[0].min() < _PATH_GAP_M[motion]:
            return False
        mid = np.c_[outline, np.full(len(outline), (box.z0 + box.z1) / 2)]
        if site.world.closest(mid)[0].min() < _SURFACE_GAP_M:
            return False
        r = np.hypot(box.length, box.width) / 2
        return all(np.hypot(box.x - o.x, box.y - o.y) > r + np.hypot(o.length, o.width) / 2 + 0.3
                   for o in taken)

    def place(near: Box | None = None) -> Box:
        for _ in range(2000):
            box = _draw_box(rng, site.path, motion, site.ground)
            if near is not None:  # moved: the same object a few metres away
                box = Box(box.x, box.y, box.yaw, near.length, near.width, box.z0,
                          box.z0 + near.z1 - near.z0)
                if not 2.0 < np.hypot(box.x - near.x, box.y - near.y) < 12.0:
                    continue
            if free(box):
                taken.append(box)
                return box
        raise ValueError(f"seed {seed}: no free place for {n_changes} changed objects")

    cls = "car" if motion == "car" else "clutter"
    out = []
    for k in range(n_changes):
        kind = CHANGE_KINDS[k % 3]
        session = int(rng.integers(1, n_sessions))
        before = place() if kind != "added" else None
        after = place(before) if kind == "moved" else (place() if kind == "added" else None)
        out.append(Change(k, kind, session, cls, before, after))
    return out


def with_objects(world: World, boxes: list[tuple[str, Box]]) -> World:
    """world with the boxes (class name, box) added; call before the world's first ray or
    closest-point query (open3d builds its BVH then)."""
    cog = list(world.class_of_geometry)
    n_tri = world.n_triangles
    for cls, box in boxes:
        v, t = box.mesh()
        gid = world.scene.add_triangles(o3d.core.Tensor((v - world.origin).astype(np.float32)),
                                        o3d.core.Tensor(t.astype(np.uint32)))
        cog += [0] * (gid + 1 - len(cog))
        cog[gid] = CLASSES.index(cls)
        n_tri += len(t)
    return World(world.scene, world.origin, world.terrain, world.centerline,
                 np.asarray(cog, dtype=np.int64), n_tri,
                 {**world.n_objects, "changed": len(boxes)})


def car_motion(path: LoopPath, site: Site, seed: int, duration_s: float, mount_height_m: float
               ) -> SmoothTrajectory:
    """A drive round path at 4-6 m/s (1.5 s standing, 2 s to speed), the lidar mount_height_m
    above the ground, level with it."""
    rng = np.random.default_rng([seed, 50])
    speed = float(rng.uniform(4.0, 6.0))
    keys = np.arange(-1.0, duration_s + 1.0, 1.0 / KEY_RATE_HZ)
    v = speed * _smoothstep((keys - 1.5) / 2.0) * (1.0 + 0.05 * np.sin(2 * np.pi * keys / 7.0))
    s = np.r_[0.0, np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(keys))]
    xy, tangent = path.xy(s), path.xy(s, 1)
    yaw = np.unwrap(np.arctan2(tangent[:, 1], tangent[:, 0]))
    poses = np.tile(np.eye(4), (len(keys), 1, 1))
    c, sn = np.cos(yaw), np.sin(yaw)
    poses[:, 0, 0], poses[:, 0, 1], poses[:, 1, 0], poses[:, 1, 1] = c, -sn, sn, c
    poses[:, :2, 3] = xy
    return SmoothTrajectory(keys, place_on_terrain(poses, site.world.terrain, mount_height_m))


@dataclass(frozen=True)
class SessionsSummary:
    """What simulate_sessions wrote: scans per session, changes, the seconds it took."""

    n_scans: list[int]
    n_changes: int
    seconds: float


def _session_path(site: Site, motion: str, i: int, n: int, seed: int, spread: float
                  ) -> LoopPath:
    """Session i's loop: the site's polygon from its own start (spread round spread x the
    lap), odd sessions reversed."""
    rng = np.random.default_rng([seed, 60, i])
    lap = float(np.sum(np.linalg.norm(np.diff(np.r_[site.corners, site.corners[:1]], axis=0),
                                      axis=1)))
    start = lap * spread * (i + float(rng.uniform(0.0, 0.5))) / n
    corner = 3.0 if motion == "car" else 0.6
    return LoopPath.polygon(site.corners, corner, bool(i % 2), start)


def simulate_sessions(out_dir: str | Path, n_sessions: int, motion: str, world_kind: str,
                      seed: int, duration_s: float, sensor: str | LidarModel = "os1-64",
                      n_changes: int = 10, imu: ImuOptions | None = None,
                      gnss: GnssOptions | None = None,
                      on_scan: Callable[[int], None] | None = None, spread: float = 1.0,
                      n_movers: int = 0) -> SessionsSummary:
    """n_sessions sequences of one seeded world (see the module doc) into out_dir; the
    sessions start round spread x the lap (1: evenly round it; less: closer together, for
    short sessions that still overlap); n_movers things move during each session
    (sim.movers; their truth in session_<i>/movers.csv)."""
    from lidar_slam.sim.movers import MOVERS_FILE, Movers, draw_movers, write_movers
    from lidar_slam.sim.sequence import write_sequence

    if motion not in SESSION_MOTIONS:
        raise ValueError(f"--sessions takes --motion {' or '.join(SESSION_MOTIONS)}, "
                         f"not {motion}")
    if world_kind not in SESSION_MOTIONS[motion]:
        raise ValueError(f"--sessions with --motion {motion} goes through --world "
                         f"{' / '.join(SESSION_MOTIONS[motion])}, not {world_kind}")
    sensor = get_sensor(sensor)
    t0 = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    changes = draw_changes(build_site(world_kind, seed, sensor), motion, n_sessions, n_changes,
                           seed)
    n_scans = []
    for i in range(n_sessions):
        site = build_site(world_kind, seed, sensor)  # a fresh scene: objects go in before a ray
        boxes = [(c.cls, c.box_in(i)) for c in changes if c.box_in(i) is not None]
        site = Site(site.kind, with_objects(site.world, boxes), site.path, site.ground,
                    site.ceiling_m, site.corners)
        path = _session_path(site, motion, i, n_sessions, seed, spread)
        session_seed = seed * 1000 + i
        if motion == "car":
            traj = car_motion(path, site, session_seed, duration_s, sensor.mount_height_m)
            text = f"A drive round the {site.kind} loop (session {i}, seed {seed}).\n"
        else:
            walk = _handheld_walk(path, site.ground, session_seed, duration_s)
            traj = walk.trajectory
            text = (f"A handheld walk round the {site.kind} loop (session {i}, seed {seed}): "
                    f"{walk.stats.distance_m:.0f} m.\n")
        n = int(round(duration_s * sensor.rate_hz))
        stamps = np.arange(n) / sensor.rate_hz
        gap = clearance_m(site.world, traj, 0.0, n / sensor.rate_hz)
        if gap.min() < CLEARANCE_M:
            raise ValueError(f"sessions {motion} {world_kind} seed {seed}, session {i}: the "
                             f"sensor comes within {gap.min():.2f} m of a surface")
        dest = out / f"session_{i}"
        movers = draw_movers(path, site.ground, motion, n_movers, session_seed)
        summary = write_sequence(dest, site.world, sensor, traj, stamps, traj(stamps),
                                 session_seed, np.eye(4), 0.0, on_scan, imu, gnss,
                                 motion=text + "truth_world.txt: these poses in the world frame "
                                 "common to every session.\n",
                                 movers=Movers(movers) if movers else None)
        write_kitti_poses(dest / TRUTH_FILE, summary.poses_world_lidar)
        if movers:
            write_movers(dest / MOVERS_FILE, movers, stamps, sensor.period_s)
        n_scans.append(summary.n_scans)
    doc = {"seed": seed, "motion": motion, "world": world_kind, "sessions": n_sessions,
           "frame": "world (the frame of every session's truth_world.txt)",
           "box": "centre x, y (m), yaw (rad), length, width (m), z0, z1 (m)",
           "changes": [{**asdict(c), "before": None if c.before is None else asdict(c.before),
                        "after": None if c.after is None else asdict(c.after)}
                       for c in changes]}
    write_text_atomic(out / CHANGES_FILE, json.dumps(doc, indent=1) + "\n")
    return SessionsSummary(n_scans, len(changes), time.perf_counter() - t0)


WALK_DRAWS = 8  # random walks drawn for a session before giving up


def _handheld_walk(path, ground, session_seed: int, duration_s: float):
    """A hand-held walk along path: handheld_motion's for session_seed, or, when its random
    bursts cannot be kept within the motion limits (a long walk draws many), the first of
    session_seed + 100 k (k = 1 .. WALK_DRAWS - 1) that can; the same seed, the same walk."""
    for k in range(WALK_DRAWS):
        try:
            return handheld_motion(path, ground, session_seed + 100 * k, duration_s)
        except ValueError:
            if k == WALK_DRAWS - 1:
                raise


def read_changes(path: str | Path) -> list[Change]:
    """The changes of a changes.json."""
    doc = json.loads(Path(path).read_text())

    def box(d):
        return None if d is None else Box(**d)

    return [Change(c["object_id"], c["kind"], c["session"], c["cls"], box(c["before"]),
                   box(c["after"])) for c in doc["changes"]]


def simulate_sessions_job(out: Path, n_sessions: int, motion: str, world_kind: str,
                          duration_s: float, sensor: str, seed: int, n_changes: int,
                          overwrite: bool, rates: tuple, n_movers: int = 0) -> str:
    """`simulate --sessions`: the --out rule, a progress bar, simulate_sessions; the line to
    print. rates: (imu_rate_hz, gnss_rate_hz, imu_extrinsic, gnss_datum, gnss_lever_arm) as
    `simulate` parses them."""
    from lidar_slam.errors import RunFailed
    from lidar_slam.run.outdir import prepare_out_dir
    from lidar_slam.run.progress import progress as make_progress
    from lidar_slam.sim.jobs import HandheldJob, _inertial

    if rates[1] is not None and world_kind != "outdoor":
        raise RunFailed("--gnss needs --world outdoor: a receiver indoors has no fix")
    prepare_out_dir(out, tuple(f"session_{i}" for i in range(n_sessions)) + (CHANGES_FILE,),
                    overwrite)
    imu, gnss = _inertial(HandheldJob(str(out), world_kind, duration_s, sensor, seed, overwrite,
                                      *rates))
    total = n_sessions * int(round(duration_s * get_sensor(sensor).rate_hz))
    bar = make_progress(f"simulate {out.name}", total, unit="scans")
    try:
        summary = simulate_sessions(out, n_sessions, motion, world_kind, seed, duration_s,
                                    sensor, n_changes, imu, gnss, on_scan=bar.tick,
                                    n_movers=n_movers)
    except ValueError as exc:
        raise RunFailed(str(exc)) from None
    finally:
        bar.close()
    return (f"simulated {n_sessions} sessions ({', '.join(map(str, summary.n_scans))} scans, "
            f"{summary.n_changes} objects changed between them) into {out}: {motion} "
            f"{world_kind}, {summary.seconds:.0f} s")
