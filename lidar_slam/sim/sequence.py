"""Sweeps cast in a world, written as a KITTI-layout sequence; KITTI ground truth read back."""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidar_slam.geometry import inverse
from lidar_slam.io.atomic import atomic_path, write_text_atomic
from lidar_slam.io.trajectory import (
    camera_to_lidar_poses,
    read_kitti_calib_tr,
    read_kitti_poses,
    read_times,
    write_kitti_poses,
)
from lidar_slam.sim.imu_gnss import (
    GnssOptions,
    ImuOptions,
    SmoothTrajectory,
    simulate_gnss,
    simulate_imu,
    write_gnss,
    write_imu,
)
from lidar_slam.sim.sensor import LidarModel, PoseInterpolator, get_sensor
from lidar_slam.sim.world import (
    ALBEDO,
    CLASSES,
    World,
    WorldParams,
    build_world,
    place_on_terrain,
)

log = logging.getLogger(__name__)

# The instant a scan's stamp (times.txt) and pose (poses.txt) refer to: the sweep's start or its
# end (start + 1 / rate_hz); per-point times are relative to it (negative for "end").
STAMPS = ("start", "end")
OVERLAY_FILE = "lidar_slam.yaml"


# ----------------------------------------------------------------------------------------------
# Scans


@dataclass(frozen=True)
class SimScan:
    """One simulated sweep: raw points (N, 3) in the sensor frame at each point's capture time,
    intensity (N,) in [0, 1], times_s (N,) seconds after the sweep start."""

    points: np.ndarray
    intensity: np.ndarray
    times_s: np.ndarray


def simulate_scan(world: World, sensor: LidarModel, poses_at, stamp_s: float, rng,
                  frame: int = 0, seed: int = 0, movers=None) -> SimScan:
    """Cast one sweep starting at stamp_s (s); poses_at(times) -> T_world_lidar (N, 4, 4).
    frame is the sweep's index and seed the sequence's (a non-repetitive pattern moves on with
    them); rng draws the noise; movers (sim.movers.Movers), things moving in the world."""
    sweep = sensor.sweep(frame, seed)
    tau = sweep.times_s
    T = poses_at(stamp_s + tau)  # (A, 4, 4) the sensor pose at each firing instant
    d_loc = sweep.directions  # (A, B, 3) nominal: what the points are computed with
    d_true = sweep.directions_true
    d_world = np.einsum("aij,abj->abi", T[:, :3, :3], d_true).reshape(-1, 3)
    n_b = d_loc.shape[1]
    o_world = np.repeat(T[:, :3, 3], n_b, axis=0)
    hit = world.cast(o_world, d_world)
    r = hit["t_hit"].astype(np.float64)
    if movers is not None:  # each ray meets a mover where it is at the ray's firing instant
        t_m, n_m, c_m = movers.cast(o_world, d_world, np.repeat(stamp_s + tau, n_b))
        closer = t_m < np.where(np.isfinite(r), r, np.inf)
        r[closer] = t_m[closer]
        hit = {"class": np.where(closer, c_m, hit["class"]),
               "prim": np.where(closer, 0, hit["prim"]),
               "normal": np.where(closer[:, None], n_m, hit["normal"])}
    cos_inc = np.abs(np.sum(hit["normal"] * d_world, axis=1))
    u = rng.random(len(r))
    noise = np.clip(rng.normal(0.0, sensor.range_noise_m, len(r)), -3 * sensor.range_noise_m,
                    3 * sensor.range_noise_m)
    # Dropouts: a base rate, and most returns at grazing incidence are lost.
    p_drop = sensor.dropout + 0.6 * np.clip(1.0 - cos_inc / 0.12, 0.0, 1.0)
    ok = np.isfinite(r) & (r >= sensor.min_range_m) & (r <= sensor.max_range_m) & (u >= p_drop)
    rn = r[ok] + noise[ok]
    points = d_loc.reshape(-1, 3)[ok] * rn[:, None]
    albedo = np.array([ALBEDO[c] for c in CLASSES])[hit["class"][ok]]
    texture = 0.8 + 0.4 * ((hit["prim"][ok].astype(np.int64) * 2654435761) % 1000) / 1000.0
    intensity = np.clip(albedo * texture * (0.35 + 0.65 * cos_inc[ok]) * np.exp(-rn / 400.0),
                        0.0, 1.0)
    times = np.repeat(tau, n_b)[ok]
    return SimScan(points, intensity, times)


