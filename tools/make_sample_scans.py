"""Generate sample_scans/: a small simulated VLP-16-like sequence that drives one closed circuit.

The circuit is a rounded rectangle (superellipse) of ~100 m; the car starts on a straight, drives
once around and goes on ~15 m past its start, so the last scans revisit the first ones in the same
direction. The input heights follow a gentle hill plus a 0.4 m drift over the drive (as a real
ground truth's vertical drift), so the two passes over the start disagree in height; the simulator
fits one ground surface and writes the poses it really simulated. Deterministic.

    python tools/make_sample_scans.py [OUT_DIR]      (default: <repo>/sample_scans)
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import shutil
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from lidar_slam.sim import SENSORS, WorldParams, simulate_sequence

REPO = Path(__file__).resolve().parents[1]

SEED = 7
RATE_HZ = 5.0  # VLP-16 spins at 5..20 Hz; 5 Hz keeps the frame count small at city speed
SENSOR = dataclasses.replace(SENSORS["vlp16"], name="vlp16-lite", n_azimuth=256, rate_hz=RATE_HZ)
SEMI_AXES_M = (18.0, 11.5)
EXPONENT = 2.5
OVERLAP_M = 12.0
MAX_SPEED_MPS = 11.0
MAX_LATERAL_ACC_MPS2 = 5.0
START_SPEED_MPS = 0.5
START_ACC_MPS2 = 2.5


def loop_trajectory() -> tuple[np.ndarray, np.ndarray]:
    """(stamps_s (K,), T_world_lidar (K, 4, 4)) along the circuit, one pose per sweep start."""
    a, b = SEMI_AXES_M
    th = np.linspace(-np.pi / 2, 3 * np.pi / 2, 40001)  # start mid bottom straight, counter-clockwise
    c, s = np.cos(th), np.sin(th)
    x = a * np.sign(c) * np.abs(c) ** (2 / EXPONENT)
    y = b * np.sign(s) * np.abs(s) ** (2 / EXPONENT)
    seg = np.hypot(np.diff(x), np.diff(y))
    arc = np.r_[0.0, np.cumsum(seg)]
    perimeter = arc[-1]
    heading = np.unwrap(np.arctan2(np.gradient(y), np.gradient(x)))
    curvature = np.abs(np.gradient(heading) / np.maximum(np.gradient(arc), 1e-9))
    speed = np.minimum(MAX_SPEED_MPS, np.sqrt(MAX_LATERAL_ACC_MPS2 / np.maximum(curvature, 1e-6)))
    speed = gaussian_filter1d(speed, 600, mode="wrap")  # smooth braking and accelerating
    # Go once around and on past the start by OVERLAP_M.
    extra = arc <= OVERLAP_M
    arc = np.r_[arc, perimeter + arc[extra][1:]]
    x, y = np.r_[x, x[extra][1:]], np.r_[y, y[extra][1:]]
    heading = np.r_[heading, heading[extra][1:] + 2 * np.pi]
    speed = np.r_[speed, speed[extra][1:]]
    # Start from (nearly) rest, as a real drive does, accelerating at START_ACC_MPS2.
    speed = np.minimum(speed, np.sqrt(START_SPEED_MPS**2 + 2 * START_ACC_MPS2 * arc))
    t = np.r_[0.0, np.cumsum(np.diff(arc) / (0.5 * (speed[1:] + speed[:-1])))]
    stamps = np.arange(0.0, t[-1], 1.0 / RATE_HZ)
    xs, ys = np.interp(stamps, t, x), np.interp(stamps, t, y)
    yaw = np.interp(stamps, t, heading)
    s_at = np.interp(stamps, t, arc)
    z = 0.6 * np.sin(xs / 9.0) + 0.4 * np.cos(ys / 7.0) + 0.4 * s_at / arc[-1]
    poses = np.tile(np.eye(4), (len(stamps), 1, 1))
    poses[:, :3, :3] = Rotation.from_euler("z", yaw[:, None]).as_matrix()
    poses[:, :3, 3] = np.c_[xs, ys, z + SENSOR.mount_height_m]
    return stamps, poses


README = """# sample_scans: a small simulated loop

