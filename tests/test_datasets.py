"""Public dataset layouts (lidar_slam.io.datasets): each committed fixture (tests/data/datasets,
written by tools/make_dataset_fixtures.py in the real file formats) is detected, runs and is
scored against the ground truth its reader finds; each ground-truth conversion against a value
worked out by hand; a partial layout is one line naming what is missing."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_one_line_error

from lidar_slam.errors import InputError
from lidar_slam.io.datasets import boreas, kitti360, mulran, nclt, newer_college
from lidar_slam.io.datasets.common import rigid, rot_z
from lidar_slam.io.sources import open_source

DATA = Path(__file__).parent / "data" / "datasets"
ROOT = Path(__file__).resolve().parents[1]
FIXTURES = {  # kind: (sequence path, config overlay)
    "newer_college": ("newer_college/01_short_experiment", None),
    "mulran": ("mulran/KAIST01", None),
    "nclt": ("nclt/2012-01-08", "nclt/lidar_slam.yaml"),
    "kitti360": ("kitti360/data_3d_raw/2013_05_28_drive_0000_sync", None),
    "boreas": ("boreas/boreas-2021-08-05-13-34", None),
}


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lidar_slam.cli", *args], capture_output=True,
                          text=True, cwd=ROOT, timeout=300)


def test_fixtures_stay_small():
    total = sum(p.stat().st_size for p in DATA.rglob("*") if p.is_file())
    assert total < 5e6, f"{total / 1e6:.2f} MB"


@pytest.mark.parametrize("kind", sorted(FIXTURES))
def test_each_layout_is_detected_with_its_ground_truth(kind):
    source = open_source(DATA / FIXTURES[kind][0])
    assert source.kind == kind
    assert len(source) >= 10
    assert source.ground_truth is not None and source.ground_truth.shape == (len(source), 4, 4)
    first = next(source.scans())
    assert len(first.points) > 1000 and np.isfinite(first.points).all()
    has_times = kind in ("newer_college", "boreas")  # the formats with per-point times
    assert (first.point_times is not None) == has_times
    if kind == "boreas":  # stamped at mid-sweep: times on both sides of it
        assert first.point_times.min() < -0.04 and first.point_times.max() > 0.04


def test_sub_folders_of_a_layout_are_detected_too():
    assert open_source(DATA / FIXTURES["kitti360"][0] / "velodyne_points").kind == "kitti360"
    assert open_source(DATA / "mulran/KAIST01/sensor_data").kind == "mulran"


@pytest.mark.parametrize("kind", sorted(FIXTURES))
def test_run_writes_poses_and_eval_finds_the_ground_truth(kind, tmp_path):
    seq, overlay = FIXTURES[kind]
    out = tmp_path / "run"
    args = ["run", str(DATA / seq), "--out", str(out), "--no-loops"]
    if overlay:
        args += ["--config", str(DATA / overlay)]
    proc = _cli(*args)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["input_kind"] == kind
    assert summary["frames"] == len(open_source(DATA / seq))
    assert summary["ate_rmse_m"] < 0.2
    if kind in ("newer_college", "nclt"):  # NCD: the OS1's own mounting; NCLT: the overlay's
        assert summary["imu"]["used"] is True, summary["imu"]
    if kind == "mulran":  # MulRan publishes no IMU mounting: said, not guessed
        assert summary["imu"]["used"] is False
        assert "T_lidar_imu" in summary["imu"]["reason"]
    if kind in ("nclt", "mulran"):  # read, but the fixtures' fixes span too little to align
        gnss = summary["gnss"]
        assert gnss["source"] and gnss["used"] is False and not gnss["geo_referenced"], gnss
        assert "need" in gnss["reason"], gnss
    proc = _cli("eval", str(out / "poses_tum.txt"), str(DATA / seq))
    assert proc.returncode == 0, proc.stderr
    ate = next(ln for ln in proc.stdout.splitlines() if ln.startswith("ATE RMSE"))
    assert abs(float(ate.split()[2]) - summary["ate_rmse_m"]) < 1e-3


def test_newer_college_imu_mounting_comes_from_the_dataset(tmp_path):
    """The OS1's IMU-to-lidar transform lands in the effective config (config.yaml)."""
    out = tmp_path / "run"
    proc = _cli("run", str(DATA / FIXTURES["newer_college"][0]), "--out", str(out), "--no-loops",
                "--n-scans", "3")
    assert proc.returncode == 0, proc.stderr
    import yaml

    T = np.array(yaml.safe_load((out / "config.yaml").read_text())["imu"]["T_lidar_imu"])
    np.testing.assert_allclose(T.reshape(4, 4), newer_college.T_LIDAR_IMU, atol=1e-12)