# ----------------------------------------------------------------------------------------------
# Sequences


@dataclass(frozen=True)
class SimSummary:
    """What simulate_sequence wrote: poses are the simulated T_world_lidar at the scan stamps."""

    out_dir: Path
    sensor: LidarModel
    seed: int
    n_scans: int
    stamps_s: np.ndarray
    poses_world_lidar: np.ndarray  # (n, 4, 4) simulated, in the input world frame
    T_world_seq: np.ndarray  # the sequence frame (poses.txt) = lidar frame of the first scan
    Tr_cam_lidar: np.ndarray
    points_per_scan: float
    seconds_per_scan: float
    world_seconds: float
    n_triangles: int
    n_objects: dict = dataclasses.field(default_factory=dict)
    imu: ImuOptions | None = None
    gnss: GnssOptions | None = None
    n_imu: int = 0
    n_gnss: int = 0
    motion: str | None = None  # the README's account of the poses; None: KITTI trajectory
    stamp: str = "start"  # the instant stamps and poses refer to (STAMPS)


def write_calib(path: Path, Tr_cam_lidar: np.ndarray) -> None:
    """calib.txt with P0..P3 placeholders (KITTI cam0 intrinsics) and the Tr line."""
    p = "7.188560e+02 0.0 6.071928e+02 0.0 0.0 7.188560e+02 1.852157e+02 0.0 0.0 0.0 1.0 0.0"
    tr = " ".join(f"{v:.12e}" for v in Tr_cam_lidar[:3, :4].ravel())
    write_text_atomic(path, "".join(f"P{i}: {p}\n" for i in range(4)) + f"Tr: {tr}\n")


def _write_readme(out: Path, summary: SimSummary) -> None:
    s = summary.sensor
    write_text_atomic(
        out / "README.txt",
        f"Simulated by lidar_slam.sim (sensor {s.name}: {s.pattern_text}, "
        f"{s.rate_hz:g} Hz, max range {s.max_range_m:g} m, "
        f"range noise {s.range_noise_m * 100:g} cm), seed {summary.seed}, "
        f"{summary.n_scans} scans.\n"
        "velodyne/NNNNNN.bin: float32 x y z intensity, raw (motion-distorted) sensor frame.\n"
        "velodyne_times/NNNNNN.bin: float32 seconds of each point after the scan stamp; the stamp\n"
        + _STAMP_TEXT[summary.stamp] +
        "poses.txt: KITTI camera-frame poses P_i = Tr @ T_seq_lidar_i @ inv(Tr) (Tr from\n"
        "  calib.txt); read back with inv(Tr) @ P_i @ Tr. The sequence frame is the lidar "
        "frame of\n"
        "  scan 0 (P_0 = I). " + (summary.motion or _KITTI_POSES) + _inertial_readme(summary))


_STAMP_TEXT = {
    "start": ("  (times.txt) is the START of the sweep and the scan's pose refers to that "
              "instant.\n"),
    "end": ("  (times.txt) is the END of the sweep (its start + 1 / rate: the times are "
            "negative, the\n  last point's ~0) and the scan's pose refers to that instant.\n")}
_KITTI_POSES = ("These are the poses actually simulated (z and roll/pitch from the\n"
                "  fitted terrain), not the input trajectory.\n")


