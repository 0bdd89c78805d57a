"""Time the rosbag reader: open + read every shared container, and decode_pointcloud2 alone.

Usage: python tools/bench_rosbag.py [../shared/data/rosbags]
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from lidar_slam.io.rosbag import RosbagSource, decode_pointcloud2, open_bag

ROOT = Path(sys.argv[1] if len(sys.argv) > 1 else Path(__file__).parents[2] / "shared/data/rosbags")
CONTAINERS = ["ouster_os1_64_points_ros1_profile.mcap",
              "converted_by_rosbags/ouster_os1_64_points.bag",
              "converted_by_rosbags/ouster_os1_64_points_ros2_sqlite3",
              "converted_by_rosbags/ouster_os1_64_points_ros2_mcap"]


def main() -> None:
    for name in CONTAINERS:
        t0 = time.perf_counter()
        source = RosbagSource(ROOT / name)
        t1 = time.perf_counter()
        scans = list(source.scans())
        t2 = time.perf_counter()
        print(f"{name}: open {1e3 * (t1 - t0):.1f} ms, {len(scans)} scans in "
              f"{1e3 * (t2 - t1):.1f} ms, points {[len(s.points) for s in scans]}")
    with open_bag(ROOT / CONTAINERS[1]) as bag:
        msg = next(bag.raw_messages("/os1_cloud_node/points"))[0]()
    runs = 50
    t0 = time.perf_counter()
    for _ in range(runs):
        cloud = decode_pointcloud2(msg)
    dt_ms = 1e3 * (time.perf_counter() - t0) / runs
    print(f"decode_pointcloud2 {msg.height}x{msg.width} = {msg.height * msg.width} points: "
          f"{dt_ms:.2f} ms ({len(cloud.points)} kept, {cloud.n_dropped} dropped)")


if __name__ == "__main__":
    main()
