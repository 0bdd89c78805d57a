"""`lidar-slam simulate` as jobs: one sequence per KITTI pose file, several on the Ray fleet of
`batch` (lidar_slam.batch.fan_out), else one after another; or one handheld walk. Nothing here
imports typer: a Ray worker imports this module."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from lidar_slam.errors import LidarSlamError, RunFailed

log = logging.getLogger("lidar_slam")

SIMULATE_OUTPUTS = ("velodyne", "velodyne_times", "poses.txt", "times.txt", "calib.txt",
                    "README.txt", "imu.csv", "imu_truth.csv", "gnss.csv", "gnss_truth.csv",
                    "T_world_seq.txt", "bursts.csv", "lidar_slam.yaml")


@dataclass(frozen=True)
class SimulateJob:
    """One sequence of `simulate`: the pose file, the files beside it and the options."""

    poses: str
    out: str
    calib: str | None = None
    times: str | None = None
    sensor: str = "hdl64"
    start: int = 0
    n_scans: int | None = None
    seed: int = 0
    overwrite: bool = False
    imu_rate_hz: float | None = None  # None: no IMU
    gnss_rate_hz: float | None = None  # None: no GNSS
    imu_extrinsic: tuple[float, ...] | None = None  # x, y, z (m), roll, pitch, yaw (deg)
    gnss_datum: tuple[float, ...] | None = None  # lat, lon (deg), height (m)
    gnss_lever_arm: tuple[float, ...] | None = None  # m, lidar frame
    stamp: str = "start"  # the instant of the sweep times.txt and poses.txt refer to
    imu_time_offset_s: float = 0.0  # the IMU's clock reads the lidar's minus this (s)


def simulate_one(job: SimulateJob, progress: bool = True) -> str:
    """Simulate one sequence into job.out (the --out rule applies); returns the line to print.
    A missing --calib is looked up as ../calib/<name>.txt beside POSES, as --times."""
    import numpy as np

    from lidar_slam.io.trajectory import (
        camera_to_lidar_poses,
        read_kitti_calib_tr,
        read_kitti_poses,
        read_times,
    )
    from lidar_slam.run.outdir import prepare_out_dir, scan_range
    from lidar_slam.run.progress import progress as make_progress
    from lidar_slam.sim.sequence import simulate_sequence

    poses, out = Path(job.poses), Path(job.out)
    calib = Path(job.calib) if job.calib else poses.parent.parent / "calib" / poses.name
    if job.calib is None and not calib.is_file():
        raise RunFailed(f"{poses}: no --calib given and no {calib} beside it; pass --calib")
    Tr = read_kitti_calib_tr(calib)
    poses_lidar = camera_to_lidar_poses(read_kitti_poses(poses), Tr)
    times = Path(job.times) if job.times else poses.parent.parent / "times" / poses.name
    if times.is_file():
        stamps = read_times(times)
    else:
        log.warning("%s not found: poses taken as 0.1 s apart (10 Hz); pass --times", times)
        stamps = np.arange(len(poses_lidar)) * 0.1
    if len(stamps) != len(poses_lidar):
        raise RunFailed(f"{times}: {len(stamps)} stamps for {len(poses_lidar)} poses")
    total = scan_range(poses, job.start, job.n_scans, len(poses_lidar), "pose",
                       count=str(len(poses_lidar)))
    imu, gnss = _inertial(job)
    # after every argument is checked: a refused --start left an empty --out behind
    prepare_out_dir(out, SIMULATE_OUTPUTS, job.overwrite)
    bar = make_progress(f"simulate {out.name}", total, unit="scans", shown=progress)
    try:
        summary = simulate_sequence(poses_lidar, stamps, out, sensor=job.sensor, seed=job.seed,
                                    start=job.start, n_scans=job.n_scans, Tr_cam_lidar=Tr,
                                    on_scan=bar.tick, imu=imu, gnss=gnss, stamp=job.stamp)
    finally:
        bar.close()
    extra = "".join(f", {n} {what}" for n, what in ((summary.n_imu, "IMU samples"),
                                                       (summary.n_gnss, "GNSS fixes")) if n)
    return (f"simulated {summary.n_scans} scans ({summary.points_per_scan:.0f} points/scan, "
            f"{summary.seconds_per_scan:.3f} s/scan{extra}) into {out}")


@dataclass(frozen=True)
class HandheldJob:
    """`simulate --motion handheld|legged|drone`: a walk, a trot or a flight through a seeded
    world, no pose file."""

    out: str
    world: str = "indoor"
    duration_s: float = 60.0
    sensor: str = "os1-64"
    seed: int = 0
    overwrite: bool = False
    imu_rate_hz: float | None = None
    gnss_rate_hz: float | None = None
    imu_extrinsic: tuple[float, ...] | None = None
    gnss_datum: tuple[float, ...] | None = None
    gnss_lever_arm: tuple[float, ...] | None = None
    stamp: str = "start"
    imu_time_offset_s: float = 0.0
    motion: str = "handheld"  # or legged, drone (lidar_slam.sim.motions.MOTIONS)


def simulate_handheld_one(job: HandheldJob, progress: bool = True) -> str:
    """Simulate one walk, trot or flight into job.out (the --out rule applies); returns the
    line to print, with the realised motion maxima."""
    from lidar_slam.run.outdir import prepare_out_dir
    from lidar_slam.run.progress import progress as make_progress
    from lidar_slam.sim.motions import simulate_motion
    from lidar_slam.sim.sensor import get_sensor

    out = Path(job.out)
    prepare_out_dir(out, SIMULATE_OUTPUTS, job.overwrite)
    imu, gnss = _inertial(job)
    total = int(round(job.duration_s * get_sensor(job.sensor).rate_hz))
    bar = make_progress(f"simulate {out.name}", total, unit="scans", shown=progress)
    try:
        summary, st = simulate_motion(out, job.motion, job.world, job.seed, job.duration_s,
                                      job.sensor, imu, gnss, on_scan=bar.tick, stamp=job.stamp)
    finally:
        bar.close()
    extra = "".join(f", {n} {what}" for n, what in ((summary.n_imu, "IMU samples"),
                                                       (summary.n_gnss, "GNSS fixes")) if n)
    return (f"simulated {summary.n_scans} scans ({summary.points_per_scan:.0f} points/scan, "
            f"{summary.seconds_per_scan:.3f} s/scan{extra}) into {out}: {job.motion} "
            f"{job.world}, {st.distance_m:.0f} m, {st.laps:.2f} laps, max rate "
            f"{st.max_rate_dps:.0f} deg/s, max acceleration {st.max_accel_mps2:.1f} m/s^2")


def _inertial(job: SimulateJob | HandheldJob):
    """The job's ImuOptions and GnssOptions (None for those it does not simulate)."""
    from lidar_slam.sim.imu_gnss import GnssOptions, ImuOptions

    imu = gnss = None
    if job.imu_rate_hz is not None:
        imu = ImuOptions(rate_hz=job.imu_rate_hz, T_lidar_imu=_extrinsic(job.imu_extrinsic),
                         time_offset_s=job.imu_time_offset_s)
    if job.gnss_rate_hz is not None:
        gnss = GnssOptions(rate_hz=job.gnss_rate_hz,
                           datum=job.gnss_datum or GnssOptions().datum,
                           lever_arm_m=job.gnss_lever_arm or GnssOptions().lever_arm_m)
    return imu, gnss


