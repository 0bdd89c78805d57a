"""Loop-stage settings that follow the data: the config's "auto" values, fixed at the first scan.

Indoors most returns lie within ~20 m, so an 80 m Scan Context puts a whole room in 3-4 rings,
2 m keyframes are few, and "skip the newest 60 m" skips the whole loop. Outdoors the opposite
holds. The horizontal range within which 99 % of the first scan's points lie tells them apart
(measured: Ouster OS0 indoors 22.8 m; KITTI 00 56.8 m; simulated HDL-64E 54-64 m; the 16-beam
sample 43 m), and sets:

- descriptor radius = 1.5 x that range, rounded up to 10 m, within 20-80 m;
- keyframe spacing = radius / 40 in 0.5 m steps, within 0.5-2 m;
- recent keyframes skipped by loop search = 0.75 x radius of travelled path;
- the sensor height that descriptors fall back to where a keyframe's own ground fit fails =
  the height of the ground fitted in the first scan (2 m if none; simulated HDL-64E: 1.73 m).
"""

from __future__ import annotations

import logging

import numpy as np

from lidar_slam.config import SlamConfig
from lidar_slam.loop.scan_context import DEFAULT_SENSOR_HEIGHT_M
from lidar_slam.registration import level_ground

log = logging.getLogger(__name__)
OUTDOOR_FALLBACK_RANGE_M = 60.0  # a first scan with no point in range: assume outdoors


# The settings that can be "auto": scan-context ones, then keyframe ones.
SCAN_CONTEXT_KEYS = ("max_radius_m", "exclude_recent_m", "sensor_height_m")
KEYFRAME_KEYS = ("distance_m",)


def _auto_keys(cfg: SlamConfig) -> list[str]:
    """Names of the settings that are "auto" in cfg."""
    sc, kf = cfg.loop.scan_context, cfg.keyframes
    return ([k for k in SCAN_CONTEXT_KEYS if getattr(sc, k) == "auto"]
            + [k for k in KEYFRAME_KEYS if getattr(kf, k) == "auto"])


def auto_values(cfg: SlamConfig, points_sensor: np.ndarray | None) -> dict[str, float]:
    """The settings that are "auto" in cfg, from the first scan's points (sensor frame, m);
    the 99 % horizontal range is reported as range_p99_m."""
    sc, kf = cfg.loop.scan_context, cfg.keyframes
    if not _auto_keys(cfg):
        return {}
    p99 = OUTDOOR_FALLBACK_RANGE_M
    if points_sensor is not None and len(points_sensor):
        r = np.hypot(points_sensor[:, 0], points_sensor[:, 1])
        r = r[(r > cfg.data.min_range_m) & (r < cfg.data.max_range_m)]
        if len(r):
            p99 = float(np.percentile(r, 99))
    radius = sc.max_radius_m
    if radius == "auto":
        radius = float(np.clip(10.0 * np.ceil(1.5 * p99 / 10.0), 20.0, 80.0))
    out = {"range_p99_m": round(p99, 2), "max_radius_m": radius}
    if kf.distance_m == "auto":
        out["distance_m"] = float(np.clip(np.round(radius / 40.0 * 2.0) / 2.0, 0.5, 2.0))
    if sc.exclude_recent_m == "auto":
        out["exclude_recent_m"] = 0.75 * radius
    if sc.sensor_height_m == "auto":
        height = None
        if points_sensor is not None and len(points_sensor):
            height = level_ground(points_sensor, max_tilt_deg=sc.max_tilt_deg).height_m
        out["sensor_height_m"] = DEFAULT_SENSOR_HEIGHT_M if height is None else round(height, 2)
    return out


def covers(cfg: SlamConfig, values: dict[str, float]) -> bool:
    """True when values hold every setting that is "auto" in cfg."""
    return all(k in values for k in _auto_keys(cfg))


def apply(cfg: SlamConfig, values: dict[str, float]) -> SlamConfig:
    """cfg with its "auto" settings replaced by values (from auto_values)."""
    if not values:
        return cfg
    sc = cfg.loop.scan_context.model_copy(update={
        k: values[k] for k in SCAN_CONTEXT_KEYS if k in values})
    kf = cfg.keyframes.model_copy(update={k: values[k] for k in KEYFRAME_KEYS if k in values})
    loop = cfg.loop.model_copy(update={"scan_context": sc})
    return cfg.model_copy(update={"loop": loop, "keyframes": kf})


def describe(values: dict[str, float]) -> str:
    """One log line for the chosen settings."""
    parts = [f"descriptor radius {values['max_radius_m']:.0f} m"]
    if "distance_m" in values:
        parts.append(f"keyframes every {values['distance_m']:.1f} m")
    if "exclude_recent_m" in values:
        parts.append(f"loops skip the last {values['exclude_recent_m']:.0f} m of path")
    if "sensor_height_m" in values:
        parts.append(f"sensor {values['sensor_height_m']:.2f} m above the ground")
    return (", ".join(parts) + f" (auto: 99 % of the first scan within "
            f"{values['range_p99_m']:.1f} m)")
