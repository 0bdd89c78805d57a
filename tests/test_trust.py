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


def test_a_run_stopped_by_a_bad_scan_says_why_in_its_summary(tmp_path):
    """A .bin cut short mid-sequence stops the run there (frames so far written, exit 2); the
    summary used to say only `interrupted: false`. It now says why and how far it got."""
    seq = tmp_path / "seq"
    shutil.copytree(SAMPLE, seq)
    bad = seq / "velodyne" / "000010.bin"
    bad.write_bytes(bad.read_bytes()[:1000])
    proc = lidar_slam("run", seq, "--out", tmp_path / "o", "--no-loops")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert "000010.bin" in last and "not a multiple of 16" in last and "stopped there" in last
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["frames"] == 10 and summary["frames_requested"] == 71
    assert summary["interrupted"] is False
    assert summary["stopped"].startswith("input error: ") and "000010.bin" in summary["stopped"]
    done = lidar_slam("run", SAMPLE, "--out", tmp_path / "ok", "--no-loops", "--n-scans", 3)
    assert done.returncode == 0, done.stderr
    assert json.loads((tmp_path / "ok" / "summary.json").read_text())["stopped"] == \
        "end of input"


def test_eval_calls_a_reference_a_reference(tmp_path, ouster_loop, kitti16):
    """The Ouster set's README says its poses are a reference odometry, not ground truth: the
    eval table, metrics.json and plots say "reference" (they said "ground truth")."""
    poses = ouster_loop / "poses.txt"
    proc = lidar_slam("eval", poses, poses, "--out", tmp_path / "e")
    assert proc.returncode == 0, proc.stderr
    assert json.loads((tmp_path / "e" / "metrics.json").read_text())["gt_label"] == "reference"
    assert any(ln.startswith("gt_label") and ln.endswith("reference")
               for ln in proc.stdout.splitlines()), proc.stdout
    assert (tmp_path / "e" / "trajectory_top.png").is_file()
    kitti = lidar_slam("eval", kitti16 / "poses.txt", kitti16 / "poses.txt")
    assert "ground truth" in kitti.stdout
    named = lidar_slam("eval", poses, poses, "--gt-label", "BALM initial poses")
    assert "BALM initial poses" in named.stdout
    from lidar_slam.eval.evaluate import truth_label

    # the dataset folder given as GT (its README in it, not one folder up): the same label
    assert truth_label(ouster_loop) == truth_label(poses) == "reference"


def test_plots_take_the_label(tmp_path, monkeypatch):
    from lidar_slam.eval import evaluate

    seen = []
    real = evaluate.plot_top_view
    monkeypatch.setattr(evaluate, "plot_top_view",
                        lambda *a, **k: (seen.append(a[-1]), real(*a, **k)))
    T = np.tile(np.eye(4), (5, 1, 1))
    T[:, 0, 3] = np.arange(5.0)
    T[:, 1, 3] = np.arange(5.0) ** 2
    evaluate.write_plots(tmp_path, T, T, gt_label="reference")
    assert seen == ["reference"]
