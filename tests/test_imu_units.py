"""The units of an imu.csv told from its data (lidar_slam.io.imu_units): stamps in ms, us or ns
and accelerations in g converted with one warning naming the file, the rest refused."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from lidar_slam.errors import InputError
from lidar_slam.io.imu_gnss import read_imu_csv

HEADER = "stamp_s,wx,wy,wz,ax,ay,az\n"


def walk_rows(n: int = 400, rate_hz: float = 200.0, t0: float = 12.0) -> np.ndarray:
    """A sensor swaying by hand: gravity on z plus up to ~3 m/s^2 of motion, turning."""
    t = t0 + np.arange(n) / rate_hz
    wave = np.sin(2 * np.pi * 1.5 * (t - t0))
    return np.c_[t, 0.2 * wave, 0.1 * wave, 0.5 + 0.3 * wave, 3.0 * wave, 1.0 * wave,
                 9.81 + 0.5 * wave]


def write(path, rows: np.ndarray, stamp_fmt: str = "%.9f"):
    np.savetxt(path, rows, delimiter=",", header=HEADER.strip(), comments="",
               fmt=[stamp_fmt] + ["%.10g"] * 6)
    return path


@pytest.mark.parametrize("unit,scale", [("ms", 1e3), ("us", 1e6), ("ns", 1e9)])
def test_stamps_in_ms_us_or_ns_are_converted_with_one_warning(tmp_path, caplog, unit, scale):
    rows = walk_rows()
    bad = rows.copy()
    bad[:, 0] = np.round(rows[:, 0] * scale)
    path = write(tmp_path / "imu.csv", bad, "%d")
    with caplog.at_level(logging.WARNING):
        imu = read_imu_csv(path)
    np.testing.assert_allclose(imu.stamp_s, rows[:, 0], atol=1e-6)
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1 and said[0].startswith(f"{path}: stamps read as {unit} "), said
    assert "converted to s" in said[0]


def test_stamps_in_seconds_and_accelerations_in_mps2_pass_unchanged_and_unsaid(tmp_path, caplog):
    rows = walk_rows()
    with caplog.at_level(logging.WARNING):
        imu = read_imu_csv(write(tmp_path / "imu.csv", rows))
    np.testing.assert_allclose(imu.stamp_s, rows[:, 0], atol=1e-9)
    np.testing.assert_allclose(imu.accel_mps2, rows[:, 4:7], rtol=1e-9)
    assert not caplog.records


def test_stamps_that_fit_no_imu_rate_in_any_unit_are_refused_naming_the_file(tmp_path):
    rows = walk_rows(n=50)
    rows[:, 0] = np.arange(50) * 0.15  # 6.7 Hz in s, 6.7 kHz in ms: no unit fits
    path = write(tmp_path / "imu.csv", rows)
    with pytest.raises(InputError) as err:
        read_imu_csv(path)
    assert str(err.value).startswith(f"{path}: median stamp spacing 0.15 is not that of an IMU")


def test_accelerations_in_g_are_converted_with_one_warning(tmp_path, caplog):
    rows = walk_rows()
    bad = rows.copy()
    bad[:, 4:7] /= 9.80665
    path = write(tmp_path / "imu.csv", bad)
    with caplog.at_level(logging.WARNING):
        imu = read_imu_csv(path)
    np.testing.assert_allclose(imu.accel_mps2, rows[:, 4:7], rtol=1e-8)
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1 and said[0].startswith(f"{path}: accelerations read as g"), said


def test_accelerations_with_gravity_removed_are_refused_not_taken_for_g(tmp_path):
    """A moving sensor with gravity removed has a median norm of ~1 m/s^2 too, but ~0 at every
    pause: not g."""
    rows = walk_rows()
    rows[:, 4:7] = np.c_[1.5 * np.sin(np.linspace(0, 12 * np.pi, len(rows))), np.zeros(
        (len(rows), 2))]
    with pytest.raises(InputError, match="expected about 9.81 with gravity included"):
        read_imu_csv(write(tmp_path / "imu.csv", rows))


@pytest.mark.parametrize("rate_hz,unit,scale,t0", [
    (1.0, "ns", 1e9, 1.7e9), (10.0, "ns", 1e9, 1.7e9), (50.0, "ns", 1e9, 1.7e9),
    (1.0, "ms", 1e3, 1.7e9), (1.0, "ns", 1e9, 0.0), (1.0, "s", 1.0, 1.7e9),
    (1 / 60, "s", 1.0, 1.7e9), (50.0, "s", 1.0, 1.7e9), (1.0, "s", 1.0, 0.0)])
def test_gnss_stamps_in_ns_or_ms_are_converted_and_sparse_or_fast_fixes_left_in_s(
        tmp_path, caplog, rate_hz, unit, scale, t0):
    """gnss.csv in ns was taken as s (1e9 s apart: no overlap with the scans). A fix a minute
    in s, a 50 Hz receiver in s or in ns, stamps from 0: each read in its own unit."""
    from lidar_slam.io.imu_gnss import read_gnss_csv

    t = t0 + np.arange(20) / rate_hz
    rows = np.c_[np.round(t * scale) if scale != 1.0 else t, np.full(20, 49.0),
                 np.full(20, 8.4), np.full(20, 110.0), np.ones(20), np.full(20, 2.0)]
    path = tmp_path / "gnss.csv"
    np.savetxt(path, rows, delimiter=",", comments="",
               header="stamp_s,lat_deg,lon_deg,alt_m,sigma_h_m,sigma_v_m",
               fmt=["%d" if scale != 1.0 else "%.6f"] + ["%.10g"] * 5)
    with caplog.at_level(logging.WARNING):
        fixes = read_gnss_csv(path)
    np.testing.assert_allclose(fixes.stamp_s, t, atol=1e-3)
    said = [r.getMessage() for r in caplog.records]
    if unit == "s":
        assert not said and fixes.read_as == {}
    else:
        assert len(said) == 1 and said[0].startswith(f"{path}: stamps read as {unit} ")
        assert fixes.read_as == {"stamps": unit}
