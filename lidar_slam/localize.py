"""Localisation in a saved map (a finished run folder, lidar_slam.map.saved).

Per scan:  deskew (motion model) -> track: point-to-plane ICP (small_gicp) against the fixed
map's clouds around the constant-velocity prediction, kept when the scan's above-ground points
fit the map and the correction of the prediction is small (for the platform: the map run's own
poses say how far the prediction misses on it) -> else relocalise: Scan Context
against the map's keyframes, each candidate verified by the loop-closure ICP gates
(lidar_slam.loop.verify: a wrong pose is worse than none) -> else lost: the pose is the motion
model's prediction. The map never grows and no loops are searched, so a frame costs less than
the odometry's.

Statuses: `localized` (a relocalisation, or the --initial-pose, verified in this frame),
`tracking` (registered against the map from the prediction), `lost`. Poses are T_map_scan at
the scan's stamp, map = the frame of the map run's poses_kitti.txt. Before the first
localisation a lost frame holds the initial pose (or the map origin).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from lidar_slam.config import SlamConfig
from lidar_slam.frontend.crop import range_mask
from lidar_slam.frontend.deskew import DeskewedScan, Deskewer
from lidar_slam.frontend.odometry import VoxelSelector
from lidar_slam.geometry import inverse, make_pose, rotation_angle_deg
from lidar_slam.loop.scan_context import ScanContextIndex
from lidar_slam.loop.verify import verify
from lidar_slam.map.saved import SavedMap
from lidar_slam.registration import PlaneTarget, level_ground, voxel_centroids
from lidar_slam.types import LoopCandidate, Scan

log = logging.getLogger(__name__)


class Status(str, Enum):
    LOCALIZED = "localized"
    TRACKING = "tracking"
    LOST = "lost"


@dataclass(frozen=True)
class LocalizedFrame:
    """One scan's result: T_map_scan at its stamp, status, and the fitness of the registration
    that decided it (tracking: structure fitness against the map; localized: the verification's
    fitness; lost: the best failed attempt's, NaN when none was made)."""

    index: int
    stamp_s: float
    T_map_scan: np.ndarray
    status: Status
    fitness: float


@dataclass
class LocalizeStats:
    """Counters and times for summary.json."""

    relocalisation_attempts: int = 0
    relocalisations: int = 0
    seconds: dict[str, float] = field(default_factory=lambda: {"track": 0.0, "relocalise": 0.0,
                                                                "deskew": 0.0})

    def compute_s(self) -> float:
        """Seconds spent localising (deskew, tracking, relocalisation; no reading)."""
        return sum(self.seconds.values())


def initial_pose_matrix(x: float, y: float, z: float, yaw_deg: float) -> np.ndarray:
    """T_map_scan from a position (m) and a heading about the map's z axis (deg)."""
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    return make_pose(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), [x, y, z])


def registration_points(deskewed: DeskewedScan, cfg: SlamConfig) -> np.ndarray:
    """The points registered against the map (N, 3), sensor frame at the reference instant:
    the scan's deskewed points in range, one per localize.source_voxel_m voxel (centroids)."""
    d = cfg.data
    pts = deskewed.points
    if not deskewed.selected:  # raw points: crop them (a selection is cropped already)
        pts = pts[range_mask(pts, d.min_range_m, d.max_range_m)]
    return voxel_centroids(pts, cfg.localize.source_voxel_m)


def structure_points(points: np.ndarray, min_height_m: float) -> np.ndarray:
    """The points (N, 3), sensor frame, more than min_height_m above the ground fitted below
    the sensor (all of them when no ground is found): the road matches the map anywhere along
    it, so it says nothing about the pose."""
    ground = level_ground(points)
    if ground.height_m is None:
        return points
    return points[points @ ground.R_level_sensor[2] + ground.height_m > min_height_m]


class MapTarget(PlaneTarget):
    """The tracking target: map-frame points with the localize section's voxel, iterations and
    inlier distance. Tracking is point-to-plane ICP against it."""

    def __init__(self, points_map: np.ndarray, cfg: SlamConfig):
        lc = cfg.localize
        super().__init__(points_map, lc.map_voxel_m, lc.max_iterations, lc.inlier_m)


