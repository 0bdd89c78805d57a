"""End-to-end `lidar-slam run` and the CLI's handling of bad input and interruption."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_one_line_error

from lidar_slam.io.trajectory import read_kitti_poses, read_tum

REPO = Path(__file__).resolve().parents[1]


def lidar_slam(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "lidar_slam.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout)


def test_missing_path(tmp_path):
    assert_one_line_error(lidar_slam("run", tmp_path / "nope", "--out", tmp_path / "o"),
                          "nope", "does not exist")


def test_folder_without_scans(tmp_path):
    (tmp_path / "notes.txt").write_text("hi")
    assert_one_line_error(lidar_slam("run", tmp_path, "--out", tmp_path / "o"), "no scans found")


def test_bin_of_wrong_size_names_the_file(tmp_path):
    points = np.random.default_rng(0).uniform(-9, 9, (500, 4)).astype(np.float32)
    points.tofile(tmp_path / "000000.bin")
    (tmp_path / "000001.bin").write_bytes(b"\0" * 30)
    proc = lidar_slam("run", tmp_path, "--out", tmp_path / "o", "--no-loops")
    assert_one_line_error(proc, "000001.bin", "not a multiple of 16")
    # What was computed before the bad file is kept.
    assert len(read_kitti_poses(tmp_path / "o" / "poses_kitti.txt")) == 1


def test_unreadable_pcd(tmp_path):
    (tmp_path / "a.pcd").write_bytes(b"\x00garbage")
    assert_one_line_error(lidar_slam("run", tmp_path, "--out", tmp_path / "o"), "a.pcd")


def test_bad_config_is_one_line(tmp_path, kitti16):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("odometry:\n  voxel_size_m: [1, 2]\n")
    assert_one_line_error(lidar_slam("run", kitti16, "--out", tmp_path / "o", "--config", cfg),
                          "odometry.voxel_size_m")


def test_empty_and_nan_scans_are_skipped_not_fatal(tmp_path, kitti16):
    data = tmp_path / "scans"
    data.mkdir()
    for i, src in enumerate(sorted((kitti16 / "velodyne").glob("*.bin"))[:4]):
        pts = np.fromfile(src, np.float32).reshape(-1, 4)
        if i == 1:
            pts[:100, 0] = np.nan
        if i == 2:
            pts = pts[:0]
        pts.tofile(data / f"{i:06d}.bin")
    proc = lidar_slam("run", data, "--out", tmp_path / "o", "--no-loops")
    assert proc.returncode == 0, proc.stderr
    assert "dropped 100 points with NaN/inf" in proc.stderr
    assert "empty scan" in proc.stderr
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["frames"] == 4 and summary["skipped_empty_scans"] == 1


def test_empty_first_scan_with_loops_on(tmp_path, kitti16):
    """An empty first scan still gets keyframe 0 (a node in the pose graph, no descriptor)."""
    data = tmp_path / "scans"
    data.mkdir()
    for i, src in enumerate(sorted((kitti16 / "velodyne").glob("*.bin"))[:6]):
        pts = np.fromfile(src, np.float32).reshape(-1, 4)
        (pts[:0] if i == 0 else pts).tofile(data / f"{i:06d}.bin")
    proc = lidar_slam("run", data, "--out", tmp_path / "o")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["frames"] == 6 and summary["skipped_empty_scans"] == 1


def test_interrupted_run_keeps_frames_so_far(tmp_path, kitti16):
    """pipeline.run raises; a caller that drives Pipeline itself (as the CLI does) keeps every
    frame computed before the interruption."""
    from lidar_slam import pipeline
    from lidar_slam.config import load_config
    from lidar_slam.io.sources import open_source
    from lidar_slam.run.outputs import write_run

    src = open_source(kitti16)

    def scans_then_ctrl_c():
        for scan in src.scans(0, 5):
            yield scan
        raise KeyboardInterrupt

    cfg = load_config()
    with pytest.raises(KeyboardInterrupt):
        pipeline.run(scans_then_ctrl_c(), cfg)
    pipe = pipeline.Pipeline(cfg, tmp_path)
    with pytest.raises(KeyboardInterrupt):
        for scan in scans_then_ctrl_c():
            pipe.process(scan)
    result = pipe.finish()
    assert len(result.indices) == 5
    write_run(tmp_path, result, cfg, src.ground_truth, 1.0, extra={"interrupted": True})
    pipe.close()
    assert len(read_kitti_poses(tmp_path / "poses_kitti.txt")) == 5
    assert json.loads((tmp_path / "summary.json").read_text())["interrupted"] is True


def test_sigint_writes_partial_outputs(tmp_path, kitti16):
    import signal
    import time

    proc = subprocess.Popen([sys.executable, "-m", "lidar_slam.cli", "run", str(kitti16),
                             "--out", str(tmp_path / "o"), "--no-loops"],
                            stderr=subprocess.PIPE, text=True)
    time.sleep(2.5)  # past the imports; the run may or may not have finished
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert "Traceback" not in err
    assert proc.returncode in (0, 130)
    poses = read_kitti_poses(tmp_path / "o" / "poses_kitti.txt")
    assert 1 <= len(poses) <= 16


def test_a_signal_after_the_command_is_over_is_ignored(tmp_path):
    """The command's process ignores Ctrl-C once its command is over: Python restores the default
    handler while it shuts down, and a Ctrl-C there killed a finished run with exit -2 (a CI
    failure of test_sigint_writes_partial_outputs). The caller's own process keeps its handler."""
    import signal

    code = ("import signal, sys\n"
            "from lidar_slam.cli import entry\n"
            "sys.argv = ['lidar-slam', '--version']\n"
            "try:\n    entry()\nexcept SystemExit as e:\n"
            "    print(signal.getsignal(signal.SIGINT) is signal.SIG_IGN, e.code)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)
    assert proc.stdout.split()[-2:] == ["True", "0"], proc.stdout + proc.stderr
    before = signal.getsignal(signal.SIGINT)
    from lidar_slam.cli import app

    with pytest.raises(SystemExit):
        app(args=["--version"])
    assert signal.getsignal(signal.SIGINT) is before


def _wait_for_odometry_lines(proc, out: Path, lines: int) -> Path:
    """Wait (up to 2 min) until a running `lidar-slam run` streamed `lines` odometry lines."""
    import time

    odo = out / "odometry_kitti.txt"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if odo.is_file() and len(odo.read_text().splitlines()) >= lines:
            break
        time.sleep(0.05)
    return odo


def test_sigterm_writes_partial_outputs(tmp_path, ouster_loop):
    """SIGTERM (kill, timeout, docker stop) keeps what was computed, like Ctrl-C."""
    import signal

    out = tmp_path / "o"
    proc = subprocess.Popen([sys.executable, "-m", "lidar_slam.cli", "run", str(ouster_loop),
                             "--out", str(out), "--no-loops"], stderr=subprocess.PIPE, text=True)
    _wait_for_odometry_lines(proc, out, 3)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert "Traceback" not in err
    assert proc.returncode == 130, err
    assert "interrupted" in err
    poses = read_kitti_poses(out / "poses_kitti.txt")
    assert 3 <= len(poses) < 77
    assert json.loads((out / "summary.json").read_text())["interrupted"] is True


def test_killed_run_keeps_its_odometry(tmp_path, ouster_loop):
    """Even SIGKILL (no handler can run) leaves the odometry computed so far, line by line."""
    import signal

    out = tmp_path / "o"
    proc = subprocess.Popen([sys.executable, "-m", "lidar_slam.cli", "run", str(ouster_loop),
                             "--out", str(out), "--no-loops"], stderr=subprocess.DEVNULL)
    odo = _wait_for_odometry_lines(proc, out, 3)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=60)
    poses = read_kitti_poses(odo)
    assert 3 <= len(poses) < 77
    assert np.allclose(poses[0], np.eye(4))


