"""The bank's worlds and motions (issue 29): an office of identical rooms that aliases, a
pillared warehouse, a legged robot's trot and a drone's flight, each kept 0.5 m from every
surface and within its stated limits."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lidar_slam.sim import SENSORS
from lidar_slam.sim import drone as drone_mod
from lidar_slam.sim import legged as legged_mod
from lidar_slam.sim.floors import OfficeLayout
from lidar_slam.sim.handheld import CLEARANCE_M, build_site, clearance_m, handheld_motion
from lidar_slam.sim.imu_gnss import GRAVITY_MPS2, ImuOptions
from lidar_slam.sim.motions import CORNER_M, MOTION_WORLDS, simulate_motion

SMALL_OS1 = dataclasses.replace(SENSORS["os1-64"], n_azimuth=256)


def ring_ranges(world, xyz: np.ndarray, yaw: float = 0.0, n: int = 360) -> np.ndarray:
    """Ranges (m) of n horizontal rays from xyz, the first at heading yaw."""
    a = yaw + 2 * np.pi * np.arange(n) / n
    dirs = np.c_[np.cos(a), np.sin(a), np.zeros(n)]
    return world.cast(np.tile(xyz, (n, 1)), dirs)["t_hit"]


def test_office_aliases_a_room_further_on_and_a_half_turn_across():
    site = build_site("office", 0, SMALL_OS1)
    lay = OfficeLayout.draw(np.random.default_rng([0, 30]))
    w = site.world
    assert w.n_objects["door"] >= 20 and w.n_objects["furniture"] >= 20
    # On the first corridor, one room further on: the same ranges all round.
    p = np.array([lay.corridor_m / 2 + 1.3 * lay.room_m, 0.0, 1.2])
    q = p + [lay.room_m, 0.0, 0.0]
    a, b = ring_ranges(w, p), ring_ranges(w, q)
    near = (a < 6.0) & (b < 6.0)
    assert near.mean() > 0.5 and np.median(np.abs(a - b)[near]) < 0.02
    # The middle of a block is symmetric: the corridor above, turned 180 deg, looks the same
    # for the rays that stay within the block's walls and doors.
    mid = np.array([lay.length_m / 2, lay.pitch_m / 2, 1.2])
    c, d = ring_ranges(w, mid - [0, lay.pitch_m / 2, 0]), ring_ranges(
        w, mid + [0, lay.pitch_m / 2, 0], np.pi)
    short = (c < 2.0) & (d < 2.0)  # the walls either side of the corridor
    assert short.mean() > 0.3 and np.median(np.abs(c - d)[short]) < 0.05


def test_warehouse_has_a_pillar_grid_racks_and_a_low_ceiling():
    site = build_site("warehouse", 0, SMALL_OS1)
    assert site.world.n_objects["pillar"] >= 8 and site.world.n_objects["furniture"] >= 15
    assert 6.5 < site.ceiling_m < 8.0
    up = site.world.cast(np.array([[*site.path.xy(0.0), 1.0]]), np.array([[0.0, 0.0, 1.0]]))
    assert abs(up["t_hit"][0] - (site.ceiling_m - 1.0)) < 0.05  # the ceiling over the aisle


@pytest.mark.parametrize("motion", ["handheld", "legged", "drone"])
def test_every_motion_keeps_half_a_metre_from_every_surface_in_its_worlds(motion):
    make = {"handheld": lambda s, seed: handheld_motion(s.path, s.ground, seed, 45.0),
            "legged": lambda s, seed: legged_mod.legged_motion(s.path, s.ground, seed, 45.0),
            "drone": lambda s, seed: drone_mod.drone_motion(s.path, s.ground, seed, 45.0,
                                                            s.ceiling_m)}[motion]
    for kind in MOTION_WORLDS[motion]:
        for seed in (0, 1):
            site = build_site(kind, seed, SMALL_OS1, CORNER_M.get(motion))
            m = make(site, seed)
            assert clearance_m(site.world, m.trajectory, 0.0, 45.0).min() >= CLEARANCE_M, kind
            if motion == "drone" or kind in ("office", "warehouse"):  # ring, plaza: ~60 m
                assert m.stats.laps > 0.95, (kind, seed, m.stats)  # it comes back: loops


def test_legged_trot_bounces_2_to_3_hz_stops_turns_on_the_spot_within_limits():
    site = build_site("office", 3, SMALL_OS1)
    m = legged_mod.legged_motion(site.path, site.ground, 3, 40.0)
    st = m.stats
    assert st.max_rate_dps <= legged_mod.MAX_RATE_DPS
    assert st.max_accel_mps2 <= legged_mod.MAX_ACCEL_MPS2
    assert 1.0 < st.max_speed_mps < 1.7 and st.n_bursts >= 5  # starts from standing
    t = np.arange(0.0, 40.0, 0.01)
    T = m.trajectory(t)
    v = np.linalg.norm(m.trajectory.position(t, 1), axis=1)
    w = np.degrees(np.linalg.norm(m.trajectory.attitude(t, 1), axis=1))
    assert v[t < m.trot.stand_s - 0.3].max() < 1e-3  # at rest first
    assert np.any((v < 0.05) & (w > 40.0))  # a turn on the spot
    z = T[:, 2, 3]
    assert 0.5 < z.min() and z.max() < 0.6
    walking = (v > 0.9 * m.trot.speed_mps)
    spectrum = np.abs(np.fft.rfft(np.where(walking, z - z[walking].mean(), 0.0)))
    f = np.fft.rfftfreq(len(z), 0.01)
    assert 2.0 <= f[np.argmax(spectrum[1:]) + 1] <= 3.1
    roll = np.degrees(np.arctan2(T[:, 2, 1], T[:, 2, 2]))
    assert 1.0 < np.abs(roll[walking]).max() < 4.0  # a few degrees of roll


def test_drone_flies_1_5_to_6_m_tilted_along_its_thrust_within_limits():
    for kind in ("outdoor", "warehouse"):
        site = build_site(kind, 2, SMALL_OS1, CORNER_M["drone"])
        m = drone_mod.drone_motion(site.path, site.ground, 2, 40.0, site.ceiling_m)
        st = m.stats
        assert st.max_rate_dps <= drone_mod.MAX_RATE_DPS
        assert st.max_accel_mps2 <= drone_mod.MAX_ACCEL_MPS2
        assert st.laps > 1.0 and st.n_bursts >= 2  # yaw spins
        t = np.arange(0.0, 40.0, 0.01)
        T = m.trajectory(t)
        height = T[:, 2, 3] - site.ground(T[:, :2, 3])
        top = drone_mod.MAX_HEIGHT_M if site.ceiling_m is None else site.ceiling_m - 1.0
        assert drone_mod.MIN_HEIGHT_M - 1e-6 <= height.min() and height.max() <= top + 1e-6
        assert height.max() - height.min() > 1.0  # climbs and descents
        v = m.trajectory.position(t, 1)
        assert np.linalg.norm(v[t < 1.0], axis=1).max() < 1e-3  # hovering first
        thrust = m.trajectory.position(t, 2) + [0, 0, GRAVITY_MPS2] + drone_mod.DRAG_PER_S * v
        cos = np.sum(T[:, :3, 2] * thrust, axis=1) / np.linalg.norm(thrust, axis=1)
        assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 1.0
        tilt = np.degrees(np.arccos(np.clip(T[:, 2, 2], -1.0, 1.0)))
        assert 5.0 < tilt.max() < 40.0  # it banks and pitches


def test_simulate_motion_writes_a_sequence_and_refuses_a_drone_in_corridors(tmp_path):
    s, st = simulate_motion(tmp_path / "l", "legged", "office", 4, 0.5, SMALL_OS1,
                            imu=ImuOptions())
    assert s.n_scans == 5 and (tmp_path / "l" / "imu.csv").is_file()
    assert "legged robot's trot (office, seed 4)" in (tmp_path / "l" / "README.txt").read_text()
    with pytest.raises(ValueError, match="drone goes through outdoor, warehouse"):
        simulate_motion(tmp_path / "d", "drone", "office", 0, 0.5, SMALL_OS1)
