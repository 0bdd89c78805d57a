"""Replay a run's graph.g2o through the pipeline's back-end, keyframe by keyframe.

Usage: python tools/backend_replay.py RUN/graph.g2o [--lag 10] [--config FILE]

Keyframes arrive in id order with their odometry (the chained odometry edges); each loop edge
(ids not consecutive) arrives when keyframe query + lag arrives, as the loop worker's results
are applied in a run. Prints the back-end's milliseconds per loop update (median by thirds of
the keyframes, and the maximum), the RSS growth of this process over the replay, and the
final solve's time, so back-end settings can be compared without re-running the front-end.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import psutil

from lidar_slam.backend.slam_backend import Backend
from lidar_slam.config import load_config
from lidar_slam.io.g2o import read_g2o
from lidar_slam.types import LoopConstraint


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("graph")
    ap.add_argument("--lag", type=int, default=None, help="keyframes (default: the config's)")
    ap.add_argument("--config", default=None)
    args = ap.parse_args()
    cfg = load_config(args.config)
    lag = cfg.loop.collect_lag_keyframes if args.lag is None else args.lag
    g = read_g2o(args.graph)
    odo = {e.i: e for e in g.edges if e.j == e.i + 1}
    loops: dict[int, list] = {}
    for e in g.edges:
        if e.j != e.i + 1:
            match, query = min(e.i, e.j), max(e.i, e.j)
            T = e.T_i_j if e.i == match else np.linalg.inv(e.T_i_j)
            loops.setdefault(query + lag, []).append(
                LoopConstraint(query, match, T, e.information, 1.0, 0.0))
    n = max(g.poses) + 1
    proc = psutil.Process()
    backend = Backend(cfg.backend)
    T = np.eye(4)
    rss0 = proc.memory_info().rss / 2**20
    t_run = time.perf_counter()
    rss = []
    for k in range(n):
        if k > 0:
            T = T @ odo[k - 1].T_i_j
        backend.add_keyframe(k, T)
        for c in loops.get(k, []):
            backend.add_loop(c)
        backend.update(force=False)
        if k % 500 == 0:
            rss.append((k, proc.memory_info().rss / 2**20))
    t_run = time.perf_counter() - t_run
    t0 = time.perf_counter()
    backend.finish()
    t_finish = time.perf_counter() - t0
    ms = np.array([(kf, s * 1e3) for kf, s in backend.loop_update_s])
    thirds = [np.median(ms[(ms[:, 0] >= a * n / 3) & (ms[:, 0] < (a + 1) * n / 3), 1])
              if np.any((ms[:, 0] >= a * n / 3) & (ms[:, 0] < (a + 1) * n / 3)) else np.nan
              for a in range(3)]
    print(f"keyframes={n} loops={sum(len(v) for v in loops.values())} "
          f"loop_updates={len(ms)}")
    print("backend_ms_per_loop_median_by_third=" + " / ".join(f"{x:.1f}" for x in thirds)
          + f" max={ms[:, 1].max():.1f} total_s={t_run:.1f} finish_s={t_finish:.1f}")
    print("rss_mb " + " ".join(f"{k}:{r - rss0:+.1f}" for k, r in rss))


if __name__ == "__main__":
    main()
