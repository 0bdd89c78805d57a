"""Trajectory metrics: KITTI drift, ATE, RPE, drift vs distance, loop precision/recall. Pure NumPy.

Poses are (K, 4, 4) float64 arrays T_world_sensor; frame i of the estimate corresponds to frame i of
the ground truth (association is the caller's job, see evaluate.py). No I/O, no plotting.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from lidar_slam.geometry import inverse, quat_from_matrix

# The official KITTI odometry devkit (evaluate_odometry.cpp): segment lengths along the ground truth
# and a segment starting every 10 frames (every second at 10 Hz).
KITTI_LENGTHS_M = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
KITTI_STEP_FRAMES = 10


def _check_pair(poses_est: np.ndarray, poses_gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    est = np.asarray(poses_est, dtype=np.float64)
    gt = np.asarray(poses_gt, dtype=np.float64)
    if est.ndim != 3 or est.shape[1:] != (4, 4) or gt.ndim != 3 or gt.shape[1:] != (4, 4):
        raise ValueError(f"poses must be (K, 4, 4); got {est.shape} and {gt.shape}")
    if len(est) != len(gt):
        raise ValueError(f"estimate has {len(est)} poses, ground truth {len(gt)}")
    return est, gt


def path_distances_m(poses: np.ndarray) -> np.ndarray:
    """Cumulative distance travelled (m) at each pose, 0 at the first one (float64)."""
    steps = np.linalg.norm(np.diff(np.asarray(poses)[:, :3, 3], axis=0), axis=1)
    return np.r_[0.0, np.cumsum(steps)]


def path_length_m(poses: np.ndarray) -> float:
    """Length (m) of the polyline through the poses' positions."""
    if len(poses) < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum())


def end_drift_pct(poses_est: np.ndarray, poses_gt: np.ndarray) -> float | None:
    """Distance between the last estimated and true positions, in % of the ground truth's path
    length (None when the ground truth does not move)."""
    gt_len = path_length_m(poses_gt)
    if not gt_len > 0:
        return None
    return float(100.0 * np.linalg.norm(poses_est[-1, :3, 3] - poses_gt[-1, :3, 3]) / gt_len)


# ----------------------------------------------------------------------------------- KITTI drift


@dataclass(frozen=True)
class DriftAtLength:
    """Devkit drift averaged over the segments of one length (the devkit's *_tl / *_rl plots)."""

    length_m: float
    t_err_pct: float
    r_err_deg_per_100m: float
    n_segments: int


@dataclass(frozen=True)
class KittiDrift:
    """KITTI drift: t_err in % of distance, r_err in deg per 100 m, averaged over all segments.

    t_err_pct / r_err_deg_per_100m are None (never 0) when no segment fits; `note` then says why.
    """

    t_err_pct: float | None
    r_err_deg_per_100m: float | None
    n_segments: int
    gt_path_length_m: float
    by_length: tuple[DriftAtLength, ...] = ()
    note: str | None = None


@dataclass(frozen=True)
class KittiSegments:
    """Per-segment devkit errors: t_err in m/m, r_err in rad/m (as the devkit stores them)."""

    first_frame: np.ndarray
    last_frame: np.ndarray
    length_m: np.ndarray
    t_err: np.ndarray
    r_err: np.ndarray


def _devkit_distances_f32(poses_gt: np.ndarray) -> np.ndarray:
    """trajectoryDistances() in the devkit's float32 arithmetic (dx, dy, dz, dist are float)."""
    d = np.diff(poses_gt[:, :3, 3], axis=0).astype(np.float32)
    step = np.sqrt((d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]) + d[:, 2] * d[:, 2])
    # Sequential float32 accumulation, as dist[i] = dist[i-1] + step (ufunc.accumulate is ordered).
    return np.add.accumulate(np.r_[np.float32(0.0), step], dtype=np.float32)


