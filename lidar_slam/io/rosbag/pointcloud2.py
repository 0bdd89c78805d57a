"""sensor_msgs/PointCloud2 messages decoded into points, per-point times (s from the header
stamp, lidar_slam.io.point_times) and intensity, invalid returns removed."""

from __future__ import annotations

import logging
from typing import Any, NamedTuple

import numpy as np

from lidar_slam.io.point_times import relative_seconds
from lidar_slam.io.pointcloud import INTENSITY_FIELDS, TIME_FIELDS

log = logging.getLogger(__name__)


POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
# PointField datatype -> NumPy type code (sensor_msgs/PointField INT8..FLOAT64).
_DATATYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}

_warned_intensity: list[bool] = []  # once per process, as point_times warns


class PointCloud2Error(ValueError):
    """A PointCloud2 message whose layout cannot be decoded (missing x/y/z, short data, ...)."""


class DecodedCloud(NamedTuple):
    """One decoded PointCloud2, invalid returns removed.

    points (N,3) float64 m in the message frame; point_times (N,) float64 s relative to the
    header stamp, or None; intensity (N,) float32, or None (none, or not all finite);
    n_dropped = NaN/inf or (0,0,0) returns.
    """

    points: np.ndarray
    point_times: np.ndarray | None
    intensity: np.ndarray | None
    n_dropped: int


def header_stamp_ns(msg: Any) -> int:
    """Header stamp of a rosbags message in integer nanoseconds."""
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def decode_pointcloud2(msg: Any) -> DecodedCloud:
    """x/y/z, per-point time (s from the header stamp) and intensity of a PointCloud2 message."""
    fields: dict[str, Any] = {}
    for f in msg.fields:
        fields.setdefault(f.name, f)
    if missing := [n for n in "xyz" if n not in fields]:
        have = ", ".join(fields) or "none"
        raise PointCloud2Error(f"PointCloud2 lacks field(s) {', '.join(missing)} (fields: {have})")
    wanted = {"x": fields["x"], "y": fields["y"], "z": fields["z"]}
    tname = next((n for n in TIME_FIELDS if n in fields), None)
    iname = next((n for n in INTENSITY_FIELDS if n in fields), None)
    if tname:
        wanted["t"] = fields[tname]
    if iname:
        wanted["i"] = fields[iname]
    rec = _records(msg, wanted)

    x, y, z = rec["x"], rec["y"], rec["z"]
    # Column-wise: reductions along axis 1 of an (N,3) array are several times slower.
    keep = np.isfinite(x) & np.isfinite(y) & np.isfinite(z) & ((x != 0) | (y != 0) | (z != 0))
    xyz = np.empty((len(rec), 3), dtype=np.float64)
    xyz[:, 0], xyz[:, 1], xyz[:, 2] = x, y, z
    n_dropped = int(len(keep) - np.count_nonzero(keep))
    if n_dropped:
        xyz = xyz[keep]
    times = intensity = None
    if tname:
        times = relative_seconds(rec["t"][keep] if n_dropped else rec["t"], header_stamp_ns(msg))
    if iname:
        with np.errstate(over="ignore", invalid="ignore"):  # beyond float32: inf, refused below
            intensity = (rec["i"][keep] if n_dropped else rec["i"]).astype(np.float32)
        if not np.isfinite(intensity).all():
            if not _warned_intensity:
                _warned_intensity.append(True)
                log.warning("PointCloud2 %s field has NaN/inf values (or beyond float32); such "
                            "scans are used without intensity", iname)
            intensity = None
    return DecodedCloud(xyz, times, intensity, n_dropped)


def _records(msg: Any, wanted: dict[str, Any]) -> np.ndarray:
    """The wanted fields of every point as a 1-D structured array (rows concatenated)."""
    step, row_step = int(msg.point_step), int(msg.row_step)
    height, width = int(msg.height), int(msg.width)
    order = ">" if msg.is_bigendian else "<"
    formats, offsets = [], []
    for f in wanted.values():
        code = _DATATYPES.get(int(f.datatype))
        if code is None:
            raise PointCloud2Error(f"field {f.name!r} has unknown datatype {f.datatype}")
        if f.offset + int(code[1]) > step:
            raise PointCloud2Error(
                f"field {f.name!r} (offset {f.offset}) does not fit in point_step {step}")
        formats.append(order + code)
        offsets.append(int(f.offset))
    dtype = np.dtype({"names": list(wanted), "formats": formats, "offsets": offsets,
                      "itemsize": step})
    if height * width == 0:
        return np.zeros(0, dtype=dtype)
    data = msg.data if isinstance(msg.data, np.ndarray) else np.frombuffer(msg.data, np.uint8)
    if height > 1 and row_step < width * step:
        raise PointCloud2Error(f"row_step {row_step} < width {width} x point_step {step}")
    need = (height - 1) * row_step + width * step
    if data.nbytes < need:
        raise PointCloud2Error(
            f"data holds {data.nbytes} bytes, {height}x{width} points need {need}")
    grid = np.ndarray((height, width), dtype=dtype, buffer=data,
                      strides=(row_step if height > 1 else width * step, step))
    return grid.reshape(-1)


