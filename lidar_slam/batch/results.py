"""One results table for many runs: a row per sequence and a TOTAL row, as results.md, .json
and .csv. `lidar-slam batch` writes it, and tools/benchmark.py for its lidar-slam runs.

Columns (units in the names): frames, path_length_m (estimated path), t_err_pct and
r_err_deg_100m (KITTI devkit drift over 100-800 m segments; empty without ground truth or under
100 m of path), ate_m (ATE RMSE after rigid alignment, empty without ground truth),
loops_accepted, fps (frames / the run's wall time), peak_rss_mb (the run's process and its
loop-worker process). status is `ok` or `error`; message says why a row failed or was skipped.
"""

from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lidar_slam.geometry import inverse
from lidar_slam.io.atomic import write_text_atomic

COLUMNS = ("sequence", "status", "message", "frames", "path_length_m", "t_err_pct",
           "r_err_deg_100m", "ate_m", "loops_accepted", "fps", "peak_rss_mb")
OK, ERROR = "ok", "error"
TOTAL = "TOTAL"
# Decimals of each number column in results.md (the CSV and JSON keep 6).
_DIGITS = {"path_length_m": 1, "t_err_pct": 3, "r_err_deg_100m": 4, "ate_m": 3, "fps": 2,
           "peak_rss_mb": 0}


@dataclass
class SequenceResult:
    """One row of the table (exactly COLUMNS) and what lies behind it (segment counts for the
    pooled drift, the run folder, whether it was computed now or found finished)."""

    row: dict
    details: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.row["status"] == OK


def _row(sequence: str, status: str, message: str = "", **values) -> dict:
    row = dict.fromkeys(COLUMNS)
    row.update(sequence=sequence, status=status, message=message, **values)
    return row


def run_row(sequence: str, run_dir: Path, ground_truth: np.ndarray | None = None,
            message: str = "", computed_now: bool = True) -> SequenceResult:
    """The row of a finished run folder: counts from summary.json, drift and ATE of
    poses_kitti.txt against ground_truth (T_world_lidar of every input scan, or None)."""
    from lidar_slam.eval.evaluate import trajectory_metrics
    from lidar_slam.io.trajectory import read_kitti_poses

    summary = json.loads((run_dir / "summary.json").read_text())
    row = _row(sequence, OK, message, frames=summary["frames"],
               path_length_m=summary.get("path_length_m"),
               loops_accepted=summary.get("loops_accepted"), fps=summary.get("fps"),
               peak_rss_mb=summary.get("peak_rss_mb"))
    details = {"run_dir": str(run_dir), "computed_now": computed_now,
               "frames_computed": (summary["frames"] - summary.get("resumed_at_frame", 0)
                                   if computed_now else 0),
               "wall_s": summary.get("wall_s"), "kitti_segments": 0}
    start = summary.get("start", 0)
    if ground_truth is not None:
        poses = read_kitti_poses(run_dir / "poses_kitti.txt")
        gt = np.asarray(ground_truth)[start:start + len(poses)]
        covered = np.isfinite(gt).all(axis=(1, 2)) if len(gt) == len(poses) else None
        if covered is not None and not covered.all() and covered.sum() >= 2:
            # a dataset's ground truth that does not reach every scan: scored where it does
            poses, gt = inverse(poses[covered][0]) @ poses[covered], gt[covered]
        if len(poses) >= 2 and len(gt) == len(poses) and np.isfinite(gt).all():
            m = trajectory_metrics(poses, inverse(gt[0]) @ gt)
            row.update(t_err_pct=m["t_err_pct"], r_err_deg_100m=m["r_err_deg_per_100m"],
                       ate_m=m["ate_rmse_m"])
            details.update(kitti_segments=m["kitti_segments"],
                           gt_path_length_m=m["path_length_m"], eval=m)
    return SequenceResult(row, details)


def error_row(sequence: str, message: str, summary: dict | None = None) -> SequenceResult:
    """The row of a sequence that failed: its one-line message, and its frame count when it
    stopped after writing the frames so far."""
    frames = summary.get("frames") if summary else None
    return SequenceResult(_row(sequence, ERROR, " ".join(message.split()), frames=frames),
                          {"computed_now": True})