def kitti_segments(poses_est: np.ndarray, poses_gt: np.ndarray,
                   devkit_float32: bool = True) -> KittiSegments:
    """Devkit segments of one sequence: 100..800 m along the GT, a start every 10 frames.

    devkit_float32=True reproduces the official C++ devkit bit for bit where it matters: distances,
    the segment end test and the per-segment errors are float32 there (r_err from acosf of a float
    trace, so rotation errors below ~0.02 deg are quantised). False does everything in float64.
    """
    est, gt = _check_pair(poses_est, poses_gt)
    n = len(gt)
    f32 = np.float32 if devkit_float32 else np.float64
    dist = _devkit_distances_f32(gt) if devkit_float32 else path_distances_m(gt)
    firsts = np.arange(0, n, KITTI_STEP_FRAMES)
    first_l, last_l, len_l = [], [], []
    for length in KITTI_LENGTHS_M:
        # lastFrameFromSegmentLength: first i >= first with dist[i] > dist[first] + len. dist is
        # non-decreasing, so that is searchsorted(..., side="right") over the whole array.
        thresh = (dist[firsts] + f32(length)).astype(f32)
        last = np.searchsorted(dist, thresh, side="right")
        ok = last < n
        first_l.append(firsts[ok])
        last_l.append(last[ok])
        len_l.append(np.full(int(ok.sum()), length))
    # Devkit order: for each first frame, lengths ascending (matters only for the float32 sum).
    first = np.concatenate(first_l)
    last = np.concatenate(last_l)
    length_m = np.concatenate(len_l)
    order = np.lexsort((length_m, first))
    first, last, length_m = first[order], last[order], length_m[order]
    if len(first) == 0:
        empty = np.zeros(0)
        return KittiSegments(first, last, length_m, empty.astype(f32), empty.astype(f32))
    # General (not rigid) inverses, as the devkit's Matrix::inv.
    d_gt = np.linalg.inv(gt[first]) @ gt[last]
    d_est = np.linalg.inv(est[first]) @ est[last]
    E = np.linalg.inv(d_est) @ d_gt
    if devkit_float32:
        a, b, c = (E[:, i, i].astype(np.float32) for i in range(3))
        cos = (0.5 * ((a + b + c).astype(np.float64) - 1.0)).astype(np.float32)
        r = np.arccos(np.clip(cos, np.float32(-1.0), np.float32(1.0)))
        t3 = E[:, :3, 3].astype(np.float32)
        t = np.sqrt((t3[:, 0] * t3[:, 0] + t3[:, 1] * t3[:, 1]) + t3[:, 2] * t3[:, 2])
        lf = length_m.astype(np.float32)
        return KittiSegments(first, last, length_m, t / lf, r / lf)
    cos = 0.5 * (np.trace(E[:, :3, :3], axis1=1, axis2=2) - 1.0)
    r = np.arccos(np.clip(cos, -1.0, 1.0))
    t = np.linalg.norm(E[:, :3, 3], axis=1)
    return KittiSegments(first, last, length_m, t / length_m, r / length_m)


def _mean(values: np.ndarray, devkit_float32: bool) -> float:
    if devkit_float32:
        # saveStats(): a float running sum divided by a float count.
        total = np.add.accumulate(values.astype(np.float32), dtype=np.float32)[-1]
        return float(total / np.float32(len(values)))
    return float(np.mean(values))


