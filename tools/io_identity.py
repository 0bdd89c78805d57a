"""Are the poses of every input byte-identical across two checkouts? (issue 30, item 1)

Three steps, so the inputs are made once and each checkout runs on the same bytes:

    python tools/io_identity.py prepare /tmp/hio/inputs          # simulated sequence + pcaps
    python tools/io_identity.py run /tmp/hio/inputs /tmp/hio/before --checkout /path/to/old
    python tools/io_identity.py run /tmp/hio/inputs /tmp/hio/after  --checkout .
    python tools/io_identity.py compare /tmp/hio/before /tmp/hio/after

`run` calls `python -m lidar_slam.cli run` with the checkout first on PYTHONPATH (`git archive
main | tar -x -C /tmp/old` gives an old one), one output folder per input; the old checkout
runs with this tool's cases, so a case it cannot read shows as missing. `compare` cmp's
poses_kitti.txt and odometry_kitti.txt and compares summary.json's `imu`, `gnss` and
`input_kind` (less imu.calibration.window_seconds, a wall-clock time); it prints one line per
input and exits 1 on any difference. The inputs: the repo's sample_scans, the tests' dataset
fixtures, ../shared/data (KITTI 00's first 16 scans, the Ouster OS0 loop, the four Ouster bag
containers) and, from `prepare`, a 10 s simulated handheld walk with imu.csv + gnss.csv, its
first 60 scans with IMU and GNSS as a ROS2 bag (run with the overlay's IMU calibration and
without: found from the data), an Ouster pcap and a Velodyne pcap written by
tests/pcap_writers.py. ~4 min per `run` on 2 cores.
"""

from __future__ import annotations

import argparse
import filecmp
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("LIDAR_SLAM_SHARED_DATA", ROOT.parent / "shared" / "data"))
FIXTURES = ROOT / "tests" / "data" / "datasets"
BAGS = SHARED / "rosbags"


def cases(inputs: Path) -> dict[str, list[str]]:
    """Name -> the `run` arguments before --out."""
    return {
        "sample_scans": [str(ROOT / "sample_scans")],
        "kitti00_first16": [str(SHARED / "kitti00_first16")],
        "ouster_os0_loop_balm": [str(SHARED / "ouster_os0_loop_balm"), "--n-scans", "30"],
        "bag_ros1": [str(BAGS / "converted_by_rosbags" / "ouster_os1_64_points.bag")],
        "bag_ros2_db3": [str(BAGS / "converted_by_rosbags" / "ouster_os1_64_points_ros2_sqlite3")],
        "bag_ros2_mcap": [str(BAGS / "converted_by_rosbags" / "ouster_os1_64_points_ros2_mcap")],
        "mcap_ros1": [str(BAGS / "ouster_os1_64_points_ros1_profile.mcap")],
        "sim_handheld_imu_gnss": [str(inputs / "sim")],
        "ouster_pcap": [str(inputs / "os1.pcap"), "--no-loops"],
        "velodyne_pcap": [str(inputs / "vlp16.pcap"), "--no-loops"],
        "sim_bag_imu_gnss": [str(inputs / "sim_bag"), "--no-loops",
                             "--config", str(inputs / "sim" / "lidar_slam.yaml")],
        "sim_bag_imu_gnss_auto": [str(inputs / "sim_bag"), "--no-loops"],
        "newer_college": [str(FIXTURES / "newer_college/01_short_experiment"), "--no-loops"],
        "mulran": [str(FIXTURES / "mulran/KAIST01"), "--no-loops"],
        "nclt": [str(FIXTURES / "nclt/2012-01-08"), "--no-loops",
                 "--config", str(FIXTURES / "nclt/lidar_slam.yaml")],
        "kitti360": [str(FIXTURES / "kitti360/data_3d_raw/2013_05_28_drive_0000_sync"),
                     "--no-loops"],
        "boreas": [str(FIXTURES / "boreas/boreas-2021-08-05-13-34"), "--no-loops"],
    }


