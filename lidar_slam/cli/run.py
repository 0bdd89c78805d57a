"""`lidar-slam run`: one input into one run folder (lidar_slam.run.run_sequence)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from lidar_slam.cli.common import app, reports_errors, summary_table


@app.command()
@reports_errors
def run(
    data: Path = typer.Argument(..., help="Folder of scans, one scan file, KITTI sequence, KITTI "
                                          "raw drive, or rosbag/mcap."),
    out: Path = typer.Option(..., "--out", "-o", help="Run folder to write."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="YAML config overlay."),
    start: int = typer.Option(0, "--start", min=0, help="First scan (0-based)."),
    n_scans: Optional[int] = typer.Option(None, "--n-scans", min=1, help="Number of scans."),
    topic: Optional[str] = typer.Option(None, "--topic", help="PointCloud2 topic of a bag."),
    no_loops: bool = typer.Option(False, "--no-loops", help="Odometry only."),
    no_deskew: bool = typer.Option(False, "--no-deskew", help="Do not deskew."),
    viz: bool = typer.Option(False, "--viz", help="Open the rerun viewer."),
    rrd: Optional[Path] = typer.Option(None, "--rrd", help="Record a rerun .rrd file."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace a previous run in --out."),
    resume: bool = typer.Option(False, "--resume",
                                help="Continue the killed run in --out from its checkpoint."),
) -> None:
    """Run SLAM on DATA and write poses, map, config and summary into --out.

    DATA: a folder of scans (.bin/.pcd/.ply/.npy), one scan file, a KITTI sequence or raw
    drive, or a rosbag (.bag, ROS2 bag folder, .mcap).
    """
    from lidar_slam.run.runner import run_sequence

    outcome = run_sequence(data, out, config=config, start=start, n_scans=n_scans, topic=topic,
                           overrides=run_overrides(no_loops, no_deskew), viz=viz, rrd=rrd,
                           overwrite=overwrite, resume=resume)
    typer.echo(summary_table(outcome.summary))
    typer.echo(f"wrote {out}")
    if outcome.failure is not None:
        raise outcome.failure


def run_overrides(no_loops: bool, no_deskew: bool) -> dict:
    """The config overrides of --no-loops and --no-deskew."""
    overrides: dict = {}
    if no_loops:
        overrides["loop"] = {"enabled": False}
    if no_deskew:
        overrides["data"] = {"deskew": False}
    return overrides