# Ground-truth conversions, against values worked out by hand (not with the readers' code).

def test_mulran_base_to_lidar_is_the_published_calibration():
    # kiss-icp's mulran.py prints this matrix of calib_base2ouster.txt (its T_lidar_to_base)
    expected = np.array([[-9.9998295e-01, -5.8398386e-03, -5.2257060e-06, 1.7042000e00],
                         [5.8398386e-03, -9.9998295e-01, 1.7758769e-06, -2.1000000e-02],
                         [-5.2359878e-06, 1.7453292e-06, 1.0000000e00, 1.8047000e00],
                         [0, 0, 0, 1.0]])
    T_world_base = rigid(rot_z(np.pi / 2), [10.0, 0.0, 0.0])
    got = mulran.base_to_lidar(T_world_base)
    # the lidar 1.7 m ahead of the base: with the base turned to +y, 1.7 m along world y
    np.testing.assert_allclose(got[:3, 3], [10.021, 1.7042, 1.8047], atol=1e-6)
    np.testing.assert_allclose(mulran.base_to_lidar(np.eye(4)), expected, atol=1e-7)


def test_nclt_body_z_down_to_lidar_z_up():
    # body at (1, 2, 3) (north, east, down) turned 90 deg to the east: in the z-up frames the
    # position is (1, -2, -3) and the turn is -90 deg about the new z
    T_world_body = rigid(rot_z(np.pi / 2), [1.0, 2.0, 3.0])
    got = nclt.body_to_lidar(T_world_body)
    expected = np.array([[0, 1.0, 0, 1], [-1.0, 0, 0, -2], [0, 0, 1.0, -3], [0, 0, 0, 1]])
    np.testing.assert_allclose(got, expected, atol=1e-12)


def test_nclt_velodyne_sync_decoding(tmp_path):
    # 20000 * 0.005 - 100 = 0 m; 20200 -> +1 m; 19800 -> -1 m; body (0, 1, -1) -> z-up (0, -1, 1)
    f = tmp_path / "1.bin"
    np.array([(20000, 20200, 19800, 7, 3)], dtype=nclt.POINT).tofile(f)
    cloud = nclt.read_velodyne_sync(f)
    np.testing.assert_allclose(cloud.points, [[0.0, -1.0, 1.0]], atol=1e-12)
    assert cloud.intensity[0] == 7


def test_nclt_ground_truth_row(tmp_path):
    f = tmp_path / "groundtruth_x.csv"
    f.write_text("100,nan,nan,nan,nan,nan,nan\n2000000,1,2,3,0,0,1.5707963267948966\n")
    stamps, poses = nclt.read_ground_truth(f)
    assert stamps.tolist() == [2.0]
    np.testing.assert_allclose(poses[0], rigid(rot_z(np.pi / 2), [1, 2, 3]), atol=1e-12)


def test_newer_college_base_to_lidar_is_kiss_icps_T_CL():
    # kiss-icp ncd.py: T_CL = quaternion (x 0, y 0, z 0.924, w 0.383), t (-0.084, -0.025, 0.050):
    # a 135 deg turn about z
    T = newer_college.base_to_lidar(np.eye(4))
    np.testing.assert_allclose(T[:3, :3], rot_z(np.radians(135.0)), atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [-0.084, -0.025, 0.050], atol=6e-4)
    # and the OS1 IMU sits 6.253 mm behind / 11.775 mm left of the sensor origin, lidar turned
    # 180 deg: the IMU in the lidar frame is at (-6.253, 11.775, 7.645 - 36.18) mm
    np.testing.assert_allclose(newer_college.T_LIDAR_IMU[:3, 3], [-0.006253, 0.011775,
                                                                  -0.028535], atol=1e-9)