def prepare(inputs: Path) -> None:
    """The simulated inputs: a handheld walk with imu.csv + gnss.csv, and two pcaps."""
    inputs.mkdir(parents=True, exist_ok=True)
    cli = [sys.executable, "-m", "lidar_slam.cli"]
    subprocess.run([*cli, "simulate", "--motion", "handheld", "--imu", "--gnss",
                    "--world", "outdoor", "--duration-s", "10", "--out", str(inputs / "sim"),
                    "--overwrite"],
                   check=True, cwd=ROOT)
    sys.path.insert(0, str(ROOT / "tests"))
    import numpy as np
    from pcap_writers import write_ouster_pcap, write_vlp16_pcap

    from lidar_slam.sim.handheld import build_site
    from lidar_slam.sim.motions import make_motion, simulate_handheld
    from lidar_slam.sim.sensor import get_sensor

    try:  # the module's name before and after the issue 30 rename
        from lidar_slam.sim.imu_gnss import ImuOptions
    except ImportError:
        from lidar_slam.sim.inertial import ImuOptions
    lever_m = (0.006253, -0.011775, 0.007645)  # as tests/test_pcap.py
    T_lidar_imu = np.eye(4)
    T_lidar_imu[:3, 3] = lever_m
    simulate_handheld(inputs / "os1_seq", "indoor", 0, 3.0, imu=ImuOptions(T_lidar_imu=T_lidar_imu))
    write_ouster_pcap(inputs / "os1_seq", inputs / "os1.pcap",
                      imu_to_sensor_mm=tuple(1000 * v for v in lever_m))
    site = build_site("indoor", 0, get_sensor("vlp16"))
    motion = make_motion("handheld", site, 0, 2.0)
    write_vlp16_pcap(inputs / "vlp16.pcap", site.world, motion.trajectory, 2.0,
                     hour_s=1_700_002_800.0)
    _sim_bag(inputs / "sim", inputs / "sim_bag")


def _sim_bag(seq: Path, out: Path, n_scans: int = 60, t0_ns: int = 1_700_000_000 * 10**9
             ) -> None:
    """The first n_scans of a simulated KITTI-layout sequence with imu.csv and gnss.csv as a
    ROS2 bag (MCAP storage): PointCloud2 (x, y, z, intensity, float32 t in s from the stamp),
    sensor_msgs/Imu and NavSatFix, every stamp moved t0_ns on (an epoch clock)."""
    import numpy as np
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types

    def header(stamp_s: float, frame: str):
        ns = t0_ns + round(stamp_s * 1e9)
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
            sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame)

    def cloud(k: int, stamp_s: float):
        xyzi = np.fromfile(seq / "velodyne" / f"{k:06d}.bin", np.float32).reshape(-1, 4)
        t = np.fromfile(seq / "velodyne_times" / f"{k:06d}.bin", np.float32)
        data = np.column_stack([xyzi, t]).astype(np.float32)
        fields = [T["sensor_msgs/msg/PointField"](name=n, offset=4 * i, datatype=7, count=1)
                  for i, n in enumerate(("x", "y", "z", "intensity", "t"))]
        return T["sensor_msgs/msg/PointCloud2"](
            header=header(stamp_s, "lidar"), height=1, width=len(data), fields=fields,
            is_bigendian=False, point_step=20, row_step=20 * len(data),
            data=np.frombuffer(data.tobytes(), np.uint8), is_dense=True)

    v3, zero9 = T["geometry_msgs/msg/Vector3"], np.zeros(9)
    quat = T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)

    def imu(row):
        return T["sensor_msgs/msg/Imu"](
            header=header(row[0], "imu"), orientation=quat, orientation_covariance=zero9,
            angular_velocity=v3(x=row[1], y=row[2], z=row[3]), angular_velocity_covariance=zero9,
            linear_acceleration=v3(x=row[4], y=row[5], z=row[6]),
            linear_acceleration_covariance=zero9)

    def fix(row):
        cov = np.diag([row[4] ** 2, row[4] ** 2, row[5] ** 2]).ravel()
        return T["sensor_msgs/msg/NavSatFix"](
            header=header(row[0], "gnss"),
            status=T["sensor_msgs/msg/NavSatStatus"](status=0, service=1), latitude=row[1],
            longitude=row[2], altitude=row[3], position_covariance=cov,
            position_covariance_type=2)

    stamps = np.loadtxt(seq / "times.txt")[:n_scans]
    end = stamps[-1] + 0.1
    imu_rows = [r for r in np.loadtxt(seq / "imu.csv", delimiter=",", skiprows=1) if r[0] <= end]
    fix_rows = [r for r in np.loadtxt(seq / "gnss.csv", delimiter=",", skiprows=1) if r[0] <= end]
    streams = {"/points": ("sensor_msgs/msg/PointCloud2",
                           [(s, cloud(k, s)) for k, s in enumerate(stamps)]),
               "/imu": ("sensor_msgs/msg/Imu", [(r[0], imu(r)) for r in imu_rows]),
               "/fix": ("sensor_msgs/msg/NavSatFix", [(r[0], fix(r)) for r in fix_rows])}
    if out.exists():
        import shutil

        shutil.rmtree(out)
    with Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        for topic, (msgtype, msgs) in streams.items():
            conn = writer.add_connection(topic, msgtype, typestore=ts)
            for stamp_s, msg in msgs:
                writer.write(conn, t0_ns + round(stamp_s * 1e9), ts.serialize_cdr(msg, msgtype))


