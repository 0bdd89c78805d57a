"""tools/benchmark.py: lidar-slam and its peers side by side on a 4-scan KITTI slice."""

from __future__ import annotations

import csv
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

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
    assert "| sequence | system | t_err % | r_err deg/100 m | ATE m |" in md
    assert "| kitti00_first16 | lidar-slam |" in md and "| kitti00_first16 | KISS-ICP" in md
    assert md.splitlines()[0] in proc.stdout  # the table is printed too
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
    assert bench.cells(row)[5] == "2 / 1"


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