def test_kitti360_pose_to_velodyne():
    # T_pose_cam0 = 1 m along x; T_velo_cam0 = 90 deg about z: T_pose_velo = [Rz(-90) | (1,0,0)]
    T_pose_cam0 = rigid(np.eye(3), [1.0, 0, 0])
    T_velo_cam0 = rigid(rot_z(np.pi / 2), [0, 0, 0])
    got = kitti360.pose_to_velo(np.eye(4), T_pose_cam0, T_velo_cam0)
    expected = np.array([[0, 1.0, 0, 1], [-1.0, 0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1]])
    np.testing.assert_allclose(got, expected, atol=1e-12)


def test_kitti360_frames_without_a_pose_are_interpolated():
    source = open_source(DATA / FIXTURES["kitti360"][0])  # poses.txt leaves out frame 4
    gt = source.ground_truth
    assert np.isfinite(gt).all()
    mid = gt[4][:3, 3]
    assert np.linalg.norm(mid - 0.5 * (gt[3][:3, 3] + gt[5][:3, 3])) < 0.02


def test_boreas_pose_row_follows_pyboreas():
    # pyboreas yaw(y) = [[c, s, 0], [-s, c, 0], [0, 0, 1]]: heading pi/2 gives [[0,1,0],[-1,0,0],..]
    row = np.array([0, 5.0, 6.0, 7.0, 0, 0, 0, 0.0, 0.0, np.pi / 2, 0, 0, 0])
    expected = np.array([[0, 1.0, 0, 5], [-1.0, 0, 0, 6], [0, 0, 1.0, 7], [0, 0, 0, 1]])
    np.testing.assert_allclose(boreas.pose_from_row(row), expected, atol=1e-12)


# A bad or partial layout: one line naming what is missing.

def test_kitti360_poses_without_calibration_is_one_line(tmp_path):
    root = tmp_path / "kitti360"
    shutil.copytree(DATA / "kitti360", root)
    shutil.rmtree(root / "calibration")
    proc = _cli("run", str(root / "data_3d_raw/2013_05_28_drive_0000_sync"), "--out",
                str(tmp_path / "out"))
    assert_one_line_error(proc, "calib_cam_to_pose.txt", "missing")


def test_a_layout_without_scans_is_one_line(tmp_path):
    seq = tmp_path / "01_short_experiment"
    (seq / "raw_format" / "ouster_scan").mkdir(parents=True)
    proc = _cli("run", str(seq), "--out", str(tmp_path / "out"))
    assert_one_line_error(proc, "ouster_scan", "no .pcd scans")


def test_a_bad_scan_name_is_one_line(tmp_path):
    seq = tmp_path / "boreas-x"
    shutil.copytree(DATA / FIXTURES["boreas"][0], seq)
    next((seq / "lidar").glob("*.bin")).rename(seq / "lidar" / "first.bin")
    proc = _cli("run", str(seq), "--out", str(tmp_path / "out"))
    assert_one_line_error(proc, "lidar", "not a stamp")