def test_run_on_kitti_writes_everything(tmp_path, kitti16):
    out = tmp_path / "run"
    proc = lidar_slam("run", kitti16, "--out", out)
    assert proc.returncode == 0, proc.stderr
    for name in ("poses_kitti.txt", "poses_tum.txt", "odometry_kitti.txt", "map.ply",
                 "config.yaml", "summary.json"):
        assert (out / name).is_file(), name
    poses = read_kitti_poses(out / "poses_kitti.txt")
    stamps, tum = read_tum(out / "poses_tum.txt")
    assert len(poses) == len(tum) == 16
    np.testing.assert_allclose(tum, poses, atol=1e-6)
    np.testing.assert_allclose(stamps, np.loadtxt(kitti16 / "times.txt"), atol=1e-6)
    summary = json.loads((out / "summary.json").read_text())
    for key in ("frames", "keyframes", "wall_s", "fps", "peak_rss_mb", "path_length_m",
                "rpe_trans_m_mean", "rpe_rot_deg_mean", "end_drift_pct"):
        assert key in summary, key
    assert summary["frames"] == 16
    # Stock KISS-ICP scores 8.6 cm per frame here (much of it the truth's own error).
    assert summary["rpe_trans_m_mean"] < 0.09
    assert 11.0 < summary["path_length_m"] < 13.5  # truth: 12.9 m; the scans say 11.8 m

    from lidar_slam.o3d import o3d

    cloud = o3d.t.io.read_point_cloud(str(out / "map.ply"))
    pts = cloud.point.positions.numpy()
    assert len(pts) >= 20_000
    assert "intensity" in cloud.point
    # The map spans the whole drive: points around the first and the last sensor position.
    for T in (poses[0], poses[-1]):
        near = np.linalg.norm(pts[:, :2] - T[:2, 3], axis=1) < 5.0
        assert near.sum() > 500


