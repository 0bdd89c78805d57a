"""tools/benchmark.py: lidar-slam and its peers side by side on a 4-scan KITTI slice."""

from __future__ import annotations

import csv
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lidar_slam.geometry import inverse, to_xyz_quat
from lidar_slam.io.sources import open_source
from lidar_slam.io.trajectory import read_kitti_poses

REPO = Path(__file__).resolve().parents[1]
TOOL = REPO / "tools" / "benchmark.py"


def load_tool():
    return importlib.import_module("tools.benchmark")


def test_benchmark_table_on_kitti_slice(kitti16, tmp_path):
    systems = ["lidar-slam", "kiss-icp"]
    if importlib.util.find_spec("kiss_slam") is not None:
        systems.append("kiss-slam")
    out = tmp_path / "bench"
    proc = subprocess.run(
        [sys.executable, str(TOOL), str(kitti16), "--out", str(out), "--repeats", "1",
         "--n-scans", "4", "--systems", ",".join(systems)],
        capture_output=True, text=True, timeout=300, cwd=REPO)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    md = (out / "benchmark.md").read_text()
    table = json.loads((out / "benchmark.json").read_text())
    assert "| sequence | system | t_err % | r_err deg/100 m | ATE m | ATE max m |" in md
    assert "| kitti00_first16 | lidar-slam |" in md and "| kitti00_first16 | KISS-ICP" in md
    assert md.splitlines()[0] in proc.stdout  # the table is printed too
    # lidar_slam's modules were byte-compiled before the timing, as pip does for the peers'
    pkg = Path(table["bytecode_compiled"])
    assert (pkg / "pipeline.py").is_file()
    assert list((pkg / "__pycache__").glob("pipeline.*.pyc"))
    rows = {r["system"]: r for r in table["rows"]}
    assert sorted(rows) == sorted(systems)
    for name, row in rows.items():
        assert row["error"] is None, row
        assert row["frames"] == 4
        # 4 frames = 2.6 m of path: no KITTI segment, so drift is n/a, never 0.
        assert row["t_err_pct"] is None and row["r_err_deg_per_100m"] is None
        assert row["cells"]["t_err %"] == "n/a (<100 m)"
        # The truth itself is off by ~8 cm/frame here (see the data README), hence the loose bound.
        assert 0.0 < row["ate_rmse_m"] < 0.5, row
        assert 0.0 < row["fps"] < 100.0
        assert 30.0 < row["peak_mb"] < 8000.0
        assert len(read_kitti_poses(out / "kitti00_first16" / name / "poses_kitti.txt")) == 4
    assert rows["lidar-slam"]["loops_accepted"] == 0  # no revisit in 4 frames
    assert rows["kiss-icp"]["cells"]["loops accepted / correct"] == "- (odometry only)"
    # Same scans, same kiss-icp underneath: the two odometries agree closely on 4 frames.
    assert abs(rows["lidar-slam"]["ate_rmse_m"] - rows["kiss-icp"]["ate_rmse_m"]) < 0.05
    # lidar-slam is scored by `lidar-slam batch`'s results code, and gets its table too.
    with (out / "lidar-slam" / "results.csv").open(newline="") as fh:
        ours = list(csv.DictReader(fh))
    assert [r["sequence"] for r in ours] == ["kitti00_first16", "TOTAL"]
    assert ours[0]["status"] == "ok" and ours[0]["frames"] == "4" and ours[0]["t_err_pct"] == ""
    assert float(ours[0]["ate_m"]) == pytest.approx(rows["lidar-slam"]["ate_rmse_m"], abs=1e-6)
    assert (out / "kitti00_first16" / "lidar-slam" / "eval" / "trajectory_top.png").is_file()


def _gt_slice(kitti16, n):
    gt = open_source(kitti16).ground_truth[:n]
    return inverse(gt[0]) @ gt


def test_loops_csv_scored_against_truth(kitti16, tmp_path):
    bench = load_tool()
    gt = _gt_slice(kitti16, 16)
    T_true = inverse(gt[2]) @ gt[12]
    T_bad = T_true.copy()
    T_bad[0, 3] += 2.0  # 2 m off: wrong
    header = ["query_frame", "match_frame", "descriptor_distance", "yaw_guess_deg", "fitness",
              "rmse_m", "accepted", "reason", "x", "y", "z", "qx", "qy", "qz", "qw"]
    path = tmp_path / "loops.csv"
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerow([12, 2, 0.1, 0.0, 0.9, 0.05, 1, "ok", *to_xyz_quat(T_true)])
        w.writerow([13, 3, 0.1, 0.0, 0.2, 0.50, 0, "low fitness", *to_xyz_quat(T_true)])
        w.writerow([14, 4, 0.1, 0.0, 0.9, 0.05, 1, "ok", *to_xyz_quat(T_bad)])
    seq = bench.Sequence(kitti16, "kitti00_first16", 0, 16, gt, None)
    row = bench.Row(seq.name, "lidar-slam", 16)
    bench.score_loops(row, *bench.lidar_slam_loops(path, 0, 16), seq)
    assert (row.loops_accepted, row.loops_correct) == (2, 1)
    assert bench.cells(row)[6] == "2 / 1"


