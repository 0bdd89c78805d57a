"""The SLAM pipeline in flow order:
reader -> deskew -> crop + odometry -> keyframe? -> scan-context query -> ICP verify -> pose graph
-> map / metrics.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from lidar_slam.config import SlamConfig
from lidar_slam.errors import LidarSlamError
from lidar_slam.frontend.crop import range_mask
from lidar_slam.frontend.deskew import deskew
from lidar_slam.frontend.downsample import voxel_first_indices
from lidar_slam.geometry import interpolate, inverse, transform_points
from lidar_slam.keyframes import KeyframeSelector
from lidar_slam.odometry import Odometry
from lidar_slam.types import Keyframe, Scan

log = logging.getLogger(__name__)


@dataclass
class RunResult:
    """Everything a run computed, frame by frame (lists grow as scans are processed)."""

    indices: list[int] = field(default_factory=list)
    stamps_s: list[float] = field(default_factory=list)
    odom_poses: list[np.ndarray] = field(default_factory=list)  # T_world_scan before loops
    frame_kf: list[int] = field(default_factory=list)  # keyframe each frame hangs off
    keyframes: list[Keyframe] = field(default_factory=list)
    kf_poses: dict[int, np.ndarray] = field(default_factory=dict)  # final T_world_kf
    loops: list = field(default_factory=list)  # LoopRecord rows for loops.csv
    skipped_empty: int = 0
    interrupted: bool = False
    error: str | None = None  # a bad input that stopped the run early
    internal_error: str | None = None  # traceback of a bug that stopped the run early
    graph: object | None = None  # the keyframe PoseGraph when loops are on (for graph.g2o)
    seconds: dict[str, float] = field(default_factory=lambda: {"odometry": 0.0, "loops": 0.0})

    def final_poses(self) -> np.ndarray:
        """Every frame's pose, moved with its keyframe's optimised pose (K, 4, 4)."""
        out = np.empty((len(self.odom_poses), 4, 4))
        kf_by_id = {kf.id: kf for kf in self.keyframes}
        for i, (T_odom, kf_id) in enumerate(zip(self.odom_poses, self.frame_kf)):
            kf = kf_by_id[kf_id]
            out[i] = self.kf_poses[kf_id] @ inverse(kf.T_world_kf_odom) @ T_odom
        return out


class Pipeline:
    """Calls the stages in flow order for one scan at a time."""

    def __init__(self, cfg: SlamConfig, viz=None):
        self.cfg = cfg
        self.odometry = Odometry(cfg)
        self.keyframes = KeyframeSelector(cfg.keyframes)
        self.result = RunResult()
        self.loop_closer = None
        if cfg.loop.enabled:
            from lidar_slam.loop.closer import LoopCloser

            self.loop_closer = LoopCloser(cfg)
            self.result.graph = self.loop_closer.graph
        self.viz = viz
        self._last_stamp: float | None = None
        self._last_dt = 0.1
        self._last_ref_s = 0.0  # mid-sweep offset from the stamp of the last registered scan
        self._first_ref_s = 0.0  # the same for frame 0, whose pose is fixed once motion is known

    def process(self, scan: Scan) -> None:
        """Run one scan through every stage."""
        r, t0 = self.result, time.perf_counter()
        if self._last_stamp is not None and scan.stamp_s > self._last_stamp:
            dt = scan.stamp_s - self._last_stamp
        else:
            dt = self._last_dt
        points, ref_s = scan.points, 0.0
        if self.cfg.data.deskew and scan.point_times is not None and len(points):
            # Deskew (once) to the middle of the sweep: the correction, and with it the effect of
            # a wrong velocity guess, is half what deskewing to an end of the sweep gives; that
            # feedback makes start-referenced deskew diverge on fast sparse scans.
            times = scan.point_times
            ref_s = 0.5 * (float(times.min()) + float(times.max()))
            points = deskew(points, times - ref_s, self.odometry.last_delta, self._last_dt)
        T_world_ref = self.odometry.step(points)  # range-cropped inside, as kiss-icp does
        if T_world_ref is None:
            log.warning("%s: empty scan after cropping, skipped (pose predicted)", scan.source)
            r.skipped_empty += 1
            # The prediction is of the sweep's middle, like every registration: move it to the
            # stamp with the last scan's offset, and keep the clock going so that the next scan's
            # dt spans one period, not two.
            T_pred = self.odometry.predict()
            if self._last_ref_s != 0.0:
                T_pred = T_pred @ interpolate(np.eye(4), self.odometry.last_delta,
                                              -self._last_ref_s / dt)
            self._last_dt, self._last_stamp = dt, scan.stamp_s
            self._append(scan, T_pred)
            return
        T_ref_stamp = np.eye(4)
        if ref_s != 0.0:  # the pose (and the cloud) refer to the stamp, not the mid-sweep
            T_ref_stamp = interpolate(np.eye(4), self.odometry.last_delta, -ref_s / dt)
        T_world_scan = T_world_ref @ T_ref_stamp
        if len(r.odom_poses) == 1 and self._first_ref_s:
            # Frame 0 was registered before any velocity was known, so its pose is of its
            # sweep's middle (the world origin). With the first motion now estimated, move it to
            # its stamp like every other frame. Keyframe 0 stays at the middle, where its cloud is.
            r.odom_poses[0] = interpolate(np.eye(4), self.odometry.last_delta,
                                          -self._first_ref_s / dt)
        if not r.odom_poses:
            self._first_ref_s = ref_s
        self._last_dt, self._last_stamp, self._last_ref_s = dt, scan.stamp_s, ref_s
        r.seconds["odometry"] += time.perf_counter() - t0
        is_kf = self.keyframes.is_keyframe(T_world_scan)
        if is_kf:
            self._add_keyframe(scan, points, T_ref_stamp, T_world_scan)
        self._append(scan, T_world_scan)
        if self.viz is not None:
            keep = range_mask(points, self.cfg.data.min_range_m, self.cfg.data.max_range_m)
            self.viz.log_scan(self, scan, transform_points(inverse(T_ref_stamp), points[keep]),
                              T_world_scan, is_kf)

    def _append(self, scan: Scan, T_world_scan: np.ndarray) -> None:
        r = self.result
        if not r.keyframes:  # an empty first scan still needs a keyframe to hang off
            self._add_keyframe(scan, np.zeros((0, 3)), np.eye(4), T_world_scan)
        r.indices.append(scan.index)
        r.stamps_s.append(scan.stamp_s)
        r.odom_poses.append(T_world_scan)
        r.frame_kf.append(r.keyframes[-1].id)

    def _add_keyframe(self, scan: Scan, points: np.ndarray, T_ref_stamp: np.ndarray,
                      T_world_scan: np.ndarray) -> None:
        """Keyframe cloud: points (deskewed, in the odometry's reference frame) within the map
        range, one per voxel, moved to the stamp frame, with their intensity."""
        r = self.result
        max_range_m = min(self.cfg.data.max_range_m, self.cfg.map.max_range_m)
        near = np.flatnonzero(range_mask(points, self.cfg.data.min_range_m, max_range_m))
        idx = near[voxel_first_indices(points[near], self.cfg.keyframes.cloud_voxel_m)]
        pts = points[idx]
        if not np.array_equal(T_ref_stamp, np.eye(4)):  # deskewed to mid-sweep: move to stamp
            pts = transform_points(inverse(T_ref_stamp), pts)
        inten = scan.intensity[idx] if scan.intensity is not None else None
        kf = Keyframe(len(r.keyframes), scan.index, T_world_scan, pts.astype(np.float32),
                      None if inten is None else inten.astype(np.float32))
        r.keyframes.append(kf)
        r.kf_poses[kf.id] = T_world_scan
        if self.loop_closer is not None:  # empty clouds too: the graph needs every keyframe
            t0 = time.perf_counter()
            r.loops.extend(self.loop_closer.add_keyframe(kf))
            r.kf_poses.update(self.loop_closer.kf_poses())
            r.seconds["loops"] += time.perf_counter() - t0


def run(scans: Iterable[Scan], cfg: SlamConfig,
        on_scan: Callable[[Scan, RunResult], None] | None = None, viz=None) -> RunResult:
    """Process scans in order; Ctrl-C stops early and keeps everything computed so far."""
    pipe = Pipeline(cfg, viz)
    try:
        for scan in scans:
            pipe.process(scan)
            if on_scan is not None:
                on_scan(scan, pipe.result)
    except KeyboardInterrupt:
        log.warning("interrupted: keeping the %d frames processed so far", len(pipe.result.indices))
        pipe.result.interrupted = True
    except LidarSlamError as exc:
        pipe.result.error = str(exc)
    except Exception:  # a bug must not cost the frames already computed: keep them, report it
        import traceback

        pipe.result.internal_error = traceback.format_exc()
        log.error("internal error after %d frames", len(pipe.result.indices))
    return pipe.result