def test_start_and_n_scans(tmp_path, kitti16):
    proc = lidar_slam("run", kitti16, "--out", tmp_path / "o", "--start", 4, "--n-scans", 6,
                      "--no-loops")
    assert proc.returncode == 0, proc.stderr
    stamps, _ = read_tum(tmp_path / "o" / "poses_tum.txt")
    np.testing.assert_allclose(stamps, np.loadtxt(kitti16 / "times.txt")[4:10], atol=1e-6)
    assert_one_line_error(lidar_slam("run", kitti16, "--out", tmp_path / "p", "--start", 99),
                          "--start 99")


def test_simulate_then_run_round_trip(tmp_path, kitti_gt):
    out = tmp_path / "sim"
    proc = lidar_slam_env("simulate", kitti_gt / "poses" / "07.txt", "--calib",
                          kitti_gt / "calib" / "07.txt", "--out", out, "--n-scans", "6",
                          "--sensor", "vlp16", env={"LIDAR_SLAM_PROGRESS_S": "0"})
    assert proc.returncode == 0, proc.stderr
    progress = [ln for ln in proc.stderr.splitlines() if "scans/s" in ln]
    assert len(progress) == 6 and "6/6 scans (100 %)" in progress[-1], proc.stderr
    run = lidar_slam("run", out, "--out", tmp_path / "run", "--no-loops")
    assert run.returncode == 0, run.stderr
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["frames"] == 6 and summary["rpe_trans_m_mean"] < 0.3
    # simulate follows the --out rule too: a second simulate into the folder needs --overwrite
    again = ("simulate", kitti_gt / "poses" / "07.txt", "--calib", kitti_gt / "calib" / "07.txt",
             "--out", out, "--n-scans", "3", "--sensor", "vlp16")
    assert_one_line_error(lidar_slam(*again), "already holds files", "--overwrite")
    assert lidar_slam(*again, "--overwrite").returncode == 0
    assert len(list((out / "velodyne").glob("*.bin"))) == 3  # no stale scans left
    # ... and never over its own inputs: poses and calib copied into --out survive
    q = tmp_path / "q"
    q.mkdir()
    for name, src in (("poses.txt", kitti_gt / "poses" / "07.txt"),
                      ("calib.txt", kitti_gt / "calib" / "07.txt")):
        (q / name).write_bytes(src.read_bytes())
    assert_one_line_error(lidar_slam("simulate", q / "poses.txt", "--calib", q / "calib.txt",
                                     "--out", q, "--n-scans", "3", "--overwrite"),
                          "an input of simulate lies in --out")
    assert (q / "poses.txt").is_file() and (q / "calib.txt").is_file()


def test_optimize_and_eval_bad_input(tmp_path):
    bad = tmp_path / "bad.g2o"
    bad.write_text("EDGE_SE2 0 1 nope\n")
    assert_one_line_error(lidar_slam("optimize", bad, "--out", tmp_path / "o.g2o"), "bad.g2o")
    # the input is never the output, and an existing output is replaced only when asked
    assert_one_line_error(lidar_slam("optimize", bad, "--out", bad, "--overwrite"),
                          "--out is the input graph")
    assert bad.read_text() == "EDGE_SE2 0 1 nope\n"
    (tmp_path / "o.g2o").write_text("mine\n")
    assert_one_line_error(lidar_slam("optimize", bad, "--out", tmp_path / "o.g2o"),
                          "already exists", "--overwrite")
    assert (tmp_path / "o.g2o").read_text() == "mine\n"
    est = tmp_path / "est.txt"
    est.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 3)
    gt = tmp_path / "gt.txt"
    gt.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 4)
    assert_one_line_error(lidar_slam("eval", est, gt), "est.txt")


def test_optimize_prints_errors(tmp_path, posegraphs):
    proc = lidar_slam("optimize", posegraphs / "se-sync" / "intel.g2o", "--out", tmp_path / "o.g2o")
    assert proc.returncode == 0, proc.stderr
    lines = dict(ln.split("=", 1) for ln in proc.stdout.splitlines() if ln.startswith(("initial_",
                                                                                         "final_")))
    assert abs(float(lines["final_error"]) - 22.50) / 22.50 < 0.01
    assert float(lines["initial_error"]) > float(lines["final_error"])
    out = proc.stdout
    assert "init=lago (file=skipped (starts higher), lago=22.50" in out  # --init auto, 2D
    assert "repaired_information=0" in out and "robust=none" in out
    sesync = float(out.split("sesync_objective=", 1)[1].split()[0])
    assert abs(sesync - 54.50) / 54.50 < 0.01  # the README's SE-Sync F at LM's solution
    assert "rotations_certified=yes (ShonanAveraging2" in out


