"""Stock KISS-SLAM (kiss_slam 0.0.2, default config) on a sequence; writes KITTI poses + closures.

Usage: python tools/peers/kiss_slam_peer.py DATA OUT_POSES [--closures FILE.json] [--start N]
       [--n-scans N] [--config FILE]

Scans are read with lidar_slam's readers, everything else is what kiss_slam.pipeline.SlamPipeline
does in _run_pipeline: process_scan per scan, then generate_new_node(), erase_last_local_map() and
fine_grained_optimization() for per-frame poses. Per-point times are normalised to [0, 1] as
kiss-icp's own readers do (it deskews to the sweep end); scans without times get an empty array.

The closures JSON maps KISS-SLAM's local maps back to frames: local map 0 starts at frame 0 and
local map m > 0 starts (its keypose) at the frame where map m-1 was split off. A closure between
local maps (ref, query) with ICP result T_query_ref becomes the frame pair
(query_frame, match_frame) = (start of query, start of ref) with T_match_query = inv(T_query_ref).
Frames are 0-based input positions, as in lidar-slam's loops.csv.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

# open3d (imported by kiss_slam) needs libusb preloaded where the system lacks it;
# lidar_slam.o3d does that, so it comes first (it was sorted after kiss_slam once, and the peer
# failed on a fresh machine: "libusb-1.0.so.0: cannot open shared object file").
from lidar_slam.o3d import o3d  # noqa: F401

# isort: split
from kiss_slam.config import load_config
from kiss_slam.slam import KissSLAM

from lidar_slam.geometry import inverse, to_xyz_quat
from lidar_slam.io.sources import open_source
from lidar_slam.io.trajectory import write_kitti_poses


def normalised_times(point_times: np.ndarray | None) -> np.ndarray:
    """Per-point times scaled to [0, 1] over the sweep, or an empty array (no deskew)."""
    if point_times is None or len(point_times) == 0:
        return np.array([])
    span = max(float(np.ptp(point_times)), 1e-9)
    return (point_times - point_times.min()) / span


class ClosureSpy:
    """Records (ref_id, query_id, T_query_ref) of every closure KISS-SLAM's LoopCloser accepts."""

    def __init__(self, slam: KissSLAM):
        self.records: list[tuple[int, int, np.ndarray]] = []
        self._compute = slam.closer.compute
        slam.closer.compute = self._recording_compute  # KISS-SLAM's own code path is unchanged

    def _recording_compute(self, query_id, points, local_map_graph):
        is_good, ref_id, query, pose_constraint = self._compute(query_id, points, local_map_graph)
        if is_good:
            self.records.append((int(ref_id), int(query), np.array(pose_constraint)))
        return is_good, ref_id, query, pose_constraint


def local_map_start_frames(slam: KissSLAM, first_frame: int) -> dict[int, int]:
    """Input frame index at each local map's keypose (see module docstring)."""
    starts, frame = {}, first_frame
    for node in slam.local_map_graph.local_maps():
        starts[int(node.id)] = frame
        # Map 0 holds frames 0..n0-1; map m > 0 repeats its start frame as local_trajectory[0].
        frame += len(node.local_trajectory) - 1
    return starts


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("data")
    ap.add_argument("out")
    ap.add_argument("--closures", default=None, help="JSON file for the closures found")
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--n-scans", type=int, default=None)
    ap.add_argument("--config", default=None, help="KISS-SLAM YAML (default: its defaults)")
    args = ap.parse_args()
    slam = KissSLAM(load_config(Path(args.config) if args.config else None))
    spy = ClosureSpy(slam)
    n = 0
    for scan in open_source(args.data).scans(args.start, args.n_scans):
        slam.process_scan(scan.points, normalised_times(scan.point_times))
        n += 1
    # As SlamPipeline._run_pipeline: close the last local map, drop the empty one it opens.
    slam.generate_new_node()
    slam.local_map_graph.erase_last_local_map()
    poses, _ = slam.fine_grained_optimization()
    poses = np.array(poses)
    if len(poses) != n:
        raise SystemExit(f"kiss-slam returned {len(poses)} poses for {n} scans")
    write_kitti_poses(args.out, poses)
    if args.closures:
        starts = local_map_start_frames(slam, args.start)
        closures = []
        for ref_id, query_id, T_query_ref in spy.records:
            closures.append({
                "query_local_map": query_id, "match_local_map": ref_id,
                "query_frame": starts[query_id], "match_frame": starts[ref_id],
                "T_match_query_xyz_quat": to_xyz_quat(inverse(T_query_ref)).tolist(),
            })
        Path(args.closures).write_text(json.dumps({
            "frames": n, "local_maps": len(starts), "closures": closures,
            "local_map_start_frames": {str(k): v for k, v in starts.items()},
        }, indent=2) + "\n")


if __name__ == "__main__":
    main()
