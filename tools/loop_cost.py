"""Cost of loop detection + verification per keyframe on KITTI-sized scans (~120k points).

KITTI 00 frames 0-15 hold no loop, so the last scan is queried against the others (recent ones
not excluded) and verified against several earlier ones 3-13 m back, with the ground truth
saying whether the verified pose is right (1 m / 5 deg). Keyframe clouds are built like the
pipeline's (range <= map.max_range_m, keyframes.cloud_voxel_m voxels); query and match clouds are
submaps (LoopCloser: the keyframe and its predecessors / +-N neighbours, merged with GT poses).

Prints wall and CPU milliseconds (CPU sums threads; on a shared machine it is the fairer number).
Usage: python tools/loop_cost.py [KITTI_SEQ_DIR] [--config FILE] [--set a.b=value] [--repeats N]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from lidar_slam.config import load_config
from lidar_slam.frontend.downsample import voxel_downsample
from lidar_slam.geometry import inverse, relative, rotation_angle_deg, transform_points
from lidar_slam.io.sources import KittiSource
from lidar_slam.loop.scan_context import ScanContextIndex, describe
from lidar_slam.loop.verify import verify
from lidar_slam.types import LoopCandidate

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data" / "kitti00_first16"


def timed(fn, repeats: int):
    """(result, median wall ms, median CPU ms) of fn() over repeats runs."""
    walls, cpus = [], []
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        out = fn()
        walls.append((time.perf_counter() - w) * 1e3)
        cpus.append((time.process_time() - c) * 1e3)
    return out, float(np.median(walls)), float(np.median(cpus))


def main() -> None:
    from loop_sweep import overrides  # same folder

    ap = argparse.ArgumentParser()
    ap.add_argument("data", nargs="?", default=str(DEFAULT_DATA))
    ap.add_argument("--config", default=None)
    ap.add_argument("--set", action="append", default=[], help="config override a.b=value")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    cfg = load_config(args.config, overrides(args.set))
    sc_cfg, v_cfg = cfg.loop.scan_context.model_copy(update={"exclude_recent": 0}), cfg.loop.verify
    src = KittiSource(Path(args.data))
    poses = src.ground_truth
    raw = [s.points for s in src.scans()]
    print(f"{len(raw)} scans, {np.mean([len(p) for p in raw]):.0f} points each on average")

    def kf_cloud(pts: np.ndarray) -> np.ndarray:
        pts = pts[np.linalg.norm(pts, axis=1) <= cfg.map.max_range_m]
        return voxel_downsample(pts, cfg.keyframes.cloud_voxel_m)[0]

    clouds, w, c = timed(lambda: [kf_cloud(p) for p in raw], 1)
    print(f"keyframe cloud (crop + {cfg.keyframes.cloud_voxel_m} m voxels, pipeline's cost): "
          f"{w / len(raw):.1f} ms wall per scan -> {np.mean([len(p) for p in clouds]):.0f} points")
    _, w, c = timed(lambda: describe(raw[-1], sc_cfg), args.repeats)
    print(f"scan context of a raw scan ({len(raw[-1])} points): {w:.1f} ms wall, {c:.1f} ms CPU")
    _, w, c = timed(lambda: describe(clouds[-1], sc_cfg), args.repeats)
    print(f"scan context of a keyframe cloud ({len(clouds[-1])} points): {w:.1f} ms wall, "
          f"{c:.1f} ms CPU")
    q = len(clouds) - 1

    def detect():
        index = ScanContextIndex(sc_cfg)
        for k in range(q):
            index.add(k, clouds[k])
        t = time.perf_counter(), time.process_time()
        res = index.query(q, clouds[q])
        return res, (time.perf_counter() - t[0]) * 1e3, (time.process_time() - t[1]) * 1e3

    res, w, c = detect()
    print(f"detection (query vs {q} keyframes, incl. descriptor): {w:.1f} ms wall, {c:.1f} ms CPU;"
          f" best match {res.best_match} at distance {res.best_distance:.3f}")

    def submap(k: int, before: int, after: int) -> np.ndarray:
        parts = [transform_points(relative(poses[k], poses[j]), clouds[j])
                 for j in range(max(0, k - before), min(len(clouds), k + after + 1))]
        return np.vstack(parts)

    r = v_cfg.submap_radius
    source = submap(q, r, 0)
    print(f"verification (query submap {len(source)} points, match submaps +-{r}):")
    for m in (0, 3, 5, 8, 10):
        target = submap(m, r, r)
        dist, yaw = 0.0, 0.0
        for cand in res.candidates:
            if cand.match == m:
                dist, yaw = cand.score, cand.yaw_guess_rad
        cand = LoopCandidate(q, m, dist, yaw)
        v, w, c = timed(lambda: verify(cand, source, target, v_cfg), args.repeats)
        d = inverse(relative(poses[m], poses[q])) @ v.T_match_query
        err_m, err_deg = float(np.linalg.norm(d[:3, 3])), float(rotation_angle_deg(d))
        ok = err_m < 1.0 and err_deg < 5.0
        print(f"  {q} -> {m} ({np.linalg.norm(poses[q][:3, 3] - poses[m][:3, 3]):4.1f} m, "
              f"{len(target)} pts): {w:6.1f} ms wall {c:6.1f} ms CPU  fitness {v.fitness:.2f} "
              f"margin {v.margin:.2f} {'ACCEPT' if v.accepted else 'reject'} "
              f"{'correct' if ok else 'WRONG'} ({err_m:.2f} m {err_deg:.1f} deg)  {v.reason}")


if __name__ == "__main__":
    main()
