"""Interleaved before / after timing of `lidar-slam run` on the same sequences.

    python tools/speed_ab.py --out DIR SEQ [SEQ ...] --variant before=/path/to/checkout
        --variant after=/path/to/other/checkout [--rounds 3] [--config-name lidar_slam.yaml]

Each round runs every variant once on each sequence (A, B, A, B, ...), each as its own process
`python -m lidar_slam.cli run SEQ --out DIR/<seq>-<variant> --overwrite [--config SEQ/<name>]`
with PYTHONPATH set to the variant's checkout (this interpreter and its packages for all). It
prints per run and as medians: frames/s of the whole process (wall), and the CPU time (user +
sys) of the run's own process, not of its loop worker or top-view helper: on a machine shared
with other work the wall time measures the neighbours as much as the run, while the run's own
CPU time is what its single critical thread (kiss-icp on one thread) costs. Every run's
poses_kitti.txt and odometry_kitti.txt are compared with the first run's of the sequence:
"poses: identical" or which differ.
"""

from __future__ import annotations

import argparse
import compileall
import filecmp
import json
import os
import resource
import runpy
import statistics
import subprocess
import sys
import time
from pathlib import Path

POSE_FILES = ("poses_kitti.txt", "odometry_kitti.txt")


def _child() -> None:
    """`speed_ab.py --child CPU_FILE ARGS...`: the CLI in this process, then its own CPU time."""
    cpu_file, args = sys.argv[2], sys.argv[3:]

    def report() -> None:
        r = resource.getrusage(resource.RUSAGE_SELF)
        Path(cpu_file).write_text(f"{r.ru_utime + r.ru_stime:.3f}\n")

    import atexit

    atexit.register(report)
    sys.argv = ["lidar_slam.cli", *args]
    runpy.run_module("lidar_slam.cli", run_name="__main__", alter_sys=True)


def run_once(seq: Path, checkout: Path, out: Path, config: Path | None) -> tuple[float, float, int]:
    """Wall s, the run process's CPU s, frames."""
    cpu_file = out.with_name(out.name + ".cpu")
    cmd = [sys.executable, __file__, "--child", str(cpu_file), "run", str(seq), "--out", str(out),
           "--overwrite", *(["--config", str(config)] if config else [])]
    env = dict(os.environ, PYTHONPATH=str(checkout))
    t0 = time.perf_counter()
    subprocess.run(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
    wall = time.perf_counter() - t0
    frames = json.loads((out / "summary.json").read_text())["frames"]
    return wall, float(cpu_file.read_text()), frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequences", nargs="+", type=Path)
    ap.add_argument("--variant", action="append", required=True, help="label=checkout")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--config-name", default="lidar_slam.yaml",
                    help="the overlay beside each sequence (bank sequences: lidar_slam.yaml)")
    args = ap.parse_args()
    variants = dict(v.split("=", 1) for v in args.variant)
    args.out.mkdir(parents=True, exist_ok=True)
    for checkout in variants.values():  # as pip would have: benchmark.compile_ours
        compileall.compile_dir(str(Path(checkout) / "lidar_slam"), quiet=1)
    for seq in args.sequences:
        config = seq / args.config_name
        config = config if config.is_file() else None
        fps: dict[str, list[float]] = {k: [] for k in variants}
        cpu: dict[str, list[float]] = {k: [] for k in variants}
        first: Path | None = None
        same = True
        for r in range(args.rounds):
            for label, checkout in variants.items():
                out = args.out / f"{seq.name}-{label}-{r}"
                wall, c, frames = run_once(seq, Path(checkout), out, config)
                fps[label].append(frames / wall)
                cpu[label].append(c)
                first = first or out
                same &= all(filecmp.cmp(first / f, out / f, shallow=False) for f in POSE_FILES)
                print(f"{seq.name} round {r} {label}: {wall:.2f} s wall, {frames / wall:.1f} "
                      f"frames/s, run process CPU {c:.2f} s, load {os.getloadavg()[0]:.1f}",
                      flush=True)
        for label in variants:
            print(f"{seq.name} {label}: median {statistics.median(fps[label]):.1f} frames/s "
                  f"({', '.join(f'{v:.1f}' for v in fps[label])}), run process CPU median "
                  f"{statistics.median(cpu[label]):.2f} s "
                  f"({', '.join(f'{v:.2f}' for v in cpu[label])})", flush=True)
        print(f"{seq.name} poses: {'identical' if same else 'DIFFER'} over every run", flush=True)


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == "--child":
        _child()
    else:
        main()
