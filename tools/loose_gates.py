"""Wrong loops from the front-end against the back-end: each sequence is run with its normal
config and with configs/loose_gates.yaml on top (verification gates that admit wrong loops),
with backend.robust gnc (and any other kernel asked for); every accepted loop is scored against
the simulated ground truth, and the ATE compared with the normal run.

    python tools/loose_gates.py SEQ [SEQ ...] --out DIR [--config configs/sim_hdl64.yaml]
        [--loose configs/loose_gates.yaml] [--kernels gnc huber] [--start N] [--n-scans N]

A loop is wrong when its T_match_query is more than 1 m / 5 deg from the truth's (as
tools/benchmark.py and `lidar-slam eval` score loops). Per run: loops accepted, wrong loops
admitted (accepted by the gates), how many of those the back-end rejected (loops.csv column
`backend`), true loops it rejected, ATE (m, rigid alignment, from summary.json) and its ratio to
the normal run's, and the back-end's time and share of the run. Writes DIR/loose_gates.md and
DIR/loose_gates.json; the run folders stay under DIR/<sequence>/.
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from lidar_slam.config import dump_config, load_config
from lidar_slam.eval import metrics
from lidar_slam.geometry import from_xyz_quat
from lidar_slam.io.sources import open_source

HERE = Path(__file__).resolve().parent
POSE_COLUMNS = ("x", "y", "z", "qx", "qy", "qz", "qw")


def accepted_loops(loops_csv: Path, start: int) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Accepted rows of a run's loops.csv: (query, match) positions in the slice, T_match_query,
    and the back-end's verdict."""
    with loops_csv.open(newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r["accepted"] == "1"]
    pairs = np.array([[int(r["query_frame"]) - start, int(r["match_frame"]) - start]
                      for r in rows], dtype=np.int64).reshape(-1, 2)
    T = np.array([from_xyz_quat(np.array([float(r[c]) for c in POSE_COLUMNS])) for r in rows])
    return pairs, T.reshape(-1, 4, 4), [r.get("backend", "") for r in rows]


def score_run(run_dir: Path, gt: np.ndarray, start: int) -> dict:
    """Loop counts against the truth and the run's summary numbers."""
    summary = json.loads((run_dir / "summary.json").read_text())
    pairs, T, verdict = accepted_loops(run_dir / "loops.csv", start)
    correct = (metrics.loop_precision_recall(pairs, T, gt).correct if len(pairs)
               else np.zeros(0, dtype=bool))
    rejected = np.array([v == "rejected" for v in verdict], dtype=bool)
    return {"ate_m": summary.get("ate_rmse_m"),
            "odometry_ate_m": summary.get("odometry_ate_rmse_m"),
            "loops_accepted": len(pairs), "wrong_admitted": int((~correct).sum()),
            "wrong_rejected_by_backend": int((~correct & rejected).sum()),
            "true_rejected_by_backend": int((correct & rejected).sum()),
            "backend_s": summary.get("backend_s"),
            "backend_share_pct": summary.get("backend_share_pct"),
            "backend_final_init": summary.get("backend_final_init"),
            "wall_s": summary.get("wall_s")}


def run_once(seq: Path, out: Path, config: Path, start: int, n_scans: int | None) -> float:
    """`lidar-slam run` in its own process; its wall time (s)."""
    cmd = [sys.executable, "-m", "lidar_slam.cli", "run", str(seq), "--out", str(out),
           "--config", str(config), "--start", str(start), "--overwrite"]
    if n_scans is not None:
        cmd += ["--n-scans", str(n_scans)]
    t0 = time.perf_counter()
    with open(out.with_suffix(".log"), "w") as log:
        subprocess.run(cmd, check=True, stdout=log, stderr=subprocess.STDOUT)
    return time.perf_counter() - t0


def loose_config(base: Path, loose: Path, kernel: str, path: Path) -> Path:
    """base, overlaid by the loose gates and backend.robust = kernel, written to path."""
    overlay = yaml.safe_load(loose.read_text()) or {}
    overlay.setdefault("backend", {})["robust"] = kernel
    dump_config(load_config(base, overlay), path)
    return path


def table(rows: list[dict]) -> str:
    cols = ["sequence", "run", "ATE m", "ATE / normal", "loops accepted", "wrong admitted",
            "wrong rejected by back-end", "true rejected by back-end", "back-end s (share %)"]
    out = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        ratio = "" if r.get("ate_ratio") is None else f"{r['ate_ratio']:.3f}"
        share = ("" if r["backend_s"] is None else
                 f"{r['backend_s']:.2f} ({r['backend_share_pct']:.1f})")
        out.append("| " + " | ".join(str(v) for v in [
            r["sequence"], r["run"], f"{r['ate_m']:.3f}", ratio, r["loops_accepted"],
            r["wrong_admitted"], r["wrong_rejected_by_backend"], r["true_rejected_by_backend"],
            share]) + " |")
    return "\n".join(out) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequences", nargs="+", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--config", type=Path, default=HERE.parent / "configs" / "sim_hdl64.yaml")
    ap.add_argument("--loose", type=Path, default=HERE.parent / "configs" / "loose_gates.yaml")
    ap.add_argument("--kernels", nargs="+", choices=["gnc", "huber", "none"], default=["gnc"])
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--n-scans", type=int, default=None)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for seq in args.sequences:
        source = open_source(seq)
        n = len(source) - args.start if args.n_scans is None else args.n_scans
        if source.ground_truth is None:
            raise SystemExit(f"{seq}: no ground truth (poses.txt); cannot score loops")
        gt = source.ground_truth[args.start:args.start + n]
        folder = args.out / seq.name
        folder.mkdir(exist_ok=True)
        runs = [("normal", args.config)] + [
            (f"loose {k}", loose_config(args.config, args.loose, k, folder / f"loose_{k}.yaml"))
            for k in args.kernels]
        normal_ate = None
        for name, config in runs:
            run_dir = folder / name.replace(" ", "_")
            run_once(seq, run_dir, config, args.start, args.n_scans)
            row = {"sequence": seq.name, "run": name, "config": str(config),
                   **score_run(run_dir, gt, args.start)}
            if name == "normal":
                normal_ate = row["ate_m"]
            row["ate_ratio"] = (None if not normal_ate or row["ate_m"] is None
                                else row["ate_m"] / normal_ate)
            rows.append(row)
            print(json.dumps(row), flush=True)
    text = (f"scans {args.start}..{'end' if args.n_scans is None else args.start + args.n_scans}"
            f"; normal config {args.config.name}, loose overlay {args.loose.name}\n\n"
            + table(rows))
    print(text)
    (args.out / "loose_gates.md").write_text(text)
    (args.out / "loose_gates.json").write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