def test_optimize_gnc_and_init_file(tmp_path, posegraphs):
    proc = lidar_slam("optimize", posegraphs / "se-sync" / "smallGrid3D.g2o", "--out",
                      tmp_path / "o.g2o", "--robust", "gnc", "--init", "file", "--certify", "off")
    assert proc.returncode == 0, proc.stderr
    assert "init=file (file=" in proc.stdout and "robust=gnc" in proc.stdout
    assert "loops: rejected=" in proc.stdout and "rotations_certified=not_run" in proc.stdout
    assert "iterations=- " in proc.stdout


def test_unwritable_outputs_are_one_line(tmp_path, kitti16):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    assert_one_line_error(lidar_slam("run", kitti16, "--out", blocker / "run", "--n-scans", 2,
                                     "--no-loops"), "file")
    assert_one_line_error(lidar_slam("run", kitti16, "--out", tmp_path / "ok", "--n-scans", 2,
                                     "--no-loops", "--rrd", blocker / "x.rrd"), "x.rrd")


def test_a_bug_mid_run_keeps_the_frames_so_far(tmp_path, kitti16, monkeypatch):
    """pipeline.Pipeline raises; the CLI writes the frames so far, the traceback to a file, and
    exits 1 with one line."""
    from typer.testing import CliRunner

    from lidar_slam import pipeline
    from lidar_slam.cli import app

    calls = {"n": 0}
    real = pipeline.Pipeline.process

    def flaky(self, scan):
        calls["n"] += 1
        if calls["n"] == 4:
            raise ZeroDivisionError("a bug")
        return real(self, scan)

    monkeypatch.setattr(pipeline.Pipeline, "process", flaky)
    out = tmp_path / "o"
    res = CliRunner().invoke(app, ["run", str(kitti16), "--out", str(out), "--n-scans", "8"])
    assert res.exit_code == 1
    assert len(read_kitti_poses(out / "poses_kitti.txt")) == 3
    assert "ZeroDivisionError" in (out / "error_traceback.txt").read_text()


def test_eval_empty_pose_file_is_one_line(tmp_path):
    empty = tmp_path / "est.txt"
    empty.write_text("")
    gt = tmp_path / "gt.txt"
    gt.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    assert_one_line_error(lidar_slam("eval", empty, gt), "est.txt", "empty")


def test_more_bad_inputs_are_one_line(tmp_path, kitti16):
    g2o = tmp_path / "g.g2o"
    g2o.write_text("EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n")
    assert_one_line_error(lidar_slam("optimize", g2o, "--out", tmp_path / "o.g2o", "--robust",
                                     "huber", "--huber-k", "0"), "--huber-k")
    binary = tmp_path / "b.g2o"
    binary.write_bytes(b"EDGE_SE2 \xff\xfe\x00\x01\n")
    assert_one_line_error(lidar_slam("optimize", binary, "--out", tmp_path / "o.g2o"),
                          "b.g2o", "UTF-8")
    # A KITTI sequence whose calib has a typo, and one whose times.txt has two columns.
    import shutil

    seq = tmp_path / "seq"
    shutil.copytree(kitti16, seq)
    calib = seq / "calib.txt"
    text = calib.read_text()
    calib.write_text("\n".join(
        ln.replace("Tr:", "Tr: O.5", 1) if ln.startswith("Tr:") else ln
        for ln in text.splitlines()) + "\n")
    assert_one_line_error(lidar_slam("run", seq, "--out", tmp_path / "o1"), "calib.txt", "Tr")
    calib.write_text(text)
    times = seq / "times.txt"
    stamps = np.loadtxt(times)
    np.savetxt(times, np.c_[stamps, stamps])
    assert_one_line_error(lidar_slam("run", seq, "--out", tmp_path / "o2"), "times.txt",
                          "one stamp per line")


SAMPLE = REPO / "sample_scans"


def test_out_folder_rule(tmp_path):
    """An --out that holds files is refused unless --overwrite (which deletes only our files)
    or --resume; both together is an error."""
    out = tmp_path / "o"
    out.mkdir()
    (out / "mine.txt").write_text("keep me")
    (out / "summary.json").write_text("{}")
    args = ("run", SAMPLE, "--out", out, "--n-scans", 3, "--no-loops")
    assert_one_line_error(lidar_slam(*args), "already holds files", "--overwrite")
    assert_one_line_error(lidar_slam(*args, "--overwrite", "--resume"), "exclude")
    assert lidar_slam(*args, "--overwrite").returncode == 0
    assert (out / "mine.txt").read_text() == "keep me"
    assert json.loads((out / "summary.json").read_text())["frames"] == 3
    # --resume on a missing folder starts fresh; with another config it is refused
    assert lidar_slam("run", SAMPLE, "--out", tmp_path / "new", "--n-scans", 3, "--no-loops",
                      "--resume").returncode == 0
    assert_one_line_error(lidar_slam("run", SAMPLE, "--out", tmp_path / "new", "--n-scans", 3,
                                     "--resume"), "cannot resume", "config")


