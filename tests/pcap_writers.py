"""Sensor pcaps written at test time from simulated sweeps, for tests/test_pcap.py (test code
only: the readers under test are lidar_slam/io/ouster_pcap.py and velodyne_pcap.py).

- Ouster: ouster-sdk writes the pcap itself. A metadata JSON for a simulated OS1-64 whose beams
  are the simulator's os1-64 (no beam azimuth offsets, no beam origin offset, the lidar frame
  turned 180 deg about z into the sensor frame as on a real OS1), so XYZLut points are the
  simulated ones to the millimetre ranges; each simulated sweep becomes a LidarFrame (RANGE in
  mm, per-column timestamps), `frame_to_packets` makes the lidar packets and `pcap.record`
  writes them with the IMU packets, in time order.
- Velodyne: velodyne-decoder only decodes, so `vlp16_packets` encodes VLP-16 data packets after
  the VLP-16 user manual's layout, and dpkt writes them as UDP in a pcap.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

G0 = 9.80665  # the legacy IMU packet's accelerations are in g

# ----------------------------------------------------------------------------------------------
# Ouster (ouster-sdk)

OS1_ELEVATIONS_DEG = np.linspace(16.6, -16.6, 64).round(4)  # lidar_slam.sim's "os1-64"
OS1_COLUMNS = 1024
SWEEP_NS = 100_000_000  # 10 Hz


def os1_metadata(imu_to_sensor_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> dict:
    """Ouster sensor metadata (the legacy layout of firmware 2.x) of a simulated OS1-64 whose
    XYZLut directions are the simulator's os1-64 beams: column j at azimuth pi - 2 pi j / 1024
    in the sensor frame."""
    T_imu = np.eye(4)
    T_imu[:3, 3] = imu_to_sensor_mm
    return {
        "prod_line": "OS-1-64", "prod_sn": "992200000001", "build_rev": "v2.3.0",
        "initialization_id": 1, "json_calibration_version": 4, "status": "RUNNING",
        "lidar_mode": "1024x10", "udp_port_lidar": 7502, "udp_port_imu": 7503,
        "beam_altitude_angles": OS1_ELEVATIONS_DEG.tolist(),
        "beam_azimuth_angles": [0.0] * 64,
        "lidar_origin_to_beam_origin_mm": 0.0,
        "lidar_to_sensor_transform": [-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1],
        "imu_to_sensor_transform": T_imu.ravel().tolist(),
        "data_format": {"pixels_per_column": 64, "columns_per_packet": 16,
                        "columns_per_frame": OS1_COLUMNS, "column_window": [0, OS1_COLUMNS - 1],
                        "pixel_shift_by_row": [0] * 64, "udp_profile_lidar": "LEGACY",
                        "udp_profile_imu": "LEGACY"},
    }


def os1_pixels(points: np.ndarray, times_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(row, column) of each simulated os1-64 point: the column from its firing time, the row
    from its elevation (the simulator fires every beam of a column at once, on nominal
    directions)."""
    col = np.rint(times_s * OS1_COLUMNS * 10.0).astype(np.int64)
    el = np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1])))
    step = (OS1_ELEVATIONS_DEG[0] - OS1_ELEVATIONS_DEG[-1]) / 63
    row = np.rint((OS1_ELEVATIONS_DEG[0] - el) / step).astype(np.int64)
    assert col.min() >= 0 and col.max() < OS1_COLUMNS and row.min() >= 0 and row.max() < 64
    return row, col


