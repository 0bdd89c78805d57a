"""Evaluate an estimated trajectory against ground truth: metrics.json, a table, PNG plots.

Frames: the estimate is assumed to be in the lidar frame already (T_world_lidar, as the pipeline
writes it). KITTI ground truth is in the left camera (cam0) frame; with calib_path it is moved to
the lidar frame as T_world_lidar(i) = inv(Tr) @ P_i @ Tr. Without calib both are compared as given.

Pairing: each file is KITTI (12 numbers per line) or TUM (stamp + 7), told by its columns unless a
format is forced, and the two may differ. When both carry stamps (TUM, or KITTI ground truth with
its times file) poses are paired by nearest stamp; otherwise line by line, estimate line k with
ground-truth line start + k, where start is the --start the run was made with (loops.csv numbers
frames the same way: input scan positions).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidar_slam.errors import InputError
from lidar_slam.eval import metrics
from lidar_slam.geometry import from_xyz_quat, inverse
from lidar_slam.io.atomic import atomic_path, write_text_atomic
from lidar_slam.io.trajectory import (
    camera_to_lidar_poses,
    read_kitti_calib_tr,
    read_kitti_poses,
    read_times,
    read_tum,
)

log = logging.getLogger(__name__)

# Optional loops.csv columns holding the verified T_match_query (translation m, quaternion xyzw).
LOOP_POSE_COLUMNS = ("x", "y", "z", "qx", "qy", "qz", "qw")  # as loops.csv writes them


@dataclass(frozen=True)
class Associated:
    """Estimate and GT poses paired frame by frame; est_rows[k] is the estimate row of pair k,
    frames[k] its input scan position (est_rows + the run's start); `pairing` says how."""

    est: np.ndarray
    gt: np.ndarray
    est_rows: np.ndarray
    frames: np.ndarray
    pairing: str


@dataclass(frozen=True)
class Trajectory:
    """Poses (K, 4, 4) of a trajectory file, with stamps (K,) in s when the file has them."""

    poses: np.ndarray
    stamps: np.ndarray | None
    fmt: str


@dataclass(frozen=True)
class AcceptedLoops:
    """Accepted loops from loops.csv as frame indices, with T_match_query when the file has it."""

    pairs: np.ndarray
    T_match_query: np.ndarray | None
    n_rows: int


def _check_finite(path: str | Path, poses: np.ndarray) -> None:
    if not np.all(np.isfinite(poses)):
        raise InputError(path, "pose file contains NaN or infinite values")


def trajectory_format(path: str | Path) -> str:
    """'kitti' (12 numbers per line) or 'tum' (8), from the first data line of the file."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "pose file does not exist")
    try:
        with p.open() as fh:
            line = next((ln for ln in fh if ln.strip() and not ln.startswith("#")), "")
    except UnicodeDecodeError:
        raise InputError(p, "not a text pose file (KITTI or TUM lines); a recording or a "
                            "binary file?") from None
    except OSError as exc:
        raise InputError(p, f"unreadable pose file ({exc.strerror or exc})") from exc
    n = len(line.replace(",", " ").split())
    if n == 12:
        return "kitti"
    if n == 8:
        return "tum"
    if not line:
        raise InputError(p, "pose file is empty")
    raise InputError(p, f"{n} numbers per line: neither KITTI (12) nor TUM (8: stamp tx ty tz "
                        f"qx qy qz qw)")


def read_trajectory(path: str | Path, fmt: str = "auto",
                    times_path: str | Path | None = None) -> Trajectory:
    """A KITTI or TUM file (fmt 'auto': told by its columns); times_path gives a KITTI file the
    stamps of its lines (one per line, as KITTI's times.txt). A folder is an input `run` reads
    (a dataset's sequence, a KITTI sequence...): its reader's ground truth, T_world_lidar at the
    scan stamps."""
    if Path(path).is_dir():
        return input_ground_truth(path)
    fmt = trajectory_format(path) if fmt == "auto" else fmt
    if fmt == "kitti":
        poses, stamps = read_kitti_poses(path), None
    elif fmt == "tum":
        stamps, poses = read_tum(path)
    else:
        raise InputError(path, f"unknown trajectory format {fmt!r} (auto, kitti or tum)")
    if times_path is not None and stamps is None:
        stamps = read_times(times_path)
        if stamps.ndim != 1 or len(stamps) != len(poses):
            raise InputError(times_path, f"{len(stamps)} stamps for the {len(poses)} poses of "
                                         f"{path}")
    _check_finite(path, poses)
    return Trajectory(poses, stamps, fmt)


def input_ground_truth(path: str | Path) -> Trajectory:
    """The ground truth the reader of an input folder finds (lidar frame, at the scan stamps),
    without the scans it does not reach; one InputError when it finds none."""
    from lidar_slam.io.sources import open_source

    if (Path(path) / "poses_kitti.txt").is_file() and (Path(path) / "summary.json").is_file():
        raise InputError(path, "a run folder, not an input: give its poses_kitti.txt")
    source = open_source(path)
    if source.ground_truth is None:
        raise InputError(path, f"no ground truth found for this {source.kind} input (see the "
                               "README's inputs table for where each layout keeps it)")
    covered = np.isfinite(source.ground_truth).all(axis=(1, 2))
    if covered.sum() < 2:
        raise InputError(path, f"the ground truth reaches {int(covered.sum())} of its scans")
    stamps = np.asarray(source.stamps, dtype=np.float64)
    return Trajectory(source.ground_truth[covered], stamps[covered], "input")


def load_associated(est_path: str | Path, gt_path: str | Path, fmt: str = "auto",
                    start: int | None = None, gt_times: str | Path | None = None,
                    max_time_diff_s: float = 0.01) -> Associated:
    """Read both trajectories and pair them: by nearest stamp (within max_time_diff_s) when both
    have stamps, else line by line from ground-truth line `start` (the run's --start)."""
    est_t = read_trajectory(est_path, fmt)
    gt_t = read_trajectory(gt_path, fmt, gt_times)
    offset = start or 0
    if est_t.stamps is not None and gt_t.stamps is not None:
        rows, gt_rows = _associate(est_t.stamps, gt_t.stamps, max_time_diff_s)
        if len(rows) < 2:
            raise InputError(est_path, f"only {len(rows)} stamps match {gt_path} within "
                                       f"{max_time_diff_s} s")
        log.info("associated %d of %d estimated poses with ground truth", len(rows),
                 len(est_t.poses))
        pairing = f"by stamp ({len(rows)} of {len(est_t.poses)} estimated poses)"
        est, gt = est_t.poses[rows], gt_t.poses[gt_rows]
    else:
        est, n_gt = est_t.poses, len(gt_t.poses)
        if start is None and len(est) != n_gt:
            raise InputError(est_path, f"{len(est)} poses but the ground truth {gt_path} has "
                                       f"{n_gt}; line-by-line files must match, or pass --start "
                                       f"N for a run made with --start N / --n-scans")
        if offset + len(est) > n_gt:
            raise InputError(est_path, f"{len(est)} poses from ground-truth line {offset} need "
                                       f"{offset + len(est)} lines; {gt_path} has {n_gt}")
        rows = np.arange(len(est))
        gt = gt_t.poses[offset:offset + len(est)]
        pairing = f"line by line (ground-truth lines {offset}..{offset + len(est) - 1})"
    if len(est) < 2:
        raise InputError(est_path, f"{len(est)} pose(s); the metrics need at least 2")
    return Associated(est, gt, rows, rows + offset, pairing)


def _associate(t_est: np.ndarray, t_gt: np.ndarray, max_diff_s: float) -> tuple[np.ndarray,
                                                                                   np.ndarray]:
    """Rows (est, gt) of nearest stamps within max_diff_s, each GT stamp used at most once."""
    order = np.argsort(t_gt)
    ts = t_gt[order]
    pos = np.clip(np.searchsorted(ts, t_est), 1, max(len(ts) - 1, 1))
    left, right = ts[pos - 1], ts[np.minimum(pos, len(ts) - 1)]
    nearest = np.where(np.abs(t_est - left) <= np.abs(t_est - right), pos - 1, pos)
    nearest = np.minimum(nearest, len(ts) - 1)
    ok = np.abs(ts[nearest] - t_est) <= max_diff_s
    est_rows = np.flatnonzero(ok)
    gt_rows = order[nearest[ok]]
    _, first = np.unique(gt_rows, return_index=True)
    keep = np.sort(first)
    return est_rows[keep], gt_rows[keep]


def truthy(value: str) -> bool:
    """Whether a loops.csv flag (accepted, ...) says yes: 1 / true / yes / y, any case."""
    return value.strip().lower() in ("1", "true", "yes", "y")


def read_loops_csv(path: str | Path) -> AcceptedLoops:
    """Accepted rows of loops.csv (columns query_frame, match_frame, ..., accepted); a row
    that is short, long or not numbers where numbers are due is refused with its line."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "loops file does not exist")
    try:
        with p.open(newline="") as f:
            reader = csv.DictReader(f)
            reader.fieldnames = [h.strip() for h in reader.fieldnames or ()]  # "a, b" as "a,b"
            rows = [(reader.line_num, r) for r in reader]
            header = set(reader.fieldnames)
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(p, f"unreadable loops CSV ({exc})") from exc
    need = {"query_frame", "match_frame", "accepted"}
    if not need <= header:
        raise InputError(p, f"missing columns {sorted(need - header)}")
    has_pose = set(LOOP_POSE_COLUMNS) <= header
    pairs, poses = [], []
    for line, r in rows:
        if None in r or None in r.values():  # DictReader's marks of a long / short row
            n = sum(v is not None for k, v in r.items() if k is not None) + len(r.get(None, ()))
            raise InputError(p, f"line {line}: {n} columns, the header has "
                                f"{len(reader.fieldnames)}")
        try:
            if not truthy(r["accepted"]):
                continue
            pairs.append([int(r["query_frame"]), int(r["match_frame"])])
            if has_pose:
                v = np.array([float(r[c]) for c in LOOP_POSE_COLUMNS])
                if not np.isfinite(v).all() or not np.linalg.norm(v[3:]) > 0:
                    raise ValueError("a pose that is not finite, or a zero quaternion")
                poses.append(from_xyz_quat(v))
        except (TypeError, ValueError) as exc:
            raise InputError(p, f"line {line}: bad value in an accepted row ({exc})") from exc
    pairs = np.array(pairs, dtype=np.int64).reshape(-1, 2)
    T = np.array(poses).reshape(-1, 4, 4) if has_pose else None
    return AcceptedLoops(pairs, T, len(rows))


def _loop_metrics(loops_csv: str | Path, assoc: Associated, revisit_gap: int
                  ) -> tuple[dict, np.ndarray, np.ndarray]:
    """Loop precision/recall entries; also the scored pairs (positions in assoc) and correctness.
    A revisit is a return within 5 m to a place passed more than revisit_gap frames before."""
    loops = read_loops_csv(loops_csv)
    to_pos = {int(f): k for k, f in enumerate(assoc.frames)}
    keep = np.array([int(q) in to_pos and int(m) in to_pos for q, m in loops.pairs], dtype=bool)
    n_unmatched = int((~keep).sum())
    if n_unmatched:
        log.warning("%d accepted loops reference frames without ground truth; not scored",
                    n_unmatched)
    pairs = np.array([[to_pos[int(q)], to_pos[int(m)]] for q, m in loops.pairs[keep]],
                     dtype=np.int64).reshape(-1, 2)
    if loops.T_match_query is not None:
        T = loops.T_match_query[keep]
        source = "loops.csv T_match_query"
    else:
        # No measured relative pose in the file: judge the final trajectory between the frames.
        T = inverse(assoc.est[pairs[:, 1]]) @ assoc.est[pairs[:, 0]]
        source = "estimated trajectory"
    s = metrics.loop_precision_recall(pairs, T, assoc.gt, min_frame_gap=revisit_gap)
    out = {
        "loop_pose_source": source,
        "loops_proposed": loops.n_rows,
        "loops_accepted": s.n_accepted,
        "loops_correct": s.n_correct,
        "loops_unscored": n_unmatched,
        "loop_precision": s.precision,
        "loop_recall_events": s.recall_events,
        "loop_recall_frames": s.recall_frames,
        "revisit_events": s.n_revisit_events,
        "revisit_events_found": s.n_revisit_events_found,
        "revisit_frames": s.n_revisit_frames,
        "revisit_frames_covered": s.n_revisit_frames_covered,
        "revisit_gap_frames": revisit_gap,
    }
    return out, pairs, s.correct


def run_eval(est_path: str | Path, gt_path: str | Path, fmt: str = "auto",
             calib_path: str | Path | None = None, out_dir: str | Path | None = None,
             loops_csv: str | Path | None = None, start: int | None = None,
             gt_times: str | Path | None = None, revisit_gap: int = 100,
             gt_label: str | None = None) -> dict:
    """All metrics of one trajectory (t_err %, r_err deg/100 m, ATE m, RPE m/deg, loops).

    start: the run's --start (ground-truth line of the estimate's first pose, and the offset of
    loops.csv frame numbers); gt_times: stamps of a KITTI ground truth, to pair it with a TUM
    estimate by time; revisit_gap: frames between two passes for loop recall to count a revisit;
    gt_label: what GT is called in the plots and metrics.json (default: truth_label(gt_path)).
    """
    if out_dir is not None and Path(out_dir).exists() and not Path(out_dir).is_dir():
        raise InputError(out_dir, "--out is a file, not a folder")
    assoc = load_associated(est_path, gt_path, fmt, start=start, gt_times=gt_times)
    if calib_path is not None:
        gt = camera_to_lidar_poses(assoc.gt, read_kitti_calib_tr(calib_path))
        assoc = dataclasses.replace(assoc, gt=gt)
    est, gt = assoc.est, assoc.gt
    out = trajectory_metrics(est, gt)
    out["gt_frame"] = "lidar (GT moved with calib Tr)" if calib_path else "as given"
    out["pairing"] = assoc.pairing
    out["gt_label"] = gt_label = gt_label or truth_label(gt_path)
    pairs, correct = np.zeros((0, 2), dtype=np.int64), np.zeros(0, dtype=bool)
    if loops_csv is not None:
        loop_out, pairs, correct = _loop_metrics(loops_csv, assoc, revisit_gap)
        out.update(loop_out)
    if out_dir is not None:
        d = Path(out_dir)
        d.mkdir(parents=True, exist_ok=True)
        if (d / "metrics.json").is_file():  # replaced silently before, beside a stale plot
            log.warning("%s: replacing the evaluation there (metrics.json and its plots)", d)
        write_text_atomic(d / "metrics.json", json.dumps(out, indent=2) + "\n")
        write_plots(d, est, gt, pairs, correct, gt_label)
    return out


def trajectory_metrics(est: np.ndarray, gt: np.ndarray, warn: bool = True) -> dict:
    """KITTI drift (t_err %, r_err deg/100 m; None under 100 m of path), ATE (m) and RPE (m, deg)
    of est against gt, both (K, 4, 4) and paired frame by frame; warn: log the frame mix-up
    warning (it is in the result either way)."""
    drift = metrics.kitti_drift(est, gt)
    a = metrics.ate(est, gt)
    r = metrics.rpe(est, gt)
    out: dict = {
        "t_err_pct": drift.t_err_pct,
        "r_err_deg_per_100m": drift.r_err_deg_per_100m,
        "ate_rmse_m": a.rmse_m,
        "rpe_trans_m_mean": r.trans_m_mean,
        "rpe_rot_deg_mean": r.rot_deg_mean,
        "note": drift.note,
        "kitti_segments": drift.n_segments,
        "ate_mean_m": a.mean_m,
        "ate_median_m": a.median_m,
        "ate_max_m": a.max_m,
        "rpe_trans_m_max": r.trans_m_max,
        "rpe_rot_deg_max": r.rot_deg_max,
        "n_frames": len(est),
        "path_length_m": drift.gt_path_length_m,
        "est_path_length_m": float(metrics.path_distances_m(est)[-1]),
        "drift_by_length": [
            {"length_m": b.length_m, "t_err_pct": b.t_err_pct,
             "r_err_deg_per_100m": b.r_err_deg_per_100m, "segments": b.n_segments}
            for b in drift.by_length
        ],
    }
    mean_step_m = out["path_length_m"] / (len(gt) - 1)
    if mean_step_m > 0 and r.trans_m_mean > 0.5 * mean_step_m:
        # Per-frame errors as large as the motion itself: almost always a frame mix-up (camera vs
        # lidar, a missing or extra calib), not a bad estimate.
        out["warning"] = (f"per-frame RPE {r.trans_m_mean:.3f} m vs mean step {mean_step_m:.3f} m:"
                          " estimate and ground truth are probably in different sensor frames")
        if warn:
            log.warning(out["warning"])
    return out


def run_summary_metrics(est: np.ndarray, gt_world: np.ndarray) -> dict:
    """A run's summary.json figures against ground truth: trajectory_metrics' RPE means and ATE
    RMSE, and the end drift (% of the path), of est (K, 4, 4, frame 0 = identity) against
    gt_world (K, 4, 4) re-expressed in its first frame."""
    gt = inverse(gt_world[0]) @ gt_world
    if len(est) < 2:
        return {"ate_rmse_m": metrics.ate(est, gt).rmse_m}
    m = trajectory_metrics(est, gt, warn=False)
    out = {"rpe_trans_m_mean": m["rpe_trans_m_mean"], "rpe_rot_deg_mean": m["rpe_rot_deg_mean"]}
    drift = metrics.end_drift_pct(est, gt)
    if drift is not None:
        out["end_drift_pct"] = drift
    out["ate_rmse_m"] = m["ate_rmse_m"]
    return out


GROUND_TRUTH, REFERENCE = "ground truth", "reference"
# What a data set's README says of poses that are an odometry or another estimate.
_NOT_TRUTH = re.compile(r"not\s+(?:survey\s+)?ground[-\s]truth", re.IGNORECASE)


def truth_label(gt_path: str | Path) -> str:
    """What to call the trajectory scored against, in plots and tables: "reference" where the
    README beside it (or one folder up; for a dataset folder given as GT, in it) says it is not
    ground truth, else "ground truth"."""
    path = Path(gt_path).resolve()
    folder = path if path.is_dir() else path.parent
    for where in (folder, folder.parent):
        for name in ("README.txt", "README.md", "README"):
            try:
                text = (where / name).read_text(errors="replace")
            except OSError:
                continue
            return REFERENCE if _NOT_TRUTH.search(text) else GROUND_TRUTH
    return GROUND_TRUTH


def write_plots(out_dir: Path, est: np.ndarray, gt: np.ndarray, pairs: np.ndarray | None = None,
                correct: np.ndarray | None = None, gt_label: str = GROUND_TRUTH) -> None:
    """The top view (with the scored loops), error against distance and, with 100 m of path or
    more, drift against segment length, as PNGs in out_dir; gt_label names the trajectory
    scored against ("ground truth" or "reference")."""
    pairs = np.zeros((0, 2), dtype=np.int64) if pairs is None else pairs
    correct = np.zeros(0, dtype=bool) if correct is None else correct
    plot_top_view(out_dir / "trajectory_top.png", est, gt, pairs, correct, gt_label)
    plot_error_vs_distance(out_dir / "error_vs_distance.png", metrics.error_vs_distance(est, gt),
                           gt_label)
    drift = metrics.kitti_drift(est, gt)
    if drift.by_length:
        plot_drift_vs_length(out_dir / "drift_vs_length.png", drift.by_length)
    else:  # an earlier evaluation's would stand beside this one's metrics
        (out_dir / "drift_vs_length.png").unlink(missing_ok=True)


# ----------------------------------------------------------------------------------- plots


def save_png(fig, path: Path) -> None:
    """fig written to path as a PNG (120 dpi), atomically."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, format="png")


def _top_axes(gt: np.ndarray) -> tuple[int, int]:
    """The two axes of largest GT spread: x-y for lidar frames, x-z for KITTI camera frames."""
    keep = np.sort(np.argsort(np.ptp(gt[:, :3, 3], axis=0))[1:])
    return int(keep[0]), int(keep[1])


def plot_top_view(path: Path, est: np.ndarray, gt: np.ndarray, pairs: np.ndarray,
                  correct: np.ndarray, gt_label: str = GROUND_TRUTH) -> None:
    """Top view of GT and estimate (started at the GT's first pose), accepted loops as edges."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    est_w = gt[0] @ inverse(est[0]) @ est
    i, j = _top_axes(gt)
    fig = Figure(figsize=(7, 7))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.plot(gt[:, i, 3], gt[:, j, 3], "k-", lw=1.2, label=gt_label)
    ax.plot(est_w[:, i, 3], est_w[:, j, 3], "b-", lw=1.0, label="estimate")
    for ok, colour, name in ((True, "g", "correct loop"), (False, "r", "wrong loop")):
        sel = pairs[correct == ok]
        for n, (q, m) in enumerate(sel):
            ax.plot(est_w[[q, m], i, 3], est_w[[q, m], j, 3], colour + "-", lw=0.8,
                    label=f"{name} ({len(sel)})" if n == 0 else None)
    ax.plot(gt[0, i, 3], gt[0, j, 3], "ko", label="start")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(f"{'xyz'[i]} [m]")
    ax.set_ylabel(f"{'xyz'[j]} [m]")
    ax.legend(loc="best", fontsize=8)
    ax.set_title(f"top view (estimate started at the {gt_label}'s first pose)")
    save_png(fig, path)


def plot_run_top_view(path: Path, poses: np.ndarray, map_ply: Path | None,
                      bins: int = 600) -> None:
    """Top view (x-y of the map frame) of a run without ground truth: the map's point density
    (map_ply, read a chunk at a time) and the trajectory on it, as `eval`'s top view."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    xy = poses[:, :2, 3]
    rows = _ply_rows(map_ply) if map_ply is not None and map_ply.is_file() else None
    fig = Figure(figsize=(7, 7))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    draw_map_density(ax, rows, xy, bins)
    ax.plot(xy[:, 0], xy[:, 1], "b-", lw=1.0, label=f"trajectory ({len(xy)} frames)")
    ax.plot(xy[0, 0], xy[0, 1], "ko", label="start")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(loc="best", fontsize=8)
    ax.set_title("top view: trajectory on the map (grey: map points per cell, log)")
    save_png(fig, path)


def draw_map_density(ax, rows: np.ndarray | None, xy: np.ndarray, bins: int = 600) -> None:
    """Grey, log scale: map points (rows (N, >=2), x-y in the map frame, read a chunk at a
    time) per cell of a square grid over them and the trajectory points xy (M, 2)."""
    from matplotlib.colors import LogNorm

    if rows is None or len(rows) == 0:
        return
    lo = np.minimum(xy.min(axis=0), rows[:, :2].min(axis=0))
    hi = np.maximum(xy.max(axis=0), rows[:, :2].max(axis=0))
    side = float(max(hi - lo)) or 1.0
    edges = [np.linspace(lo[k], lo[k] + side, bins + 1) for k in (0, 1)]
    counts = np.zeros((bins, bins))
    for start in range(0, len(rows), 1 << 20):  # bounded memory on a long run's map
        chunk = np.asarray(rows[start:start + (1 << 20), :2], dtype=np.float64)
        counts += np.histogram2d(chunk[:, 0], chunk[:, 1], bins=edges)[0]
    if not counts.any():
        return
    # From the median occupied cell up: floors and ceilings (few points per cell) light,
    # walls and poles (many, stacked) dark.
    floor = float(np.median(counts[counts > 0]))
    ax.imshow(np.where(counts > 0, counts, np.nan).T, origin="lower", cmap="Greys",
              norm=LogNorm(vmin=floor, vmax=max(2.0 * floor, float(counts.max())), clip=True),
              extent=(edges[0][0], edges[0][-1], edges[1][0], edges[1][-1]),
              interpolation="nearest")


def _ply_rows(path: Path) -> np.ndarray:
    """The float32 vertex rows of a binary PLY such as the run's map.ply, memory-mapped."""
    with open(path, "rb") as fh:
        header = []
        while not header or header[-1] != "end_header":
            line = fh.readline()
            if not line:
                return np.zeros((0, 3), np.float32)
            header.append(line.decode("ascii", "replace").strip())
        start = fh.tell()
    n = int(next((h.split()[2] for h in header if h.startswith("element vertex")), 0))
    ncol = sum(h.startswith("property float") for h in header)
    if n == 0 or ncol < 3:
        return np.zeros((0, 3), np.float32)
    return np.memmap(path, dtype="<f4", mode="r", offset=start, shape=(n, ncol))


def plot_error_vs_distance(path: Path, series: metrics.ErrorVsDistance,
                           gt_label: str = GROUND_TRUTH) -> None:
    """Translation error (m) from frame 0 against GT distance travelled (m)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 4))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.plot(series.distance_m, series.trans_err_m, "b-", lw=1.0)
    ax.set_xlabel(f"distance travelled along the {gt_label} [m]")
    ax.set_ylabel("translation error [m]")
    ax.set_title("position error, both trajectories expressed in their first pose")
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    save_png(fig, path)


def plot_drift_vs_length(path: Path, by_length) -> None:
    """The KITTI devkit's figure: translation (%) and rotation (deg/100 m) drift averaged over
    the segments of each length (100 .. 800 m)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    lengths = [b.length_m for b in by_length]
    fig = Figure(figsize=(9, 3.8))
    FigureCanvasAgg(fig)
    for k, (values, label) in enumerate((
            ([b.t_err_pct for b in by_length], "translation error [%]"),
            ([b.r_err_deg_per_100m for b in by_length], "rotation error [deg/100 m]"))):
        ax = fig.add_subplot(1, 2, k + 1)
        ax.plot(lengths, values, "bs-", lw=1.0, ms=4)
        ax.set_xlabel("path length [m]")
        ax.set_ylabel(label)
        ax.set_ylim(bottom=0)
        ax.grid(True, alpha=0.3)
    fig.suptitle("drift against segment length (KITTI devkit segments)")
    fig.tight_layout()
    save_png(fig, path)


# ----------------------------------------------------------------------------------- table

_UNITS = (
    ("_deg_per_100m", "deg/100 m"),
    ("_pct", "%"),
    ("_deg_mean", "deg"),
    ("_deg_max", "deg"),
    ("_m_mean", "m"),
    ("_m_max", "m"),
    ("_m", "m"),
)
_LABELS = {
    "t_err_pct": "KITTI t_err",
    "r_err_deg_per_100m": "KITTI r_err",
    "ate_rmse_m": "ATE RMSE",
    "ate_mean_m": "ATE mean",
    "ate_median_m": "ATE median",
    "ate_max_m": "ATE max",
    "rpe_trans_m_mean": "RPE translation mean (per frame)",
    "rpe_trans_m_max": "RPE translation max (per frame)",
    "rpe_rot_deg_mean": "RPE rotation mean (per frame)",
    "rpe_rot_deg_max": "RPE rotation max (per frame)",
    "path_length_m": "GT path length",
    "est_path_length_m": "estimated path length",
    "n_frames": "frames",
    "kitti_segments": "KITTI segments",
}


def _unit(key: str) -> str:
    for suffix, unit in _UNITS:
        if key.endswith(suffix):
            return unit
    return ""


def format_table(m: dict) -> str:
    """The metrics as aligned 'name  value unit' lines; every number carries its unit."""
    lines = []
    for key in _LABELS:
        if key not in m:
            continue
        value, unit = m[key], _unit(key)
        if value is None:
            text = "n/a"
        elif isinstance(value, int):
            text = f"{value:d}"
        else:
            digits = 4 if unit in ("m", "deg") and abs(value) < 1 else 3
            text = f"{value:.{digits}f} {unit}".rstrip()
        lines.append(f"{_LABELS[key]:<34} {text}")
    for key in ("gt_label", "pairing", "note", "warning"):
        if m.get(key):
            lines.append(f"{key:<34} {m[key]}")
    if "loops_accepted" in m:
        counts = f"{m['loops_accepted']} / {m['loops_correct']} (of {m['loops_proposed']} proposed)"
        lines.append(f"{'loops accepted / correct':<34} {counts}")
        for key, label, num, den in (
            ("loop_precision", "loop precision", "loops_correct", "loops_accepted"),
            ("loop_recall_events", "loop recall (revisit events)", "revisit_events_found",
             "revisit_events"),
            ("loop_recall_frames", "loop recall (revisit frames)", "revisit_frames_covered",
             "revisit_frames"),
        ):
            v = m[key]
            text = "n/a" if v is None else f"{100 * v:.1f} %"
            lines.append(f"{label:<34} {text} ({m[num]} / {m[den]})")
    return "\n".join(lines)
