"""Deskewing only the used points against deskewing every point: odometry difference and cost.

Usage: python tools/compare_deskew.py DATA [--config FILE] [--start N] [--n-scans N]

Runs the odometry (no loops) twice on the same scans, once with `data.deskew_all_points: true`
(every point deskewed, then selected, as before) and once with the default (one point per voxel
selected, then deskewed), and prints: the per-frame difference of the two odometries' relative
poses (median and max, mm and deg), each one's ATE and per-frame RPE against the ground truth
when there is one, and odometry ms per frame (front-end + registration, median of the run).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from lidar_slam.config import load_config
from lidar_slam.eval.metrics import ate, rpe
from lidar_slam.geometry import inverse, rotation_angle_deg
from lidar_slam.io.sources import open_source
from lidar_slam.pipeline import Pipeline


def odometry(scans, cfg) -> tuple[np.ndarray, float]:
    pipe = Pipeline(cfg)
    ms = []
    for scan in scans:
        t0 = time.perf_counter()
        pipe.process(scan)
        ms.append(1e3 * (time.perf_counter() - t0))
    poses = np.stack(pipe.result.odom_poses)
    pipe.close()
    return inverse(poses[0]) @ poses, float(np.median(ms))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("data")
    ap.add_argument("--config")
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--n-scans", type=int)
    args = ap.parse_args()
    src = open_source(args.data)
    scans = list(src.scans(args.start, args.n_scans))
    runs = {}
    for name, all_points in (("all points", True), ("used points", False)):
        cfg = load_config(args.config, {"loop": {"enabled": False},
                                        "data": {"deskew_all_points": all_points}})
        runs[name] = odometry(scans, cfg)
    (A, _), (B, _) = runs["all points"], runs["used points"]
    dA, dB = inverse(A[:-1]) @ A[1:], inverse(B[:-1]) @ B[1:]
    E = inverse(dA) @ dB
    dt_mm = 1e3 * np.linalg.norm(E[:, :3, 3], axis=1)
    dr_deg = np.array([rotation_angle_deg(e) for e in E])
    print(f"{args.data}: {len(scans)} scans")
    print(f"per-frame relative-pose difference: median {np.median(dt_mm):.3f} mm / "
          f"{np.median(dr_deg):.4f} deg, max {dt_mm.max():.1f} mm / {dr_deg.max():.3f} deg")
    if src.ground_truth is not None:
        G = src.ground_truth[args.start:args.start + len(scans)]
        G = inverse(G[0]) @ G
        for name, (P, ms) in runs.items():
            r = rpe(P, G)
            print(f"{name:>11}: ATE {ate(P, G).rmse_m:.4f} m, RPE {1e3 * r.trans_m_mean:.2f} mm / "
                  f"{r.rot_deg_mean:.4f} deg per frame, {ms:.1f} ms/frame")
    else:
        for name, (_, ms) in runs.items():
            print(f"{name:>11}: {ms:.1f} ms/frame")


if __name__ == "__main__":
    main()
