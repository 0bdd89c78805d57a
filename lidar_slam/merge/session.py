"""A finished run folder opened as one session of a merge: its saved map (keyframes, their
final poses, descriptors), the edges of its keyframe pose graph and its per-frame poses."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidar_slam.errors import InputError
from lidar_slam.geometry import interpolate, inverse
from lidar_slam.io.g2o import G2oEdge, read_g2o
from lidar_slam.io.trajectory import read_kitti_poses, read_tum
from lidar_slam.map.keyframes import TABLE_DTYPE
from lidar_slam.map.saved import SavedMap, open_map

log = logging.getLogger(__name__)

# Odometry between keyframes where the run left no graph.g2o (loop closure off).
ODOMETRY_ROT_SIGMA_DEG = 0.5
ODOMETRY_TRANS_SIGMA_M = 0.05


@dataclass
class Session:
    """One run: index (its place in the merge's argument list), the saved map (T_map_kf in the
    run's own frame), the keyframe graph's edges (keyframe ids; odometry (i, i+1) and loops),
    and every frame's stamp (s) and pose T_run_frame (the rows of its poses_kitti.txt)."""

    index: int
    run_dir: Path
    map: SavedMap
    odometry: list[G2oEdge]
    loops: list[G2oEdge]
    stamps_s: np.ndarray
    T_run_frame: np.ndarray
    kf_stamps_s: np.ndarray  # (K,) each keyframe's scan stamp (s)

    def __len__(self) -> int:
        return len(self.map)

    def frames_in(self, T_merged_kf: np.ndarray) -> np.ndarray:
        """Every frame's pose in the merged frame (F, 4, 4): its own pose carried by the
        correction T_merged_kf @ inv(T_run_kf) of the keyframes either side of its stamp,
        interpolated by time (the nearest keyframe's before the first, after the last)."""
        corr = T_merged_kf @ inverse(self.map.T_map_kf)
        kf_stamps = self.kf_stamps_s
        out = np.empty_like(self.T_run_frame)
        for f, (t, T) in enumerate(zip(self.stamps_s, self.T_run_frame)):
            k = int(np.searchsorted(kf_stamps, t, "right"))
            if k == 0:
                C = corr[0]
            elif k == len(corr):
                C = corr[-1]
            else:
                s = (t - kf_stamps[k - 1]) / max(kf_stamps[k] - kf_stamps[k - 1], 1e-9)
                C = interpolate(corr[k - 1], corr[k], float(s))
            out[f] = C @ T
        return out

    def close(self) -> None:
        self.map.close()


def open_session(index: int, run_dir: str | Path) -> Session:
    """The run folder as a session; InputError (one line naming the path) when it is not a
    finished run with keyframes and poses."""
    root = Path(run_dir)
    if merged_from(root):  # its keyframes carry no stamps: "an older run" misled a user
        raise InputError(root, "a merged map, not a run: merge its runs (summary.json "
                               "merged_from) with the new ones, or add a run to it with "
                               f"`lidar-slam run DATA --extend {root}`")
    saved = open_map(root)
    if len(saved) == 0 or not saved.counts.any():
        saved.close()
        raise InputError(root, "the run has no keyframes with points: nothing to merge")
    kitti, tum = root / "poses_kitti.txt", root / "poses_tum.txt"
    for path in (kitti, tum):
        if not path.is_file():
            saved.close()
            raise InputError(path, "missing: a merge carries every frame of a run")
    T_run_frame = read_kitti_poses(kitti)
    stamps, _ = read_tum(tum)
    if len(stamps) != len(T_run_frame):
        saved.close()
        raise InputError(tum, f"{len(stamps)} rows, poses_kitti.txt {len(T_run_frame)}")
    kf_stamps = np.fromfile(root / "keyframes" / "table.bin", dtype=TABLE_DTYPE,
                            count=len(saved))["stamp_s"]
    if np.isnan(kf_stamps).any() or np.any(np.diff(kf_stamps) < 0):
        saved.close()
        raise InputError(root / "keyframes", "keyframes without stamps (an older run): run it "
                         "again")
    odometry, loops = _graph_edges(root / "graph.g2o", saved)
    return Session(index, root, saved, odometry, loops, stamps, T_run_frame, kf_stamps)


def map_summary(root: Path) -> dict:
    """A saved map's summary.json ({} when missing or unreadable): a merged map's names its
    runs (merged_from) and its reference."""
    import json

    try:
        summary = json.loads((root / "summary.json").read_text())
    except (OSError, ValueError):
        return {}
    return summary if isinstance(summary, dict) else {}


def merged_from(root: Path) -> list | None:
    """A merged map's runs, else None (a run, or no summary)."""
    return map_summary(root).get("merged_from")


def _graph_edges(path: Path, saved: SavedMap) -> tuple[list[G2oEdge], list[G2oEdge]]:
    """Odometry between consecutive keyframes and the run's loops. The odometry's measurement
    is the run's final relative pose (with an IMU or GNSS the run's final poses come from its
    inertial solve, better than the keyframe graph's lidar odometry), its information the keyframe
    graph's (graph.g2o); without graph.g2o, fixed sigmas and no loops."""
    n = len(saved)
    T = saved.T_map_kf
    infos: dict[int, np.ndarray] = {}
    loops: list[G2oEdge] = []
    if path.is_file() and n > 1:  # one keyframe: no odometry, and its graph has no edge
        g2o = read_g2o(path)
        if set(g2o.poses) == set(range(n)):
            infos = {e.i: e.information for e in g2o.edges if e.j == e.i + 1}
            loops = [e for e in g2o.edges if e.j != e.i + 1]
        else:
            log.warning("%s: nodes are not the %d keyframes; fixed odometry sigmas", path, n)
    from lidar_slam.backend.factors import sigmas_to_information

    fixed = sigmas_to_information(ODOMETRY_ROT_SIGMA_DEG, ODOMETRY_TRANS_SIGMA_M, 3)
    return [G2oEdge(k, k + 1, inverse(T[k]) @ T[k + 1], infos.get(k, fixed))
            for k in range(n - 1)], loops