def write_ouster_pcap(seq: Path, out: Path, t0_ns: int = 1_000_000_000_000,
                      imu_to_sensor_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Path:
    """An Ouster pcap (and its metadata JSON beside it) of the simulated sequence folder seq
    (velodyne/*.bin, velodyne_times/*.bin, times.txt with sweep-start stamps, imu.csv): the
    sweeps as lidar packets, frame_id k, column j stamped t0_ns + stamp_k + j * 0.1 s / 1024;
    each imu.csv row as one legacy IMU packet (g, deg/s) on the same clock; the metadata puts
    the IMU at imu_to_sensor_mm."""
    from ouster.sdk import core
    from ouster.sdk.pcap import record
    from ouster.sdk.util import frame_to_packets

    meta = os1_metadata(imu_to_sensor_mm)
    out.with_suffix(".json").write_text(json.dumps(meta, indent=1))
    info = core.SensorInfo(json.dumps(meta))
    stamps_ns = t0_ns + np.rint(np.loadtxt(seq / "times.txt", ndmin=1) * 1e9).astype(np.int64)
    col_ns = np.rint(np.arange(OS1_COLUMNS) * SWEEP_NS / OS1_COLUMNS).astype(np.int64)
    timed = []  # (sensor ns, packet)
    for k, stamp_ns in enumerate(stamps_ns):
        cloud = np.fromfile(seq / "velodyne" / f"{k:06d}.bin", np.float32).reshape(-1, 4)
        times = np.fromfile(seq / "velodyne_times" / f"{k:06d}.bin", np.float32)
        row, col = os1_pixels(cloud[:, :3], times.astype(np.float64))
        frame = core.LidarFrame(info)
        frame.frame_id = k
        frame.timestamp[:] = stamp_ns + col_ns
        frame.measurement_id[:] = np.arange(OS1_COLUMNS)
        frame.status[:] = 1  # every column valid
        frame.field("RANGE")[row, col] = np.rint(
            np.linalg.norm(cloud[:, :3].astype(np.float64), axis=1) * 1000.0)
        frame.field("REFLECTIVITY")[row, col] = np.rint(cloud[:, 3] * 255.0)
        per_packet = info.format.columns_per_packet
        for i, packet in enumerate(frame_to_packets(frame, info)):  # in column order
            timed.append((int(stamp_ns + col_ns[i * per_packet]), packet))
    imu = np.loadtxt(seq / "imu.csv", delimiter=",", skiprows=1, ndmin=2)
    fmt = core.PacketFormat.from_info(info)
    for stamp_s, wx, wy, wz, ax, ay, az in imu:
        ts = t0_ns + int(np.rint(stamp_s * 1e9))
        packet = core.ImuPacket(fmt)
        # the legacy IMU packet (Ouster's firmware 2.x user guide): sys, accel and gyro
        # stamps (u64 ns), then accel x, y, z (g) and gyro x, y, z (deg/s) as float32
        body = struct.pack("<3Q6f", ts, ts, ts, ax / G0, ay / G0, az / G0,
                           *np.degrees([wx, wy, wz]))
        packet.buf[:48] = np.frombuffer(body, np.uint8)
        timed.append((ts, packet))
    timed.sort(key=lambda item: item[0])
    for ts, packet in timed:
        packet.host_timestamp = ts  # the capture clock = the sensor's here: deterministic bytes
    record([p for _, p in timed], str(out))
    return out


# ----------------------------------------------------------------------------------------------
# Velodyne VLP-16 (the encoder; velodyne-decoder decodes)
#
# After the VLP-16 user manual (Velodyne 63-9243, "Data Packet Format" and "Precision Azimuth
# Calculation"): a 1206-byte UDP payload (port 2368) of 12 data blocks of 100 bytes, each the
# flag 0xFFEE, the azimuth (uint16, 0.01 deg, clockwise from the sensor's y axis seen from
# above) of its first firing and 32 channel records (distance uint16 in 2 mm, 0 = no return;
# reflectivity uint8): two firing sequences of the 16 lasers. Then the timestamp (uint32, us
# since the top of the hour, of the first firing of the packet) and the two factory bytes:
# return mode 0x37 (strongest) and product id 0x22 (VLP-16). Lasers fire 2.304 us apart, a
# sequence every 55.296 us; laser l points l deg up (odd l) or l - 15 deg (even l), from a beam
# origin the manual's "vertical correction" above the sensor's origin (its table of the laser
# angles, in mm, added to z).

VLP16_ELEVATIONS_DEG = np.array([lz if lz % 2 else lz - 15 for lz in range(16)], np.float64)
VLP16_Z_OFFSETS_M = 1e-3 * np.array([11.2, -0.7, 9.7, -2.2, 8.1, -3.7, 6.6, -5.1, 5.1, -6.6,
                                     3.7, -8.1, 2.2, -9.7, 0.7, -11.2])
FIRING_US, SEQUENCE_US = 2.304, 55.296
PACKET_US = 12 * 2 * SEQUENCE_US
DISTANCE_UNIT_M = 0.002


def vlp16_firings(n_packets: int, t0_us: int, rpm: float = 600.0
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every firing of n_packets packets from t0_us (us past the top of the hour): the packets'
    timestamps (P,) us, the firing times (P, 12, 2, 16) us and the azimuths (P, 12, 2, 16) deg,
    the head turning at rpm from azimuth 0 at t0_us."""
    stamps_us = np.rint(t0_us + np.arange(n_packets) * PACKET_US).astype(np.int64)
    block = np.arange(12)[None, :, None, None]
    seq = np.arange(2)[None, None, :, None]
    laser = np.arange(16)[None, None, None, :]
    times_us = (stamps_us[:, None, None, None] + (2 * block + seq) * SEQUENCE_US
                + laser * FIRING_US)
    azimuth_deg = ((times_us - t0_us) * 1e-6 * rpm / 60.0 * 360.0) % 360.0
    return stamps_us, times_us, azimuth_deg


def vlp16_directions(azimuth_deg: np.ndarray) -> np.ndarray:
    """(..., 3) unit beams in the ROS sensor frame (x ahead, y left, z up) that velodyne-decoder
    gives its points in: azimuth clockwise from x, laser elevation from the last axis's index."""
    az = np.radians(azimuth_deg)
    el = np.radians(VLP16_ELEVATIONS_DEG)
    return np.stack([np.cos(el) * np.cos(az), -np.cos(el) * np.sin(az),
                     np.broadcast_to(np.sin(el), az.shape)], axis=-1)


def vlp16_packet(stamp_us: int, block_azimuth_deg: np.ndarray, ranges_m: np.ndarray,
                 reflectivity: np.ndarray) -> bytes:
    """One 1206-byte data packet: block_azimuth_deg (12,), ranges_m and reflectivity (12, 32)
    in firing order (NaN or beyond 131 m: no return)."""
    dist = np.where(np.isfinite(ranges_m), np.rint(ranges_m / DISTANCE_UNIT_M), 0)
    dist = np.where(dist > 0xFFFF, 0, dist).astype("<u2")
    out = bytearray()
    for b in range(12):
        out += b"\xff\xee" + struct.pack("<H", int(round(block_azimuth_deg[b] * 100)) % 36000)
        records = np.zeros(32, dtype=[("d", "<u2"), ("r", "u1")])
        records["d"], records["r"] = dist[b], reflectivity[b]
        out += records.tobytes()
    out += struct.pack("<I", stamp_us % 3_600_000_000) + bytes([0x37, 0x22])
    assert len(out) == 1206
    return bytes(out)


def write_udp_pcap(path: Path, payloads: list[tuple[float, bytes]], port: int = 2368) -> Path:
    """payloads (capture stamp s, UDP payload) as Ethernet / IPv4 / UDP records, through dpkt."""
    import dpkt

    with path.open("wb") as fh:
        writer = dpkt.pcap.Writer(fh)
        for stamp, data in payloads:
            udp = dpkt.udp.UDP(sport=port, dport=port, data=data)
            udp.ulen = len(udp)
            ip = dpkt.ip.IP(src=bytes([192, 168, 1, 201]), dst=bytes([255, 255, 255, 255]),
                            p=dpkt.ip.IP_PROTO_UDP, data=udp)
            ip.len = len(ip)
            eth = dpkt.ethernet.Ethernet(src=b"\x60\x76\x88\x00\x00\x01", dst=b"\xff" * 6,
                                         type=dpkt.ethernet.ETH_TYPE_IP, data=ip)
            writer.writepkt(bytes(eth), ts=stamp)
    return path


@dataclass(frozen=True)
class Vlp16Capture:
    """A written VLP-16 pcap and the simulated returns in it: their firing times (s on the
    sensor's clock: the capture's top of the hour + the packets' us), their points (m, the
    sensor frame at that instant, unquantised) and the laser that fired them."""

    path: Path
    times_s: np.ndarray
    points: np.ndarray
    laser: np.ndarray


def write_vlp16_pcap(path: Path, world, poses_at, duration_s: float,
                     hour_s: float = 1_700_002_800.0, t0_us: int = 1_200_000_000,
                     max_range_m: float = 100.0, min_range_m: float = 0.5) -> Vlp16Capture:
    """Ray-cast a VLP-16 at 600 rpm through a lidar_slam.sim World for duration_s, the sensor
    at poses_at(s since the start) -> T_world_lidar (N, 4, 4), and write its data packets as a
    pcap captured at hour_s (a top of the hour, UTC) + the packets' stamps."""
    n_packets = int(duration_s * 1e6 / PACKET_US)
    stamps_us, times_us, azimuth_deg = vlp16_firings(n_packets, t0_us)
    T = poses_at(((times_us - t0_us) * 1e-6).ravel())
    d = vlp16_directions(azimuth_deg).reshape(-1, 3)
    origin = np.zeros_like(d)  # each laser's beam origin in the sensor frame
    origin[:, 2] = np.broadcast_to(VLP16_Z_OFFSETS_M, times_us.shape).ravel()
    hit = world.cast(np.einsum("nij,nj->ni", T[:, :3, :3], origin) + T[:, :3, 3],
                     np.einsum("nij,nj->ni", T[:, :3, :3], d))
    r = np.asarray(hit["t_hit"], dtype=np.float64)
    ok = np.isfinite(r) & (r >= min_range_m) & (r <= max_range_m)
    r = np.where(ok, r, np.nan).reshape(n_packets, 12, 32)
    reflectivity = np.full((12, 32), 100, np.uint8)
    block_azimuth = azimuth_deg[:, :, 0, 0]
    payloads = [(hour_s + stamps_us[p] * 1e-6,
                 vlp16_packet(int(stamps_us[p]), block_azimuth[p], r[p], reflectivity))
                for p in range(n_packets)]
    write_udp_pcap(path, payloads)
    laser = np.broadcast_to(np.arange(16), times_us.shape).ravel()
    return Vlp16Capture(path, hour_s + times_us.ravel()[ok] * 1e-6,
                        origin[ok] + d[ok] * r.ravel()[ok, None], laser[ok])