class LocalMaps:
    """The tracking target around a pose: the clouds of the keyframe nearest to it, of the
    localize.submap_behind keyframes before it and localize.submap_ahead after it, placed with
    their final poses. A scan is registered against the part of the map that its own stretch of
    the map run saw (mostly what was already mapped when the run passed there), so it lands where
    the map run's poses put that stretch, also where the map drifts over longer spans."""

    def __init__(self, saved_map: SavedMap):
        self.map = saved_map
        self.positions = saved_map.T_map_kf[:, :3, 3]
        self._cache: dict[int, MapTarget] = {}

    def around(self, T_map: np.ndarray) -> MapTarget:
        """The target for a pose near T_map (built once per nearest keyframe, a few kept)."""
        centre = int(np.argmin(np.linalg.norm(self.positions - T_map[:3, 3], axis=1)))
        target = self._cache.get(centre)
        if target is None:
            lc = self.map.cfg.localize
            ids = range(max(0, centre - lc.submap_behind),
                        min(len(self.map), centre + lc.submap_ahead + 1))
            points = np.concatenate([self.map.points_map(k)[0] for k in ids])
            target = MapTarget(points, self.map.cfg)
            if len(self._cache) >= 4:  # the nearest keyframe may swap back and forth
                self._cache.pop(next(iter(self._cache)))
            self._cache[centre] = target
        return target


@dataclass(frozen=True)
class CorrectionGates:
    """How far tracking may move a fresh constant-velocity prediction (m, deg), and whether the
    prediction is good enough for the fine stage alone (predictable)."""

    max_m: float
    max_deg: float
    predictable: bool

    @classmethod
    def for_map(cls, saved_map: SavedMap) -> CorrectionGates:
        """The localize section's gates, widened to correction_margin x the largest miss of the
        prediction along the map run's own poses where that is more. The gates were set for a
        car at 10 Hz; a hand-held sensor at 2 Hz turns up to 40 deg a frame and its prediction
        misses by up to 29 deg: a correction that size is its normal motion, not a jump, and a
        gate at 5 deg relocalised every other frame. The map run saw the same kind of motion
        at the same frame rate, so its poses measure what a correction of normal motion is."""
        lc = saved_map.cfg.localize
        miss_m, miss_deg = saved_map.prediction_error_m, saved_map.prediction_error_deg
        gates = cls(max(lc.max_correction_m, lc.correction_margin * miss_m),
                    max(lc.max_correction_deg, lc.correction_margin * miss_deg),
                    miss_m <= lc.max_correction_m and miss_deg <= lc.max_correction_deg)
        log.info("the map run's motion model missed by up to %.2f m / %.1f deg: tracking may "
                 "correct the prediction by %.2f m / %.1f deg%s", miss_m, miss_deg, gates.max_m,
                 gates.max_deg, "" if gates.predictable else ", pulled in coarse every frame")
        return gates


