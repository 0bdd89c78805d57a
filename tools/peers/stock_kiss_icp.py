"""Stock KISS-ICP (kiss_icp.kiss_icp.KissICP, default config) on a sequence; writes KITTI poses.

Usage: python tools/peers/stock_kiss_icp.py DATA OUT_POSES [--start N] [--n-scans N] [--deskew]
Scans are read with lidar_slam's readers (NumPy only for .bin), everything else is kiss-icp's own.
With --deskew, per-point times are normalised to [0, 1] and passed to register_frame, which then
deskews internally (to the sweep end, as kiss-icp does).
"""

from __future__ import annotations

import argparse

import numpy as np
from kiss_icp.config import load_config
from kiss_icp.kiss_icp import KissICP

from lidar_slam.io.sources import open_source
from lidar_slam.io.trajectory import write_kitti_poses


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("data")
    ap.add_argument("out")
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--n-scans", type=int, default=None)
    ap.add_argument("--deskew", action="store_true")
    args = ap.parse_args()
    odom = KissICP(load_config(None))
    poses = []
    for scan in open_source(args.data).scans(args.start, args.n_scans):
        times = np.array([])
        if args.deskew and scan.point_times is not None:
            span = max(float(np.ptp(scan.point_times)), 1e-9)
            times = (scan.point_times - scan.point_times.min()) / span
        odom.register_frame(scan.points, times)
        poses.append(odom.last_pose.copy())
    write_kitti_poses(args.out, np.stack(poses))


if __name__ == "__main__":
    main()
