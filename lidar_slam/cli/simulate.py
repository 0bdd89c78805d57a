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
    xt32 = "xt32"
    os0_128 = "os0-128"
    mid360 = "mid360"


class Stamp(str, Enum):
    start = "start"
    end = "end"


class Motion(str, Enum):
    handheld = "handheld"
    legged = "legged"
    drone = "drone"
    car = "car"


class WorldKind(str, Enum):
    indoor = "indoor"
    outdoor = "outdoor"
    office = "office"
    warehouse = "warehouse"


@app.command()
@reports_errors
def simulate(
    poses: Optional[list[Path]] = typer.Argument(None, help="KITTI pose file(s) (left-camera "
                                                 "frame, as poses/XX.txt); several: one "
                                                 "sequence each. None with --motion."),
    out: Path = typer.Option(..., "--out", "-o",
                             help="KITTI-layout sequence folder to write; with several POSES, "
                                  "the folder of one sequence per file (OUT/<name>)."),
    calib: Optional[Path] = typer.Option(None, "--calib",
                                         help="KITTI calib with Tr (velodyne -> cam0); "
                                              "default: ../calib/<name>.txt beside POSES."),
    times: Optional[Path] = typer.Option(None, "--times", help="Stamps (s); default: "
                                         "../times/<name>.txt beside POSES, else 10 Hz."),
    sensor: Optional[Sensor] = typer.Option(None, "--sensor", help="Lidar model to simulate "
                                            "(default hdl64; os1-64 with --motion handheld; "
                                            "mid360: non-repetitive, no rings)."),
    stamp: Stamp = typer.Option(Stamp.start, "--stamp", help="The instant of each sweep that "
                                "times.txt and poses.txt refer to: start, or end (the "
                                "per-point times are then negative)."),
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
    imu_time_offset: float = typer.Option(
        0.0, "--imu-time-offset", min=-1.0, max=1.0, help="With --imu: imu.csv on a clock S "
        "seconds behind the lidar's (IMU stamp = lidar time - S), so the config's "
        "imu.time_offset_s, added to every IMU stamp, is S; written with T_lidar_imu into "
        "OUT/lidar_slam.yaml."),
    gnss: bool = typer.Option(False, "--gnss", help="Also write gnss.csv (noise, dropouts, "
                              "multipath jumps) and its truth; needs pyproj (lidar-slam\\[geo])."),
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
    motion: Optional[Motion] = typer.Option(
        None, "--motion", help="handheld: a person walking laps with the lidar in the hand "
        "(quick looks, flicks, shakes: up to 180 deg/s, 10 m/s^2); legged: a quadruped's trot "
        "0.55 m up, abrupt starts and stops, turns on the spot; drone: a multirotor at "
        "1.5-6 m, climbs, yaw spins, tilts (outdoor or warehouse). Through --world; no POSES."),
    world: Optional[WorldKind] = typer.Option(None, "--world", help="With --motion: indoor "
                                              "(rooms, corridors, a hall; default), outdoor "
                                              "(a plaza among streets and buildings; the "
                                              "drone's default), office (parallel corridors of "
                                              "identical rooms) or warehouse (pillars, racks, "
                                              "parked cars, a low ceiling)."),
    duration_s: Optional[float] = typer.Option(None, "--duration-s", min=0.5,
                                               help="With --motion: seconds of walk (default "
                                               "60; one scan per sweep from t = 0)."),
    sessions: Optional[int] = typer.Option(
        None, "--sessions", min=1, help="With --motion handheld or car: N recordings of one "
        "world into OUT/session_<i>, each from its own start in its own frame (odd ones the "
        "other way round), truth_world.txt beside each, objects changed between them "
        "(OUT/changes.json). car: --world outdoor only."),
    changes: int = typer.Option(10, "--changes", min=0, help="With --sessions: objects moved, "
                                "added or removed between sessions."),
    movers: int = typer.Option(0, "--movers", min=0, help="With --sessions: things moving "
                               "during each session (pedestrians; a car for --motion car), "
                               "their truth in session_<i>/movers.csv."),
) -> None:
    """Ray-cast a lidar along a real trajectory through a procedural street world, or along a
    handheld walk, a legged robot's trot or a drone's flight (--motion) through a built world.

    POSES: KITTI pose files (left-camera frame, as poses/XX.txt). With several, each becomes
    OUT/<name>, simulated in parallel when Ray is installed (`lidar-slam\\[cluster]`).
    """
    from lidar_slam.sim.jobs import SimulateJob, simulate_many, simulate_one

    if imu_time_offset and not imu:
        raise fail("--imu-time-offset goes with --imu")
    if gnss:  # before anything is simulated: it stopped after the scans and the IMU were out
        from lidar_slam.geo import require_pyproj

        require_pyproj()
    timing = {"stamp": stamp.value, "imu_time_offset_s": imu_time_offset}
    rates = (imu_rate if imu else None, gnss_rate if gnss else None,
             _numbers(imu_extrinsic, 6, "--imu-extrinsic"), _numbers(gnss_datum, 3, "--gnss-datum"),
             _numbers(gnss_lever_arm, 3, "--gnss-lever-arm"))
    if motion is not None:
        others = {"POSES": poses, "--calib": calib, "--times": times, "--start": start or None,
                  "--n-scans": n_scans, "--address": address, "--workers": workers}
        given = [name for name, value in others.items() if value]
        if given:
            raise fail(f"--motion {motion.value} walks its own path in its own world: "
                       f"{', '.join(given)} not taken (--duration-s sets the length)")
        default = WorldKind.outdoor if motion in (Motion.drone, Motion.car) else WorldKind.indoor
        if sessions is not None:
            from lidar_slam.sim.sessions import simulate_sessions_job

            if stamp is not Stamp.start or imu_time_offset:
                raise fail("--stamp end and --imu-time-offset go with one recording: --sessions "
                           "are stamped at the sweep's start on the IMU's clock")

            typer.echo(simulate_sessions_job(out, sessions, motion.value,
                                             (world or default).value, duration_s or 60.0,
                                             (sensor or Sensor.os1_64).value, seed, changes,
                                             overwrite, rates, movers))
            return
        if movers:
            raise fail("--movers goes with --sessions")
        if motion is Motion.car:
            raise fail("--motion car goes with --sessions (one drive: give POSES)")
        _handheld(out, motion, world or default, duration_s or 60.0,
                  (sensor or Sensor.os1_64).value, seed, overwrite, rates, timing)
        return
    if world is not None or duration_s is not None or sessions is not None or movers:
        raise fail("--world, --duration-s and --sessions go with --motion handheld (or legged, "
                   "drone, car)")
    if not poses:
        raise fail("simulate needs POSES (KITTI pose files) or --motion handheld")
    sensor = sensor or Sensor.hdl64
    if overwrite:  # --overwrite deletes the sequence files it writes: poses.txt, calib.txt, ...
        _refuse_inputs_in_out(out, [*poses, calib, times])
    if len(poses) == 1:
        typer.echo(simulate_one(SimulateJob(str(poses[0]), str(out), _str(calib), _str(times),
                                            sensor.value, start, n_scans, seed, overwrite,
                                            *rates, **timing)))
        return
    from lidar_slam.batch import sequence_names

    if times is not None:
        raise fail("--times takes one POSES; with several, each uses ../times/<name>.txt "
                   "beside it (else 10 Hz)")
    paths = [p.absolute() for p in poses]
    names = sequence_names(paths)
    out.mkdir(parents=True, exist_ok=True)
    jobs = [SimulateJob(str(p), str((out / name).absolute()), _str(calib and calib.absolute()),
                        None, sensor.value, start, n_scans, seed, overwrite, *rates, **timing)
            for p, name in zip(paths, names)]
    simulate_many(jobs, names, address, workers, on_done=typer.echo)