class Localizer:
    """Tracks scans in a saved map, relocalising when tracking is lost; step() per scan."""

    def __init__(self, saved_map: SavedMap, initial_pose: np.ndarray | None = None):
        self.map = saved_map
        self.cfg = cfg = saved_map.cfg
        self.deskew = Deskewer(cfg.data, 0.5 * cfg.voxel_size_m(), VoxelSelector())
        self.maps = LocalMaps(saved_map)
        self.places = ScanContextIndex(cfg.loop.scan_context)
        for kf_id, grid in zip(*saved_map.descriptor_grids()):
            self.places.add_grid(int(kf_id), grid)
        self.initial_pose = initial_pose
        self.T_map_ref: np.ndarray | None = None  # last pose (reference instant of its sweep)
        self.delta = np.eye(4)  # motion model: T_prev_curr, per frame
        self.predicted = 0  # frames since the last registered one
        # delta measured between the last two frames, both registered (else it is stale, or
        # the identity before any measurement: the prediction may be off by a frame's motion)
        self.motion_fresh = False
        # a relocalised frame, or one with its stamp after the sweep's middle, waiting for the
        # next frame's motion
        self._pending: tuple | None = None
        self.stats = LocalizeStats()
        self.gates = CorrectionGates.for_map(saved_map)

    def step(self, scan: Scan) -> list[LocalizedFrame]:
        """Localise one scan; returns the frames whose result is final, in order: usually this
        one; a relocalised frame, and a tracked one stamped after the middle of its sweep (stamps
        at sweep end), wait for the next frame's motion to move their pose from the middle of the
        sweep to the stamp: between two registrations, not extrapolated along the last motion
        (as lidar_slam.pipeline does; finish() returns a frame still waiting)."""
        t0 = time.perf_counter()
        deskewed = self.deskew(scan, self.delta)
        source = registration_points(deskewed, self.cfg)
        self.stats.seconds["deskew"] += time.perf_counter() - t0
        T, status, fitness = self._locate(deskewed, source)
        if status == Status.TRACKING and self.predicted == 0:  # registered twice in a row
            if self._pending is not None and self._pending[3] == Status.LOCALIZED:
                T = self._refine_start(deskewed, T)
            self.delta = inverse(self.T_map_ref) @ T
            self.motion_fresh = True
        else:
            self.motion_fresh = False
        if status == Status.LOST:
            self.predicted += 1
            if self.T_map_ref is not None:
                self.T_map_ref = self.T_map_ref @ self.delta
        else:
            self.predicted = 0
            self.initial_pose = None
            self.T_map_ref = T
        # Never localised yet: the initial pose, or the map origin.
        T = self.T_map_ref if self.T_map_ref is not None else (
            np.eye(4) if self.initial_pose is None else self.initial_pose)
        out = [] if self._pending is None else [self._final(*self._pending)]
        self._pending = None
        frame = (scan.index, scan.stamp_s, T, status, float(fitness), deskewed)
        if status == Status.LOCALIZED or (status == Status.TRACKING and deskewed.ref_s < 0.0):
            self._pending = frame
        else:
            out.append(self._final(*frame))
        return out

    def _locate(self, deskewed: DeskewedScan, source: np.ndarray
                ) -> tuple[np.ndarray | None, Status, float]:
        """Track from the prediction, else relocalise: (T_map_ref or None, status, fitness)."""
        if len(source) == 0:
            return None, Status.LOST, np.nan
        fitness = np.nan
        if self.T_map_ref is not None and self.predicted <= self.cfg.localize.max_predicted_frames:
            t0 = time.perf_counter()
            T, fitness = self._track(source, self.T_map_ref @ self.delta)
            self.stats.seconds["track"] += time.perf_counter() - t0
            if T is not None:
                return T, Status.TRACKING, fitness
        t0 = time.perf_counter()
        T, reloc_fitness = self._relocalise(deskewed)
        self.stats.seconds["relocalise"] += time.perf_counter() - t0
        if T is not None:
            return T, Status.LOCALIZED, reloc_fitness
        return None, Status.LOST, fitness if np.isnan(reloc_fitness) else reloc_fitness

    def finish(self) -> list[LocalizedFrame]:
        """The frame still waiting for the next frame's motion, if any."""
        out = [] if self._pending is None else [self._final(*self._pending)]
        self._pending = None
        return out

    def _refine_start(self, deskewed: DeskewedScan, T_map_ref: np.ndarray) -> np.ndarray:
        """The first two registered frames after a (re)start were deskewed with a motion not
        yet measured: deskew both again along the motion between their poses and register them
        again (twice); updates the waiting frame, returns this frame's pose."""
        index, stamp_s, T_prev, status, fitness, prev = self._pending
        # The motion between the two spans this frame's period; the waiting frame's own may be
        # a gap in the data (a jump), which is no sweep duration.
        prev = dataclasses.replace(prev, period_s=deskewed.period_s)
        for _ in range(2):
            delta = inverse(T_prev) @ T_map_ref
            prev, deskewed = prev.with_motion(delta), deskewed.with_motion(delta)
            corr = self.cfg.localize.max_correspondence_m
            T_prev = self.maps.around(T_prev).align(registration_points(prev, self.cfg), T_prev,
                                                    corr)
            T_map_ref = self.maps.around(T_map_ref).align(
                registration_points(deskewed, self.cfg), T_map_ref, corr)
        self._pending = (index, stamp_s, T_prev, status, fitness, prev)
        self.T_map_ref = T_prev
        return T_map_ref

    def _final(self, index: int, stamp_s: float, T_map_ref: np.ndarray, status: Status,
               fitness: float, deskewed: DeskewedScan) -> LocalizedFrame:
        """The frame's result, its pose moved from the reference instant to its stamp along the
        current motion model."""
        return LocalizedFrame(index, stamp_s, T_map_ref @ deskewed.T_ref_stamp(self.delta),
                              status, fitness)

    def _track(self, source: np.ndarray, guess: np.ndarray) -> tuple[np.ndarray | None, float]:
        """Register against the map from the prediction; (T_map_ref or None, fitness)."""
        lc = self.cfg.localize
        target = self.maps.around(guess)
        T = guess
        # The prediction may be off by a frame's motion, or by more than the fine stage pulls
        # in on this platform: pull it in.
        if not self.motion_fresh or not self.gates.predictable:
            T = target.align(source, T, lc.coarse_correspondence_m)
        T = target.align(source, T, lc.max_correspondence_m)
        correction = inverse(guess) @ T
        fitness = target.fitness(structure_points(source, lc.structure_min_height_m), T)
        moved_m = float(np.linalg.norm(correction[:3, 3]))
        turned_deg = float(rotation_angle_deg(correction))
        # Without a fresh motion the prediction may be off by metres: only the fitness gates.
        off = self.motion_fresh and (moved_m > self.gates.max_m or turned_deg > self.gates.max_deg)
        if fitness < lc.min_fitness or off:
            log.debug("tracking lost: fitness %.2f, correction %.2f m %.1f deg", fitness,
                      moved_m, turned_deg)
            return None, fitness
        return T, fitness

    def _relocalise(self, deskewed: DeskewedScan) -> tuple[np.ndarray | None, float]:
        """Global relocalisation (or the initial pose): (T_map_ref or None, fitness)."""
        c = self.cfg
        points, _ = deskewed.cloud(c.keyframes.cloud_voxel_m, c.data.min_range_m,
                                   min(c.data.max_range_m, c.map.max_range_m))
        if len(points) == 0:
            return None, np.nan
        self.stats.relocalisation_attempts += 1
        radius = c.loop.verify.submap_radius
        tries: list[tuple[LoopCandidate, np.ndarray | None]] = []
        if self.initial_pose is not None:  # the user's pose: verify it against the nearest kf
            near = int(np.argmin(np.linalg.norm(self.map.T_map_kf[:, :3, 3]
                                                - self.initial_pose[:3, 3], axis=1)))
            tries.append((LoopCandidate(-1, near, 0.0, 0.0),
                          inverse(self.map.T_map_kf[near]) @ self.initial_pose))
        found = self.places.query_all(points)
        tries += [(cand, None) for cand in found.candidates[: c.localize.max_verify]]
        best_fitness = np.nan
        for cand, T_init in tries:
            res = verify(cand, points, self.map.submap(cand.match, radius), c.loop.verify,
                         T_match_query_init=T_init)
            best_fitness = np.nanmax([best_fitness, res.fitness])
            if res.accepted:
                self.stats.relocalisations += 1
                log.info("relocalised at frame %d on keyframe %d (fitness %.2f)",
                         deskewed.scan.index, cand.match, res.fitness)
                T = self.map.T_map_kf[cand.match] @ res.T_match_query
                off = (np.inf if self.initial_pose is None
                       else float(np.linalg.norm(T[:3, 3] - self.initial_pose[:3, 3])))
                # A guess beyond ICP's coarse reach was not what the scan confirmed: said.
                if np.isfinite(off) and (cand.query != -1
                                         or off > c.localize.coarse_correspondence_m):
                    log.warning("frame %d: localised %.1f m from --initial-pose (%s): the pose "
                                "comes from the scan, not from it", deskewed.scan.index, off,
                                "found by the global search" if cand.query != -1
                                else "beyond localize.coarse_correspondence_m")
                return T, res.fitness
        return None, best_fitness