# summary.json fields that measure the machine, not the input: wall-clock and CPU seconds, rates,
# shares of the wall time and peak memory (the loop worker's and the final solves' durations).
# Every other field, and every other file of a run folder, repeats byte for byte.
TIMING_FIELDS = ("wall_s", "fps", "odometry_ms_per_frame", "loops_ms_per_frame",
                 "loop_worker_ms_per_frame", "loop_wait_ms_per_frame", "loop_wait_final_s",
                 "loop_worker_urgent_s", "backend_ms_per_loop_max", "backend_s",
                 "backend_final_s", "backend_share_pct", "peak_rss_mb",
                 "inertial_solve.seconds", "imu.calibration.window_seconds",
                 "covariance_refinement_floor.seconds")


def without_timing(summary: dict) -> dict:
    """summary.json without TIMING_FIELDS (dotted: a field of a section)."""
    out = json.loads(json.dumps(summary))
    for name in TIMING_FIELDS:
        *sections, key = name.split(".")
        d = out
        for s in sections:
            d = d.get(s) or {}  # a section may be null (covariance_refinement_floor)
        d.pop(key, None)
    return out


def assert_same_run_folders(a: Path, b: Path) -> None:
    """Every file of run folders a and b byte for byte (summary.json without TIMING_FIELDS)."""
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    for name in ("poses_kitti.txt", "poses_tum.txt", "odometry_kitti.txt", "covariances.csv",
                 "loops.csv", "map.ply", "summary.json"):
        assert Path(name) in files, name
    for f in files:
        if f != Path("summary.json"):
            assert (a / f).read_bytes() == (b / f).read_bytes(), f
    sa, sb = (json.loads((d / "summary.json").read_text()) for d in (a, b))
    assert without_timing(sa) == without_timing(sb)


def test_two_runs_write_identical_files(tmp_path):
    """The default config: two runs of the same input write the same bytes. Loop detection runs
    in a worker process; its results are applied at fixed keyframes, so runs do not depend on
    timing (sample_scans: loops accepted); kiss-icp's TBB reductions sum in a varying order on
    more than one thread, and the odometry rounds its pose (odometry.max_num_threads)."""
    for name in ("a", "b"):
        assert lidar_slam("run", SAMPLE, "--out", tmp_path / name).returncode == 0
    assert_same_run_folders(tmp_path / "a", tmp_path / "b")
    summary = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert summary["loops_accepted"] >= 3
    assert summary["odometry_failures"] == 0 and summary["odometry_failure_frames"] == []
    # The back-end's share of the run, and its verdict on every accepted loop (all true here).
    assert 0 < summary["backend_s"] < summary["wall_s"] and 0 < summary["backend_share_pct"] < 100
    assert summary["loops_backend_rejected"] == 0
    assert summary["loops_submap_splits"] == 0  # a smooth KITTI drive: no odometry jump
    rows = [ln.split(",") for ln in (tmp_path / "a" / "loops.csv").read_text().splitlines()]
    assert rows[0][-1] == "backend"
    assert [r[-1] for r in rows[1:] if r[6] == "1"] == ["inlier"] * summary["loops_accepted"]
    assert all(r[-1] == "" for r in rows[1:] if r[6] == "0")


def test_two_runs_with_an_imu_write_identical_files(tmp_path):
    """With an IMU (front-end smoother and the final inertial solve, gtsam) too; and a run with
    kiss-icp on one thread writes the same poses as the default's every core."""
    import dataclasses

    from lidar_slam.sim import SENSORS
    from lidar_slam.sim.imu_gnss import ImuOptions
    from lidar_slam.sim.motions import simulate_handheld

    walk = tmp_path / "walk"
    simulate_handheld(walk, "outdoor", 3, 2.5, dataclasses.replace(SENSORS["os1-64"],
                                                                   n_azimuth=512),
                      imu=ImuOptions(), gnss=None)
    for name in ("a", "b"):  # 2.5 s cannot calibrate the IMU: its overlay gives the values
        assert lidar_slam("run", walk, "--out", tmp_path / name, "--config",
                          walk / "lidar_slam.yaml").returncode == 0
    assert_same_run_folders(tmp_path / "a", tmp_path / "b")
    summary = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert summary["imu"]["used"] and summary["imu_frontend"]["scans_deskewed_by_imu"] > 10
    one = tmp_path / "one.yaml"
    one.write_text((walk / "lidar_slam.yaml").read_text() + "odometry:\n  max_num_threads: 1\n")
    assert lidar_slam("run", walk, "--out", tmp_path / "one", "--config", one).returncode == 0
    for name in ("poses_kitti.txt", "odometry_kitti.txt", "covariances.csv"):
        assert (tmp_path / "one" / name).read_bytes() == (tmp_path / "a" / name).read_bytes()