Made by `python tools/make_sample_scans.py` (deterministic: seed {seed}); see
`lidar_slam/sim/` for the simulator. Not real data.

- Sensor: VLP-16-like, 16 beams at -15..+15 deg, {n_az} azimuth steps per sweep ({res:.1f} deg,
  reduced from the real 0.1-0.4 deg to keep the folder small), {rate:g} Hz sweeps, max range
  {rng:g} m, range noise {noise:g} cm, random and grazing-angle dropouts.
- Trajectory: a closed circuit of {perimeter:.0f} m (superellipse {a:g} x {b:g} m semi-axes),
  driven counter-clockwise from rest (accelerating at {acc:g} m/s^2) at up to {vmax:g} m/s, slowing
  in the bends; the car goes once round and
  {overlap:g} m on, so scans {revisit} revisit the start region (scans 0..) in the same direction.
  {n} scans, {length:.0f} m in {dur:.1f} s.
- World: a procedural street lining the circuit on both sides (facades with irregular outlines
  and gaps, parked cars, poles, trees, bushes, clutter) on one smooth ground surface with curbs.

Layout (KITTI odometry style, readable by stock kiss-icp and by `lidar_slam`):

| file | content |
|---|---|
| `velodyne/NNNNNN.bin` | float32 x, y, z, intensity per point, raw (motion-distorted) sensor frame |
| `velodyne_times/NNNNNN.bin` | float32 time of each point in seconds after the scan stamp, same order |
| `times.txt` | scan stamps (s) = START of each sweep; a scan's pose refers to that instant |
| `calib.txt` | `Tr:` identity (the lidar is the "camera"), plus placeholder P0..P3 |
| `poses.txt` | true poses, KITTI 3x4 rows: P_i = Tr @ T_seq_lidar_i @ inv(Tr) = T_seq_lidar_i, in the frame of scan 0 |

The poses are the ones simulated: the input path's x, y and heading, with z and roll/pitch taken
from the fitted ground (the input heights drift by 0.4 m over the drive, the ground does not).
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out_dir", nargs="?", default=str(REPO / "sample_scans"))
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    out = Path(args.out_dir)
    for sub in ("velodyne", "velodyne_times"):
        shutil.rmtree(out / sub, ignore_errors=True)
    stamps, poses = loop_trajectory()
    # A closed circuit needs no straight road run-outs past its ends.
    summary = simulate_sequence(poses, stamps, out, sensor=SENSOR, seed=SEED,
                                params=WorldParams(extend_m=0.0))
    p = summary.poses_world_lidar[:, :3, 3]
    d = np.linalg.norm(p[:, None, :2] - p[None, :, :2], axis=2)
    idx = np.arange(len(p))
    revisit = [int(j) for j in idx if np.any((d[j] < 5.0) & (idx < j - 20))]
    a, b = SEMI_AXES_M
    th = np.linspace(0, 2 * np.pi, 40001)
    perim = np.sum(np.hypot(np.diff(a * np.sign(np.cos(th)) * np.abs(np.cos(th)) ** (2 / EXPONENT)),
                            np.diff(b * np.sign(np.sin(th)) * np.abs(np.sin(th)) ** (2 / EXPONENT))))
    length = float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))
    (out / "README.md").write_text(README.format(
        seed=SEED, n_az=SENSOR.n_azimuth, res=360 / SENSOR.n_azimuth, rate=SENSOR.rate_hz,
        rng=SENSOR.max_range_m, noise=SENSOR.range_noise_m * 100, perimeter=perim, a=a, b=b,
        vmax=MAX_SPEED_MPS, acc=START_ACC_MPS2, overlap=OVERLAP_M, n=summary.n_scans, length=length,
        dur=summary.stamps_s[-1] - summary.stamps_s[0],
        revisit=f"{revisit[0]}..{revisit[-1]}" if revisit else "(none)"))
    (out / "README.txt").unlink(missing_ok=True)
    size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    print(f"{summary.n_scans} scans, {summary.points_per_scan:.0f} points/scan, "
          f"{size / 1e6:.2f} MB, {summary.seconds_per_scan:.3f} s/scan, revisits {revisit}")


if __name__ == "__main__":
    main()
