"""Replay a finished run's keyframes through the loop detector in this one process, and print
where its CPU time goes (what the loop worker process did during the run, without the odometry
beside it).

Usage: python tools/loop_worker_replay.py RUN_DIR [--top N]

RUN_DIR: a finished `lidar-slam run` folder with loops on (its config.yaml, summary.json
auto_settings and keyframes/). The store is copied to a temporary folder (the detector writes
its descriptor grids next to it). Prints the seconds per 200 keyframes, the accepted loops, and
cProfile's top functions by own time. Full sim 00: ~40 s.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import shutil
import tempfile
import time
from pathlib import Path

from lidar_slam.config import load_config
from lidar_slam.loop import adapt
from lidar_slam.loop.detector import LoopDetector
from lidar_slam.map.keyframes import TABLE_DTYPE, KeyframeReader


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--top", type=int, default=20)
    args = ap.parse_args()
    summary = json.loads((args.run / "summary.json").read_text())
    cfg = adapt.apply(load_config(args.run / "config.yaml"), summary.get("auto_settings", {}))
    tmp = Path(tempfile.mkdtemp(prefix="loop_replay_"))
    try:
        for name in ("table.bin", "points.bin"):
            shutil.copy(args.run / "keyframes" / name, tmp / name)
        n = (tmp / "table.bin").stat().st_size // TABLE_DTYPE.itemsize
        detector = LoopDetector(cfg, KeyframeReader(tmp))
        per, accepted = [], 0
        prof = cProfile.Profile()
        prof.enable()
        for kf_id in range(n):
            t0 = time.perf_counter()
            accepted += detector.process(kf_id).constraint is not None
            per.append(time.perf_counter() - t0)
        prof.disable()
        detector.index.close()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"{n} keyframes, {accepted} loops accepted, {sum(per):.1f} s")
    for start in range(0, n, 200):
        print(f"  keyframes {start}-{min(n, start + 200) - 1}: {sum(per[start:start + 200]):.2f} s")
    pstats.Stats(prof).sort_stats("tottime").print_stats(args.top)


if __name__ == "__main__":
    main()
