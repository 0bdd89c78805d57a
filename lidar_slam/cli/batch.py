"""`lidar-slam batch`: many sequences on Ray (lidar_slam.batch), one results table."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import typer

from lidar_slam.cli.common import app, fail, reports_errors
from lidar_slam.cli.run import run_overrides
from lidar_slam.errors import EXIT_INTERRUPTED


@app.command()
@reports_errors
def batch(
    data: list[str] = typer.Argument(..., help="Sequences, each as `run` takes it, or quoted "
                                               "globs ('/data/sequences/*')."),
    out: Path = typer.Option(..., "--out", "-o", help="Folder of the run folders (DIR/<name>/) "
                                                      "and results.md/.json/.csv."),
    address: Optional[str] = typer.Option(None, "--address",
                                          help="Ray cluster: auto (one started with `ray "
                                               "start`) or ray://HOST:PORT. Default: Ray "
                                               "inside this command, on this machine."),
    workers: Optional[int] = typer.Option(None, "--workers", min=1,
                                          help="Sequences at once (default: CPU count / "
                                               "--cpus-per-run; with --address: as many as "
                                               "the cluster's CPUs allow)."),
    cpus_per_run: int = typer.Option(1, "--cpus-per-run", min=1,
                                     help="CPUs each run reserves, and its kiss-icp threads "
                                          "(odometry.max_num_threads)."),
    config: Optional[Path] = typer.Option(None, "--config", "-c",
                                          help="YAML config overlay for every run."),
    start: int = typer.Option(0, "--start", min=0, help="First scan of every sequence."),
    n_scans: Optional[int] = typer.Option(None, "--n-scans", min=1,
                                          help="Scans per sequence (default: all)."),
    topic: Optional[str] = typer.Option(None, "--topic", help="PointCloud2 topic of the bags."),
    imu_topic: Optional[str] = typer.Option(None, "--imu-topic",
                                            help="sensor_msgs/Imu topic of the bags."),
    gnss_topic: Optional[str] = typer.Option(None, "--gnss-topic",
                                             help="sensor_msgs/NavSatFix topic of the bags."),
    no_imu: bool = typer.Option(False, "--no-imu", help="Do not read the IMU (imu.csv / topic)."),
    no_gnss: bool = typer.Option(False, "--no-gnss",
                                 help="Do not read the GNSS (gnss.csv / topic)."),
    no_loops: bool = typer.Option(False, "--no-loops", help="Odometry only."),
    no_deskew: bool = typer.Option(False, "--no-deskew", help="Do not deskew."),
    overwrite: bool = typer.Option(False, "--overwrite",
                                   help="Run every sequence again (by default finished ones are "
                                        "skipped and partial ones resumed)."),
) -> None:
    """Run SLAM on many sequences, one Ray task each, and write one results table.

    Each sequence is run as `lidar-slam run DATA --out DIR/<name> --resume` would, so
    re-running the same command skips the finished sequences and resumes the partial ones.
    Exit code 0 when every sequence is ok, 1 when some failed, 130 after Ctrl-C.
    """
    from lidar_slam import __version__
    from lidar_slam.batch import BatchJob, expand_inputs, run_batch, sequence_names
    from lidar_slam.batch.fleet import INSTALL, Fleet, ray_installed
    from lidar_slam.batch.results import as_markdown
    from lidar_slam.provenance import git_commit
    from lidar_slam.run.progress import progress_interval_s

    if not ray_installed():
        raise fail(f"batch runs on Ray, which is not installed: {INSTALL}")
    if out.exists() and not out.is_dir():
        raise fail(f"{out}: --out is a file, not a folder")
    if config is not None and not config.is_file():
        raise fail(f"{config}: config file does not exist")
    paths = expand_inputs(data)
    names = sequence_names(paths)
    overrides = run_overrides(no_loops, no_deskew, no_imu, no_gnss)
    overrides["odometry"] = {"max_num_threads": cpus_per_run}
    jobs = [BatchJob(name, str(path), str((out / name).absolute()),
                     str(config.absolute()) if config else None, start, n_scans, topic,
                     overrides, overwrite, cluster=address is not None, imu_topic=imu_topic,
                     gnss_topic=gnss_topic)
            for name, path in zip(names, paths)]
    fleet = Fleet(address, workers, cpus_per_run)
    meta = {"command": "lidar-slam batch " + " ".join(sys.argv[2:]), "version": __version__,
            "git_commit": git_commit(), "address": address or "embedded",
            "cpus_per_run": cpus_per_run, "workers": workers}
    report = run_batch(jobs, out, fleet, progress_interval_s(), meta)
    typer.echo(as_markdown(report.rows), nl=False)
    typer.echo(f"wrote {out / 'results.md'}, results.json and results.csv")
    n, finished = len(report.results), len(report.results) - report.failed
    if report.interrupted:
        raise fail(f"interrupted; {finished} of {n} sequences finished and kept in {out}; "
                    f"re-run the same command to resume the others", EXIT_INTERRUPTED)
    if report.failed:
        raise fail(f"{report.failed} of {n} sequences failed, {finished} ok (see "
                    f"{out / 'results.md'})", 1)
