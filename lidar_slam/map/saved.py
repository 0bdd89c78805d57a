"""A finished run folder opened as a map: its keyframe clouds, their final poses in the map frame,
their Scan Context descriptors and the run's config (the layout is documented in
lidar_slam.map.keyframes). What `localize` and `export` read."""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidar_slam.config import LocalizeConfig, SlamConfig, load_config, overlay_config
from lidar_slam.errors import InputError
from lidar_slam.geo import GeoReference
from lidar_slam.geometry import inverse, rotation_angle_deg, transform_points
from lidar_slam.io.trajectory import read_tum
from lidar_slam.loop import adapt
from lidar_slam.loop.scan_context import describe
from lidar_slam.map.keyframes import TABLE_DTYPE, KeyframeReader, check_version
from lidar_slam.types import Keyframe

log = logging.getLogger(__name__)


@dataclass
class SavedMap:
    """A run's map. T_map_kf (K, 4, 4): final keyframe poses in the map frame (the frame of the
    run's poses_kitti.txt); frame_index (K,): the input frame of each keyframe; counts (K,):
    points per keyframe cloud; cfg: the run's effective config. prediction_error_m / _deg: the
    largest miss of the constant-velocity prediction along the run's own poses (0 when they
    are not there), see prediction_errors. geo: where the map frame lies on the Earth (a run
    with GNSS: summary.json's `geo`), else None."""

    run_dir: Path
    cfg: SlamConfig
    T_map_kf: np.ndarray
    frame_index: np.ndarray
    counts: np.ndarray
    has_intensity: bool
    descriptor_file: Path | None
    descriptor_rows: int
    _reader: KeyframeReader
    prediction_error_m: float = 0.0
    prediction_error_deg: float = 0.0
    geo: GeoReference | None = None

    def __len__(self) -> int:
        return len(self.T_map_kf)

    @property
    def n_points(self) -> int:
        return int(self.counts.sum())

    def keyframe(self, kf_id: int) -> Keyframe:
        """Keyframe kf_id with its cloud in its own frame (float32, metres)."""
        return self._reader.get(kf_id)

    def points_map(self, kf_id: int) -> tuple[np.ndarray, np.ndarray | None]:
        """Keyframe kf_id's cloud in the map frame (N, 3) float64, and its intensity or None."""
        kf = self._reader.get(kf_id)
        return transform_points(self.T_map_kf[kf_id], kf.points.astype(np.float64)), kf.intensity

    def all_points_map(self) -> np.ndarray:
        """Every keyframe cloud in the map frame, stacked (N, 3) float64."""
        parts = [self.points_map(k)[0] for k in range(len(self)) if self.counts[k]]
        return np.concatenate(parts) if parts else np.zeros((0, 3))

    def submap(self, kf_id: int, radius: int) -> np.ndarray:
        """Clouds of keyframes kf_id-radius..kf_id+radius in keyframe kf_id's frame (N, 3), as
        loop verification builds its match side."""
        T_kf_map = np.linalg.inv(self.T_map_kf[kf_id])
        parts = [transform_points(T_kf_map @ self.T_map_kf[j],
                                  self._reader.get(j).points.astype(np.float64))
                 for j in range(max(0, kf_id - radius), min(len(self), kf_id + radius + 1))]
        return np.concatenate(parts)

    def descriptor_grids(self) -> tuple[np.ndarray, np.ndarray]:
        """(ids (M,), grids (M, rings, sectors)) of every keyframe with a cloud: the run's
        stored grids, computed from the clouds where the run did not store them."""
        sc = self.cfg.loop.scan_context
        ids = np.flatnonzero(self.counts > 0)
        grids = np.zeros((len(ids), sc.rings, sc.sectors))
        rows = min(self.descriptor_rows, len(ids))
        if rows and self.descriptor_file is not None:
            raw = np.fromfile(self.descriptor_file, dtype="<f4", count=rows * sc.rings * sc.sectors)
            grids[:rows] = raw.reshape(rows, sc.rings, sc.sectors)
        for j in range(rows, len(ids)):
            grids[j] = describe(self._reader.get(int(ids[j])).points.astype(np.float64), sc).grid
        if rows < len(ids):
            log.info("computed %d of %d keyframe descriptors", len(ids) - rows, len(ids))
        return ids, grids

    def close(self) -> None:
        self._reader.close()


