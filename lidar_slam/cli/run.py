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
                                          "raw drive, rosbag/mcap, or sensor .pcap."),
    out: Path = typer.Option(..., "--out", "-o", help="Run folder to write."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="YAML config overlay."),
    start: int = typer.Option(0, "--start", min=0, help="First scan (0-based)."),
    n_scans: Optional[int] = typer.Option(None, "--n-scans", min=1, help="Number of scans."),
    topic: Optional[str] = typer.Option(None, "--topic", help="PointCloud2 topic of a bag."),
    meta: Optional[Path] = typer.Option(None, "--meta", help="Ouster pcap: the sensor metadata "
                                        "JSON (default: the pcap's name with .json)."),
    imu_topic: Optional[str] = typer.Option(None, "--imu-topic",
                                            help="sensor_msgs/Imu topic of a bag."),
    gnss_topic: Optional[str] = typer.Option(None, "--gnss-topic",
                                             help="sensor_msgs/NavSatFix topic of a bag."),
    no_imu: bool = typer.Option(False, "--no-imu", help="Do not read the IMU (imu.csv / topic)."),
    no_gnss: bool = typer.Option(False, "--no-gnss",
                                 help="Do not read the GNSS (gnss.csv / topic)."),
    no_loops: bool = typer.Option(False, "--no-loops", help="Odometry only."),
    no_deskew: bool = typer.Option(False, "--no-deskew", help="Do not deskew."),
    viz: bool = typer.Option(False, "--viz", help="Open the rerun viewer."),
    rrd: Optional[Path] = typer.Option(None, "--rrd", help="Record a rerun .rrd file."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace a previous run in --out."),
    resume: bool = typer.Option(False, "--resume",
                                help="Continue the killed run in --out from its checkpoint."),
    extend: Optional[Path] = typer.Option(None, "--extend", help="A saved map (a run, or a "
                                          "`merge` whose runs are still there): DATA is run "
                                          "into OUT/run, then merged with the map's sessions "
                                          "into OUT, in the map's frame (as `merge`)."),
) -> None:
    """Run SLAM on DATA and write poses, map, config and summary into --out.

    DATA: a folder of scans (.bin/.pcd/.ply/.npy), one scan file, a KITTI sequence or raw
    drive, a rosbag (.bag, ROS2 bag folder, .mcap), or an Ouster / Velodyne .pcap.
    """
    from lidar_slam.run.runner import run_sequence

    run_dir = out
    if extend is not None:
        from lidar_slam.merge.build import MERGE_OUTPUTS, sessions_of
        from lidar_slam.run.outdir import prepare_out_dir, refuse_input_as_out

        sessions, _ = sessions_of(extend)  # a bad MAP is refused before the run, not after
        refuse_input_as_out(out, {"map to extend": extend, "input": data,
                                  **{f"map's session {s}": s for s in sessions}})
        prepare_out_dir(out, (*MERGE_OUTPUTS, "run"), overwrite, resume)
        run_dir = out / "run"
    outcome = run_sequence(data, run_dir, config=config, start=start, n_scans=n_scans, topic=topic,
                           imu_topic=imu_topic, gnss_topic=gnss_topic, meta=meta,
                           overrides=run_overrides(no_loops, no_deskew, no_imu, no_gnss),
                           viz=viz, rrd=rrd,
                           overwrite=overwrite, resume=resume)
    typer.echo(summary_table(outcome.summary))
    if extend is not None and outcome.failure is None:
        from lidar_slam.merge.build import extend_map

        result = extend_map(extend, run_dir, out)
        kept = sum(s["kept"] for s in result.sessions)
        typer.echo(f"merged with {extend}: {kept} of {len(result.sessions)} sessions kept, "
                   f"{result.loops} loops between them")
    typer.echo(f"nothing to resume in {run_dir}: finished before" if outcome.finished_before
               else f"wrote {out}")
    if outcome.failure is not None:
        raise outcome.failure


def run_overrides(no_loops: bool, no_deskew: bool, no_imu: bool = False,
                  no_gnss: bool = False) -> dict:
    """The config overrides of --no-loops, --no-deskew, --no-imu and --no-gnss."""
    overrides: dict = {}
    if no_imu:
        overrides["imu"] = {"enabled": False}
    if no_gnss:
        overrides["gnss"] = {"enabled": False}
    if no_loops:
        overrides["loop"] = {"enabled": False}
    if no_deskew:
        overrides["data"] = {"deskew": False}
    return overrides
