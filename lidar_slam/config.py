"""One pydantic model per stage, gathered in SlamConfig; YAML overlay load and dump."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError

from lidar_slam.errors import ConfigError, InputError


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid")


class DataConfig(_Section):
    min_range_m: float = 0.0
    max_range_m: float = 100.0
    # Deskew with per-point times (constant velocity) when the scans carry them. Done once, here.
    deskew: bool = True
    # Deskew every point of every scan (slow; for comparison): by default only the points used,
    # one per odometry voxel and the keyframe clouds.
    deskew_all_points: bool = False
    # kiss-icp's 0.205 deg vertical correction for KITTI HDL-64E scans (KITTI layout only).
    kitti_vertical_correction: bool = False


class OdometryConfig(_Section):
    voxel_size_m: float | None = None  # default: max_range_m / 100, as kiss-icp
    max_points_per_voxel: int = 20
    initial_threshold_m: float = 2.0
    min_motion_m: float = 0.1
    max_num_iterations: int = 500
    convergence_criterion: float = 1e-4
    max_num_threads: int = 0


class KeyframeConfig(_Section):
    distance_m: float = 2.0
    rotation_deg: float = 15.0
    cloud_voxel_m: float = 0.5


class ScanContextConfig(_Section):
    rings: int = 20
    sectors: int = 60
    max_radius_m: float = 80.0
    sensor_height_m: float = 2.0
    candidates: int = 10
    threshold: float = 0.3
    exclude_recent: int = 30
    local_search_sectors: int = 2
    # Level each cloud on its fitted ground plane before binning (hand-held / tilted sensors); the
    # yaw guess is then about the ground normal. Bins use the fitted sensor height when found.
    level_to_ground: bool = True
    max_tilt_deg: float = 30.0


class VerifyConfig(_Section):
    method: Literal["point_to_plane", "gicp"] = "point_to_plane"
    voxel_m: float = 0.5
    submap_radius: int = 2
    # Coarse stage (every yaw hypothesis): clouds at coarse_voxel_m, correspondences up to
    # coarse_correspondence_m then half of it, to pull in the few metres between revisits.
    coarse_voxel_m: float = 1.5
    coarse_correspondence_m: float = 3.0
    # Hypotheses are ranked (and the margin taken) by coarse fitness: share of coarse query
    # points within coarse_inlier_m of the match after the coarse stage.
    coarse_inlier_m: float = 0.5
    # The winner is re-aligned from starts pushed this far sideways (0: off); a different pose
    # found that way competes in the margin like another yaw hypothesis.
    probe_shift_m: float = 4.0
    # Fine stage at voxel_m.
    max_correspondence_m: float = 0.6
    # Query points used (a fixed random subset beyond this; 0 = all) in the coarse / fine stage.
    coarse_max_points: int = 500
    fine_max_points: int = 4000
    min_fitness: float = 0.5
    # RMSE of the inliers (so at most inlier_m): a loose guard; ~0.19 m for true loops here.
    max_rmse_m: float = 0.25
    # ICP may turn at most this far from the yaw hypothesis it started at (the yaw guess plus a
    # multiple of 90 deg): a guess a few sectors off must still pass, a slide must not.
    max_yaw_disagreement_deg: float = 30.0
    try_yaw_offsets: bool = True
    # Fitness = share of query points with a match point within inlier_m after ICP.
    inlier_m: float = 0.3
    # The best hypothesis must beat the best *different* converged pose by this much coarse fitness.
    min_margin: float = 0.12
    max_translation_m: float = 10.0
    max_iterations: int = 20
    # Level both clouds on their ground planes to build the yaw hypotheses about gravity.
    level_to_ground: bool = True
    # The information matrix keeps the shape of the point-to-plane Hessian but is scaled down
    # so that no direction is more certain than these (residuals of neighbouring points correlate).
    info_min_trans_sigma_m: float = 0.02
    info_min_rot_sigma_deg: float = 0.2


class BackendConfig(_Section):
    odom_rot_sigma_deg: float = 0.1
    odom_trans_sigma_m: float = 0.05
    prior_rot_sigma_deg: float = 1e-3
    prior_trans_sigma_m: float = 1e-3
    huber_k: float = 1.345
    max_iterations: int = 100


class LoopConfig(_Section):
    enabled: bool = True
    # Candidates verified per keyframe query (best descriptor distance first).
    max_verify: int = 3
    # Detection runs in a worker process (or thread; "inline": in the main flow, for
    # debugging); the result of keyframe k is applied to the graph when keyframe
    # k + collect_lag_keyframes is made (or at the end), whatever the worker's speed, so runs
    # are deterministic.
    worker: Literal["process", "thread", "inline"] = "process"
    collect_lag_keyframes: int = 10
    scan_context: ScanContextConfig = ScanContextConfig()
    verify: VerifyConfig = VerifyConfig()


class MapConfig(_Section):
    voxel_size_m: float = 0.2
    max_range_m: float = 60.0


class CheckpointConfig(_Section):
    # A checkpoint (for `run --resume`) every this many keyframes; 0 = none.
    every_keyframes: int = 100


class SlamConfig(_Section):
    data: DataConfig = DataConfig()
    odometry: OdometryConfig = OdometryConfig()
    keyframes: KeyframeConfig = KeyframeConfig()
    loop: LoopConfig = LoopConfig()
    backend: BackendConfig = BackendConfig()
    map: MapConfig = MapConfig()
    checkpoint: CheckpointConfig = CheckpointConfig()

    def voxel_size_m(self) -> float:
        """Effective odometry voxel size in metres."""
        if self.odometry.voxel_size_m is not None:
            return self.odometry.voxel_size_m
        return self.data.max_range_m / 100.0


def _merge(base: dict, overlay: dict) -> dict:
    out = dict(base)
    for key, value in overlay.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def load_config(path: str | Path | None = None, overrides: dict | None = None) -> SlamConfig:
    """Defaults, overlaid by a YAML file, overlaid by a dict of overrides."""
    data: dict = {}
    if path is not None:
        p = Path(path)
        if not p.is_file():
            raise InputError(p, "config file does not exist")
        try:
            data = yaml.safe_load(p.read_text()) or {}
        except yaml.YAMLError as exc:
            raise InputError(p, f"not valid YAML ({str(exc).splitlines()[0]})") from exc
        if not isinstance(data, dict):
            raise InputError(p, "config must be a mapping of sections")
    data = _merge(data, overrides or {})
    try:
        return SlamConfig(**data)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(x) for x in err["loc"])
        raise ConfigError(f"{path or 'config'}: {where}: {err['msg']}") from exc


def dump_config(config: SlamConfig, path: str | Path) -> None:
    """Write the effective config as YAML."""
    Path(path).write_text(yaml.safe_dump(config.model_dump(), sort_keys=False))