def prediction_errors(T_world_scan: np.ndarray, stamps_s: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """How far the constant-velocity prediction (the last frame's motion repeated) misses each
    pose of a trajectory (K, 4, 4) with stamps (K,) s: (metres, degrees) for every frame whose
    two frame intervals before it agree within 25 % (a dropped frame or a gap in the data says
    nothing about how the platform moves)."""
    if len(T_world_scan) < 3:
        return np.zeros(0), np.zeros(0)
    dt = np.diff(stamps_s)
    even = np.flatnonzero(np.abs(dt[1:] - dt[:-1]) <= 0.25 * np.maximum(dt[:-1], 1e-9)) + 2
    prev, last = T_world_scan[even - 2], T_world_scan[even - 1]
    miss = inverse(last @ inverse(prev) @ last) @ T_world_scan[even]
    return np.linalg.norm(miss[:, :3, 3], axis=1), rotation_angle_deg(miss)


def _run_prediction_error(root: Path) -> tuple[float, float]:
    """The largest (m, deg) of prediction_errors along the run's poses_tum.txt, (0, 0) without
    it or with fewer than 3 evenly spaced frames."""
    path = root / "poses_tum.txt"
    if not path.is_file():
        log.info("%s not found: localisation assumes the motion model predicts well", path)
        return 0.0, 0.0
    stamps, poses = read_tum(path)
    err_m, err_deg = prediction_errors(poses, stamps)
    if len(err_m) == 0:
        return 0.0, 0.0
    return float(err_m.max()), float(err_deg.max())


def open_map(run_dir: str | Path, overlay: str | Path | None = None) -> SavedMap:
    """Open a finished run folder as a map; config: the run's config.yaml, overlaid by the
    YAML file overlay when given. Raises InputError with one line when it is not a map."""
    root = Path(run_dir)
    kf_dir = root / "keyframes"
    manifest_path = kf_dir / "manifest.json"
    if not root.is_dir():
        raise InputError(root, "is a file, not a run folder" if root.exists()
                         else "map run folder does not exist")
    if not manifest_path.is_file():
        raise InputError(root, "not a run folder with a map (no keyframes/manifest.json)")
    try:
        manifest = json.loads(manifest_path.read_text())
    except ValueError as exc:
        raise InputError(manifest_path, f"not valid JSON ({exc})") from exc
    check_version(manifest_path, manifest)
    info = manifest.get("map")
    if info is None:
        raise InputError(root, "the run did not finish writing its map (keyframes/manifest.json "
                         "has no \"map\": a run still going, killed, or an older layout); run it "
                         "again")
    cfg_path = (kf_dir / info["config"]).resolve()
    if not cfg_path.is_file():
        raise InputError(root / "config.yaml", "missing: the map's config is needed")
    # The map's sensor, keyframe and loop settings; localize.* are this version's defaults
    # (the map run froze its own into config.yaml), overlaid by the overlay.
    cfg = load_config(cfg_path).model_copy(update={"localize": LocalizeConfig()})
    if overlay is not None:
        cfg = overlay_config(cfg, overlay)
    n = int(manifest["keyframes"])
    table = np.fromfile(kf_dir / "table.bin", dtype=TABLE_DTYPE, count=n)
    poses_path = kf_dir / info["poses"]
    size = poses_path.stat().st_size if poses_path.is_file() else -1
    if len(table) != n or size != n * 128:
        raise InputError(kf_dir, f"manifest says {n} keyframes, table.bin holds {len(table)}, "
                         f"{info['poses']} {max(size, 0) // 128}: damaged map")
    T_map_kf = np.fromfile(poses_path, dtype="<f8").reshape(n, 4, 4)
    points = os.path.getsize(kf_dir / "points.bin") // 16
    if points < int(manifest["points"]):
        raise InputError(kf_dir / "points.bin", f"holds {points} points, the manifest "
                         f"{manifest['points']}: damaged map")
    desc = info.get("descriptors")
    # The map run's "auto" loop settings, as it fixed them (summary.json), else from its first
    # keyframe cloud (lidar_slam.loop.adapt).
    try:
        summary = json.loads((root / "summary.json").read_text())
    except (OSError, ValueError):
        summary = {}
    summary = summary if isinstance(summary, dict) else {}
    auto = summary.get("auto_settings")
    geo = _geo_reference(root / "summary.json", summary.get("geo"))
    reader = KeyframeReader(kf_dir)
    if auto is None or not adapt.covers(cfg, auto):  # (older runs fixed fewer of them)
        auto = {**adapt.auto_values(cfg, reader.get(0).points if n else None), **(auto or {})}
    cfg = adapt.apply(cfg, auto)
    err_m, err_deg = _run_prediction_error(root)
    return SavedMap(root, cfg, T_map_kf, table["frame_index"].copy(), table["count"].copy(),
                    bool(n) and bool(table["has_intensity"].all()),
                    None if desc is None else kf_dir / desc, int(info.get("descriptor_rows", 0)),
                    reader, err_m, err_deg, geo)


def _geo_reference(path: Path, section: dict | None) -> GeoReference | None:
    """The run's geo reference from its summary.json `geo` section (None without one)."""
    if section is None:
        return None
    try:
        return GeoReference.from_dict(section)
    except ValueError as exc:
        raise InputError(path, str(exc)) from None