def kitti_drift_pooled(sequences: Sequence[tuple[np.ndarray, np.ndarray]],
                       devkit_float32: bool = True) -> KittiDrift:
    """KITTI drift pooled over sequences [(poses_est, poses_gt), ...]: one mean over all segments.

    As the devkit's stats.txt: longer sequences weigh more because they have more segments.
    """
    segs = [kitti_segments(e, g, devkit_float32) for e, g in sequences]
    gt_len = float(sum(path_distances_m(np.asarray(g))[-1] for _, g in sequences))
    t = np.concatenate([s.t_err for s in segs]) if segs else np.zeros(0)
    r = np.concatenate([s.r_err for s in segs]) if segs else np.zeros(0)
    lengths = np.concatenate([s.length_m for s in segs]) if segs else np.zeros(0)
    if len(t) == 0:
        note = (f"no KITTI segment: the ground truth path is {gt_len:.1f} m, the shortest segment "
                f"needs more than {KITTI_LENGTHS_M[0]:.0f} m; t_err/r_err undefined")
        return KittiDrift(None, None, 0, gt_len, (), note)
    by_length = []
    for length in KITTI_LENGTHS_M:
        sel = lengths == length
        # The devkit plots a length only with at least 3 segments.
        if sel.sum() >= 3:
            by_length.append(DriftAtLength(
                length, 100.0 * _mean(t[sel], devkit_float32),
                float(np.degrees(_mean(r[sel], devkit_float32)) * 100.0), int(sel.sum())))
    return KittiDrift(
        t_err_pct=100.0 * _mean(t, devkit_float32),
        r_err_deg_per_100m=float(np.degrees(_mean(r, devkit_float32)) * 100.0),
        n_segments=int(len(t)),
        gt_path_length_m=gt_len,
        by_length=tuple(by_length),
    )


def kitti_drift(poses_est: np.ndarray, poses_gt: np.ndarray,
                devkit_float32: bool = True) -> KittiDrift:
    """KITTI drift of one sequence (t_err %, r_err deg/100 m), as the official devkit."""
    return kitti_drift_pooled([(poses_est, poses_gt)], devkit_float32)


# ------------------------------------------------------------------------------------------- ATE


@dataclass(frozen=True)
class AteResult:
    """Absolute trajectory error (m) after aligning the estimate onto the GT with T_gt_est."""

    rmse_m: float
    mean_m: float
    median_m: float
    max_m: float
    errors_m: np.ndarray
    T_gt_est: np.ndarray


