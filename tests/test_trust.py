"""Inputs that used to give a silently wrong result (issue 23): each is now refused in one line,
or skipped with a warning and counted in summary.json."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

from lidar_slam.io.trajectory import read_kitti_poses

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample_scans"


def lidar_slam(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "lidar_slam.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout)


def _cut_scan(seq: Path, frame: int, n: int, seed: int = 0) -> None:
    """Keep n random points (and their times) of one scan of a KITTI-layout copy."""
    rng = np.random.default_rng(seed)
    scan = seq / "velodyne" / f"{frame:06d}.bin"
    pts = np.fromfile(scan, np.float32).reshape(-1, 4)
    keep = np.sort(rng.choice(len(pts), n, replace=False))
    pts[keep].tofile(scan)
    times = seq / "velodyne_times" / f"{frame:06d}.bin"
    np.fromfile(times, np.float32)[keep].tofile(times)


def test_a_scan_too_small_to_register_is_skipped_and_counted(tmp_path):
    """A 3-point scan in sample_scans used to be registered (kiss-icp only printed "source
    point cloud is too small"): odometry 0.73 m off at that frame, exit 0, nothing said. Now
    it is skipped like an empty scan (pose predicted), with a warning, and counted."""
    clean, cut = tmp_path / "clean", tmp_path / "cut"
    shutil.copytree(SAMPLE, clean)
    shutil.copytree(SAMPLE, cut)
    _cut_scan(cut, 5, 3)
    a = lidar_slam("run", clean, "--out", tmp_path / "a", "--no-loops")
    b = lidar_slam("run", cut, "--out", tmp_path / "b", "--no-loops")
    assert a.returncode == 0 and b.returncode == 0, b.stderr
    assert "000005.bin: 3 points after cropping (data.min_points: 100)" in b.stderr, b.stderr
    summary = json.loads((tmp_path / "b" / "summary.json").read_text())
    assert summary["skipped_small_scans"] == 1 and summary["skipped_empty_scans"] == 0
    assert summary["frames"] == 71
    A = read_kitti_poses(tmp_path / "a" / "poses_kitti.txt")
    B = read_kitti_poses(tmp_path / "b" / "poses_kitti.txt")
    off = np.linalg.norm(A[:, :3, 3] - B[:, :3, 3], axis=1)
    assert off.max() < 0.2, f"{off.max():.3f} m off at frame {off.argmax()}"


def test_min_points_is_a_setting_and_a_run_without_enough_is_one_line(tmp_path):
    """data.min_points is a setting: with a higher minimum every scan of the demo is too small
    and the run says so in one line."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text("data:\n  min_points: 100000\n")
    proc = lidar_slam("run", SAMPLE, "--out", tmp_path / "o", "--config", cfg, "--n-scans", 5)
    assert proc.returncode == 2, proc.stderr
    assert "fewer than data.min_points 100000" in proc.stderr.strip().splitlines()[-1]