def total_row(results: list[SequenceResult], wall_s: float) -> dict:
    """TOTAL over the ok rows (finished earlier ones included): frames, path and loops summed,
    drift pooled over every KITTI segment (as the devkit's overall number), ATE pooled over
    every frame (root of the frame-weighted mean square), the highest peak RSS; fps is the
    batch's throughput: frames computed by this invocation / its wall time."""
    ok = [r for r in results if r.ok]
    n_err = len(results) - len(ok)
    skipped = sum(1 for r in ok if not r.details.get("computed_now", True))
    message = f"{len(ok)} ok" + (f" ({skipped} finished earlier)" if skipped else "")
    message += f", {n_err} failed" if n_err else ""

    def total(key):
        values = [r.row[key] for r in ok if r.row[key] is not None]
        return sum(values) if values else None

    seg = [(r.row["t_err_pct"], r.row["r_err_deg_100m"], r.details.get("kitti_segments", 0))
           for r in ok if r.row["t_err_pct"] is not None]
    n_seg = sum(n for *_, n in seg)
    ate = [(r.row["ate_m"], r.row["frames"]) for r in ok if r.row["ate_m"] is not None]
    n_ate = sum(n for _, n in ate)
    computed = sum(r.details.get("frames_computed", 0) for r in results)
    peaks = [r.row["peak_rss_mb"] for r in results if r.row["peak_rss_mb"] is not None]
    return _row(
        TOTAL, OK if not n_err else ERROR, message, frames=total("frames"),
        path_length_m=total("path_length_m"),
        t_err_pct=sum(t * n for t, _, n in seg) / n_seg if n_seg else None,
        r_err_deg_100m=sum(r * n for _, r, n in seg) / n_seg if n_seg else None,
        ate_m=math.sqrt(sum(a * a * n for a, n in ate) / n_ate) if n_ate else None,
        loops_accepted=total("loops_accepted"),
        fps=computed / wall_s if computed and wall_s > 0 else None,
        peak_rss_mb=max(peaks) if peaks else None)


def _cell(key: str, value, digits: dict | None = None) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        d = (digits or {}).get(key, 6)
        return f"{value:.{d}f}"
    return str(value)


def as_csv(rows: list[dict]) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(COLUMNS)
    for row in rows:
        writer.writerow([_cell(k, row[k]) for k in COLUMNS])
    return buf.getvalue()


def as_markdown(rows: list[dict], notes: list[str] = ()) -> str:
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for row in rows:
        cells = [_cell(k, row[k], _DIGITS).replace("|", "\\|") for k in COLUMNS]
        if row["sequence"] == TOTAL:
            cells = [f"**{c}**" if c else c for c in cells]
        lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    lines.append("fps: frames / the run's wall time (TOTAL: frames computed now / the wall "
                 "time they took together); peak_rss_mb: the run's process and its loop worker "
                 "(TOTAL: the highest); t_err_pct, r_err_deg_100m: KITTI devkit segments of "
                 "100-800 m, empty under 100 m of path or without ground truth (TOTAL: pooled "
                 "over every segment); ate_m: ATE RMSE after rigid alignment (TOTAL: pooled "
                 "over every frame); path_length_m: estimated.")
    lines += [f"- {n}" for n in notes]
    return "\n".join(lines) + "\n"


def write_results(out_dir: Path, results: list[SequenceResult], wall_s: float,
                  meta: dict | None = None, notes: list[str] = ()) -> list[dict]:
    """results.md, results.json and results.csv in out_dir (each written whole or not at all);
    returns the rows, TOTAL last."""
    rows = [r.row for r in results] + [total_row(results, wall_s)]
    out_dir.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out_dir / "results.csv", as_csv(rows))
    write_text_atomic(out_dir / "results.md", as_markdown(rows, list(notes)))
    doc = {"columns": list(COLUMNS), "rows": rows,
           "details": {r.row["sequence"]: r.details for r in results},
           "jobs_wall_s": wall_s, **(meta or {})}
    write_text_atomic(out_dir / "results.json", json.dumps(doc, indent=2) + "\n")
    return rows
