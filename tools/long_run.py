"""A long drive streamed straight from the simulator into the pipeline (no scans on disk).

Usage: python tools/long_run.py --out DIR [--frames 10000] [--sequence 00] [--config FILE]
                                [--every 500] [--uturn-frames 30]

The drive follows a KITTI ground-truth trajectory (lidar frame) forward, turns round on the
spot, drives it back in the opposite direction, turns again and drives forward again, until
--frames scans (10 Hz); so it revisits every place in both directions. Scans are simulated
HDL-64E sweeps with per-point times (true motion distortion) in the world built along the
trajectory, fed one by one to lidar_slam.pipeline.Pipeline with the run folder DIR/run (keyframe
store on disk, as `lidar-slam run`).

Every --every frames it records RSS (MB: summed, the main process, the loop worker, and the
file-backed part of the sum), the pipeline's frames/s over the
window (simulation time excluded) and the loops accepted so far; every loop's back-end update
time (ms) is recorded with its keyframe's frame. Writes DIR/long_run.csv (one row per sample),
DIR/long_run_loops.csv, DIR/long_run.json (summary: RSS at frame 2,000 and at the last frame,
per-loop back-end time by thirds of the drive, ATE against the simulated truth) and
DIR/long_run.png (RSS, frames/s and back-end ms per loop against frame index). The run's outputs
(poses, map, loops.csv) are written to DIR/run as `lidar-slam run` writes them.
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

import numpy as np
import psutil

from lidar_slam.config import load_config
from lidar_slam.geometry import make_pose
from lidar_slam.pipeline import Pipeline
from lidar_slam.run.outputs import write_run
from lidar_slam.types import Scan

REPO = Path(__file__).resolve().parents[1]
KITTI_GT = REPO.parent / "shared" / "data" / "kitti_gt"


def _yaw(rad: float) -> np.ndarray:
    c, s = np.cos(rad), np.sin(rad)
    return make_pose(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), np.zeros(3))


def drive(lap: np.ndarray, frames: int, uturn_frames: int) -> np.ndarray:
    """T_world_lidar (frames, 4, 4): lap forward, a U-turn on the spot, the lap backwards
    (facing the other way), a U-turn, forward again, ... cut at `frames`."""
    flip = _yaw(np.pi)
    back = lap[::-1] @ flip
    legs, forward = [], True
    while sum(len(x) for x in legs) < frames:
        leg = lap if forward else back
        legs.append(leg)
        end = leg[-1]
        legs.append(np.stack([end @ _yaw(np.pi * (k + 1) / (uturn_frames + 1))
                              for k in range(uturn_frames)]))
        forward = not forward
    return np.concatenate(legs)[:frames]


def rss_mb() -> dict[str, float]:
    """Resident memory (MB): summed over this process and every child it started (rss_mb),
    this process alone (main_mb), its children (workers_mb), and the file-backed part of the
    sum (file_mb: mapped libraries and files, which the kernel can drop and re-read)."""
    main = psutil.Process()
    procs = [main] + main.children(True)
    info = [p.memory_info() for p in procs]
    mb = 2**20
    return {"rss_mb": round(sum(i.rss for i in info) / mb, 1),
            "main_mb": round(info[0].rss / mb, 1),
            "workers_mb": round(sum(i.rss for i in info[1:]) / mb, 1),
            "file_mb": round(sum(i.shared for i in info) / mb, 1)}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--frames", type=int, default=10000)
    ap.add_argument("--sequence", default="00")
    ap.add_argument("--config", type=Path)
    ap.add_argument("--every", type=int, default=500)
    ap.add_argument("--uturn-frames", type=int, default=30)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    # Here, not at the top: the loop worker process (spawned) imports this module, and the
    # simulator's open3d would add ~230 MB to it that `lidar-slam run`'s worker does not have.
    from lidar_slam.sim import (
        PoseInterpolator,
        build_world,
        get_sensor,
        load_kitti_truth,
        place_on_terrain,
        simulate_scan,
    )

    args.out.mkdir(parents=True, exist_ok=True)
    truth = load_kitti_truth(KITTI_GT, args.sequence)
    sensor = get_sensor("hdl64")
    t0 = time.perf_counter()
    world = build_world(truth.poses_world_lidar, sensor, args.seed)
    poses = place_on_terrain(drive(truth.poses_world_lidar, args.frames, args.uturn_frames),
                             world.terrain, sensor.mount_height_m)
    stamps = 0.1 * np.arange(len(poses))
    interp = PoseInterpolator(stamps, poses)
    print(f"world built in {time.perf_counter() - t0:.0f} s; {len(poses)} frames to drive")
    cfg = load_config(args.config)
    pipe = Pipeline(cfg, args.out / "run")
    samples, window_s, sim_s, t_start = [], 0.0, 0.0, time.perf_counter()
    for k in range(len(poses)):
        ts = time.perf_counter()
        sim = simulate_scan(world, sensor, interp, float(stamps[k]),
                            np.random.default_rng([args.seed, 1, k]))
        scan = Scan(k, float(stamps[k]), sim.points, sim.times_s, sim.intensity.astype(np.float32),
                    f"sim:{k}")
        tp = time.perf_counter()
        sim_s += tp - ts
        pipe.process(scan)
        window_s += time.perf_counter() - tp
        if (k + 1) % args.every == 0 or k + 1 == len(poses):
            n = (k + 1) - (samples[-1]["frame"] if samples else 0)
            row = {"frame": k + 1, **rss_mb(),
                   "fps": round(n / max(window_s, 1e-9), 2),
                   "keyframes": len(pipe.result.store),
                   "loops_accepted": sum(r.accepted for r in pipe.result.loops),
                   "elapsed_s": round(time.perf_counter() - t_start, 1)}
            samples.append(row)
            window_s = 0.0
            print(" ".join(f"{key}={val}" for key, val in row.items()), flush=True)
    result = pipe.finish()
    wall = time.perf_counter() - t_start
    T0 = poses[0]
    gt = np.linalg.inv(T0) @ poses
    summary = write_run(args.out / "run", result, cfg, gt, wall, extra={"input": "long_run"})
    pipe.close()
    kf_frame = {int(k): int(f) for k, f in zip(result.store.table()["id"],
                                               result.store.table()["frame_index"])}
    loops = [(kf_frame.get(kf, -1), 1e3 * s) for kf, s in result.loop_update_s]
    with open(args.out / "long_run.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(samples[0]))
        w.writeheader()
        w.writerows(samples)
    with open(args.out / "long_run_loops.csv", "w", newline="") as fh:
        csv.writer(fh).writerows([("frame", "backend_ms")] + [(f, f"{ms:.2f}") for f, ms in loops])
    at = {r["frame"]: r["rss_mb"] for r in samples}
    thirds = np.array_split(np.array([ms for _, ms in loops]), 3) if loops else []
    report = {
        "frames": len(poses), "wall_s": round(wall, 1), "simulation_s": round(sim_s, 1),
        "pipeline_fps": round(len(poses) / max(wall - sim_s, 1e-9), 2),
        "rss_mb_at_2000": at.get(2000), "rss_mb_at_last": samples[-1]["rss_mb"],
        "rss_mb_max_sampled": max(r["rss_mb"] for r in samples),
        "loops_accepted": summary.get("loops_accepted"), "ate_rmse_m": summary.get("ate_rmse_m"),
        "odometry_ate_rmse_m": summary.get("odometry_ate_rmse_m"),
        "backend_ms_per_loop_median_by_third": [round(float(np.median(t)), 2) if len(t) else None
                                                for t in thirds],
        "config": str(args.config) if args.config else "default",
    }
    (args.out / "long_run.json").write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps(report, indent=2))
    plot(samples, loops, args.out / "long_run.png")


def plot(samples: list[dict], loops: list[tuple[int, float]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    f = [r["frame"] for r in samples]
    fig, ax = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    for key, label in (("rss_mb", "summed"), ("main_mb", "main process"),
                       ("workers_mb", "loop worker")):
        if key in samples[0]:
            ax[0].plot(f, [r[key] for r in samples], "o-", label=label)
    ax[0].legend(fontsize=8)
    ax[0].set_ylabel("RSS (MB)")
    ax[1].plot(f, [r["fps"] for r in samples], "o-")
    ax[1].set_ylabel("pipeline frames/s")
    if loops:
        ax[2].plot([x for x, _ in loops], [ms for _, ms in loops], ".")
    ax[2].set_ylabel("back-end ms per loop")
    ax[2].set_xlabel("frame")
    for a in ax:
        a.grid(True, alpha=0.3)
    fig.suptitle("lidar-slam on a long streamed drive (simulated HDL-64E)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


if __name__ == "__main__":
    main()
