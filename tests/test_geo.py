"""Geo-referenced outputs (issue 22 item 4): with a geo reference (RunResult.geo, the map frame
tied to the Earth) a run writes poses_enu.txt, poses_wgs84.csv and summary.json's `geo`, and its
LAS / LAZ export is in UTM with the CRS; without one nothing changes. Checked on a simulated
KITTI 07 slice with GNSS, whose world frame is ENU at the GNSS datum, so the true geo reference
is known exactly: T_enu_map = T_world_seq (the map frame is the lidar frame of the first scan,
at its stamp, which is the sequence frame)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import shared_path

from lidar_slam.geo import GeoReference, LocalEnu, utm_epsg, utm_to_wgs84, wgs84_to_utm
from lidar_slam.io.trajectory import read_kitti_poses

GEO_START, GEO_SCANS = 400, 30  # 07 turned 130 deg left, 170 m from its start
GEO_FILES = {"poses_enu.txt", "poses_wgs84.csv"}


def lidar_slam(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "lidar_slam.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout)


@dataclass(frozen=True)
class GeoRun:
    """The same run written twice: `plain` without a geo reference, `geo` with the true one."""

    plain: Path
    geo: Path
    truth: object  # lidar_slam.sim.SimSummary
    reference: GeoReference


@pytest.fixture(scope="module")
def geo_run(tmp_path_factory) -> GeoRun:
    """Simulate 07 scans 400..429 with GNSS, map them, write the outputs without and with
    geo."""
    from lidar_slam.config import load_config
    from lidar_slam.io.sources import open_source
    from lidar_slam.pipeline import run
    from lidar_slam.run.outputs import write_run
    from lidar_slam.sim import load_kitti_truth, simulate_sequence
    from lidar_slam.sim.imu_gnss import GnssOptions

    kt = load_kitti_truth(shared_path("kitti_gt"), 7)
    root = tmp_path_factory.mktemp("geo")
    gnss = GnssOptions()
    truth = simulate_sequence(kt.poses_world_lidar, kt.stamps_s, root / "seq", start=GEO_START,
                              n_scans=GEO_SCANS, Tr_cam_lidar=kt.Tr_cam_lidar, gnss=gnss)
    assert np.allclose(np.loadtxt(root / "seq" / "T_world_seq.txt").reshape(3, 4),
                       truth.T_world_seq[:3], rtol=1e-8, atol=1e-8)
    cfg = load_config(None, {"odometry": {"max_num_threads": 1}})
    source = open_source(root / "seq")
    result = run(source.scans(0, GEO_SCANS), cfg, root / "run")
    try:
        write_run(root / "run", result, cfg, source.ground_truth, 1.0)
        shutil.copytree(root / "run", root / "plain")
        reference = GeoReference(LocalEnu(*gnss.datum), truth.T_world_seq)
        result.geo = reference
        write_run(root / "run", result, cfg, source.ground_truth, 1.0)
    finally:
        result.store.close()
    return GeoRun(root / "plain", root / "run", truth, reference)


def test_utm_zone_and_round_trip_through_pyproj():
    assert utm_epsg(49.011, 8.424) == 32632  # Karlsruhe: WGS 84 / UTM zone 32N
    assert utm_epsg(-33.86, 151.21) == 32756  # Sydney: zone 56S
    assert utm_epsg(10.0, 12.0) == 32633  # on a border: the zone east of it
    llh = np.array([[49.011, 8.424, 112.0], [49.02, 8.41, 300.0]])
    enh = wgs84_to_utm(llh, 32632)
    assert np.all((enh[:, 0] > 166e3) & (enh[:, 0] < 834e3)) and np.allclose(enh[:, 2], llh[:, 2])
    assert np.allclose(utm_to_wgs84(enh, 32632), llh, atol=1e-10)


def test_heading_is_the_map_x_axis_clockwise_from_north():
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", 30.0, degrees=True).as_matrix()  # x 30 deg left of east
    geo = GeoReference(LocalEnu(np.float64(49.011), 8.424, 112.0), T)
    assert geo.heading_deg == pytest.approx(60.0, abs=1e-6)
    assert np.allclose(geo.origin_wgs84, (49.011, 8.424, 112.0), atol=1e-9)
    T[:3, 3] = [2000.0, 0.0, 0.0]  # 2 km east: true north turns (meridian convergence)
    assert GeoReference(geo.enu, T).heading_deg == pytest.approx(60.0 + 0.0204, abs=2e-3)
    again = GeoReference.from_dict(json.loads(json.dumps(geo.to_dict())))
    assert again.enu == geo.enu and np.array_equal(again.T_enu_map, geo.T_enu_map)


def test_a_geo_run_writes_enu_and_wgs84_poses_within_half_a_metre_of_the_truth(geo_run):
    summary = json.loads((geo_run.geo / "summary.json").read_text())["geo"]
    lat, lon, alt = geo_run.reference.origin_wgs84
    assert summary["utm_epsg"] == 32632
    assert (summary["origin_lat_deg"], summary["origin_lon_deg"]) == (lat, lon)
    assert summary["origin_alt_m"] == alt
    assert np.array_equal(summary["T_enu_map"], geo_run.truth.T_world_seq)
    assert summary["enu_datum"] == {"lat_deg": 49.011, "lon_deg": 8.424, "alt_m": 112.0}
    x_axis = geo_run.truth.T_world_seq[:3, 0]
    assert summary["heading_deg"] == pytest.approx(
        np.degrees(np.arctan2(x_axis[0], x_axis[1])) % 360, abs=0.01)

    true_xyz = geo_run.truth.poses_world_lidar[:, :3, 3]  # the sim world = ENU at the datum
    enu = read_kitti_poses(geo_run.geo / "poses_enu.txt")
    assert enu.shape == (GEO_SCANS, 4, 4)
    err_enu = np.linalg.norm(enu[:, :3, 3] - true_xyz, axis=1)
    assert err_enu.max() < 0.5, err_enu
    rows = np.loadtxt(geo_run.geo / "poses_wgs84.csv", delimiter=",", skiprows=1, ndmin=2)
    header = (geo_run.geo / "poses_wgs84.csv").read_text().splitlines()[0]
    assert header == "frame,stamp_s,lat_deg,lon_deg,alt_m"
    assert np.array_equal(rows[:, 0], np.arange(GEO_SCANS))
    assert np.allclose(rows[:, 1], geo_run.truth.stamps_s, atol=1e-6)
    err_wgs = np.linalg.norm(LocalEnu(49.011, 8.424, 112.0).from_wgs84(rows[:, 2:5]) - true_xyz,
                             axis=1)
    assert err_wgs.max() < 0.5, err_wgs
    assert np.allclose(err_wgs, err_enu, atol=1e-3)  # the same poses, 4 decimals of height


def test_las_export_of_a_geo_run_is_utm_with_its_epsg_on_the_simulated_world(geo_run, tmp_path):
    import laspy
    from pyproj import CRS, Transformer

    from lidar_slam.sim import sequence_world

    proc = lidar_slam("export", geo_run.geo, "--out", tmp_path / "map.laz")
    assert proc.returncode == 0, proc.stderr
    las = laspy.read(tmp_path / "map.laz")
    crs = las.header.parse_crs()
    assert crs is not None and crs.to_epsg() == 32632
    assert np.all(las.header.scales == 0.001)
    xyz = np.c_[las.x, las.y, las.z]
    assert np.all(np.abs(xyz - las.header.offsets).max(axis=0) < 2e4)  # offsets at the data
    # Back to the simulated world by pyproj alone (the EPSG read back, then ENU at the datum).
    lon, lat, h = Transformer.from_crs(crs, CRS.from_epsg(4979), always_xy=True).transform(
        xyz[:, 0], xyz[:, 1], xyz[:, 2])
    world_xyz = LocalEnu(49.011, 8.424, 112.0).from_wgs84(np.c_[lat, lon, h])
    kt_poses = _kitti07_lidar_poses()
    world = sequence_world(kt_poses, GEO_START, GEO_START + GEO_SCANS)
    dist, _ = world.closest(world_xyz)
    print(f"LAS points {len(dist)}: distance to the world's surfaces median "
          f"{np.median(dist):.3f} m, 99% {np.quantile(dist, 0.99):.3f} m, max {dist.max():.3f} m")
    assert dist.max() < 0.5
    assert np.median(dist) < 0.1  # range noise, the elevation error of the sim's HDL-64, drift


def _kitti07_lidar_poses() -> np.ndarray:
    from lidar_slam.sim import load_kitti_truth

    return load_kitti_truth(shared_path("kitti_gt"), 7).poses_world_lidar


def test_occupancy_export_of_a_geo_run_writes_the_origin(geo_run, tmp_path):
    for run, out in ((geo_run.geo, tmp_path / "geo"), (geo_run.plain, tmp_path / "plain")):
        proc = lidar_slam("export", run, "--occupancy", "--out", out, "--resolution", "0.5")
        assert proc.returncode == 0, proc.stderr
    meta = yaml.safe_load((tmp_path / "geo" / "map.yaml").read_text())
    lat, lon, alt = geo_run.reference.origin_wgs84
    assert meta["geo"]["origin_lat_deg"] == pytest.approx(lat, abs=1e-9)
    assert meta["geo"]["origin_lon_deg"] == pytest.approx(lon, abs=1e-9)
    assert meta["geo"]["origin_alt_m"] == pytest.approx(alt, abs=1e-4)
    assert meta["geo"]["utm_epsg"] == 32632
    corner = geo_run.reference.map_to_utm(np.r_[meta["origin"][:2], 0.0])[0]
    assert np.allclose(meta["geo"]["image_origin_utm"], corner, atol=1e-3)
    plain = (tmp_path / "plain" / "map.yaml").read_text()
    assert "geo" not in yaml.safe_load(plain)
    assert (tmp_path / "geo" / "map.yaml").read_text().startswith(plain)  # map_server's keys
    assert (tmp_path / "geo" / "map.png").read_bytes() == (tmp_path / "plain" / "map.png"
                                                           ).read_bytes()


def test_without_geo_nothing_is_written_and_the_map_stays_local(geo_run, tmp_path):
    from lidar_slam.map.export import map_points
    from lidar_slam.map.saved import open_map

    plain = {p.name for p in geo_run.plain.iterdir()}
    assert not plain & GEO_FILES
    assert {p.name for p in geo_run.geo.iterdir()} == plain | GEO_FILES
    for name in plain - {"summary.json", "keyframes", "checkpoint"}:
        assert (geo_run.geo / name).read_bytes() == (geo_run.plain / name).read_bytes(), name
    summary = json.loads((geo_run.plain / "summary.json").read_text())
    with_geo = json.loads((geo_run.geo / "summary.json").read_text())
    assert "geo" not in summary and with_geo.pop("geo")
    for d in (summary, with_geo):
        d.pop("peak_rss_mb")
    assert with_geo == summary
    saved = open_map(geo_run.plain)
    try:
        assert saved.geo is None
        local = map_points(saved)
    finally:
        saved.close()
    import laspy

    proc = lidar_slam("export", geo_run.plain, "--out", tmp_path / "map.las")
    assert proc.returncode == 0, proc.stderr
    las = laspy.read(tmp_path / "map.las")
    assert las.header.parse_crs() is None
    assert np.abs(np.c_[las.x, las.y, las.z] - local.points).max() < 1e-3


def test_a_damaged_geo_section_is_one_line(geo_run, tmp_path):
    from conftest import assert_one_line_error

    run = tmp_path / "run"
    shutil.copytree(geo_run.geo, run)
    summary = json.loads((run / "summary.json").read_text())
    summary["geo"]["T_enu_map"] = [[1, 0], [0, 1]]
    (run / "summary.json").write_text(json.dumps(summary))
    proc = lidar_slam("export", run, "--out", tmp_path / "map.las")
    assert_one_line_error(proc, "summary.json", "T_enu_map")


def test_overwrite_removes_the_geo_outputs_of_an_earlier_run(tmp_path):
    from lidar_slam.run.outdir import RUN_OUTPUTS, prepare_out_dir

    for name in (*GEO_FILES, "poses_kitti.txt", "notes.txt"):
        (tmp_path / name).write_text("x\n")
    prepare_out_dir(tmp_path, RUN_OUTPUTS, overwrite=True)
    assert [p.name for p in tmp_path.iterdir()] == ["notes.txt"]