def _umeyama(points_src: np.ndarray, points_dst: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Umeyama 1991, dst ~ c R src + t: R, the two means, and the similarity's scale c (nan
    when src does not spread)."""
    x = np.asarray(points_src, dtype=np.float64)
    y = np.asarray(points_dst, dtype=np.float64)
    mx, my = x.mean(axis=0), y.mean(axis=0)
    cov = (y - my).T @ (x - mx) / len(x)
    u, d, vt = np.linalg.svd(cov)
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0.0:
        s[2, 2] = -1.0
    var = float(((x - mx) ** 2).sum()) / len(x)
    c = float((d * np.diag(s)).sum()) / var if var > 0.0 else float("nan")
    return u @ s @ vt, mx, my, c


def umeyama_rigid(points_src: np.ndarray, points_dst: np.ndarray) -> np.ndarray:
    """Least-squares rigid T_dst_src (no scale) with dst ~ R src + t (Umeyama 1991, as evo)."""
    R, mx, my, _ = _umeyama(points_src, points_dst)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = my - R @ mx
    return T


def scale_excess(poses_est: np.ndarray, poses_gt: np.ndarray) -> float:
    """How much larger the estimate is than the truth (a fraction: 0.01 = 1 % too long), from
    the scale of the least-squares similarity between their positions (Umeyama 1991): the
    error a rigid ATE leaves in, which a steady over- or under-estimate of motion gives."""
    est, gt = _check_pair(poses_est, poses_gt)
    c = _umeyama(est[:, :3, 3], gt[:, :3, 3])[3] if len(est) >= 3 else float("nan")
    if not c > 0.0:
        raise ValueError("scale of a trajectory that does not move")
    return 1.0 / c - 1.0


def ate(poses_est: np.ndarray, poses_gt: np.ndarray, align: bool = True) -> AteResult:
    """Translation ATE (m) after a rigid Umeyama alignment of positions; equals `evo_ape -a`."""
    est, gt = _check_pair(poses_est, poses_gt)
    if len(est) == 0:
        raise ValueError("ATE of an empty trajectory")
    T = umeyama_rigid(est[:, :3, 3], gt[:, :3, 3]) if align else np.eye(4)
    p = est[:, :3, 3] @ T[:3, :3].T + T[:3, 3]
    e = np.linalg.norm(gt[:, :3, 3] - p, axis=1)
    return AteResult(float(np.sqrt(np.mean(e**2))), float(e.mean()), float(np.median(e)),
                     float(e.max()), e, T)


# ------------------------------------------------------------------------------------------- RPE


def _relative_error(T_ref: np.ndarray, T_est: np.ndarray) -> np.ndarray:
    """inv(T_ref) @ T_est with the rigid (transpose) inverse, as evo."""
    return inverse(T_ref) @ T_est


def _angle_deg(T: np.ndarray) -> np.ndarray:
    """Rotation angle (deg) of the nearest rotation: file rotations are only orthonormal to ~1e-7,
    which makes arccos((trace - 1) / 2) wrong by ~1% at the 0.05 deg of a frame-to-frame step,
    and geometry.rotation_angle_deg (skew part and trace, for rotations orthonormal to machine
    precision) by ~1e-7 relative; the quaternion of the nearest rotation is right to 1e-9."""
    q = quat_from_matrix(T[..., :3, :3])
    return np.degrees(2.0 * np.arctan2(np.linalg.norm(q[..., :3], axis=-1), q[..., 3]))


@dataclass(frozen=True)
class RpeResult:
    """Relative pose error over `delta` frames: translation (m) and rotation (deg) per pair."""

    delta: int
    trans_m: np.ndarray
    rot_deg: np.ndarray
    trans_m_mean: float
    trans_m_max: float
    trans_m_rmse: float
    rot_deg_mean: float
    rot_deg_max: float


def rpe(poses_est: np.ndarray, poses_gt: np.ndarray, delta: int = 1) -> RpeResult:
    """RPE as evo: E_i = inv(inv(gt_i) gt_i+d) inv(est_i) est_i+d; |t(E)| m, angle(E) deg."""
    est, gt = _check_pair(poses_est, poses_gt)
    if delta < 1 or len(est) <= delta:
        raise ValueError(f"RPE needs more than delta={delta} poses, got {len(est)}")
    E = _relative_error(inverse(gt[:-delta]) @ gt[delta:], inverse(est[:-delta]) @ est[delta:])
    t = np.linalg.norm(E[:, :3, 3], axis=1)
    r = _angle_deg(E)
    return RpeResult(delta, t, r, float(t.mean()), float(t.max()), float(np.sqrt(np.mean(t**2))),
                     float(r.mean()), float(r.max()))


# ------------------------------------------------------------------------- drift vs distance


@dataclass(frozen=True)
class ErrorVsDistance:
    """Position error (m) of each frame against GT distance travelled (m), both from frame 0."""

    distance_m: np.ndarray
    trans_err_m: np.ndarray


def error_vs_distance(poses_est: np.ndarray, poses_gt: np.ndarray) -> ErrorVsDistance:
    """Odometry drift curve: both trajectories re-expressed in their first pose, no alignment."""
    est, gt = _check_pair(poses_est, poses_gt)
    est0 = inverse(est[0]) @ est
    gt0 = inverse(gt[0]) @ gt
    err = np.linalg.norm(est0[:, :3, 3] - gt0[:, :3, 3], axis=1)
    return ErrorVsDistance(path_distances_m(gt), err)


# ----------------------------------------------------------------------------------------- loops


@dataclass(frozen=True)
class LoopScore:
    """Accepted loops scored against the GT.

    precision = n_correct / n_accepted. A revisit frame j has a GT position within max_dist_m of
    some frame i < j - min_frame_gap. A revisit event is a run of revisit frames with gaps of at
    most event_gap_frames. A correct loop whose frames are more than min_frame_gap apart covers
    revisit frame j when its later frame is within event_gap_frames of j.
    recall_frames = covered revisit frames / revisit frames; recall_events = events with at least
    one covered frame / events. Ratios are None when their denominator is 0.
    """

    n_accepted: int
    n_correct: int
    precision: float | None
    n_revisit_frames: int
    n_revisit_frames_covered: int
    recall_frames: float | None
    n_revisit_events: int
    n_revisit_events_found: int
    recall_events: float | None
    correct: np.ndarray
    trans_err_m: np.ndarray
    rot_err_deg: np.ndarray


def revisit_frames(poses_gt: np.ndarray, min_frame_gap: int = 100,
                   max_dist_m: float = 5.0) -> np.ndarray:
    """(K,) bool: frame j is within max_dist_m (GT) of some frame i < j - min_frame_gap."""
    p = np.asarray(poses_gt)[:, :3, 3]
    n = len(p)
    out = np.zeros(n, dtype=bool)
    chunk = 512
    for start in range(min_frame_gap + 1, n, chunk):
        js = np.arange(start, min(start + chunk, n))
        i_max = js[-1] - min_frame_gap  # candidates i < j - gap, i.e. i <= j - gap - 1
        d2 = ((p[js, None, :] - p[None, :i_max, :]) ** 2).sum(axis=2)
        allowed = np.arange(i_max)[None, :] < (js - min_frame_gap)[:, None]
        out[js] = ((d2 <= max_dist_m**2) & allowed).any(axis=1)
    return out


def _events(frames: np.ndarray, gap: int) -> list[tuple[int, int]]:
    """Runs (first, last) of sorted frame indices split where consecutive ones differ by > gap."""
    if len(frames) == 0:
        return []
    breaks = np.flatnonzero(np.diff(frames) > gap)
    starts = np.r_[frames[0], frames[breaks + 1]]
    ends = np.r_[frames[breaks], frames[-1]]
    return list(zip(starts.tolist(), ends.tolist()))


def loop_precision_recall(pairs: np.ndarray, T_match_query_est: np.ndarray, poses_gt: np.ndarray,
                          min_frame_gap: int = 100, max_dist_m: float = 5.0,
                          max_trans_err_m: float = 1.0, max_rot_err_deg: float = 5.0,
                          event_gap_frames: int = 10) -> LoopScore:
    """Score accepted loops (query_frame, match_frame) with estimated T_match_query against GT.

    A loop is correct when inv(T_match_query_gt) @ T_match_query_est has translation <=
    max_trans_err_m and rotation <= max_rot_err_deg. See LoopScore for recall.
    """
    gt = np.asarray(poses_gt, dtype=np.float64)
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    T_est = np.asarray(T_match_query_est, dtype=np.float64).reshape(-1, 4, 4)
    if len(pairs) != len(T_est):
        raise ValueError(f"{len(pairs)} loop pairs but {len(T_est)} relative poses")
    if len(pairs) and (pairs.min() < 0 or pairs.max() >= len(gt)):
        raise ValueError(f"loop frame index outside 0..{len(gt) - 1}")
    q, m = pairs[:, 0], pairs[:, 1]
    E = _relative_error(inverse(gt[m]) @ gt[q], T_est)
    t_err = np.linalg.norm(E[:, :3, 3], axis=1)
    r_err = _angle_deg(E)
    correct = (t_err <= max_trans_err_m) & (r_err <= max_rot_err_deg)

    revisit = np.flatnonzero(revisit_frames(gt, min_frame_gap, max_dist_m))
    closing = correct & (np.abs(q - m) > min_frame_gap)
    later = np.maximum(q, m)[closing]
    covered = np.zeros(len(revisit), dtype=bool)
    if len(later):
        covered = (np.abs(revisit[:, None] - later[None, :]) <= event_gap_frames).any(axis=1)
    events = _events(revisit, event_gap_frames)
    found = sum(bool(covered[(revisit >= a) & (revisit <= b)].any()) for a, b in events)

    def ratio(num: int, den: int) -> float | None:
        return num / den if den else None

    n_acc, n_ok = len(pairs), int(correct.sum())
    return LoopScore(
        n_accepted=n_acc, n_correct=n_ok, precision=ratio(n_ok, n_acc),
        n_revisit_frames=len(revisit), n_revisit_frames_covered=int(covered.sum()),
        recall_frames=ratio(int(covered.sum()), len(revisit)),
        n_revisit_events=len(events), n_revisit_events_found=found,
        recall_events=ratio(found, len(events)),
        correct=correct, trans_err_m=t_err, rot_err_deg=r_err,
    )
