"""Wall time of many sequences: `lidar-slam batch --workers N` against a serial loop of
`lidar-slam run` (each with its default threads), on the same sequences, interleaved repeats.

Usage: python tools/bench_batch.py SEQ [SEQ ...] --out DIR [--workers 2] [--repeats 2]
       [--config FILE]

Whole-command wall time (interpreter start-up, and Ray's for the batch, included); the loop is
one `lidar-slam run` per sequence, one after another. Writes DIR/batch_vs_serial.md and .json,
the batch's results table under DIR/batch-<k>/ and the runs under DIR/serial-<k>/.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

CLI = [sys.executable, "-m", "lidar_slam.cli"]


def timed(cmd: list[str], log: Path) -> float:
    """Wall seconds of one command (its output to log); a failure stops the benchmark."""
    t0 = time.perf_counter()
    with log.open("w") as fh:
        code = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT).returncode
    wall = time.perf_counter() - t0
    if code != 0:
        sys.exit(f"{' '.join(cmd)}: exit code {code}, see {log}")
    return wall


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequences", nargs="+", type=Path)
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--config", type=Path, default=None, help="config overlay for every run")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    cfg = ["--config", str(args.config)] if args.config else []
    walls: dict[str, list[float]] = {"serial": [], "batch": []}
    frames = 0
    for rep in range(args.repeats):  # interleaved, so both see the same machine load
        serial = args.out / f"serial-{rep}"
        serial.mkdir(exist_ok=True)
        t0 = time.perf_counter()
        for seq in args.sequences:
            timed([*CLI, "run", str(seq), "--out", str(serial / seq.name), "--overwrite", *cfg],
                  serial / f"{seq.name}.log")
        walls["serial"].append(time.perf_counter() - t0)
        frames = sum(json.loads((serial / s.name / "summary.json").read_text())["frames"]
                     for s in args.sequences)
        batch = args.out / f"batch-{rep}"
        walls["batch"].append(timed(
            [*CLI, "batch", *map(str, args.sequences), "--out", str(batch), "--workers",
             str(args.workers), "--overwrite", *cfg], args.out / f"batch-{rep}.log"))
        print(f"repeat {rep + 1}/{args.repeats}: serial {walls['serial'][-1]:.1f} s, batch "
              f"{walls['batch'][-1]:.1f} s", flush=True)
    med = {k: statistics.median(v) for k, v in walls.items()}
    load = os.getloadavg()
    meta = {"date": datetime.datetime.now().isoformat(timespec="seconds"),
            "cpus": os.cpu_count(), "load_avg_1_5_15_at_end": load,
            "sequences": [str(s) for s in args.sequences], "frames": frames,
            "workers": args.workers, "repeats": args.repeats, "wall_s": walls,
            "median_wall_s": med, "batch_speedup": med["serial"] / med["batch"]}
    (args.out / "batch_vs_serial.json").write_text(json.dumps(meta, indent=2) + "\n")
    md = ["| how | wall s (median) | wall s (each repeat) | frames/s |", "|---|---|---|---|"]
    for key, label in (("serial", "serial loop of `lidar-slam run` (default threads)"),
                       ("batch", f"`lidar-slam batch --workers {args.workers}` (1 CPU per run)")):
        md.append(f"| {label} | {med[key]:.1f} | {', '.join(f'{w:.1f}' for w in walls[key])} "
                  f"| {frames / med[key]:.1f} |")
    md.append("")
    md.append(f"{len(args.sequences)} sequences, {frames} frames, {os.cpu_count()} CPUs; batch "
              f"/ serial speed-up {meta['batch_speedup']:.2f}x; load average at the end "
              f"{load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f}")
    (args.out / "batch_vs_serial.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    sys.exit(main())
