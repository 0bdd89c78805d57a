"""`lidar-slam simulate`: lidar sequences ray cast along real trajectories (lidar_slam.sim)."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Optional

import typer

from lidar_slam.cli.common import app, fail, reports_errors


class Sensor(str, Enum):
    hdl64 = "hdl64"
    vlp16 = "vlp16"
    os1_64 = "os1-64"



@app.command()
@reports_errors
def simulate(
    poses: list[Path] = typer.Argument(..., help="KITTI pose file(s) (left-camera frame, as "
                                                 "poses/XX.txt); several: one sequence each."),
    out: Path = typer.Option(..., "--out", "-o",
                             help="KITTI-layout sequence folder to write; with several POSES, "
                                  "the folder of one sequence per file (OUT/<name>)."),
    calib: Optional[Path] = typer.Option(None, "--calib",
                                         help="KITTI calib with Tr (velodyne -> cam0); "
                                              "default: ../calib/<name>.txt beside POSES."),
    times: Optional[Path] = typer.Option(None, "--times", help="Stamps (s); default: "
                                         "../times/<name>.txt beside POSES, else 10 Hz."),
    sensor: Sensor = typer.Option(Sensor.hdl64, "--sensor", help="Lidar model to simulate."),
    start: int = typer.Option(0, "--start", min=0, help="First pose to simulate (0-based)."),
    n_scans: Optional[int] = typer.Option(None, "--n-scans", min=1,
                                          help="Number of scans (default: to the last pose)."),
    seed: int = typer.Option(0, "--seed", help="World and noise seed (same seed, same bytes)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace a sequence in --out."),
    address: Optional[str] = typer.Option(None, "--address",
                                          help="Several POSES: the Ray cluster to use (as "
                                               "`batch --address`); default: this machine."),
    workers: Optional[int] = typer.Option(None, "--workers", min=1,
                                          help="Several POSES: sequences at once (default: "
                                               "the CPU count)."),
    imu: bool = typer.Option(False, "--imu", help="Also write imu.csv (a BMI088-class IMU) "
                             "and its truth; the trajectory becomes a smooth spline."),
    imu_rate: float = typer.Option(200.0, "--imu-rate", min=50.0, max=1000.0,
                                   help="IMU rate (Hz) with --imu."),
    gnss: bool = typer.Option(False, "--gnss", help="Also write gnss.csv (noise, dropouts, "
                              "multipath jumps) and its truth; needs pyproj (lidar-slam[geo])."),
    gnss_rate: float = typer.Option(1.0, "--gnss-rate", min=0.1, max=20.0,
                                    help="GNSS rate (Hz) with --gnss."),
    imu_extrinsic: Optional[str] = typer.Option(
        None, "--imu-extrinsic", help="T_lidar_imu as 'x,y,z,roll,pitch,yaw' (m, deg; "
        "R = Rz(yaw) Ry(pitch) Rx(roll)); default identity."),
    gnss_datum: Optional[str] = typer.Option(
        None, "--gnss-datum", help="WGS84 'lat,lon,height' (deg, deg, m) of the world origin; "
        "default near Karlsruhe (KITTI)."),
    gnss_lever_arm: Optional[str] = typer.Option(
        None, "--gnss-lever-arm", help="Antenna position 'x,y,z' (m) in the lidar frame; "
        "default 0,0,0."),
) -> None:
    """Ray-cast a lidar along a real trajectory through a procedural street world.

    POSES: KITTI pose files (left-camera frame, as poses/XX.txt). With several, each becomes
    OUT/<name>, simulated in parallel when Ray is installed (`lidar-slam[cluster]`).
    """
    from lidar_slam.sim.jobs import SimulateJob, simulate_many, simulate_one

    rates = (imu_rate if imu else None, gnss_rate if gnss else None,
             _numbers(imu_extrinsic, 6, "--imu-extrinsic"), _numbers(gnss_datum, 3, "--gnss-datum"),
             _numbers(gnss_lever_arm, 3, "--gnss-lever-arm"))
    if len(poses) == 1:
        typer.echo(simulate_one(SimulateJob(str(poses[0]), str(out), _str(calib), _str(times),
                                            sensor.value, start, n_scans, seed, overwrite,
                                            *rates)))
        return
    from lidar_slam.batch import sequence_names

    if times is not None:
        raise fail("--times takes one POSES; with several, each uses ../times/<name>.txt "
                   "beside it (else 10 Hz)")
    paths = [p.absolute() for p in poses]
    names = sequence_names(paths)
    out.mkdir(parents=True, exist_ok=True)
    jobs = [SimulateJob(str(p), str((out / name).absolute()), _str(calib and calib.absolute()),
                        None, sensor.value, start, n_scans, seed, overwrite, *rates)
            for p, name in zip(paths, names)]
    simulate_many(jobs, names, address, workers, on_done=typer.echo)


def _numbers(text: str | None, n: int, flag: str) -> tuple[float, ...] | None:
    """n comma-separated finite numbers, or a one-line error naming the flag."""
    if text is None:
        return None
    import math

    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != n or not all(math.isfinite(v) for v in values):
        raise fail(f"{flag} {text!r}: expected {n} comma-separated numbers")
    return values


def _str(path: Path | None) -> str | None:
    return None if path is None else str(path)
