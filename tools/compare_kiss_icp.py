"""Side by side: stock KISS-ICP vs lidar-slam (odometry only) on the same scans.

Prints per-frame RPE (translation m, rotation deg) against the ground truth for both, and
whole-process frames/s (median of --repeats runs) and peak memory of each.

Usage: python tools/compare_kiss_icp.py DATA [--repeats 3] [--start N] [--n-scans N]
       [--config FILE] [--deskew]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from lidar_slam.geometry import inverse
from lidar_slam.io.sources import open_source
from lidar_slam.io.trajectory import read_kitti_poses
from lidar_slam.metrics import rpe

HERE = Path(__file__).resolve().parent


def timed(cmd: list[str]) -> tuple[float, float]:
    """Wall seconds and peak RSS (MB) of one child process."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    err = proc.stderr.read().decode() if proc.stderr else ""
    if os.waitstatus_to_exitcode(status) != 0:
        sys.exit(f"failed: {' '.join(cmd)}\n{err}")
    return wall, usage.ru_maxrss / 1024.0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("data")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--n-scans", type=int, default=None)
    ap.add_argument("--config", default=None)
    ap.add_argument("--deskew", action="store_true", help="give stock kiss-icp the point times")
    args = ap.parse_args()
    src = open_source(args.data)
    n = len(src) - args.start if args.n_scans is None else args.n_scans
    rng = ["--start", str(args.start), "--n-scans", str(n)]
    tmp = Path(tempfile.mkdtemp(prefix="compare_"))
    stock_cmd = [sys.executable, str(HERE / "stock_kiss_icp.py"), args.data, str(tmp / "stock.txt"),
                 *rng] + (["--deskew"] if args.deskew else [])
    ours_cmd = [sys.executable, "-m", "lidar_slam.cli", "run", args.data, "--out", str(tmp / "ours"),
                "--overwrite", "--no-loops", *rng] + (["--config", args.config] if args.config else [])
    runs: dict[str, list[tuple[float, float]]] = {"stock kiss-icp": [], "lidar-slam": []}
    for _ in range(args.repeats):  # interleaved so both see the same machine load
        runs["stock kiss-icp"].append(timed(stock_cmd))
        runs["lidar-slam"].append(timed(ours_cmd))
    est = {"stock kiss-icp": read_kitti_poses(tmp / "stock.txt"),
           "lidar-slam": read_kitti_poses(tmp / "ours" / "poses_kitti.txt")}
    if src.ground_truth is not None:
        gt = src.ground_truth[args.start:args.start + n]
        gt = inverse(gt[0]) @ gt
        errs = {k: rpe(v, gt) for k, v in est.items()}
        print("frame  stock_t_m  ours_t_m  stock_r_deg  ours_r_deg")
        s, o = errs["stock kiss-icp"], errs["lidar-slam"]
        for i in range(len(s.trans_m)):
            print(f"{args.start + i + 1:5d}  {s.trans_m[i]:9.4f}  {o.trans_m[i]:8.4f}  "
                  f"{s.rot_deg[i]:11.4f}  {o.rot_deg[i]:10.4f}")
    print(f"\n{'system':16s} {'rpe_t mean m':>12s} {'rpe_r mean deg':>14s} {'frames/s':>9s} "
          f"{'peak MB':>8s}")
    fps = {}
    for name, vals in runs.items():
        wall = statistics.median(v[0] for v in vals)
        fps[name] = n / wall
        mem = max(v[1] for v in vals)
        t_mean = errs[name].trans_m_mean if src.ground_truth is not None else float("nan")
        r_mean = errs[name].rot_deg_mean if src.ground_truth is not None else float("nan")
        print(f"{name:16s} {t_mean:12.4f} {r_mean:14.4f} {fps[name]:9.2f} {mem:8.0f}")
    print(f"\nspeed ratio lidar-slam / stock = {fps['lidar-slam'] / fps['stock kiss-icp']:.3f} "
          f"(whole process, median of {args.repeats}, {n} frames)")


if __name__ == "__main__":
    main()
