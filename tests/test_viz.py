"""Rerun visualisation: an .rrd recording that rerun reads back, and no rerun import without it."""

import subprocess
import sys

import numpy as np


def _entities(rrd_path):
    from rerun.chunk import RrdReader

    store = RrdReader(str(rrd_path)).stream().collect()
    rows: dict[str, int] = {}
    for chunk in store.stream():
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    return rows


def test_rrd_recording_holds_map_and_trajectory(tmp_path, ouster_loop):
    rrd = tmp_path / "out.rrd"
    proc = subprocess.run([sys.executable, "-m", "lidar_slam.cli", "run", str(ouster_loop),
                           "--out", str(tmp_path / "run"), "--rrd", str(rrd), "--n-scans", "10",
                           "--no-loops"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    rows = _entities(rrd)
    assert rows["/world/odometry"] == 10  # the trajectory, once per scan
    assert rows["/world/scan"] == 10
    assert rows["/world/optimised"] == 1
    assert rows["/world/optimised_map"] == 1
    assert sum(1 for e in rows if e.startswith("/world/map/kf_")) >= 3  # the growing map

    from rerun.chunk import RrdReader

    store = RrdReader(str(rrd)).stream().collect()
    strips = [c for c in store.stream() if c.entity_path == "/world/optimised"][0]
    batch = strips.to_record_batch()
    col = "LineStrips3D:strips"
    pts = np.array(batch.column(col).to_pylist()[0][0])
    poses = np.loadtxt(tmp_path / "run" / "poses_kitti.txt").reshape(-1, 3, 4)
    np.testing.assert_allclose(pts, poses[:, :, 3], atol=1e-4)


def test_rerun_not_imported_without_viz_flags(kitti16, tmp_path):
    code = (
        "import sys\n"
        "from typer.testing import CliRunner\n"
        "from lidar_slam.cli import app\n"
        f"r = CliRunner().invoke(app, ['run', r'{kitti16}', '--out', r'{tmp_path / 'o'}',"
        " '--n-scans', '3', '--no-loops'])\n"
        "assert r.exit_code == 0, r.output\n"
        "print('rerun' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "False"


def test_rrd_recording_shows_keyframe_covariances_as_ellipsoids(tmp_path):
    from pathlib import Path

    from rerun.chunk import RrdReader

    from lidar_slam.run.outputs import read_covariances

    sample = Path(__file__).resolve().parents[1] / "sample_scans"
    rrd, run = tmp_path / "out.rrd", tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "lidar_slam.cli", "run", str(sample), "--out",
                           str(run), "--rrd", str(rrd), "--n-scans", "30"],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    store = RrdReader(str(rrd)).stream().collect()
    chunk = [c for c in store.stream() if c.entity_path == "/world/covariances"][0]
    batch = chunk.to_record_batch()
    centers = np.array(batch.column("Ellipsoids3D:centers").to_pylist()[0])
    half_sizes = np.array(batch.column("Ellipsoids3D:half_sizes").to_pylist()[0])
    covs = read_covariances(run / "covariances.csv")
    # each ellipsoid at its keyframe's node (the final map pose: at the sweep's middle here,
    # lidar only with point times, half a sweep from the frame's stamp pose)
    nodes = np.fromfile(run / "keyframes" / "map_poses.bin", dtype="<f8").reshape(-1, 4, 4)
    frames = sorted(covs)
    assert len(centers) == len(frames) == len(nodes)
    np.testing.assert_allclose(centers, nodes[:, :3, 3], atol=1e-4)
    # 3 sigma: the largest half-axis is 3 x the square root of the largest eigenvalue.
    last = np.linalg.eigvalsh(covs[frames[-1]][3:, 3:]).max()
    np.testing.assert_allclose(half_sizes[-1].max(), 3.0 * np.sqrt(last), rtol=1e-4)