def _handheld(out: Path, motion: Motion, world: WorldKind, duration_s: float, sensor: str,
              seed: int, overwrite: bool, rates: tuple, timing: dict) -> None:
    """One walk, trot or flight (lidar_slam.sim.motions) into out."""
    from lidar_slam.sim.jobs import HandheldJob, simulate_handheld_one
    from lidar_slam.sim.motions import MOTION_WORLDS

    if world is not WorldKind.outdoor and rates[1] is not None:
        raise fail("--gnss needs --world outdoor: a receiver indoors has no fix")
    if world.value not in MOTION_WORLDS[motion.value]:
        raise fail(f"--motion {motion.value} goes through --world "
                   f"{' / '.join(MOTION_WORLDS[motion.value])}, not {world.value}")
    typer.echo(simulate_handheld_one(HandheldJob(str(out), world.value, duration_s, sensor,
                                                 seed, overwrite, *rates, **timing,
                                                 motion=motion.value)))


def _refuse_inputs_in_out(out: Path, inputs: list[Path | None]) -> None:
    """An input (POSES, --calib, --times) inside --out would be deleted by --overwrite before
    it is read (the sequence's own poses.txt / calib.txt / times.txt are among what it
    replaces): refused in one line, nothing deleted."""
    o = out.resolve()
    for path in inputs:
        if path is not None and (o == path.resolve() or o in path.resolve().parents):
            raise fail(f"{path}: an input of simulate lies in --out {out}, which --overwrite "
                       f"would delete first; write the sequence to another folder")


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
