"""`lidar-slam export`: the occupancy grid (map_server format, checked against the simulator's
world) and the map's points as LAS / LAZ / PCD / PLY, on the session's simulated map run."""

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from lidar_slam.io.trajectory import read_kitti_poses


def lidar_slam(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "lidar_slam.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout)


def read_map_server(yaml_path: Path) -> dict:
    """A map_server map as the ROS reader sees it: per cell -1 unknown, 0 free, 100 occupied,
    row 0 at the lowest y."""
    from PIL import Image

    meta = yaml.safe_load(yaml_path.read_text())
    image = np.asarray(Image.open(yaml_path.parent / meta["image"]), dtype=np.float64)
    p = image / 255.0 if meta["negate"] else (255.0 - image) / 255.0
    state = np.where(p > meta["occupied_thresh"], 100,
                     np.where(p < meta["free_thresh"], 0, -1))[::-1]
    return {"state": state, "resolution": meta["resolution"],
            "origin": np.array(meta["origin"][:2], dtype=np.float64), "mode": meta["mode"]}


def cells_at(grid: dict, xy: np.ndarray) -> np.ndarray:
    """States of the cells holding map-frame points (N, 2)."""
    col, row = np.floor((xy - grid["origin"]) / grid["resolution"]).astype(int).T
    return grid["state"][row, col]


def test_occupancy_png_yaml_round_trip(tmp_path):
    from lidar_slam.map.occupancy import OccupancyGrid, OccupancyParams, write_map_server

    state = np.random.default_rng(0).choice(np.array([-1, 0, 100], np.int8), size=(7, 11))
    grid = OccupancyGrid(state, 0.25, np.array([-3.5, 12.0]))
    write_map_server(grid, tmp_path, OccupancyParams())
    back = read_map_server(tmp_path / "map.yaml")
    np.testing.assert_array_equal(back["state"], state)
    assert back["resolution"] == 0.25 and back["mode"] == "trinary"
    np.testing.assert_allclose(back["origin"], [-3.5, 12.0])
    centres = grid.centres(100)
    assert (cells_at(back, centres) == 100).all() and (grid.at(centres) == 100).all()


@pytest.mark.shared_data
def test_occupancy_grid_of_a_simulated_street(sim_map, tmp_path, kitti_gt):
    from lidar_slam.eval.metrics import umeyama_rigid
    from lidar_slam.sim import CLASSES, load_kitti_truth, sequence_world

    proc = lidar_slam("export", sim_map.run, "--occupancy", "--out", tmp_path / "occ")
    assert proc.returncode == 0, proc.stderr
    grid = read_map_server(tmp_path / "occ" / "map.yaml")
    assert {-1, 0, 100} <= set(np.unique(grid["state"]))
    # Every occupied cell near a surface of the world the scans were simulated in (placed with
    # the map run's trajectory aligned to the simulated one).
    kt = load_kitti_truth(kitti_gt, 7)
    world = sequence_world(kt.poses_world_lidar, 0, len(sim_map.truth.poses_world_lidar))
    est = read_kitti_poses(sim_map.run / "poses_kitti.txt")
    T_world_map = umeyama_rigid(est[:, :3, 3], sim_map.truth.poses_world_lidar[:len(est), :3, 3])
    rows, cols = np.nonzero(grid["state"] == 100)
    centres = grid["origin"] + (np.c_[cols, rows] + 0.5) * grid["resolution"]
    pts = np.c_[centres, np.zeros(len(centres))] @ T_world_map[:3, :3].T + T_world_map[:3, 3]
    pts[:, 2] = world.terrain.height(pts[:, :2]) + 1.15  # the middle of the 0.3-2.0 m band
    dist, cls = world.closest(pts)
    near = dist <= 0.5
    facade = cls == CLASSES.index("facade")
    assert near.mean() >= 0.90, (near.mean(), (near & facade).mean())
    # The driven path is free.
    free = cells_at(grid, est[:, :2, 3]) == 0
    assert free.mean() >= 0.95, free.mean()
    # --out rule: map.png / map.yaml are not replaced without --overwrite.
    again = lidar_slam("export", sim_map.run, "--occupancy", "--out", tmp_path / "occ")
    assert again.returncode == 2 and "--overwrite" in again.stderr


def _written(proc) -> int:
    assert proc.returncode == 0, proc.stderr
    found = re.search(r"wrote (\d+) points to", proc.stdout)
    assert found, proc.stdout
    return int(found.group(1))


@pytest.mark.shared_data
def test_export_las_laz_pcd_ply(sim_map, tmp_path):
    import laspy

    from lidar_slam.map.saved import open_map
    from lidar_slam.o3d import o3d

    m = open_map(sim_map.run)
    n_map, n_kf = m.n_points, len(m)
    m.close()
    for fmt in ("las", "laz"):
        n = _written(lidar_slam("export", sim_map.run, "--out", tmp_path / f"map.{fmt}"))
        las = laspy.read(tmp_path / f"map.{fmt}")
        assert n == n_map == las.header.point_count == len(las.points)
        assert las.intensity.max() > 0 and np.count_nonzero(las.intensity) > 0.9 * n
        assert las.keyframe.min() == 0 and las.keyframe.max() == n_kf - 1
    assert (tmp_path / "map.laz").stat().st_size < 0.5 * (tmp_path / "map.las").stat().st_size
    n = _written(lidar_slam("export", sim_map.run, "--out", tmp_path / "map.pcd"))
    cloud = o3d.t.io.read_point_cloud(str(tmp_path / "map.pcd"))
    assert n == n_map == len(cloud.point.positions)
    assert "intensity" in cloud.point and "keyframe" in cloud.point
    # PLY with --voxel, in-process (the CLI is the same call).
    from lidar_slam.map.export import PointFormat, map_points, write_points

    m = open_map(sim_map.run)
    n = write_points(tmp_path / "out.bin", PointFormat.ply, map_points(m, voxel_m=1.0))
    m.close()
    cloud = o3d.t.io.read_point_cloud(str(tmp_path / "out.bin"), format="ply")
    assert 0 < n == len(cloud.point.positions) < n_map / 3
    assert set(np.unique(cloud.point.keyframe.numpy())) <= set(range(n_kf))
    # The package's own reader takes the export's int keyframe column (it used to count float
    # columns only and read every point at the wrong offset).
    from lidar_slam.io.ply import read_ply

    pts, inten = read_ply(tmp_path / "out.bin")
    np.testing.assert_array_equal(pts, cloud.point.positions.numpy().astype(np.float64))
    np.testing.assert_array_equal(inten, cloud.point.intensity.numpy().ravel())
    # --out rule: an existing file is not replaced without --overwrite.
    proc = lidar_slam("export", sim_map.run, "--out", tmp_path / "map.pcd")
    assert proc.returncode == 2 and "--overwrite" in proc.stderr
    # ... and never one of the run's own files, the map it reads least of all, even with it
    for own in ("keyframes/points.bin", "poses_kitti.txt"):
        before = (sim_map.run / own).read_bytes()
        proc = lidar_slam("export", sim_map.run, "--out", sim_map.run / own, "--format", "ply",
                          "--overwrite")
        assert proc.returncode == 2 and "the run's own" in proc.stderr, proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1
        assert (sim_map.run / own).read_bytes() == before


@pytest.mark.shared_data
def test_export_las_without_laspy_says_what_to_install(sim_map, tmp_path):
    code = ("import sys; sys.modules['laspy'] = None; from lidar_slam.cli import app; "
            f"sys.argv = ['lidar-slam', 'export', {str(sim_map.run)!r}, '--out', "
            f"{str(tmp_path / 'm.laz')!r}]; app()")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "pip install 'laspy[lazrs]'" in lines[0], proc.stderr
    assert not (tmp_path / "m.laz").exists()