def test_kiss_slam_closures_scored_against_truth(kitti16, tmp_path):
    bench = load_tool()
    gt = _gt_slice(kitti16, 16)
    closures = [{"query_frame": 15, "match_frame": 0,
                 "T_match_query_xyz_quat": to_xyz_quat(inverse(gt[0]) @ gt[15]).tolist()}]
    path = tmp_path / "closures.json"
    path.write_text(json.dumps({"closures": closures}))
    seq = bench.Sequence(kitti16, "kitti00_first16", 0, 16, gt, None)
    row = bench.Row(seq.name, "kiss-slam", 16)
    bench.score_loops(row, *bench.kiss_slam_loops(path, 0), seq)
    assert (row.loops_accepted, row.loops_correct) == (1, 1)


def test_missing_peer_is_skipped_with_a_message(monkeypatch, capsys):
    bench = load_tool()
    monkeypatch.setitem(bench.PEER_PACKAGES, "kiss-slam", "no_such_package_xyz")
    assert not bench.available("kiss-slam")
    assert "skipping KISS-SLAM" in capsys.readouterr().out
    assert bench.available("lidar-slam")


@pytest.mark.parametrize("bad", ["nameonly", "=x.yaml", "seq="])
def test_config_for_rejects_malformed_pairs(bad):
    bench = load_tool()
    with pytest.raises(SystemExit):
        bench.parse_config_for([bad])


# ------------------------------------------------------------------------------ rko_lio

RKO_LIO_MISSING = (importlib.util.find_spec("rko_lio") is None
                   or importlib.util.find_spec("plyfile") is None)


def needs_rko_lio(test):
    """Skip where rko_lio is not installed (the rko or bench extra), unless
    LIDAR_SLAM_REQUIRE_RKO_LIO=1 (set by .ci/run, whose install has the rko extra): then the
    test fails on it."""
    import functools
    import os

    @functools.wraps(test)
    def wrapped(*args, **kwargs):
        if RKO_LIO_MISSING:
            msg = "rko_lio is not installed (pip install -e '.[rko]')"
            if os.environ.get("LIDAR_SLAM_REQUIRE_RKO_LIO") == "1":
                pytest.fail(msg)
            pytest.skip(msg)
        return test(*args, **kwargs)

    return wrapped


# A tilted, offset IMU: the extrinsic must reach rko_lio as it is, not as identity.
T_LIDAR_IMU = "0.1,-0.05,0.2,3,-2,90"


@pytest.fixture(scope="module")
def imu_sim(tmp_path_factory):
    """Simulated KITTI 07, 4 VLP-16 scans with a 200 Hz IMU at T_LIDAR_IMU, and a lidar-slam
    config that states that extrinsic."""
    from conftest import shared_path

    from lidar_slam.config import load_config
    from lidar_slam.sim import load_kitti_truth, simulate_sequence
    from lidar_slam.sim.imu_gnss import ImuOptions

    root = tmp_path_factory.mktemp("rko")
    cfg_file = root / "imu.yaml"
    cfg_file.write_text("imu:\n  T_lidar_imu: [" + T_LIDAR_IMU + "]\n")
    T = load_config(cfg_file).imu.T_lidar_imu_matrix()
    kt = load_kitti_truth(shared_path("kitti_gt"), 7)
    simulate_sequence(kt.poses_world_lidar, kt.stamps_s, root / "seq", sensor="vlp16",
                      n_scans=4, Tr_cam_lidar=kt.Tr_cam_lidar, imu=ImuOptions(T_lidar_imu=T))
    return root / "seq", cfg_file, T