def _inertial_readme(summary: SimSummary) -> str:
    if summary.imu is None and summary.gnss is None:
        return ""
    keys = "poses.txt" if summary.motion is None else "the motion's key poses"
    text = ("Trajectory: a cubic spline through the positions and scipy's RotationSpline through\n"
            f"  the attitudes of {keys}; the points, the IMU and the GNSS all come from it.\n"
            "  The world frame (T_world_seq.txt: the sequence frame in it, 12 numbers, row-major\n"
            "  3x4) is gravity-aligned, z up, gravity 9.81 m/s^2, and is read as ENU at the GNSS\n"
            "  datum.\n")
    if summary.imu is not None:
        o, nz = summary.imu, summary.imu.noise
        text += (
            f"imu.csv: {summary.n_imu} samples at {o.rate_hz:g} Hz from the first "
            f"{'stamp' if summary.stamp == 'start' else 'sweep start'} to the end of the\n  last "
            "sweep; stamp_s,wx,wy,wz (rad/s),ax,ay,az (m/s^2, specific "
            "force), IMU frame.\n" + _clock_text(o.time_offset_s) +
            "  T_lidar_imu (row-major 3x4): "
            f"{' '.join(f'{v:.9g}' for v in np.round(o.T_lidar_imu, 9)[:3].ravel() + 0.0)}"
            "\n  Noise (continuous time): gyro "
            f"{nz.gyro_noise_density:.3g} rad/s/sqrt(Hz), accel {nz.accel_noise_density:.3g} "
            f"m/s^2/sqrt(Hz),\n  bias random walk gyro {nz.gyro_bias_random_walk:.3g} "
            f"rad/s^2/sqrt(Hz), accel {nz.accel_bias_random_walk:.3g} m/s^3/sqrt(Hz),\n"
            f"  initial bias sigma gyro {nz.gyro_bias_sigma:.3g} rad/s, accel "
            f"{nz.accel_bias_sigma:.3g} m/s^2.\n"
            "imu_truth.csv: the noise-free gyro and specific force, the biases in imu.csv\n"
            "  (measured = truth + bias + white noise) and the IMU's velocity in the world"
            + (".\n" if not o.time_offset_s else ",\n  stamped on the lidar clock.\n"))
    if summary.gnss is not None:
        g = summary.gnss
        text += (
            f"gnss.csv: {summary.n_gnss} fixes at {g.rate_hz:g} Hz (WGS84 lat, lon, ellipsoidal "
            f"height);\n  datum {g.datum[0]:.6f} {g.datum[1]:.6f} {g.datum[2]:g} m, lever arm "
            f"{' '.join(f'{v:g}' for v in g.lever_arm_m)} m (lidar frame), white noise "
            f"{g.sigma_h_m:g} m\n  horizontal / {g.sigma_v_m:g} m vertical, "
            f"{g.dropout:.0%} of epochs dropped, {g.jump_fraction:.0%} jumped "
            f"{g.jump_range_m[0]:g}-{g.jump_range_m[1]:g} m (multipath).\n"
            "gnss_truth.csv: every epoch, the antenna's true ENU and WGS84 position, dropped "
            "(0/1), jump_m.\n")
    return text


def _clock_text(time_offset_s: float) -> str:
    if not time_offset_s:
        return ""
    return (f"  Its stamps are on the IMU's clock, {time_offset_s:g} s behind the lidar's (the "
            "times.txt clock):\n  a run adds imu.time_offset_s = "
            f"{time_offset_s:g} to them ({OVERLAY_FILE}).\n")


def write_overlay(out: Path, imu: ImuOptions | None, gnss: GnssOptions | None) -> None:
    """lidar_slam.yaml: the config overlay a run needs to use this sequence's IMU (T_lidar_imu,
    time_offset_s) and GNSS (lever_arm_m) as simulated."""
    import yaml
    from scipy.spatial.transform import Rotation

    overlay, notes = {}, ["# The config overlay for this simulated sequence: lidar-slam run SEQ "
                          f"--config SEQ/{OVERLAY_FILE}"]
    if imu is not None:
        T = np.asarray(imu.T_lidar_imu, dtype=float)
        yaw, pitch, roll = Rotation.from_matrix(T[:3, :3]).as_euler("ZYX", degrees=True)
        values = [*T[:3, 3], roll, pitch, yaw]
        overlay["imu"] = {"T_lidar_imu": [round(float(v), 9) + 0.0 for v in values],
                          "time_offset_s": float(imu.time_offset_s)}
        notes += ["# imu.T_lidar_imu: x y z (m), roll pitch yaw (deg), R = Rz(yaw) Ry(pitch) "
                  "Rx(roll);",
                  "# imu.time_offset_s: added to every imu.csv stamp to put it on the times.txt "
                  "clock."]
    if gnss is not None:
        overlay["gnss"] = {"lever_arm_m": [float(v) for v in gnss.lever_arm_m]}
        notes += ["# gnss.lever_arm_m: the antenna in the lidar frame (m)."]
    write_text_atomic(out / OVERLAY_FILE, "\n".join(notes) + "\n"
                      + yaml.safe_dump(overlay, sort_keys=False, default_flow_style=None))


def sequence_world(poses_world_lidar: np.ndarray, start: int, stop: int,
                   sensor: str | LidarModel = "hdl64", seed: int = 0,
                   params: WorldParams | None = None) -> World:
    """The world simulate_sequence builds for scans start..stop-1 of poses (K, 4, 4): it spans
    that stretch plus params.extend_m of the input path on either side."""
    params = params or WorldParams()
    xy = np.asarray(poses_world_lidar)[:, :2, 3]
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))]
    i0 = int(np.searchsorted(arc, arc[start] - params.extend_m, side="left"))
    i1 = int(np.searchsorted(arc, arc[stop - 1] + params.extend_m, side="right"))
    return build_world(poses_world_lidar[i0:i1], sensor, seed, params)


