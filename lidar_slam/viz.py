"""Rerun visualisation: the only module that imports rerun (imported only with --viz / --rrd).

Logged: the current scan (world frame), the growing map (keyframe clouds), the odometry trajectory,
keyframes, accepted loop edges, and at the end the optimised trajectory and map and the keyframe
position covariances (3-sigma ellipsoids). Time is set per scan on the `frame` (input index) and
`stamp` (seconds) timelines.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import rerun as rr

from lidar_slam.errors import InputError
from lidar_slam.frontend.downsample import voxel_downsample
from lidar_slam.geometry import quat_from_matrix, transform_points

SCAN_VOXEL_M = 0.3
COVARIANCE_SIGMAS = 3.0  # keyframe position ellipsoids are drawn at 3 sigma
log = logging.getLogger(__name__)


def _first_line(exc: Exception) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


class RerunViz:
    """Logs a run to a live viewer (spawn=True) and/or an .rrd recording."""

    def __init__(self, spawn: bool = False, rrd_path: str | Path | None = None):
        self.rec = rr.RecordingStream("lidar_slam")
        if rrd_path is not None:
            try:
                Path(rrd_path).parent.mkdir(parents=True, exist_ok=True)
                self.rec.save(str(rrd_path))
            except (OSError, RuntimeError) as exc:  # rerun reports an unwritable path this way
                raise InputError(rrd_path, f"cannot write the recording ({exc})") from exc
        if spawn:
            try:
                self.rec.spawn()
            except (RuntimeError, OSError) as exc:  # no viewer binary, or it cannot start
                log.warning("--viz: the rerun viewer did not start (%s); the run goes on",
                            _first_line(exc))
        self._n_loops = 0
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)

    def log_scan(self, pipe, scan, points_scan: np.ndarray, T_world_scan: np.ndarray,
                 is_keyframe: bool) -> None:
        """Log one processed scan and whatever the pipeline added with it."""
        rec, result = self.rec, pipe.result
        rec.set_time("frame", sequence=scan.index)
        rec.set_time("stamp", duration=float(scan.stamp_s))
        pts, _ = voxel_downsample(points_scan, SCAN_VOXEL_M)
        rec.log("world/scan", rr.Points3D(transform_points(T_world_scan, pts), radii=0.05,
                                          colors=[255, 200, 0]))
        rec.log("world/sensor", rr.Transform3D(translation=T_world_scan[:3, 3],
                                               mat3x3=T_world_scan[:3, :3]))
        odom = np.stack(result.odom_poses)[:, :3, 3]
        rec.log("world/odometry", rr.LineStrips3D([odom], colors=[200, 80, 80], radii=0.05))
        if is_keyframe:
            kf = result.store.get(len(result.store) - 1)
            rec.log(f"world/map/kf_{kf.id:06d}",
                    rr.Points3D(transform_points(kf.T_world_kf_odom, kf.points), radii=0.04,
                                colors=[150, 150, 150]))
            kf_xyz = result.store.table()["T"][:, :3, 3]
            rec.log("world/keyframes", rr.Points3D(kf_xyz, radii=0.15, colors=[60, 120, 255]))
        accepted = [row for row in result.loops if row.accepted]
        if len(accepted) != self._n_loops:
            self._n_loops = len(accepted)
            self._log_loops(accepted, pipe.current_kf_poses())

    def _log_loops(self, accepted, kf_poses) -> None:
        strips = [np.stack([kf_poses[row.query_kf][:3, 3], kf_poses[row.match_kf][:3, 3]])
                  for row in accepted]
        self.rec.log("world/loops", rr.LineStrips3D(strips, colors=[0, 220, 0], radii=0.1))

    def _log_covariances(self, covariances: dict, kf_poses: dict) -> None:
        """The position part of every keyframe's covariance as its COVARIANCE_SIGMAS ellipsoid,
        turned from the keyframe's frame into the world's."""
        keys = [k for k in sorted(covariances) if k in kf_poses]
        if not keys:
            return
        centers, half_sizes, rotations = [], [], []
        for k in keys:
            R = kf_poses[k][:3, :3]
            values, axes = np.linalg.eigh(R @ covariances[k][3:, 3:] @ R.T)
            if np.linalg.det(axes) < 0:
                axes[:, 0] = -axes[:, 0]
            centers.append(kf_poses[k][:3, 3])
            half_sizes.append(COVARIANCE_SIGMAS * np.sqrt(np.clip(values, 0.0, None)))
            rotations.append(axes)
        self.rec.log("world/covariances",
                     rr.Ellipsoids3D(centers=centers, half_sizes=half_sizes,
                                     quaternions=quat_from_matrix(np.stack(rotations)),
                                     colors=[255, 120, 0]), static=True)

    def finish(self, result, map_path: Path) -> None:
        """Log the final (optimised) trajectory and the written map, then flush the recording."""
        if result.odom_poses:
            from lidar_slam.geometry import inverse
            from lidar_slam.io.ply import read_ply

            poses = result.final_poses()
            anchor = inverse(poses[0])  # the written files' world: frame 0 at its stamp
            poses = anchor @ poses
            self.rec.log("world/optimised", rr.LineStrips3D([poses[:, :3, 3]], colors=[0, 200, 255],
                                                            radii=0.06), static=True)
            cloud, _ = voxel_downsample(read_ply(map_path)[0], SCAN_VOXEL_M)
            self.rec.log("world/optimised_map", rr.Points3D(cloud, radii=0.04), static=True)
            self._log_loops([row for row in result.loops if row.accepted],
                            {k: anchor @ T for k, T in result.kf_poses.items()})
            self._log_covariances(result.kf_covariances,
                                  {k: anchor @ T for k, T in result.kf_poses.items()})
        try:
            self.rec.flush()
            self.rec.disconnect()
        except RuntimeError as exc:  # the viewer went away or never came up (no display)
            log.warning("--viz: the rerun viewer could not be reached (%s); nothing shown",
                        _first_line(exc))