def test_resume_after_sigkill_matches_an_uninterrupted_run(tmp_path):
    """A run killed with SIGKILL at about half way and resumed with --resume ends within 1 mm /
    0.01 deg of an uninterrupted run on every frame, with the same accepted loops."""
    import signal

    from lidar_slam.geometry import inverse, rotation_angle_deg

    cfg = tmp_path / "ck.yaml"
    cfg.write_text("checkpoint:\n  every_keyframes: 5\n")
    full, killed = tmp_path / "full", tmp_path / "killed"
    assert lidar_slam("run", SAMPLE, "--out", full, "--config", cfg).returncode == 0
    proc = subprocess.Popen([sys.executable, "-m", "lidar_slam.cli", "run", str(SAMPLE), "--out",
                             str(killed), "--config", str(cfg)], stderr=subprocess.DEVNULL)
    _wait_for_odometry_lines(proc, killed, 36)  # of 71
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=60)
    assert not (killed / "poses_kitti.txt").exists()
    res = lidar_slam("run", SAMPLE, "--out", killed, "--config", cfg, "--resume")
    assert res.returncode == 0, res.stderr
    summary = json.loads((killed / "summary.json").read_text())
    assert summary["resumed_at_frame"] > 0 and summary["frames"] == 71
    A, B = read_kitti_poses(full / "poses_kitti.txt"), read_kitti_poses(killed / "poses_kitti.txt")
    assert len(A) == len(B) == 71
    for Ta, Tb in zip(A, B):
        d = inverse(Ta) @ Tb
        assert np.linalg.norm(d[:3, 3]) < 1e-3 and rotation_angle_deg(d) < 0.01

    def accepted(run):
        rows = (run / "loops.csv").read_text().splitlines()[1:]
        return [r.split(",")[:2] for r in rows if r.split(",")[6] == "1"]

    assert accepted(killed) == accepted(full) and len(accepted(full)) >= 3


# --- issue 11: a first hour without surprises ----------------------------------------------------