def simulate_sequence(poses_world_lidar: np.ndarray, stamps_s: np.ndarray, out_dir: str | Path,
                      sensor: str | LidarModel = "hdl64", seed: int = 0, start: int = 0,
                      n_scans: int | None = None, Tr_cam_lidar: np.ndarray | None = None,
                      params: WorldParams | None = None,
                      on_scan: Callable[[int], None] | None = None,
                      imu: ImuOptions | None = None,
                      gnss: GnssOptions | None = None, stamp: str = "start") -> SimSummary:
    """Simulate scans start..start+n_scans of a trajectory into a KITTI-layout folder out_dir.

    poses_world_lidar (K, 4, 4) with stamps_s (K,) in seconds. The world is built along that
    stretch only; the same seed gives the same bytes. Every file is written whole or not at all
    (temporary file + rename); on_scan(k) is called after scan k is written (progress).
    With imu and/or gnss, the poses between stamps come from a SmoothTrajectory (twice
    differentiable: what an IMU measures) instead of slerp/lerp, and imu.csv / gnss.csv and their
    truth files are written from it; without them the output is unchanged. The sweeps start at
    the input stamps; stamp says which instant of each sweep times.txt and poses.txt hold
    (STAMPS).
    """
    sensor = get_sensor(sensor)
    poses_world_lidar = np.asarray(poses_world_lidar, dtype=float)
    stamps_s = np.asarray(stamps_s, dtype=float)
    stop = len(poses_world_lidar) if n_scans is None else min(len(poses_world_lidar),
                                                              start + n_scans)
    if stop <= start:
        raise ValueError(f"nothing to simulate: start {start}, stop {stop}")
    if n_scans is not None and stop - start < n_scans:  # said, as run says a short input
        log.warning("simulating %d scans, not the %d asked for: the trajectory has %d poses "
                    "and --start is %d", stop - start, n_scans, len(poses_world_lidar), start)
    Tr = np.eye(4) if Tr_cam_lidar is None else np.asarray(Tr_cam_lidar, dtype=float)
    params = params or WorldParams()
    t0 = time.perf_counter()
    world = sequence_world(poses_world_lidar, start, stop, sensor, seed, params)
    world_s = time.perf_counter() - t0
    poses = place_on_terrain(poses_world_lidar[start:stop], world.terrain, sensor.mount_height_m)
    stamps = stamps_s[start:stop]
    smooth = imu is not None or gnss is not None
    interp = _smooth(poses_world_lidar, stamps_s, start, stop, world, sensor) if smooth \
        else PoseInterpolator(stamps, poses)
    return write_sequence(out_dir, world, sensor, interp, stamps, poses, seed, Tr, world_s,
                          on_scan, imu, gnss, first_index=start, stamp=stamp)


