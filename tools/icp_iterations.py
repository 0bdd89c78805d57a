"""How many iterations kiss-icp's ICP takes per scan, and what they cost: the run's registrations
saved (source points, local map, initial guess, kernel) and replayed with 1, 2, 3, ... iterations
allowed until the pose is the one the run got.

Why: a lidar-only hand-held walk costs 2-3x its run with the IMU, and the cost is the number of
iterations from the constant-velocity guess, not the kernel (docs/benchmarks/2026-12-05g-speed.md,
last section). --kernel M replays every saved registration with that kernel too.

Usage: python tools/icp_iterations.py SEQ [--config OVERLAY] [--every 10] [--kernel 1.0]
prints, per block of saved registrations: scan, kernel (m), local-map points, iterations, ms.
"scan" counts kiss-icp's alignment calls: lidar only, each scan makes two since the coarse pass
(odometry.coarse_every), the pass on every 4th point then the whole source from where it ended;
an overlay with `odometry: {coarse_every: null}` measures from the constant-velocity guess alone.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

LADDER = (1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128, 192, 256, 500)


def record(seq: Path, config: Path | None, every: int) -> tuple[list, object]:
    """Run `lidar-slam run` on seq in-process, saving every `every`-th registration."""
    from kiss_icp.pybind import kiss_icp_pybind as kp

    from lidar_slam.cli import entry
    from lidar_slam.frontend import odometry

    saved, count = [], [0]
    real = kp._Registration

    class Saving:
        def __init__(self, **kwargs):
            self.kwargs, self.reg = kwargs, real(**kwargs)

        def _align_points_to_map(self, points, voxel_map, initial_guess,
                                 max_correspondance_distance, kernel):
            if count[0] % every == 0:
                saved.append((count[0], np.asarray(points).copy(),
                              np.asarray(voxel_map._point_cloud()).copy(),
                              np.array(initial_guess), float(kernel)))
            count[0] += 1
            return self.reg._align_points_to_map(
                points=points, voxel_map=voxel_map, initial_guess=initial_guess,
                max_correspondance_distance=max_correspondance_distance, kernel=kernel)

    odometry.kp._Registration = Saving
    with tempfile.TemporaryDirectory() as out:
        argv = ["lidar-slam", "run", str(seq), "--out", out, "--overwrite", "--no-loops"]
        if config is not None:
            argv += ["--config", str(config)]
        sys.argv = argv
        try:
            entry()
        except SystemExit as exc:
            if exc.code:
                raise
        from lidar_slam.config import load_config

        cfg = load_config(Path(out) / "config.yaml")  # the run's effective config
    odometry.kp._Registration = real
    return saved, cfg


def _align(reg, points, vmap, guess: np.ndarray, kernel: float) -> np.ndarray:
    return reg._align_points_to_map(points=points, voxel_map=vmap, initial_guess=guess,
                                    max_correspondance_distance=3 * kernel, kernel=kernel)


def iterations(saved, cfg, kernel_m: float | None) -> np.ndarray:
    """Rows (scan, kernel, map points, iterations, ms at the run's own iteration cap)."""
    from kiss_icp.pybind import kiss_icp_pybind as kp

    o = cfg.odometry
    regs = {k: kp._Registration(max_num_iterations=k, convergence_criterion=o.convergence_criterion,
                                max_num_threads=1) for k in LADDER}
    rows = []
    for scan, src, mp, guess, kernel in saved:
        kernel = kernel if kernel_m is None else kernel_m
        vmap = kp._VoxelHashMap(voxel_size=cfg.voxel_size_m(), max_distance=cfg.data.max_range_m,
                                max_points_per_voxel=o.max_points_per_voxel)
        vmap._add_points(kp._Vector3dVector(mp))
        points = kp._Vector3dVector(src)

        t0 = time.perf_counter()
        full = _align(regs[LADDER[-1]], points, vmap, guess, kernel)
        ms = 1e3 * (time.perf_counter() - t0)
        used = next(k for k in LADDER
                    if np.abs(_align(regs[k], points, vmap, guess, kernel) - full).max() < 1e-12)
        rows.append((scan, kernel, len(mp), used, ms))
    return np.array(rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seq", type=Path)
    ap.add_argument("--config", type=Path, default=None)
    ap.add_argument("--every", type=int, default=10, help="save every N-th registration")
    ap.add_argument("--kernel", type=float, default=None,
                    help="also replay with this kernel (m) instead of the run's")
    args = ap.parse_args()
    saved, cfg = record(args.seq, args.config, args.every)
    kernels = [("run's kernel", None)]
    if args.kernel is not None:
        kernels.append((f"kernel {args.kernel} m", args.kernel))
    for label, kernel in kernels:
        r = iterations(saved, cfg, kernel)
        print(f"{args.seq.name}, {label}: iterations (at most the ladder step that gives the "
              f"run's pose) per saved registration")
        for a in range(0, len(r), 5):
            print("  " + "  ".join(f"{int(x[0]):4d}: k {x[1]:.1f} m, map {x[2] / 1e3:.0f}k, "
                                   f"it {int(x[3])}, {x[4]:.0f} ms" for x in r[a:a + 5]))
        print(f"  median: {np.median(r[:, 3]):.0f} iterations, {np.median(r[:, 4]):.0f} ms "
              f"({np.median(r[:, 4] / r[:, 3]):.2f} ms an iteration)")


if __name__ == "__main__":  # the run's loop worker is a spawned process that imports this file
    main()
