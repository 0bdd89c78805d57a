#!/usr/bin/env python3
"""Write tests/data/datasets/: a few frames of each public dataset layout lidar_slam.io.datasets
reads, in the real file formats, with point content from the project's simulator.

    python tools/make_dataset_fixtures.py [--out tests/data/datasets] [--points 2500]

One simulated drive (KITTI 07's ground truth from frame 100, 12 scans, an OS1-64, IMU at 200 Hz
mounted as the Newer College OS1's, GNSS at 5 Hz; needs ../shared/data/kitti_gt) is written in
every layout: the same points (subsampled), stamps moved onto each dataset's clock, and the
true T_world_lidar turned into each dataset's ground-truth frame with the inverse of the
reader's conversion (so a run scores against the simulated truth). What is not the datasets'
own: the point content and the Newer College IMU csv's header text (its columns are the ones
steam_icp reads); the KITTI-360 calibration files hold the published values.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lidar_slam.geometry import inverse, quat_from_matrix  # noqa: E402
from lidar_slam.io.datasets import mulran, nclt, newer_college  # noqa: E402
from lidar_slam.io.datasets.common import poses_at, rigid, rot_z, rpy_zyx  # noqa: E402
from lidar_slam.io.imu_gnss import read_gnss_csv, read_imu_csv  # noqa: E402
from lidar_slam.io.sources import KittiSource  # noqa: E402

N_SCANS = 12
# A world frame unlike the first lidar frame: the conversions must not cancel by accident.
T_WORLD_SEQ = rigid(rpy_zyx(0.02, -0.01, 1.1), [350.0, -120.0, 4.0])

# KITTI-360 calibration/calib_cam_to_pose.txt (image_0k: row-major 3x4, given here as R row by
# row then t), calib_cam_to_velo.txt and calib_sick_to_velo.txt (row-major 3x4)
KITTI360_CAM_TO_POSE = {
    "image_00": [0.0371783278, -0.0986182135, 0.9944306009, 0.9992675562, -0.0053553387,
                 -0.0378902567, 0.0090621821, 0.9951109327, 0.0983468786,
                 1.5752681039, 0.0043914093, -0.6500000000],
    "image_01": [0.0194000864, -0.1051529641, 0.9942668106, 0.9997374956, -0.0100836652,
                 -0.0205732716, 0.0121891942, 0.9944049345, 0.1049297370,
                 1.5977241400, 0.5981494900, -0.6488433108],
    "image_02": [0.9995185086, 0.0041276589, -0.0307524527, -0.0307926666, 0.0100608424,
                 -0.9994751579, -0.0038160970, 0.9999408692, 0.0101830998,
                 0.7264036936, -0.1499658517, -1.0686400091],
    "image_03": [-0.9996821702, 0.0005703407, -0.0252038325, -0.0252033830, 0.0007820814,
                 0.9996820384, 0.0005898709, 0.9999995315, -0.0007674583,
                 0.7016842127, 0.7463650950, -1.0751978255],
}
KITTI360_CAM_TO_VELO = [0.04307104361, -0.08829286498, 0.995162929, 0.8043914418,
                        -0.999004371, 0.007784614041, 0.04392796942, 0.2993489574,
                        -0.01162548558, -0.9960641394, -0.08786966659, -0.1770225824]
KITTI360_SICK_TO_VELO = [0.9998328856, -0.01305514558, -0.01279702916, -0.3971222434,
                         0.01322436405, 0.9998250388, 0.01322905751, -0.009085164561,
                         0.0126220829, -0.01339607931, 0.9998305997, -0.07072622777]


def _rows(T: np.ndarray) -> np.ndarray:
    return T[:3, :4].ravel()


def simulate(out: Path) -> None:
    imu = ",".join(f"{v:g}" for v in (*newer_college.T_LIDAR_IMU[:3, 3], 0, 0, 180))
    subprocess.run([sys.executable, "-m", "lidar_slam.cli", "simulate",
                    str(ROOT.parent / "shared/data/kitti_gt/poses/07.txt"), "--start", "100",
                    "--n-scans", str(N_SCANS), "--sensor", "os1-64", "--seed", "3", "--imu",
                    "--imu-extrinsic", imu, "--gnss", "--gnss-rate", "5", "--out", str(out),
                    "--overwrite"], check=True, cwd=ROOT)


def subsample(scan, n: int, rng) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    keep = np.sort(rng.choice(len(scan.points), size=min(n, len(scan.points)), replace=False))
    return scan.points[keep], scan.point_times[keep], scan.intensity[keep]


def write_pcd(path: Path, xyz, t_ns, inten) -> None:
    """A binary PCD with the Ouster driver's fields (as the Newer College clouds)."""
    n = len(xyz)
    rec = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"),
                             ("t", "<u4"), ("reflectivity", "<u2"), ("ring", "u1"),
                             ("noise", "<u2"), ("range", "<u4")])
    rec["x"], rec["y"], rec["z"] = xyz.T
    rec["intensity"], rec["t"] = inten, t_ns
    rec["ring"] = np.arange(n) % 64
    rec["range"] = (np.linalg.norm(xyz, axis=1) * 1000).astype(np.uint32)
    head = ("# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
            "FIELDS x y z intensity t reflectivity ring noise range\n"
            "SIZE 4 4 4 4 4 2 1 2 4\nTYPE F F F F U U U U U\nCOUNT 1 1 1 1 1 1 1 1 1\n"
            f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n")
    path.write_bytes(head.encode() + rec.tobytes())


def rows_3x4(T: np.ndarray) -> str:
    return ",".join(f"{v:.9f}" for v in T[:3, :4].ravel())


def newer_college_(out: Path, scans, stamps, T_wl, imu) -> None:
    seq = out / "newer_college" / "01_short_experiment"
    scan_dir = seq / "raw_format" / "ouster_scan"
    scan_dir.mkdir(parents=True)
    t0 = 1583836591.0
    for (xyz, t, inten), s in zip(scans, stamps):
        ns = round((t0 + s) * 1e9)
        write_pcd(scan_dir / f"cloud_{ns // 10**9}_{ns % 10**9}.pcd", xyz,
                  np.round(t * 1e9).astype(np.uint32), inten)
    gt = seq / "ground_truth"
    gt.mkdir()
    T_wb = T_wl @ inverse(newer_college.T_BASE_LIDAR)
    lines = ["#sec,nsec,x,y,z,qx,qy,qz,qw"]
    for s, T in zip(stamps, T_wb):
        ns = round((t0 + s) * 1e9)
        q = quat_from_matrix(T[:3, :3])
        lines.append(f"{ns // 10**9},{ns % 10**9}," + ",".join(f"{v:.9f}" for v in
                                                                (*T[:3, 3], *q)))
    (gt / "registered_poses.csv").write_text("\n".join(lines) + "\n")
    imu_dir = seq / "raw_format" / "ouster_imu"
    imu_dir.mkdir()
    lines = ["counter,sec,nsec,wx,wy,wz,ax,ay,az"]
    for k, (s, w, a) in enumerate(zip(imu.stamp_s, imu.gyro_radps, imu.accel_mps2)):
        ns = round((t0 + s) * 1e9)
        lines.append(f"{k},{ns // 10**9},{ns % 10**9}," + ",".join(f"{v:.9f}" for v in (*w, *a)))
    (imu_dir / "data.csv").write_text("\n".join(lines) + "\n")


def mulran_(out: Path, scans, stamps, T_wl, imu, gnss) -> None:
    seq = out / "mulran" / "KAIST01"
    ouster = seq / "sensor_data" / "Ouster"
    ouster.mkdir(parents=True)
    t0 = 1561000000
    ns = [(t0 * 10**9 + round(s * 1e9)) for s in stamps]
    for (xyz, _t, inten), n in zip(scans, ns):
        np.c_[xyz, inten].astype(np.float32).tofile(ouster / f"{n}.bin")
    T_wb = T_wl @ inverse(mulran.T_BASE_LIDAR)
    (seq / "global_pose.csv").write_text("".join(f"{n},{rows_3x4(T)}\n"
                                                 for n, T in zip(ns, T_wb)))
    imu_ns = [t0 * 10**9 + round(s * 1e9) for s in imu.stamp_s]
    (seq / "sensor_data" / "xsens_imu.csv").write_text("".join(
        f"{n},0,0,0,1,0,0,0," + ",".join(f"{v:.9f}" for v in (*w, *a)) + ",0,0,0\n"
        for n, w, a in zip(imu_ns, imu.gyro_radps, imu.accel_mps2)))
    gps_ns = [t0 * 10**9 + round(s * 1e9) for s in gnss.stamp_s]
    (seq / "sensor_data" / "gps.csv").write_text("".join(
        f"{n},{la:.9f},{lo:.9f},{al:.4f},{sh**2:.4f},0,0,0,{sh**2:.4f},0,0,0,{sv**2:.4f}\n"
        for n, la, lo, al, sh, sv in zip(gps_ns, gnss.lat_deg, gnss.lon_deg, gnss.alt_m,
                                         gnss.sigma_h_m, gnss.sigma_v_m)))
    stamps_rows = sorted([(n, "ouster") for n in ns] + [(n, "imu") for n in imu_ns]
                         + [(n, "gps") for n in gps_ns])
    (seq / "sensor_data" / "data_stamp.csv").write_text("".join(f"{n},{k}\n"
                                                                for n, k in stamps_rows))


def nclt_(out: Path, scans, stamps, T_wl, imu, gnss) -> None:
    date = "2012-01-08"
    seq = out / "nclt" / date
    (seq / "velodyne_sync").mkdir(parents=True)
    t0 = 1326030975 * 10**6
    us = [t0 + round(s * 1e6) for s in stamps]
    for (xyz, _t, inten), u in zip(scans, us):
        body = xyz * np.array([1.0, -1.0, -1.0])  # F p: the files hold body-frame points
        held = ((body > nclt.OFFSET_M) & (body < nclt.OFFSET_M + 65535 * nclt.SCALE_M)).all(1)
        body, inten = body[held], inten[held]  # what uint16 can hold
        rec = np.zeros(len(body), dtype=nclt.POINT)
        q = np.round((body - nclt.OFFSET_M) / nclt.SCALE_M).astype(np.uint16)
        rec["x"], rec["y"], rec["z"] = q.T
        rec["i"] = np.clip(inten * 255, 0, 255).astype(np.uint8)
        rec["l"] = np.arange(len(body)) % 32
        rec.tofile(seq / "velodyne_sync" / f"{u}.bin")
    gt_dir = out / "nclt" / "ground_truth"
    gt_dir.mkdir()
    T_wb = nclt.FLIP @ T_wl @ nclt.FLIP
    lines = [f"{us[0] - 10000},nan,nan,nan,nan,nan,nan"]  # the real files start so
    for u, T in zip(us, T_wb):
        R = T[:3, :3]
        yaw, pitch = np.arctan2(R[1, 0], R[0, 0]), -np.arcsin(R[2, 0])
        roll = np.arctan2(R[2, 1], R[2, 2])
        lines.append(f"{u}," + ",".join(f"{v:.9f}" for v in (*T[:3, 3], roll, pitch, yaw)))
    (gt_dir / f"groundtruth_{date}.csv").write_text("\n".join(lines) + "\n")
    (seq / "ms25.csv").write_text("".join(
        f"{t0 + round(s * 1e6)},0.2,0.1,-0.4," + ",".join(f"{v:.9f}" for v in (*a, *w)) + "\n"
        for s, w, a in zip(imu.stamp_s, imu.gyro_radps, imu.accel_mps2)))
    (seq / "gps.csv").write_text("".join(
        f"{t0 + round(s * 1e6)},3,8,{np.radians(la):.12f},{np.radians(lo):.12f},{al:.3f},0,0\n"
        for s, la, lo, al in zip(gnss.stamp_s, gnss.lat_deg, gnss.lon_deg, gnss.alt_m)))
    mount = ", ".join(f"{v:g}" for v in (*newer_college.T_LIDAR_IMU[:3, 3], 0, 0, 180))
    (out / "nclt" / "lidar_slam.yaml").write_text(
        "# This fixture's IMU mounting (NCLT publishes none; see docs/datasets.md)\n"
        f"imu:\n  T_lidar_imu: [{mount}]\n")


def kitti360_(out: Path, scans, stamps, T_wl) -> None:
    root = out / "kitti360"
    drive = "2013_05_28_drive_0000_sync"
    velo = root / "data_3d_raw" / drive / "velodyne_points"
    (velo / "data").mkdir(parents=True)
    for k, (xyz, _t, inten) in enumerate(scans):
        np.c_[xyz, inten].astype(np.float32).tofile(velo / "data" / f"{k:010d}.bin")
    t0 = datetime(2013, 5, 28, 8, 46, 2, tzinfo=timezone.utc).timestamp()
    lines = []
    for s in stamps:
        whole, frac = divmod(t0 + s, 1.0)
        text = datetime.fromtimestamp(whole, timezone.utc).strftime("%Y-%m-%d %H:%M:%S")
        lines.append(f"{text}.{round(frac * 1e9):09d}")
    (velo / "timestamps.txt").write_text("\n".join(lines) + "\n")
    calib = root / "calibration"
    calib.mkdir()
    # The published KITTI-360 calibration (calibration/*.txt), as many tools quote it
    T_pose_cam = {k: rigid(np.array(v[:9]).reshape(3, 3), v[9:]) for k, v in KITTI360_CAM_TO_POSE
                  .items()}
    T_velo_cam0 = np.vstack([np.array(KITTI360_CAM_TO_VELO).reshape(3, 4), [0, 0, 0, 1]])
    (calib / "calib_cam_to_pose.txt").write_text("".join(
        f"{k}: " + " ".join(f"{x:.10f}" for x in _rows(T)) + "\n" for k, T in T_pose_cam.items()))
    (calib / "calib_cam_to_velo.txt").write_text(" ".join(f"{x:.10g}" for x in
                                                          KITTI360_CAM_TO_VELO) + "\n")
    (calib / "calib_sick_to_velo.txt").write_text(" ".join(f"{x:.10g}" for x in
                                                           KITTI360_SICK_TO_VELO) + "\n")
    T_pose_velo = T_pose_cam["image_00"] @ inverse(T_velo_cam0)
    T_wp = T_wl @ inverse(T_pose_velo)
    poses = root / "data_poses" / drive
    poses.mkdir(parents=True)
    (poses / "poses.txt").write_text("".join(  # frame 4 left out: the real files skip frames
        f"{k} " + " ".join(f"{v:.9f}" for v in T[:3, :4].ravel()) + "\n"
        for k, T in enumerate(T_wp) if k != 4))


def boreas_(out: Path, scans, stamps, T_wl) -> None:
    seq = out / "boreas" / "boreas-2021-08-05-13-34"
    (seq / "lidar").mkdir(parents=True)
    (seq / "applanix").mkdir()
    (seq / "calib").mkdir()
    t0 = 1628184886 * 10**6
    mid = stamps[:-1] + 0.05  # Boreas stamps the sweep's middle
    T_mid = poses_at(stamps, T_wl, mid)
    rows = ["GPSTime,easting,northing,altitude,vel_east,vel_north,vel_up,roll,pitch,heading,"
            "angvel_z,angvel_y,angvel_x"]
    for (xyz, t, inten), s, T in zip(scans, mid, T_mid):
        us = t0 + round(s * 1e6)
        rec = np.c_[xyz, inten, np.arange(len(xyz)) % 128, t - 0.05].astype(np.float32)
        rec.tofile(seq / "lidar" / f"{us}.bin")
        M = T[:3, :3].T  # pyboreas's C is the transpose of Rz(y) Ry(p) Rx(r)
        yaw, pitch, roll = np.arctan2(M[1, 0], M[0, 0]), -np.arcsin(M[2, 0]), \
            np.arctan2(M[2, 1], M[2, 2])
        rows.append(f"{us}," + ",".join(f"{v:.12g}" for v in (*T[:3, 3], 0, 0, 0, roll, pitch,
                                                               yaw, 0, 0, 0)))
    (seq / "applanix" / "lidar_poses.csv").write_text("\n".join(rows) + "\n")
    np.savetxt(seq / "calib" / "T_applanix_lidar.txt", rigid(rot_z(0.75), [0.02, -0.01, 0.32]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "tests" / "data" / "datasets")
    ap.add_argument("--points", type=int, default=2500)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        sim = Path(tmp) / "sim"
        simulate(sim)
        source = KittiSource(sim)
        rng = np.random.default_rng(0)
        scans = [subsample(s, args.points, rng) for s in source.scans()]
        stamps = source.stamps - source.stamps[0] + 0.5  # 0.5 s into each dataset's clock
        imu = read_imu_csv(sim / "imu.csv")
        imu = imu.shifted(0.5 - source.stamps[0])
        gnss = read_gnss_csv(sim / "gnss.csv").shifted(0.5 - source.stamps[0])
    T_wl = T_WORLD_SEQ @ source.ground_truth
    for name in ("newer_college", "mulran", "nclt", "kitti360", "boreas"):  # README.md stays
        if (args.out / name).exists():
            shutil.rmtree(args.out / name)
    args.out.mkdir(parents=True, exist_ok=True)
    newer_college_(args.out, scans, stamps, T_wl, imu)
    mulran_(args.out, scans, stamps, T_wl, imu, gnss)
    nclt_(args.out, scans, stamps, T_wl, imu, gnss)
    kitti360_(args.out, scans, stamps, T_wl)
    boreas_(args.out, scans, stamps, T_wl)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