def write_sequence(out_dir: str | Path, world: World, sensor: LidarModel, interp,
                   stamps: np.ndarray, poses: np.ndarray, seed: int, Tr: np.ndarray,
                   world_s: float, on_scan: Callable[[int], None] | None = None,
                   imu: ImuOptions | None = None, gnss: GnssOptions | None = None,
                   first_index: int = 0, motion: str | None = None,
                   stamp: str = "start", movers=None) -> SimSummary:
    """Cast a sweep starting at each of stamps (s) in world, the sensor moving as
    interp(times) -> T_world_lidar (N, 4, 4), and write the KITTI-layout folder: scans, poses
    (T_world_lidar at the sweep starts, (n, 4, 4)) as poses.txt, times, calib, and with imu /
    gnss (interp is then a SmoothTrajectory) their files, T_world_seq.txt and the config
    overlay. With stamp "end", times.txt, poses.txt and the per-point times refer to each
    sweep's end instead (poses from interp). Scan k draws its noise from the seed and
    first_index + k (also its pattern's frame); motion, when given, is the README's account of
    the poses; movers (sim.movers.Movers) move through the world during it."""
    if stamp not in STAMPS:
        raise ValueError(f"unknown stamp {stamp!r}; choose one of {STAMPS}")
    smooth = imu is not None or gnss is not None
    out = Path(out_dir)
    (out / "velodyne").mkdir(parents=True, exist_ok=True)
    (out / "velodyne_times").mkdir(exist_ok=True)
    n = len(stamps)
    shift_s = sensor.period_s if stamp == "end" else 0.0  # sweep start -> stamp
    n_points = 0
    t1 = time.perf_counter()
    for k in range(n):
        rng = np.random.default_rng([seed, 1, first_index + k])
        scan = simulate_scan(world, sensor, interp, float(stamps[k]), rng, first_index + k, seed,
                             movers)
        # Times first: a scan file never exists without its times (a killed simulate leaves
        # scans that a run reads correctly, never a half-written one).
        with atomic_path(out / "velodyne_times" / f"{k:06d}.bin", fsync=False) as tmp:
            (scan.times_s - shift_s).astype(np.float32).tofile(tmp)
        with atomic_path(out / "velodyne" / f"{k:06d}.bin", fsync=False) as tmp:
            np.c_[scan.points, scan.intensity].astype(np.float32).tofile(tmp)
        n_points += len(scan.points)
        if on_scan is not None:
            on_scan(k)
        if k % 100 == 0:
            log.info("scan %d/%d: %d points", k, n, len(scan.points))
    per_scan = (time.perf_counter() - t1) / n
    t_end = float(stamps[-1]) + sensor.period_s  # the last sweep's end
    t_first = float(stamps[0])
    if shift_s:
        stamps = stamps + shift_s
        poses = interp(stamps)
    T_world_seq = poses[0].copy()
    write_kitti_poses(out / "poses.txt", Tr @ (inverse(T_world_seq) @ poses) @ inverse(Tr))
    with atomic_path(out / "times.txt") as tmp:
        np.savetxt(tmp, stamps, fmt="%.6f")
    write_calib(out / "calib.txt", Tr)
    n_imu = n_gnss = 0
    if smooth:
        write_kitti_poses(out / "T_world_seq.txt", T_world_seq[None])
        write_overlay(out, imu, gnss)
    if imu is not None:
        data = simulate_imu(interp, t_first, t_end, imu, np.random.default_rng([seed, 2]))
        write_imu(out, data, imu.time_offset_s)
        n_imu = len(data.stamps_s)
    if gnss is not None:
        fixes = simulate_gnss(interp, t_first, t_end, gnss, np.random.default_rng([seed, 3]))
        write_gnss(out, fixes)
        n_gnss = int((~fixes.dropped).sum())
    summary = SimSummary(out, sensor, seed, n, stamps, poses, T_world_seq, Tr,
                         n_points / n, per_scan, world_s, world.n_triangles,
                         world.n_objects, imu, gnss, n_imu, n_gnss, motion, stamp)
    _write_readme(out, summary)
    return summary


def _smooth(poses_world_lidar: np.ndarray, stamps_s: np.ndarray, start: int, stop: int,
            world: World, sensor: LidarModel) -> SmoothTrajectory:
    """The spline through the simulated poses start..stop-1, and through one more on either
    side when the input has it (so the first and last sweeps are interpolated, not
    extrapolated; place_on_terrain is per pose, so the written poses are the same)."""
    lo, hi = max(start - 1, 0), min(stop + 1, len(poses_world_lidar))
    poses = place_on_terrain(poses_world_lidar[lo:hi], world.terrain, sensor.mount_height_m)
    stamps = stamps_s[lo:hi]
    if len(stamps) < 2:
        raise ValueError("an IMU or GNSS needs at least two poses to move between")
    return SmoothTrajectory(stamps, poses)


@dataclass(frozen=True)
class KittiTruth:
    """A KITTI ground-truth trajectory in the lidar frame: T_world_lidar (K, 4, 4), stamps (s)."""

    sequence: str
    poses_world_lidar: np.ndarray
    stamps_s: np.ndarray
    Tr_cam_lidar: np.ndarray


def load_kitti_truth(kitti_gt_dir: str | Path, sequence: str | int) -> KittiTruth:
    """Read poses/XX.txt, calib/XX.txt, times/XX.txt; T_world_lidar = inv(Tr) @ P_i @ Tr."""
    root = Path(kitti_gt_dir)
    seq = f"{int(sequence):02d}"
    Tr = read_kitti_calib_tr(root / "calib" / f"{seq}.txt")
    poses = camera_to_lidar_poses(read_kitti_poses(root / "poses" / f"{seq}.txt"), Tr)
    stamps = read_times(root / "times" / f"{seq}.txt")
    return KittiTruth(seq, poses, stamps, Tr)