def _extrinsic(xyz_rpy_deg: tuple[float, ...] | None):
    """4x4 T_lidar_imu from x, y, z (m), roll, pitch, yaw (deg); identity for None."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    if xyz_rpy_deg is not None:
        roll, pitch, yaw = xyz_rpy_deg[3:]
        T[:3, :3] = Rotation.from_euler("ZYX", [yaw, pitch, roll], degrees=True).as_matrix()
        T[:3, 3] = xyz_rpy_deg[:3]
    return T


def simulate_job(job: SimulateJob) -> tuple[bool, str]:
    """simulate_one as a job of many (a Ray task): (True, its line) or (False, its error)."""
    try:
        return True, simulate_one(job, progress=False)
    except LidarSlamError as exc:
        return False, str(exc)
    except (OSError, ValueError) as exc:
        return False, f"{job.poses}: {exc}"


def simulate_many(jobs: list[SimulateJob], names: list[str], address: str | None,
                  workers: int | None, on_done: Callable[[str], None]) -> None:
    """Several sequences: in parallel on Ray when it is installed, else one after another;
    on_done(line) for each that succeeded; a failing one is reported on stderr and the others
    go on (RunFailed, exit code 1, when any failed)."""
    from lidar_slam.batch.fleet import INSTALL, Fleet, ray_installed
    from lidar_slam.batch.progress import JobProgress
    from lidar_slam.batch.runner import fan_out
    from lidar_slam.run.progress import progress_interval_s

    progress = JobProgress("simulate", names, progress_interval_s())
    failed = 0

    def report(index: int, ok: bool, text: str) -> None:
        nonlocal failed
        failed += not ok
        progress.finished(index, ok, "ok" if ok else f"error: {text}")
        if ok:
            on_done(text)

    if ray_installed():
        def finished(outcome) -> None:
            ok, text = outcome.value if outcome.error is None else (False, outcome.error)
            report(outcome.index, ok, text)

        if fan_out(Fleet(address, workers), simulate_job, jobs, progress, finished):
            raise KeyboardInterrupt  # Ray stopped: Ctrl-C as for one sequence
    else:
        if address is not None:
            raise RunFailed(f"--address needs Ray, which is not installed: {INSTALL}")
        log.warning("Ray is not installed: simulating the %d sequences one after another "
                    "(for all at once: %s)", len(jobs), INSTALL)
        for i, job in enumerate(jobs):
            report(i, *simulate_job(job))
    if failed:
        raise RunFailed(f"{failed} of {len(jobs)} sequences failed", 1)
