"""Where the odometry's time goes, per stage, in ms per frame (no loops, one process).

Usage: python tools/speed_probe.py DATA [--start N] [--n-scans N] [--repeats N]

Runs the pipeline without loops in three front-end modes, interleaved over the repeats: scans
without deskew (exactly stock kiss-icp's registration), deskew of the used points only (the
default) and deskew of every point (`data.deskew_all_points`), and prints the median total and
per-stage times: `deskewer` (selection + deskew), `select` (kiss-icp's C++ crop + voxel
selection, also at keyframes), `register` (kiss-icp's registration and map update) and
`add_keyframe`. Run it once as is and once with LIDAR_SLAM_MALLOC_DEFAULTS=1 to see what glibc's
default mmap threshold costs (lidar_slam.runtime.tune_process).
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict

import numpy as np

import lidar_slam.frontend.deskew as deskew_mod
import lidar_slam.frontend.odometry as odometry_mod
import lidar_slam.pipeline as pipeline_mod
from lidar_slam.config import load_config
from lidar_slam.io.sources import open_source
from lidar_slam.runtime import tune_process

TIMES: dict[str, float] = defaultdict(float)


def _timed(name: str, fn):
    def wrapper(*args, **kwargs):
        t0 = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            TIMES[name] += time.perf_counter() - t0

    return wrapper


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("data")
    ap.add_argument("--start", type=int, default=100)
    ap.add_argument("--n-scans", type=int, default=150)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    tune_process()  # as a run does (its malloc part; NumPy is imported already)
    odometry_mod.Odometry.register = _timed("register", odometry_mod.Odometry.register)
    odometry_mod.VoxelSelector.__call__ = _timed("select", odometry_mod.VoxelSelector.__call__)
    pipeline_mod.Pipeline._add_keyframe = _timed("add_keyframe",
                                                 pipeline_mod.Pipeline._add_keyframe)
    deskew_mod.Deskewer.__call__ = _timed("deskewer", deskew_mod.Deskewer.__call__)
    scans = list(open_source(args.data).scans(args.start, args.n_scans))
    modes = {"no deskew": {"deskew": False}, "used points": {},
             "all points": {"deskew_all_points": True}}
    results: dict[str, list[dict]] = defaultdict(list)
    for _ in range(args.repeats):
        for mode, data in modes.items():
            TIMES.clear()
            pipe = pipeline_mod.Pipeline(load_config(None, {"loop": {"enabled": False},
                                                            "data": data}))
            t0 = time.perf_counter()
            for scan in scans:
                pipe.process(scan)
            TIMES["total"] = time.perf_counter() - t0
            pipe.close()
            results[mode].append({k: 1e3 * v / len(scans) for k, v in TIMES.items()})
    print(f"{args.data} frames {args.start}..{args.start + len(scans) - 1}, median of "
          f"{args.repeats} (ms/frame)")
    for mode, runs in results.items():
        keys = sorted({k for r in runs for k in r}, key=lambda k: (k != "total", k))
        cells = ", ".join(f"{k} {np.median([r.get(k, 0.0) for r in runs]):.1f}" for k in keys)
        print(f"{mode:>12}: {cells}")


if __name__ == "__main__":
    main()
