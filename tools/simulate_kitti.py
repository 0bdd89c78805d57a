"""Simulate HDL-64 sequences along KITTI ground truths and measure stock KISS-ICP on them.

    python tools/simulate_kitti.py /work/simdata [--seqs 07 00 05 08] [--frames 1100] [--reuse]

For each sequence: simulate_sequence() into OUT/XX (KITTI layout), then stock KISS-ICP
(kiss_icp.kiss_icp.KissICP, load_config(None) defaults) registers every scan with its per-point
times (kiss-icp min-max normalises them to [0, 1] and deskews every point to the END of the sweep,
so its pose i is compared with the true pose at stamp_i + max point time). Prints KITTI drift
(t_err %, r_err deg/100 m, lidar_slam.eval.metrics.kitti_drift) and seconds per frame.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np
from kiss_icp.config import load_config
from kiss_icp.kiss_icp import KissICP

from lidar_slam.eval.metrics import ate, kitti_drift
from lidar_slam.io.trajectory import (
    camera_to_lidar_poses,
    read_kitti_calib_tr,
    read_kitti_poses,
    read_times,
)
from lidar_slam.sim import PoseInterpolator, load_kitti_truth, simulate_sequence

GT_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti_gt"
# 08's truth climbs ~0.18 m per frame while level over frames 0..~120 (see kitti_gt/README.txt).
START = {"08": 150}


def read_sequence_truth(seq_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """(stamps_s, T_seq_lidar (K, 4, 4)) of a simulated sequence, read back through its calib."""
    Tr = read_kitti_calib_tr(seq_dir / "calib.txt")
    return read_times(seq_dir / "times.txt"), camera_to_lidar_poses(
        read_kitti_poses(seq_dir / "poses.txt"), Tr)


def run_kiss_icp(seq_dir: Path) -> dict:
    """Stock KISS-ICP over a simulated sequence; drift against the truth at each sweep's end."""
    stamps, truth = read_sequence_truth(seq_dir)
    kiss = KissICP(load_config(None))
    est, t_end = [], []
    t0 = time.perf_counter()
    for k in range(len(stamps)):
        pts = np.fromfile(seq_dir / "velodyne" / f"{k:06d}.bin", np.float32).reshape(-1, 4)
        times = np.fromfile(seq_dir / "velodyne_times" / f"{k:06d}.bin", np.float32)
        kiss.register_frame(pts[:, :3].astype(np.float64), times.astype(np.float64))
        est.append(kiss.last_pose.copy())
        t_end.append(stamps[k] + float(times.max()))
    secs = (time.perf_counter() - t0) / len(stamps)
    est = np.array(est)
    gt_end = PoseInterpolator(stamps, truth)(np.array(t_end))
    drift = kitti_drift(est, gt_end)
    drift_start = kitti_drift(est, truth)
    return {
        "frames": len(stamps),
        "gt_length_m": drift.gt_path_length_m,
        "t_err_pct": drift.t_err_pct,
        "r_err_deg_per_100m": drift.r_err_deg_per_100m,
        "t_err_pct_vs_sweep_start": drift_start.t_err_pct,
        "ate_m": ate(est, gt_end).rmse_m,
        "kiss_s_per_frame": secs,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out_dir", type=Path)
    ap.add_argument("--seqs", nargs="+", default=["07", "00", "05", "08"])
    ap.add_argument("--frames", type=int, default=1100)
    ap.add_argument("--sensor", default="hdl64")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--gt-dir", type=Path, default=GT_DIR)
    ap.add_argument("--reuse", action="store_true", help="skip simulation where OUT/XX exists")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    if args.out_dir.resolve().is_relative_to(Path(__file__).resolve().parents[1]):
        ap.error("write simulations outside the repository")
    rows = []
    for seq in args.seqs:
        seq = f"{int(seq):02d}"
        out = args.out_dir / seq
        row = {"seq": seq, "start": START.get(seq, 0)}
        if not (args.reuse and (out / "poses.txt").is_file()):
            gt = load_kitti_truth(args.gt_dir, seq)
            s = simulate_sequence(gt.poses_world_lidar, gt.stamps_s, out, args.sensor, args.seed,
                                  start=row["start"], n_scans=args.frames,
                                  Tr_cam_lidar=gt.Tr_cam_lidar)
            row.update(sim_s_per_frame=s.seconds_per_scan, world_s=s.world_seconds,
                       points_per_scan=s.points_per_scan, triangles=s.n_triangles)
        row.update(run_kiss_icp(out))
        rows.append(row)
        print(json.dumps(row), flush=True)
    print("\n| seq | start | frames | GT m | t_err % | r_err deg/100m | ATE m | sim s/frame "
          "| kiss s/frame |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['seq']} | {r['start']} | {r['frames']} | {r['gt_length_m']:.0f} | "
              f"{r['t_err_pct']:.2f} | {r['r_err_deg_per_100m']:.2f} | {r['ate_m']:.2f} | "
              f"{r.get('sim_s_per_frame', float('nan')):.3f} | {r['kiss_s_per_frame']:.3f} |")
    (args.out_dir / "kiss_icp_results.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
