"""What `lidar-slam merge` costs as sessions are added: wall time and peak memory.

    python tools/merge_scale.py --root DIR [--sessions 2 4 8] [--duration-s 30] [--seed 1]
                                [--imu] [--json FILE]

Simulates max(--sessions) hand-held walks of one indoor world (`simulate --sessions`, with
movers and changes as tools/merge_bench.py), runs each (`run`, DIR/runs/<i>), each step skipped
when its folder is there, then merges the first N runs for every N of --sessions into
DIR/merged_<N>, timing each merge (wall s) and sampling its peak resident memory (the merge
process and any children, every 0.1 s). Prints one line per N: sessions, keyframes, seconds,
peak MB, and the seconds the N runs themselves took (their summary.json), to compare a merge
with running the sessions again.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import psutil

if __package__ in (None, ""):  # run as a script: `tools` importable from the repository root
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tools.merge_bench import _cli, _overlay  # noqa: E402


def measured(args: list[str]) -> tuple[float, float]:
    """Run `lidar-slam ARGS`: (wall seconds, peak RSS in MB of it and its children)."""
    t0 = time.perf_counter()
    proc = psutil.Popen([sys.executable, "-m", "lidar_slam.cli", *args],
                        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    peak = 0
    while proc.poll() is None:
        try:
            rss = proc.memory_info().rss + sum(c.memory_info().rss
                                               for c in proc.children(recursive=True))
            peak = max(peak, rss)
        except psutil.Error:
            pass
        time.sleep(0.1)
    if proc.returncode != 0:
        raise SystemExit(f"lidar-slam {' '.join(args)} failed: {proc.stderr.read()[-2000:]}")
    return time.perf_counter() - t0, peak / 1e6


def _run_seconds(run: Path) -> float:
    return float(json.loads((run / "summary.json").read_text()).get("wall_s", float("nan")))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, required=True)
    ap.add_argument("--sessions", type=int, nargs="+", default=[2, 4, 8])
    ap.add_argument("--duration-s", type=float, default=30.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--imu", action="store_true")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    n_max = max(args.sessions)
    sim, runs = args.root / "sim", args.root / "runs"
    if not (sim / "changes.json").is_file():
        _cli("simulate", "--motion", "handheld", "--sessions", n_max, "--seed", args.seed,
             "--duration-s", args.duration_s, "--changes", 10, "--movers", 2, "--out", sim,
             "--overwrite", *(("--imu",) if args.imu else ()))
    for i in range(n_max):
        if not (runs / str(i) / "summary.json").is_file():
            _cli("run", sim / f"session_{i}", "--out", runs / str(i), "--overwrite",
                 *_overlay(sim / f"session_{i}"))
    rows = []
    for n in sorted(args.sessions):
        out = args.root / f"merged_{n}"
        seconds, peak_mb = measured(["merge", *(str(runs / str(i)) for i in range(n)),
                                     "--out", str(out), "--overwrite"])
        summary = json.loads((out / "summary.json").read_text())
        row = {"sessions": n, "sessions_kept": len(summary["sessions_kept"]),
               "keyframes": summary["keyframes"], "merge_s": round(seconds, 1),
               "peak_mb": round(peak_mb), "loops_verified":
               summary["loops_between_sessions"]["verified"],
               "runs_s": round(sum(_run_seconds(runs / str(i)) for i in range(n)), 1)}
        rows.append(row)
        print(" ".join(f"{k}={v}" for k, v in row.items()), flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