def run(inputs: Path, out: Path, checkout: Path, only: list[str]) -> None:
    """Each input through `lidar-slam run` of `checkout` into out/<name>."""
    env = dict(os.environ, PYTHONPATH=str(checkout.resolve()))
    out.mkdir(parents=True, exist_ok=True)
    for name, args in cases(inputs).items():
        if only and name not in only:
            continue
        t0 = time.monotonic()
        proc = subprocess.run([sys.executable, "-m", "lidar_slam.cli", "run", *args,
                               "--out", str(out / name), "--overwrite"],
                              env=env, cwd=checkout, capture_output=True, text=True)
        (out / f"{name}.stderr.txt").write_text(proc.stderr)
        print(f"{name}: exit {proc.returncode} in {time.monotonic() - t0:.1f} s", flush=True)


WALL_CLOCK = ("window_seconds",)  # imu.calibration's time on this machine, not a result


def _without_wall_clock(value):
    if isinstance(value, dict):
        return {k: _without_wall_clock(v) for k, v in value.items() if k not in WALL_CLOCK}
    return value


def _sections(summary: Path) -> dict:
    """summary.json's input_kind, imu and gnss, wall-clock times left out."""
    if not summary.exists():
        return {}
    data = json.loads(summary.read_text())
    return {key: _without_wall_clock(data.get(key)) for key in ("input_kind", "imu", "gnss")}


def compare(before: Path, after: Path) -> int:
    """One line per input; the number of inputs that differ."""
    differ = 0
    names = sorted(p.name for p in before.iterdir() if p.is_dir())
    for name in names:
        problems = []
        for file in ("poses_kitti.txt", "odometry_kitti.txt"):
            a, b = before / name / file, after / name / file
            if not a.exists() or not b.exists():
                problems.append(f"{file} missing ({a.exists()}, {b.exists()})")
            elif not filecmp.cmp(a, b, shallow=False):
                problems.append(f"{file} differs")
        sa, sb = _sections(before / name / "summary.json"), _sections(after / name / "summary.json")
        problems += [f"summary.json {key} differs" for key in ("input_kind", "imu", "gnss")
                     if sa.get(key) != sb.get(key)]
        frames = sum(1 for _ in (before / name / "poses_kitti.txt").open()) \
            if (before / name / "poses_kitti.txt").exists() else 0
        print(f"{name:24s} {frames:4d} poses  " + ("; ".join(problems) or "identical"))
        differ += bool(problems)
    return differ


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("prepare")
    p.add_argument("inputs", type=Path)
    r = sub.add_parser("run")
    r.add_argument("inputs", type=Path)
    r.add_argument("out", type=Path)
    r.add_argument("--checkout", type=Path, default=ROOT)
    r.add_argument("--only", nargs="*", default=[])
    c = sub.add_parser("compare")
    c.add_argument("before", type=Path)
    c.add_argument("after", type=Path)
    args = parser.parse_args()
    if args.cmd == "prepare":
        prepare(args.inputs)
        return 0
    if args.cmd == "run":
        run(args.inputs, args.out, args.checkout, args.only)
        return 0
    return 1 if compare(args.before, args.after) else 0


if __name__ == "__main__":
    sys.exit(main())