def lidar_slam_env(*args, env: dict, drop=(), timeout=600):
    """lidar_slam() with extra environment variables (and some removed)."""
    import os

    full = {k: v for k, v in os.environ.items() if k not in drop}
    full.update(env)
    return subprocess.run([sys.executable, "-m", "lidar_slam.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, env=full)


def test_atomic_write_keeps_the_old_file_when_writing_fails(tmp_path, monkeypatch):
    """Outputs go through a temporary file and a rename: a writer that dies half way (an error,
    Ctrl-C, a full disk) leaves the previous file whole and no temporary file behind."""
    from lidar_slam.io import trajectory

    path = tmp_path / "poses_kitti.txt"
    trajectory.write_kitti_poses(path, np.tile(np.eye(4), (3, 1, 1)))
    before = path.read_bytes()

    def savetxt_then_fail(fname, *args, **kwargs):
        Path(fname).write_text("1 0 0 0\n")  # half a line, then the disk is full
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(trajectory.np, "savetxt", savetxt_then_fail)
    with pytest.raises(OSError):
        trajectory.write_kitti_poses(path, np.tile(np.eye(4), (5, 1, 1)))
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["poses_kitti.txt"]


def _bad_first_scan_folder(root: Path) -> Path:
    root.mkdir()
    (root / "000000.bin").write_bytes(b"\0" * 30)
    np.random.default_rng(0).uniform(-9, 9, (500, 4)).astype(np.float32).tofile(
        root / "000001.bin")
    return root


def test_run_failing_at_frame_0_leaves_no_run_folder(tmp_path):
    """A first scan that is bad: one line, exit 2, no table, no 0-frame folder; and a reused
    --out (--overwrite) holds neither the previous run's files nor a new frames: 0 summary."""
    data = _bad_first_scan_folder(tmp_path / "data")
    proc = lidar_slam("run", data, "--out", tmp_path / "new")
    assert_one_line_error(proc, "000000.bin", "not a multiple of 16")
    assert proc.stdout == "" and not (tmp_path / "new").exists()
    reused = tmp_path / "reused"
    assert lidar_slam("run", SAMPLE, "--out", reused, "--n-scans", 3, "--no-loops").returncode == 0
    (reused / "mine.txt").write_text("keep me")
    assert_one_line_error(lidar_slam("run", data, "--out", reused, "--overwrite"), "000000.bin")
    assert sorted(p.name for p in reused.iterdir()) == ["mine.txt"]


def test_input_without_valid_points_is_an_error(tmp_path):
    """Every scan empty (or NaN): exit 2 and one line, not exit 0 with an empty map."""
    data = tmp_path / "data"
    data.mkdir()
    for i in range(3):
        pts = np.full((50, 4), np.nan, np.float32) if i == 1 else np.zeros((0, 4), np.float32)
        pts.tofile(data / f"{i:06d}.bin")
    proc = lidar_slam("run", data, "--out", tmp_path / "o")
    assert_one_line_error(proc, "no valid points", "3 scans")
    assert proc.stdout == "" and not (tmp_path / "o").exists()


def test_second_ctrl_c_keeps_every_output(tmp_path):
    """Ctrl-C in a terminal goes to the whole process group, the loop worker process included;
    it used to kill the worker while it started (BrokenProcessPool: a traceback, and no
    summary.json, graph.g2o or loops.csv). A second Ctrl-C while the outputs are written waits
    for them."""
    import os
    import signal
    import time

    out = tmp_path / "o"
    proc = subprocess.Popen([sys.executable, "-m", "lidar_slam.cli", "run", str(SAMPLE), "--out",
                             str(out)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    _wait_for_odometry_lines(proc, out, 1)  # the worker process is still importing
    os.killpg(proc.pid, signal.SIGINT)
    time.sleep(0.3)
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert "Traceback" not in err and proc.returncode == 130, err
    for name in ("summary.json", "graph.g2o", "loops.csv", "poses_kitti.txt", "map.ply"):
        assert (out / name).is_file(), name
    assert json.loads((out / "summary.json").read_text())["interrupted"] is True


def test_second_signal_while_writing_is_deferred(tmp_path, monkeypatch):
    """Two signals arriving while map.ply is written: every output is still written."""
    import os
    import signal

    from typer.testing import CliRunner

    from lidar_slam.cli import app
    from lidar_slam.run import outputs

    real = outputs.write_map

    def interrupted_twice(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)
        os.kill(os.getpid(), signal.SIGINT)
        return real(*args, **kwargs)

    monkeypatch.setattr(outputs, "write_map", interrupted_twice)
    out = tmp_path / "o"
    res = CliRunner().invoke(app, ["run", str(SAMPLE), "--out", str(out), "--n-scans", "12",
                                   "--config", str(REPO / "configs" / "sample.yaml")])
    assert res.exit_code == 130, res.output
    for name in ("summary.json", "graph.g2o", "loops.csv", "map.ply"):
        assert (out / name).is_file(), name


def test_viz_without_a_display_is_one_warning_and_the_run_goes_on(tmp_path):
    """--viz with no display used to end after ~20 s in a gRPC traceback, exit 1."""
    import time

    t0 = time.monotonic()
    proc = lidar_slam_env("run", SAMPLE, "--out", tmp_path / "o", "--viz", "--n-scans", 3,
                          "--no-loops", env={}, drop=("DISPLAY", "WAYLAND_DISPLAY",
                                                      "WAYLAND_SOCKET"), timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "--viz" in lines[0] and "no display" in lines[0], lines
    assert (tmp_path / "o" / "summary.json").is_file()
    assert time.monotonic() - t0 < 15


def test_progress_lines_on_stderr_without_a_terminal(tmp_path):
    """No TTY (CI, a log file, nohup): progress lines on stderr; stdout keeps the results."""
    proc = lidar_slam_env("run", SAMPLE, "--out", tmp_path / "o", "--n-scans", 8, "--no-loops",
                          env={"CI": "true", "LIDAR_SLAM_PROGRESS_S": "0"})
    assert proc.returncode == 0, proc.stderr
    progress = [ln for ln in proc.stderr.splitlines() if "frames/s" in ln and "ETA" in ln]
    assert len(progress) == 8, proc.stderr
    assert progress[-1].startswith("lidar-slam: sample_scans: 8/8 frames (100 %)")
    assert "ETA" not in proc.stdout and proc.stdout.startswith("frames ")


def test_summary_says_what_was_assumed_and_read(tmp_path):
    """No times.txt: a warning (10 Hz assumed); --topic on a folder: a warning; summary.json has
    the version, commit, config overlay, input kind, topic and deskew state."""
    from lidar_slam import __version__

    data = tmp_path / "scans"
    data.mkdir()
    for i in range(3):
        pts = np.fromfile(SAMPLE / "velodyne" / f"{i:06d}.bin", np.float32)
        pts.tofile(data / f"{i:06d}.bin")
    cfg = REPO / "configs" / "sample.yaml"
    proc = lidar_slam("run", data, "--out", tmp_path / "o", "--no-loops", "--topic", "/points",
                      "--config", cfg)
    assert proc.returncode == 0, proc.stderr
    assert "times.txt not found" in proc.stderr and "10 Hz" in proc.stderr
    assert "--topic /points ignored" in proc.stderr
    s = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert s["version"] == __version__ and "git_commit" in s
    assert s["config_overlay"] == str(cfg) and s["input_kind"] == "folder"
    assert s["topic"] is None and s["deskew"].startswith("off (the scans carry no per-point")
    proc = lidar_slam("run", SAMPLE, "--out", tmp_path / "p", "--no-loops", "--n-scans", 2)
    assert "WARNING" not in proc.stderr, proc.stderr  # times.txt and point times present
    s = json.loads((tmp_path / "p" / "summary.json").read_text())
    assert s["input_kind"] == "kitti" and s["deskew"] == "on" and s["config_overlay"] is None


def test_version_and_help_for_every_option():
    import typer

    from lidar_slam import __version__
    from lidar_slam.cli import app

    proc = lidar_slam("--version")
    assert proc.returncode == 0 and proc.stdout.startswith(f"lidar-slam {__version__}")
    group = typer.main.get_command(app)
    # param_type_name, not isinstance: new typer ships its own click with its own Option class
    options = [p for cmd in group.commands.values() for p in cmd.params
               if p.param_type_name == "option"]
    assert len(options) > 20  # the check sees typer's options (not vacuously empty)
    missing = [f"{name} {param.name}" for name, cmd in group.commands.items()
               for param in cmd.params if param.param_type_name == "option" and not param.help]
    assert missing == []
    assert all(param.help for param in group.params if param.param_type_name == "option")


def test_usage_errors_are_one_line(tmp_path):
    """Bad option values and a --out that is a file: one line, not typer's box or 'File
    exists'."""
    for args, needle in ((("run", SAMPLE, "--out", tmp_path / "o", "--n-scans", -5), "--n-scans"),
                         (("run", SAMPLE), "--out"),
                         (("eval", "a.txt", "b.txt", "--format", "xyz"), "--format")):
        assert_one_line_error(lidar_slam(*args), needle)
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert_one_line_error(lidar_slam("run", SAMPLE, "--out", blocker, "--n-scans", 1),
                          "is a file, not a folder")
    est = SAMPLE / "poses.txt"
    assert_one_line_error(lidar_slam("eval", est, est, "--out", blocker),
                          "is a file, not a folder")


def test_single_scan_file_and_kitti_raw_drive(tmp_path, kitti16):
    """DATA may be one .bin/.pcd file, or a KITTI raw drive (velodyne_points/data +
    timestamps.txt, stamps as date-times)."""
    one = lidar_slam("run", SAMPLE / "velodyne" / "000005.bin", "--out", tmp_path / "one")
    assert one.returncode == 0, one.stderr
    s = json.loads((tmp_path / "one" / "summary.json").read_text())
    assert s["frames"] == 1 and s["input_kind"] == "file" and s["map_points"] > 1000
    drive = tmp_path / "2011_09_26_drive_0001_sync"
    (drive / "velodyne_points" / "data").mkdir(parents=True)
    stamps = np.loadtxt(kitti16 / "times.txt")[:6]
    lines = []
    for i, src in enumerate(sorted((kitti16 / "velodyne").glob("*.bin"))[:6]):
        (drive / "velodyne_points" / "data" / f"{i:010d}.bin").write_bytes(src.read_bytes())
        lines.append(f"2011-09-26 13:02:{25 + stamps[i]:012.9f}")
    (drive / "velodyne_points" / "timestamps.txt").write_text("\n".join(lines) + "\n")
    raw = lidar_slam("run", drive, "--out", tmp_path / "raw", "--no-loops")
    assert raw.returncode == 0, raw.stderr
    got, _ = read_tum(tmp_path / "raw" / "poses_tum.txt")
    assert len(got) == 6
    np.testing.assert_allclose(got - got[0], stamps - stamps[0], atol=1e-6)
    s = json.loads((tmp_path / "raw" / "summary.json").read_text())
    assert s["input_kind"] == "kitti_raw"


def test_terminal_progress_bar_has_an_eta(monkeypatch):
    from rich.progress import TimeRemainingColumn

    from lidar_slam.run.progress import Progress

    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    progress = Progress("x", 3)
    try:
        assert any(isinstance(c, TimeRemainingColumn) for c in progress.bar.columns)
        progress.tick()
    finally:
        progress.close()


def test_the_library_and_its_ray_jobs_import_without_typer():
    """Only lidar_slam.cli imports typer: the runner, batch and its Ray jobs (run_job,
    simulate_job) and localize's driver load without it (batch imported the CLI's
    run_sequence, so every Ray worker imported typer)."""
    code = ("import sys\n"
            "import lidar_slam.batch, lidar_slam.run, lidar_slam.run.localize, "
            "lidar_slam.sim.jobs\n"
            "from lidar_slam.batch import run_job\n"
            "from lidar_slam.sim.jobs import simulate_job\n"
            "print('typer' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "False"
