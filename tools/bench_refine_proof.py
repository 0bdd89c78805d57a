"""The slow-scan refinement off / always / proven, side by side (docs/benchmarks/
2026-12-03-refine-proof.md): per (data, IMU or not, mode) one `lidar-slam run` (whole-process
wall) and `lidar-slam eval` of its odometry and final poses against the data's poses.txt.

    python tools/bench_refine_proof.py OUT DATA[:noimu] ... [--modes off,always,proven]

Appends one JSON line per run to OUT/rows.jsonl and prints the markdown table of all of them.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

MODES = {"off": {"refine_below_mps": 0.0},
         "always": {"refine_evidence": False},
         "proven": {"refine_evidence": True},
         # always, on about the source proven uses on a scan of 1,000-2,000 points (every other)
         "always-1000": {"refine_evidence": False, "refine_max_points": 1000}}


def _children_cpu_s() -> float:
    """User + system CPU seconds of the finished child processes (less shaken than the wall by
    the other jobs on a shared machine)."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _eval(est: Path, data: Path, out: Path) -> dict:
    cmd = [sys.executable, "-m", "lidar_slam.cli", "eval", str(est), str(data / "poses.txt"),
           "--out", str(out)]
    if (data / "calib.txt").exists():
        cmd += ["--calib", str(data / "calib.txt")]
    subprocess.run(cmd, check=True, capture_output=True)
    return json.loads((out / "metrics.json").read_text())


def run(out: Path, spec: str, mode: str) -> dict:
    """One run of DATA[:noimu] in a mode, evaluated."""
    path, _, flag = spec.partition(":")
    data = Path(path)
    name = f"{data.name}{'-noimu' if flag else ''}-{mode}"
    cfg = out / f"{name}.yaml"
    cfg.write_text(json.dumps({"odometry": MODES[mode]}))
    cmd = [sys.executable, "-m", "lidar_slam.cli", "run", str(data), "--out", str(out / name),
           "--overwrite", "-c", str(cfg)] + (["--no-imu"] if flag else [])
    t0, cpu0 = time.perf_counter(), _children_cpu_s()
    with open(out / f"{name}.log", "w") as log:
        subprocess.run(cmd, check=True, stdout=log, stderr=subprocess.STDOUT)
    wall, cpu = time.perf_counter() - t0, _children_cpu_s() - cpu0
    s = json.loads((out / name / "summary.json").read_text())
    odo = _eval(out / name / "odometry_kitti.txt", data, out / name / "eval_odometry")
    fin = _eval(out / name / "poses_kitti.txt", data, out / name / "eval_final")
    return {"data": data.name, "imu": not flag and (data / "imu.csv").exists(), "mode": mode,
            "odo_ate_m": odo["ate_rmse_m"], "odo_rpe_m": odo["rpe_trans_m_mean"],
            "odo_rpe_deg": odo["rpe_rot_deg_mean"], "final_ate_m": fin["ate_rmse_m"],
            "wall_s": wall, "cpu_s": cpu, "odometry_ms_per_frame": s["odometry_ms_per_frame"],
            "frames": s["frames"],
            "refined": s["odometry_refined_scans"], "gate": s["odometry_refine_refused"],
            "unproven": s.get("odometry_refine_unproven", 0),
            "skipped": s.get("odometry_refine_skipped", 0)}


def table(rows: list[dict]) -> str:
    head = ("| data | IMU | refine | odometry ATE m | odometry RPE mm / mdeg | final ATE m "
            "| wall s | CPU s | refined / gate / unproven / skipped |\n"
            + "|---" * 9 + "|")
    lines = [head]
    for r in rows:
        lines.append(f"| {r['data']} | {'yes' if r['imu'] else 'no'} | {r['mode']} "
                     f"| {r['odo_ate_m']:.4f} | {1e3 * r['odo_rpe_m']:.1f} / "
                     f"{1e3 * r['odo_rpe_deg']:.0f} | {r['final_ate_m']:.4f} "
                     f"| {r['wall_s']:.1f} | {_cpu(r)} | {r['refined']} / {r['gate']} / "
                     f"{r['unproven']} / {r['skipped']} |")
    return "\n".join(lines)


def _cpu(row: dict) -> str:
    return f"{row['cpu_s']:.1f}" if "cpu_s" in row else "-"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("data", nargs="*")
    ap.add_argument("--modes", default="off,always,proven")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows_file = args.out / "rows.jsonl"
    for spec in args.data:
        for mode in args.modes.split(","):
            row = run(args.out, spec, mode)
            with open(rows_file, "a") as f:
                f.write(json.dumps(row) + "\n")
            print(json.dumps(row), flush=True)
    rows = [json.loads(x) for x in rows_file.read_text().splitlines()] if rows_file.exists() else []
    print(table(rows))


if __name__ == "__main__":
    main()
