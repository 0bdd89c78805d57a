"""`lidar-slam localize`: scans localised in a saved map (lidar_slam.run.localize)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from lidar_slam.cli.common import app, reports_errors, summary_table


@app.command()
@reports_errors
def localize(
    data: Path = typer.Argument(..., help="Scans to localise (any DATA that `run` reads)."),
    map_dir: Path = typer.Option(..., "--map", help="Run folder of the map (a finished `run`)."),
    out: Path = typer.Option(..., "--out", "-o", help="Folder to write."),
    config: Optional[Path] = typer.Option(None, "--config", "-c",
                                          help="YAML overlay on the map's config.yaml."),
    start: int = typer.Option(0, "--start", min=0, help="First scan (0-based)."),
    n_scans: Optional[int] = typer.Option(None, "--n-scans", min=1, help="Number of scans."),
    topic: Optional[str] = typer.Option(None, "--topic", help="PointCloud2 topic of a bag."),
    initial_pose: Optional[str] = typer.Option(None, "--initial-pose",
                                               help="x,y,z,yaw of the first scan in the map "
                                                    "frame (m, m, m, deg); else found by "
                                                    "relocalisation."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace the files in --out."),
) -> None:
    """Localise DATA in a saved map: poses in the map frame and a status per frame.

    Relocalisation (Scan Context + the loop-closure ICP gates) finds the pose without an
    initial guess; then each scan is registered against the fixed map from the motion model's
    prediction, and relocalised whenever tracking is lost.
    """
    from lidar_slam.run.localize import localize_sequence

    outcome = localize_sequence(data, map_dir, out, config=config, start=start, n_scans=n_scans,
                                topic=topic, initial_pose=initial_pose, overwrite=overwrite)
    typer.echo(summary_table(outcome.summary))
    typer.echo(f"wrote {out}")
    if outcome.failure is not None:
        raise outcome.failure