def test_eval_against_an_input_without_ground_truth_is_one_line(tmp_path):
    seq = tmp_path / "KAIST01"
    shutil.copytree(DATA / FIXTURES["mulran"][0], seq)
    (seq / "global_pose.csv").unlink()
    est = tmp_path / "est.txt"
    est.write_text("0 0 0 0 0 0 0 1\n1 1 0 0 0 0 0 1\n")
    proc = _cli("eval", str(est), str(seq))
    assert_one_line_error(proc, "no ground truth found", "mulran")
    # a run folder given as a trajectory is named as one (it said "no ground truth found")
    run = tmp_path / "run"
    run.mkdir()
    (run / "poses_kitti.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    (run / "summary.json").write_text("{}\n")
    assert_one_line_error(_cli("eval", str(run), str(est)), "a run folder", "poses_kitti.txt")


def test_mulran_full_scan_gets_column_times(tmp_path):
    """A 64 x 1024 MulRan scan: point k of column k // 64 at (k // 64) / 1024 of a sweep (kiss-icp's
    mulran.py get_timestamps, in seconds of the stamp spacing); a partial one gets none."""
    seq = tmp_path / "KAIST02"
    (seq / "sensor_data" / "Ouster").mkdir(parents=True)
    pts = np.ones((64 * 1024, 4), dtype=np.float32)
    for ns in (1_000_000_000, 1_100_000_000):
        pts.tofile(seq / "sensor_data" / "Ouster" / f"{ns}.bin")
    scan = next(open_source(seq).scans())
    assert scan.point_times[63] == 0.0 and scan.point_times[64] == pytest.approx(0.1 / 1024)
    assert scan.point_times[-1] == pytest.approx(0.1 * 1023 / 1024)
    pts[:100].tofile(seq / "sensor_data" / "Ouster" / "1000000000.bin")
    assert next(open_source(seq).scans()).point_times is None


def test_ground_truth_that_does_not_reach_every_scan(tmp_path):
    """Boreas poses for the first 8 of 11 scans: run scores those 8, eval pairs those 8."""
    seq = tmp_path / "boreas-2021-08-05-13-34"
    shutil.copytree(DATA / FIXTURES["boreas"][0], seq)
    csv = seq / "applanix" / "lidar_poses.csv"
    csv.write_text("\n".join(csv.read_text().splitlines()[:9]) + "\n")  # header + 8 rows
    source = open_source(seq)
    assert np.isnan(source.ground_truth[8:]).all() and np.isfinite(source.ground_truth[:8]).all()
    out = tmp_path / "run"
    proc = _cli("run", str(seq), "--out", str(out), "--no-loops")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["ground_truth_frames"] == 8 and summary["ate_rmse_m"] < 0.2
    proc = _cli("eval", str(out / "poses_tum.txt"), str(seq))
    assert proc.returncode == 0, proc.stderr
    assert "by stamp (8 of 11" in proc.stdout


def test_mulran_in_kiss_icps_flat_layout(tmp_path):
    """SEQ/Ouster/*.bin beside global_pose.csv (kiss-icp's mulran.py) is MulRan too; a bare
    Ouster/ folder is not (a folder without scans, refused)."""
    from lidar_slam.errors import InputError

    seq = tmp_path / "DCC01"
    shutil.copytree(DATA / "mulran/KAIST01/sensor_data/Ouster", seq / "Ouster")
    with pytest.raises(InputError, match="no scans found"):
        open_source(seq)
    shutil.copy(DATA / "mulran/KAIST01/global_pose.csv", seq / "global_pose.csv")
    source = open_source(seq)
    assert source.kind == "mulran" and np.isfinite(source.ground_truth).all()


def test_a_scan_named_otherwise_than_its_layout_is_one_line_naming_it(tmp_path):
    """A Newer College cloud named cloud_0.pcd said "a scan file name is not a stamp (not
    enough values to unpack ...)" about its folder; now the file and the expected name."""
    seq = tmp_path / "ncd"
    shutil.copytree(DATA / FIXTURES["newer_college"][0], seq)
    clouds = seq / "raw_format" / "ouster_scan"
    first = sorted(clouds.glob("*.pcd"))[0]
    bad = clouds / "cloud_0.pcd"
    first.rename(bad)
    assert_one_line_error(_cli("run", str(seq), "--out", str(tmp_path / "o")), str(bad),
                          "Newer College cloud_<sec>_<nsec>.pcd")


# -- a layout given half right: the message says what it looks like (a new user's pass) ---------


def _copy(kind: str, tmp_path: Path) -> Path:
    seq = tmp_path / Path(FIXTURES[kind][0]).name
    shutil.copytree(DATA / FIXTURES[kind][0], seq)
    return seq


def test_boreas_without_applanix_or_calib_names_its_lidar_folder(tmp_path):
    """It said "no scans found" of a folder whose lidar/ holds them."""
    seq = _copy("boreas", tmp_path)
    shutil.rmtree(seq / "applanix")
    shutil.rmtree(seq / "calib")
    with pytest.raises(InputError) as err:
        open_source(seq)
    text = str(err.value)
    assert "no scans found" in text and "a Boreas sequence? it needs applanix" in text
    # not "pass .../lidar": read as plain scans, Boreas's six floats are misread
    assert f"{seq / 'lidar'} (" not in text


def test_nclt_with_velodyne_for_velodyne_sync_says_nclt_not_kitti(tmp_path):
    """velodyne/ in place of velodyne_sync/ was read as KITTI: "calib file does not exist"."""
    seq = _copy("nclt", tmp_path)
    (seq / "velodyne_sync").rename(seq / "velodyne")
    with pytest.raises(InputError) as err:
        open_source(seq)
    text = str(err.value)
    assert "no calib.txt" in text and "an NCLT session? its scans go in velodyne_sync/" in text


def test_mulran_scans_numbered_not_stamped_are_one_line(tmp_path):
    """000000.bin .. were read as stamps 1 ns apart."""
    seq = _copy("mulran", tmp_path)
    ouster = seq / "sensor_data" / "Ouster"
    for k, f in enumerate(sorted(ouster.glob("*.bin"))):
        f.rename(ouster / f"{k:06d}.bin")
    with pytest.raises(InputError, match="numbered, not stamped"):
        open_source(seq)


def test_boreas_scans_of_four_floats_are_refused_not_read_as_garbage(tmp_path):
    """KITTI's four float32 a point, 3 x 8 points: a multiple of Boreas's 24 bytes, read as
    16 points of nonsense."""
    seq = _copy("boreas", tmp_path)
    first = sorted((seq / "lidar").glob("*.bin"))[0]
    points = np.c_[np.random.default_rng(0).uniform(-20, 20, (24, 3)), np.full(24, 0.5)]
    points.astype(np.float32).tofile(first)
    source = open_source(seq)
    with pytest.raises(InputError, match="not Boreas's six float32 a point"):
        next(iter(source.scans(0, 1)))


def test_kitti_raw_without_timestamps_advises_its_own_format(tmp_path, caplog):
    """The advice was "one stamp in s per scan": KITTI raw's file holds date-times."""
    drive = tmp_path / "2011_09_26_drive_0001_sync"
    (drive / "velodyne_points" / "data").mkdir(parents=True)
    for i in range(3):
        shutil.copy(sorted((ROOT / "sample_scans" / "velodyne").glob("*.bin"))[i],
                    drive / "velodyne_points" / "data" / f"{i:010d}.bin")
    source = open_source(drive)
    assert source.kind == "kitti_raw"
    assert "one date and time per scan, 2011-09-26 13:02:25.964389445" in caplog.text


def test_boreas_kept_every_20_s_and_a_nan_point_time_still_read(tmp_path):
    """Scans 20 s apart (a sequence thinned) are a lidar's; a NaN time is a point without one
    (a review of the checks above: both were refused)."""
    seq = _copy("boreas", tmp_path)
    files = sorted((seq / "lidar").glob("*.bin"))
    t0 = int(files[0].stem)
    for k, f in enumerate(files):
        f.rename(f.with_name(f"{t0 + k * 20_000_000}.bin"))
    first = sorted((seq / "lidar").glob("*.bin"))[0]
    data = np.fromfile(first, dtype=np.float32).reshape(-1, 6)
    data[0, 5] = np.nan
    data.tofile(first)
    source = open_source(seq)
    assert np.allclose(np.diff(source.stamps), 20.0)
    scan = next(iter(source.scans(0, 1)))
    assert len(scan.points) == len(data)


def test_a_folder_whose_lidar_subfolder_is_numbered_gets_no_boreas_hint(tmp_path):
    root = tmp_path / "recording"
    (root / "lidar").mkdir(parents=True)
    for i in range(2):
        shutil.copy(sorted((ROOT / "sample_scans" / "velodyne").glob("*.bin"))[i],
                    root / "lidar" / f"{i:06d}.bin")
    with pytest.raises(InputError) as err:
        open_source(root)
    assert "Boreas" not in str(err.value) and f"{root / 'lidar'} (2 scans)" in str(err.value)
