"""`lidar-slam eval`: drift, ATE and RPE of a trajectory (lidar_slam.eval.evaluate)."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Optional

import typer

from lidar_slam.cli.common import app, reports_errors


class TrajFormat(str, Enum):
    auto = "auto"
    kitti = "kitti"
    tum = "tum"


@app.command("eval")
@reports_errors
def eval_cmd(
    est: Path = typer.Argument(..., help="Estimated trajectory (KITTI or TUM file)."),
    gt: Path = typer.Argument(..., help="Ground-truth trajectory (KITTI or TUM file)."),
    fmt: TrajFormat = typer.Option(TrajFormat.auto, "--format",
                                   help="Format of both files; auto: each told by its columns "
                                        "(12 KITTI, 8 TUM), so they may differ."),
    calib: Optional[Path] = typer.Option(None, "--calib", help="KITTI calib: GT cam0 -> lidar."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="metrics.json and plots here."),
    loops: Optional[Path] = typer.Option(None, "--loops", help="loops.csv of the run."),
    start: Optional[int] = typer.Option(None, "--start", min=0,
                                        help="The run's --start: EST line 0 is GT line START "
                                             "(and loops.csv frames count from the input's "
                                             "first scan)."),
    gt_times: Optional[Path] = typer.Option(None, "--gt-times",
                                            help="Stamps of a KITTI-format GT (times.txt), to "
                                                 "pair it with a TUM estimate by time."),
    revisit_gap: int = typer.Option(100, "--revisit-gap", min=1,
                                    help="Loop recall: frames between two passes of a place "
                                         "for the second to count as a revisit."),
    gt_label: Optional[str] = typer.Option(None, "--gt-label",
                                           help="What GT is called in the plots (default: "
                                                "'reference' where a README beside GT says it "
                                                "is not ground truth, else 'ground truth')."),
) -> None:
    """KITTI drift (t_err %, r_err deg/100 m), ATE and RPE of EST against GT.

    EST and GT: KITTI (12 numbers per line) or TUM (stamp tx ty tz qx qy qz qw) files.
    """
    from lidar_slam.eval.evaluate import format_table, run_eval

    start = _run_start(est, start)
    metrics = run_eval(est, gt, fmt=fmt.value, calib_path=calib, out_dir=out, loops_csv=loops,
                       start=start, gt_times=gt_times, revisit_gap=revisit_gap,
                       gt_label=gt_label)
    typer.echo(format_table(metrics))
    if out is not None:
        typer.echo(f"wrote {out}")


def _run_start(est: Path, start: int | None) -> int | None:
    """The --start of the run EST comes from, when EST is a run's own pose file (its
    summary.json beside it says): taken when --start is not given, refused when it differs
    (every pose would be paired with another scan's truth)."""
    import json
    import logging

    from lidar_slam.errors import RunFailed

    try:
        summary = json.loads((Path(est).parent / "summary.json").read_text())
        made = summary.get("start") if isinstance(summary, dict) else None
    except (OSError, ValueError):
        return start
    if not isinstance(made, int) or isinstance(made, bool) or made == (start or 0):
        return start
    if start is None:
        logging.getLogger("lidar_slam").info("%s: the run was made with --start %d (its "
                                             "summary.json): scored from there", est, made)
        return made
    raise RunFailed(f"{est}: --start {start}, but the run was made with --start {made} (its "
                    f"summary.json); pass --start {made}")