@needs_rko_lio
def test_rko_lio_reads_the_same_points_stamps_imu_and_extrinsic_as_lidar_slam(imu_sim,
                                                                               tmp_path):
    from rko_lio.config import TimestampConfig
    from rko_lio.dataloaders.raw import RawDataLoader

    from lidar_slam.io.imu_gnss import read_imu_csv

    bench = load_tool()
    data, cfg_file, T = imu_sim
    seq = bench.load_sequence(str(data), 1, 3, {data.name: cfg_file})
    dest = tmp_path / "rko-lio" / "input"
    assert bench.write_rko_lio_input(seq, dest) is None
    ts_cfg = TimestampConfig(**bench.RKO_CONFIG["lidar_timestamps"])
    # rko_lio's own reader, as its CLI builds it
    loader = RawDataLoader(dest, timestamp_config=ts_cfg)
    T_imu_to_base, T_lidar_to_base = loader.extrinsics
    np.testing.assert_allclose(T_imu_to_base, T, atol=1e-12)
    np.testing.assert_array_equal(T_lidar_to_base, np.eye(4))
    entries = list(loader)
    imu = read_imu_csv(data / "imu.csv")
    got_imu = [d for kind, d in entries if kind == "imu"]
    assert [d["time"] for d in got_imu] == [round(t * 1e9) for t in imu.stamp_s]
    np.testing.assert_array_equal([d["angular_velocity"] for d in got_imu], imu.gyro_radps)
    np.testing.assert_array_equal([d["acceleration"] for d in got_imu], imu.accel_mps2)
    scans = list(open_source(data).scans(1, 3))
    got_scans = [d for kind, d in entries if kind == "lidar"]
    assert len(got_scans) == 3
    for scan, got in zip(scans, got_scans):
        np.testing.assert_array_equal(got["scan"], scan.points)
        want_ns = (scan.stamp_s + scan.point_times) * 1e9
        assert np.abs(got["timestamps"] - want_ns).max() <= 1.0  # ns
        assert got["end_time_ns"] == got["timestamps"].max()


@needs_rko_lio
def test_benchmark_runs_rko_lio_on_an_imu_sequence_and_warns_of_a_wrong_extrinsic(imu_sim,
                                                                                  tmp_path):
    bench = load_tool()
    data, cfg_file, _ = imu_sim
    out = tmp_path / "bench"
    assert bench.main([str(data), "--out", str(out), "--repeats", "1", "--systems", "rko-lio",
                       "--config-for", f"{data.name}={cfg_file}"]) == 0
    row = json.loads((out / "benchmark.json").read_text())["rows"][0]
    assert row["error"] is None and row["skipped"] is None, row
    assert row["ate_rmse_m"] is not None and row["fps"] > 0 and row["peak_mb"] > 0
    assert len(read_kitti_poses(out / data.name / "rko-lio" / "poses_kitti.txt")) >= 3
    assert not any("T_lidar_imu" in n for n in row["notes"])
    # the default config (identity) is not what the sequence's README.txt states
    bench.main([str(data), "--out", str(out), "--repeats", "1", "--systems", "rko-lio"])
    row = json.loads((out / "benchmark.json").read_text())["rows"][0]
    assert any("README.txt states another T_lidar_imu" in n for n in row["notes"])


def test_rko_lio_row_says_no_imu_where_the_input_has_none(kitti16, tmp_path):
    bench = load_tool()
    seq = bench.load_sequence(str(kitti16), 0, 4, {})
    rows = {"rko-lio": bench.Row(seq.name, "rko-lio", 4)}
    bench.prepare_rko_lio(rows, seq, tmp_path)
    row = rows["rko-lio"]
    assert row.skipped == "no IMU" and row.error is None
    assert bench.cells(row)[2] == "no IMU"
    assert not (tmp_path / "rko-lio" / "input").exists()


def test_rko_lio_poses_are_moved_from_its_base_frame_to_the_lidar_frame(kitti16, tmp_path):
    import yaml

    from lidar_slam.geometry import from_xyz_quat
    from lidar_slam.io.trajectory import write_tum

    bench = load_tool()
    seq = bench.load_sequence(str(kitti16), 0, 16, {})
    stamps = seq.stamps[:16] + 0.05  # mid-sweep
    truth = bench.truth_at(seq, stamps)
    # at the scan stamps, the truth itself
    np.testing.assert_allclose(bench.truth_at(seq, seq.stamps[:16]), seq.ground_truth[:16],
                               atol=1e-7)
    # Were the base the IMU: T_lidar_to_base = T_imu_lidar, and rko_lio would write
    # T_odom_base = T_odom_lidar @ T_lidar_base.
    T_base_lidar = from_xyz_quat(np.array([0.3, -0.1, 0.5, 0.0, 0.0, 0.7071068, 0.7071068]))
    (tmp_path / "input").mkdir()
    (tmp_path / "input" / "transforms.yaml").write_text(yaml.safe_dump(
        {"T_imu_to_base": np.eye(4).tolist(), "T_lidar_to_base": T_base_lidar.tolist()}))
    for k, shift in ((0, 1.0), (1, 0.0)):  # two runs: the newest (highest index) is read
        run = tmp_path / "results" / f"rko_lio_{k}"
        run.mkdir(parents=True)
        write_tum(run / f"rko_lio_{k}_tum.txt", stamps + shift,
                  truth @ inverse(T_base_lidar))
    got_stamps, T_odom_lidar = bench.rko_lio_trajectory(tmp_path)
    np.testing.assert_allclose(got_stamps, stamps, atol=1e-9)
    np.testing.assert_allclose(T_odom_lidar, truth, atol=1e-6)
