"""Side by side: lidar-slam, stock KISS-ICP, KISS-SLAM and rko_lio on the same scans, one table.

Usage: python tools/benchmark.py SEQ [SEQ ...] --out DIR [--repeats N]
       [--config-for SEQNAME=FILE ...] [--systems lidar-slam,kiss-icp,kiss-slam,rko-lio]
       [--start N] [--n-scans N]

Every system runs as its own process on the scans lidar_slam's readers produce (so all see
identical points; no KITTI vertical correction unless a lidar-slam config asks for it). Cost is
whole-process: wall time and peak RSS from os.wait4's rusage; frames/s = frames / median wall time
over the repeats (interleaved, so every system sees the same machine load), peak MB = max over the
repeats. Accuracy comes from lidar_slam.eval.evaluate.run_eval and lidar_slam.eval.metrics on the
outputs of
the last repeat, against the sequence's ground truth (reference poses for the Ouster set).

lidar-slam's rows are scored by the code of `lidar-slam batch` (lidar_slam.batch.results.run_row:
the
same t_err, r_err, ATE and counts as a batch's results table), and its runs also get that table,
DIR/lidar-slam/results.{md,json,csv}, so a benchmark and a batch can be compared row by row.

rko_lio (PRBonn's lidar-inertial odometry, `rko_lio` command of `pip install rko-lio`) runs where
the input has an IMU (the IMU lidar-slam reads: imu.csv beside a folder's scans or a bag's
sensor_msgs/Imu topic, with the lidar-slam config's imu.T_lidar_imu and imu.time_offset_s);
elsewhere its row says "no IMU". Its own CLI reads rosbags or its "raw" folder format, so the
benchmarked scans and IMU samples are written once, untimed, into DIR/<sequence>/rko-lio/input/
in that format (see write_rko_lio_input: same points, same stamps). Its base frame is the lidar
frame (transforms.yaml: T_lidar_to_base = I, T_imu_to_base = T_lidar_imu); it reports the pose
at each sweep's last point time, scored against the truth interpolated at those stamps.

Writes DIR/benchmark.md and DIR/benchmark.json (the table), and per (sequence, system) the run
outputs, logs and evaluation (metrics.json and plots) under DIR/<sequence>/<system>/.
"""

from __future__ import annotations

import argparse
import datetime
import importlib.util
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lidar_slam.batch import results
from lidar_slam.errors import LidarSlamError
from lidar_slam.eval import evaluate, metrics
from lidar_slam.geometry import from_xyz_quat, interpolate, inverse
from lidar_slam.io.sources import open_source
from lidar_slam.io.trajectory import read_kitti_poses, read_tum, write_kitti_poses

HERE = Path(__file__).resolve().parent
SYSTEMS = ("lidar-slam", "lidar-slam-lidar-only", "kiss-icp-pipeline", "kiss-icp", "kiss-slam",
           "rko-lio")
# Our own runs (scored by the batch code); the lidar-only one switches the IMU and GNSS off.
OURS = ("lidar-slam", "lidar-slam-lidar-only")
LABELS = {"lidar-slam": "lidar-slam",
          "lidar-slam-lidar-only": "lidar-slam lidar only (--no-imu --no-gnss)",
          "kiss-icp-pipeline": "kiss_icp_pipeline (stock, no deskew)",
          "kiss-icp": "KISS-ICP (stock, own deskew)", "kiss-slam": "KISS-SLAM (stock)",
          "rko-lio": "rko_lio (stock, lidar-inertial)"}
# Which Python packages each peer needs; peers live in the `bench` extra and are optional.
# rko_lio's raw folder reader needs plyfile (its `all` extra; named in the bench extra).
PEER_PACKAGES = {"kiss-icp": "kiss_icp", "kiss-icp-pipeline": "kiss_icp", "kiss-slam": "kiss_slam",
                 "rko-lio": ("rko_lio", "plyfile")}
ODOMETRY_ONLY = ("kiss-icp", "kiss-icp-pipeline", "rko-lio")
# rko_lio's raw format (rko_lio/dataloaders/raw.py of rko-lio 0.4.0): lidar/<stamp ns>.ply,
# imu.csv with these columns (stamp in ns), transforms.yaml with the two 4x4 extrinsics.
RKO_IMU_COLUMNS = ("timestamp", "gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z")
# Per-point times are written absolute, in s: told so, its timestamp heuristics are bypassed
# (relative times near the stamp of the next sweep would pass its "absolute" test).
RKO_CONFIG = {"lidar_timestamps": {"multiplier_to_seconds": 1.0, "force_absolute": True,
                                   "force_relative": False}}
# frames/s ratios are against the first of these that ran: bare odometry, then kiss-icp's deskew.
SPEED_BASELINES = ("kiss-icp-pipeline", "kiss-icp")
# loops.csv as the pipeline writes it (lidar_slam.loop.detector.loops_csv_rows): T_match_query.
LOOPS_POSE_COLUMNS = ("x", "y", "z", "qx", "qy", "qz", "qw")
MIN_DRIFT_PATH_M = metrics.KITTI_LENGTHS_M[0]
HEADER = ("sequence", "system", "t_err %", "r_err deg/100 m", "ATE m", "ATE max m",
          "loops accepted / correct",
          "frames/s", "peak MB")


@dataclass
class Sequence:
    """One input sequence as the benchmark uses it: frames start..start+n-1."""

    path: Path
    name: str
    start: int
    n: int
    gt: np.ndarray | None  # (n, 4, 4) T_first_lidar, or None
    config: Path | None
    ground_truth: np.ndarray | None = None  # T_world_lidar of every input scan (the source's)
    stamps: np.ndarray | None = None  # stamp (s) of every input scan (the source's)


@dataclass
class Row:
    """One (sequence, system) line of the table plus the raw numbers behind it."""

    sequence: str
    system: str
    frames: int
    wall_s: list[float] = field(default_factory=list)
    peak_mb: list[float] = field(default_factory=list)
    metrics: dict = field(default_factory=dict)
    loops_accepted: int | None = None
    loops_correct: int | None = None
    error: str | None = None
    skipped: str | None = None  # why the system did not run here, not an error (rko-lio: no IMU)
    notes: list[str] = field(default_factory=list)
    result: results.SequenceResult | None = None  # lidar-slam: its row of the batch table

    @property
    def fps(self) -> float | None:
        return self.frames / statistics.median(self.wall_s) if self.wall_s else None


# ------------------------------------------------------------------------------ running


def _peak_bytes(proc) -> int:
    """A process's peak resident set so far (VmHWM of /proc/PID/status), else its RSS now."""
    try:
        with open(f"/proc/{proc.pid}/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return proc.memory_info().rss


def _tree_rss_mb(pid: int) -> float:
    """Summed peak RSS (MB) so far of a process and every process it started."""
    import psutil

    try:
        proc = psutil.Process(pid)
        procs = [proc] + proc.children(recursive=True)
    except psutil.Error:
        return 0.0
    total = 0
    for p in procs:
        try:
            total += _peak_bytes(p)
        except psutil.Error:
            pass
    return total / 2**20


def timed(cmd: list[str], log_path: Path, cwd: Path | None = None) -> tuple[float, float, int]:
    """Wall seconds, peak RSS (MB) and exit code of one child process; its output goes to log.
    Peak RSS: the summed peak RSS (VmHWM) of the child and every process it started, sampled 4
    times a second; os.wait4's ru_maxrss only when no sample was taken (a child under 0.25 s),
    because Linux carries the forking parent's RSS into the child's ru_maxrss across exec (a
    640 MB parent makes `sleep 0.1` report 636 MB)."""
    import threading

    peak = [0.0]
    with log_path.open("w") as log:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=cwd)
        done = threading.Event()

        def sample() -> None:
            while not done.wait(0.25):
                peak[0] = max(peak[0], _tree_rss_mb(proc.pid))

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        done.set()
        sampler.join()
    proc.returncode = os.waitstatus_to_exitcode(status)  # already reaped by wait4
    return wall, peak[0] or usage.ru_maxrss / 1024.0, proc.returncode


def command(system: str, seq: Sequence, out: Path) -> list[str]:
    """The command line that runs one system on one sequence, writing into out."""
    rng = ["--start", str(seq.start), "--n-scans", str(seq.n)]
    if system in OURS:
        cfg = ["--config", str(seq.config)] if seq.config else []
        off = ["--no-imu", "--no-gnss"] if system == "lidar-slam-lidar-only" else []
        return [sys.executable, "-m", "lidar_slam.cli", "run", str(seq.path), "--out", str(out),
                "--overwrite", *rng, *cfg, *off]
    if system == "kiss-icp-pipeline":
        # kiss-icp's own command on the scan files (its generic loader reads .bin as KITTI
        # x, y, z, intensity: no per-point times, so no deskew), results under out/.
        scans = seq.path / "velodyne" if (seq.path / "velodyne").is_dir() else seq.path
        exe = Path(sys.executable).with_name("kiss_icp_pipeline")
        return [str(exe), str(scans), "--jump", str(seq.start), "--n-scans", str(seq.n)]
    if system == "kiss-icp":
        # --deskew: per-point times go to register_frame when the scans carry them, as
        # kiss-icp's own pipeline does (its deskew is on by default).
        return [sys.executable, str(HERE / "peers" / "stock_kiss_icp.py"), str(seq.path),
                str(out / "poses_kitti.txt"), "--deskew", *rng]
    if system == "kiss-slam":
        return [sys.executable, str(HERE / "peers" / "kiss_slam_peer.py"), str(seq.path),
                str(out / "poses_kitti.txt"), "--closures", str(out / "closures.json"), *rng]
    if system == "rko-lio":
        # rko_lio's own command on the input written by write_rko_lio_input (the range is
        # already cut there); trajectory to out/results/rko_lio_0/rko_lio_0_tum.txt.
        exe = Path(sys.executable).with_name("rko_lio")
        return [str(exe), str(out / "input"), "--dataloader", "raw", "--config",
                str(out / "rko_lio_config.yaml"), "--log_dir", str(out / "results"),
                "--run_name", "rko_lio"]
    raise ValueError(f"unknown system {system!r}")


def available(system: str) -> bool:
    """Whether the package a peer needs is importable here; says so when it is not."""
    pkgs = PEER_PACKAGES.get(system, ())
    missing = [p for p in ((pkgs,) if isinstance(pkgs, str) else pkgs)
               if importlib.util.find_spec(p) is None]
    if not missing:
        return True
    print(f"skipping {LABELS[system]}: Python package '{missing[0]}' is not installed in "
          f"{sys.executable} (peers are in the bench extra: pip install -e '.[bench]')")
    return False


# ------------------------------------------------------------------------------- rko_lio


def _stamp_ns(stamp_s: float) -> int:
    return int(round(stamp_s * 1e9))


def readme_extrinsic(path: Path) -> np.ndarray | None:
    """T_lidar_imu as a simulated sequence's README.txt states it (lidar_slam.sim), or None."""
    readme = path / "README.txt"
    if not path.is_dir() or not readme.is_file():
        return None
    for line in readme.read_text(errors="replace").splitlines():
        head, sep, values = line.partition("T_lidar_imu (row-major 3x4):")
        if sep:
            T = np.eye(4)
            T[:3] = np.array(values.split(), dtype=float).reshape(3, 4)
            return T
    return None


def write_rko_lio_input(seq: Sequence, dest: Path, lio: dict | None = None) -> str | None:
    """Write the benchmarked scans and the input's IMU in rko_lio's raw folder format under dest
    (replaced), and dest/../rko_lio_config.yaml; returns why rko_lio cannot run (no IMU) or None.

    The IMU is what lidar-slam reads from the same input (lidar_slam.io.inertial_input, with the
    lidar-slam config's imu.time_offset_s applied and its unusable rows dropped), written with
    stamps in ns. Each scan of lidar_slam's reader becomes lidar/<stamp ns>.ply with float64
    x, y, z (the reader's points) and float64 `time`, the point's absolute time in s (stamp +
    per-point time); scans without per-point times get no time field (rko_lio then warns and
    does not deskew). transforms.yaml makes the lidar the base frame: T_lidar_to_base = I,
    T_imu_to_base = imu.T_lidar_imu of the config (the IMU frame into the lidar frame).
    lio: rko_lio's LIOConfig settings (its `lio:` section) other than its defaults.
    """
    import yaml

    from lidar_slam.config import load_config
    cfg = load_config(seq.config)
    if not cfg.imu.enabled:
        return "no IMU (imu.enabled: false in the lidar-slam config)"
    src = open_source(seq.path)
    imu = src.inertial(imu_enabled=True, gnss_enabled=False,
                       imu_offset_s=cfg.imu.time_offset_s).imu
    if imu is None:
        return "no IMU"
    from plyfile import PlyData, PlyElement  # rko_lio's own PLY reader

    if dest.exists():
        shutil.rmtree(dest)
    (dest / "lidar").mkdir(parents=True)
    with (dest / "imu.csv").open("w") as fh:
        fh.write(",".join(RKO_IMU_COLUMNS) + "\n")
        for t, w, a in zip(imu.stamp_s, imu.gyro_radps, imu.accel_mps2):
            fh.write(f"{_stamp_ns(t)}," + ",".join(repr(float(v)) for v in (*w, *a)) + "\n")
    extrinsics = {"T_imu_to_base": cfg.imu.T_lidar_imu_matrix().tolist(),
                  "T_lidar_to_base": np.eye(4).tolist()}
    (dest / "transforms.yaml").write_text(yaml.safe_dump(extrinsics))
    config = {**RKO_CONFIG, **({"lio": lio} if lio else {})}
    (dest.parent / "rko_lio_config.yaml").write_text(yaml.safe_dump(config))
    for scan in src.scans(seq.start, seq.n):
        columns = [("x", "f8"), ("y", "f8"), ("z", "f8")]
        if scan.point_times is not None:
            columns.append(("time", "f8"))
        vertex = np.empty(len(scan.points), dtype=columns)
        for i, axis in enumerate("xyz"):
            vertex[axis] = scan.points[:, i]
        if scan.point_times is not None:
            vertex["time"] = scan.stamp_s + scan.point_times
        PlyData([PlyElement.describe(vertex, "vertex")]).write(
            str(dest / "lidar" / f"{_stamp_ns(scan.stamp_s)}.ply"))
    return None


def rko_lio_trajectory(out: Path) -> tuple[np.ndarray, np.ndarray]:
    """rko_lio's stamps (s) and poses of the lidar frame, T_odom_lidar (K, 4, 4).

    rko_lio writes T_odom_base per registered sweep, stamped with the sweep's last point time,
    to <log_dir>/<run_name>_<k>/<run_name>_<k>_tum.txt (k: first free index, so the newest
    run has the highest); T_odom_lidar = T_odom_base @ T_base_lidar (transforms.yaml's
    T_lidar_to_base, maps lidar points into the base frame).
    """
    import yaml

    runs = sorted(out.glob("results/rko_lio_*/rko_lio_*_tum.txt"),
                  key=lambda p: int(p.parent.name.rpartition("_")[2]))
    if not runs:
        raise FileNotFoundError(f"no rko_lio trajectory under {out / 'results'}")
    stamps, T_odom_base = read_tum(runs[-1])
    tf = yaml.safe_load((out / "input" / "transforms.yaml").read_text())
    return stamps, T_odom_base @ np.array(tf["T_lidar_to_base"], dtype=float)


def truth_at(seq: Sequence, times_s: np.ndarray) -> np.ndarray:
    """T_world_lidar of the truth at times_s (s): interpolated between the two scans around
    each time (slerp/lerp), extrapolated from the last two scans past the last one."""
    stamps, gt = seq.stamps, seq.ground_truth
    j = np.clip(np.searchsorted(stamps, times_s, side="right") - 1, 0, len(stamps) - 2)
    out = np.empty((len(times_s), 4, 4))
    for i, (t, k) in enumerate(zip(times_s, j)):
        s = (t - stamps[k]) / (stamps[k + 1] - stamps[k])
        out[i] = gt[k] @ interpolate(np.eye(4), inverse(gt[k]) @ gt[k + 1], s)
    return out


def evaluate_rko_lio(row: Row, seq: Sequence, out: Path) -> None:
    """rko_lio's poses in the lidar frame against the truth at its own stamps, both relative to
    its first pose, written as KITTI files and scored by evaluate.run_eval like the others."""
    stamps, T = rko_lio_trajectory(out)
    write_kitti_poses(out / "poses_kitti.txt", inverse(T[0]) @ T)
    if len(stamps) != seq.n:
        row.notes.append(f"rko_lio reported {len(stamps)} poses for {seq.n} scans")
    if seq.ground_truth is None or seq.stamps is None:
        return
    gt = truth_at(seq, stamps)
    write_kitti_poses(out / "ground_truth_kitti.txt", inverse(gt[0]) @ gt)
    row.metrics.update(evaluate.run_eval(out / "poses_kitti.txt", out / "ground_truth_kitti.txt",
                                         out_dir=out / "eval"))
    if row.metrics.get("warning"):
        row.notes.append(row.metrics["warning"])


# ---------------------------------------------------------------------------- evaluating


def lidar_slam_loops(path: Path, start: int, n: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Accepted loops of a lidar-slam loops.csv as positions in the slice, with T_match_query."""
    loops = evaluate.read_loops_csv(path)
    T = loops.T_match_query
    if T is None and len(loops.pairs):
        # evaluate.read_loops_csv knows other column names; the pipeline writes x..qw.
        import csv

        with path.open(newline="") as fh:
            rows = [r for r in csv.DictReader(fh)
                    if evaluate.truthy(r["accepted"])]
        if rows and set(LOOPS_POSE_COLUMNS) <= set(rows[0]):
            T = np.array([from_xyz_quat(np.array([float(r[c]) for c in LOOPS_POSE_COLUMNS]))
                          for r in rows]).reshape(-1, 4, 4)
    return loops.pairs - start, T


def kiss_slam_loops(path: Path, start: int) -> tuple[np.ndarray, np.ndarray | None]:
    """KISS-SLAM closures (from tools/peers/kiss_slam_peer.py) as frame pairs with T_match_query."""
    closures = json.loads(path.read_text())["closures"]
    pairs = np.array([[c["query_frame"], c["match_frame"]] for c in closures],
                     dtype=np.int64).reshape(-1, 2)
    T = np.array([from_xyz_quat(np.array(c["T_match_query_xyz_quat"])) for c in closures])
    return pairs - start, T.reshape(-1, 4, 4)


def score_loops(row: Row, pairs: np.ndarray, T: np.ndarray | None, seq: Sequence) -> None:
    """Fill loops accepted / correct (correct: within 1 m / 5 deg of the truth's relative pose)."""
    row.loops_accepted = len(pairs)
    inside = ((pairs >= 0) & (pairs < seq.n)).all(axis=1) if len(pairs) else np.zeros(0, bool)
    if seq.gt is None or T is None or not inside.all():
        row.notes.append("loop correctness unknown (no truth or no relative pose)")
        return
    s = metrics.loop_precision_recall(pairs, T, seq.gt)
    row.loops_correct = s.n_correct
    row.metrics["loop_score"] = {
        "pairs": pairs.tolist(), "correct": s.correct.tolist(),
        "trans_err_m": s.trans_err_m.tolist(), "rot_err_deg": s.rot_err_deg.tolist(),
        "revisit_events": s.n_revisit_events, "revisit_events_found": s.n_revisit_events_found,
    }


def sweep_end_truth(seq: Sequence) -> np.ndarray | None:
    """Truth at each sweep's last point time, for peers whose pose refers to the sweep end.

    kiss-icp (and KISS-SLAM on top of it) normalises per-point times to [0, 1] and deskews to
    the END of the sweep, so its pose i is the sensor pose at stamp_i + max point time; our
    poses refer to the stamp. Comparing each with the truth at its own instant keeps the
    comparison fair (on KITTI-like drives the difference is ~0.6 % t_err). None when the
    sequence has no per-point times (velodyne_times/ of a KITTI-layout folder).
    """
    times_dir = seq.path / "velodyne_times"
    if seq.gt is None or not times_dir.is_dir():
        return None
    stamps = np.loadtxt(seq.path / "times.txt", ndmin=1)[seq.start:seq.start + seq.n]
    files = sorted(times_dir.glob("*.bin"))[seq.start:seq.start + seq.n]
    out = np.empty_like(seq.gt)
    for i, f in enumerate(files):
        t_end = float(np.fromfile(f, np.float32).max())
        j = min(i, len(stamps) - 2)  # extrapolate the last sweep from the one before
        s = (stamps[i] + t_end - stamps[j]) / (stamps[j + 1] - stamps[j])
        out[i] = seq.gt[j] @ interpolate(np.eye(4), inverse(seq.gt[j]) @ seq.gt[j + 1], s)
    return out


def evaluate_lidar_slam(row: Row, seq: Sequence, out: Path) -> None:
    """lidar-slam's metrics as `lidar-slam batch` computes them (results.run_row), with the
    evaluation's metrics.json and plots in out/eval as for the peers."""
    row.result = results.run_row(seq.name, out, seq.ground_truth)
    m = row.result.details.get("eval")
    if m is not None:
        row.metrics.update(m)
        if m.get("warning"):
            row.notes.append(m["warning"])
        d = out / "eval"
        d.mkdir(exist_ok=True)
        (d / "metrics.json").write_text(json.dumps(m, indent=2) + "\n")
        evaluate.write_plots(d, read_kitti_poses(out / "poses_kitti.txt"), seq.gt)
    if (out / "loops.csv").is_file():
        score_loops(row, *lidar_slam_loops(out / "loops.csv", seq.start, seq.n), seq)


def evaluate_row(row: Row, seq: Sequence, out: Path, gt_file: Path | None) -> None:
    """Trajectory metrics (evaluate.run_eval) and loop counts of one finished run."""
    if row.system in OURS:
        evaluate_lidar_slam(row, seq, out)
        return
    if row.system == "rko-lio":
        try:
            evaluate_rko_lio(row, seq, out)
        except (LidarSlamError, OSError) as exc:
            row.error = f"evaluation failed: {exc}"
        return
    poses = out / "poses_kitti.txt"
    if row.system == "kiss-icp-pipeline":  # kiss-icp writes under results/<stamp>/
        found = sorted(out.glob("results/latest/*_poses_kitti.txt"))
        poses = found[0] if found else poses
    if gt_file is not None:
        try:
            row.metrics.update(evaluate.run_eval(poses, gt_file, out_dir=out / "eval"))
        except LidarSlamError as exc:
            row.error = f"evaluation failed: {exc}"
            return
        if row.metrics.get("warning"):
            row.notes.append(row.metrics["warning"])
    if row.system == "kiss-slam" and (out / "closures.json").is_file():
        score_loops(row, *kiss_slam_loops(out / "closures.json", seq.start), seq)


# ------------------------------------------------------------------------------ the table


def _num(value: float | None, digits: int) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def cells(row: Row) -> list[str]:
    """The table cells of one row, every number in the unit of its column header."""
    name = [row.sequence, LABELS[row.system]]
    if row.error:
        return name + [f"failed: {row.error}"] + [""] * 6
    if row.skipped:
        return name + [row.skipped] + [""] * 6
    m = row.metrics
    if not m:
        t_err = r_err = ate = "n/a (no truth)"
    elif m.get("t_err_pct") is None:
        short = m.get("path_length_m", 0.0) < MIN_DRIFT_PATH_M
        t_err = r_err = f"n/a (<{MIN_DRIFT_PATH_M:.0f} m)" if short else "n/a"
        ate = _num(m.get("ate_rmse_m"), 3)
    else:
        t_err, r_err = _num(m["t_err_pct"], 2), _num(m["r_err_deg_per_100m"], 3)
        ate = _num(m.get("ate_rmse_m"), 3)
    if row.system in ODOMETRY_ONLY:
        loops = "- (odometry only)"
    elif row.loops_accepted is None:
        loops = "n/a"
    else:
        correct = "?" if row.loops_correct is None else str(row.loops_correct)
        loops = f"{row.loops_accepted} / {correct}"
    ate_max = _num(m.get("ate_max_m"), 3) if m else ""
    return name + [t_err, r_err, ate, ate_max, loops, _num(row.fps, 2),
                   _num(max(row.peak_mb) if row.peak_mb else None, 0)]


def markdown(rows: list[Row], meta: dict) -> str:
    """The table as markdown, with the conditions it was measured under."""
    lines = ["| " + " | ".join(HEADER) + " |", "|" + "---|" * len(HEADER)]
    lines += ["| " + " | ".join(cells(r)) + " |" for r in rows]
    lines.append("")
    lines.append(f"frames/s: frames / median whole-process wall time over {meta['repeats']} "
                 "interleaved repeat(s), interpreter start-up and imports included, input files "
                 "read once beforehand (warm page cache); peak MB: max over the repeats of the "
                 "summed RSS of the run's processes (sampled 4/s) or its own peak (os.wait4). "
                 "t_err/r_err: KITTI devkit segments of 100-800 m "
                 "(n/a when the path is shorter). ATE: RMSE (and max) after rigid Umeyama "
                 "alignment. Loops correct: estimated T_match_query within 1 m / 5 deg of the "
                 "truth.")
    for seq, ratio in meta["fps_vs_kiss_icp"].items():
        ratio = dict(ratio)
        base = ratio.pop("baseline")
        text = ", ".join(f"{LABELS[s]} {v:.2f}x" for s, v in ratio.items())
        lines.append(f"- {seq}: frames/s relative to {LABELS[base]}: {text}")
    for r in rows:
        for note in r.notes:
            lines.append(f"- {r.sequence} / {LABELS[r.system]}: {note}")
    lines.append(f"- measured {meta['date']} at commit {meta['commit']} on {meta['cpus']} CPUs")
    return "\n".join(lines) + "\n"


def as_json(rows: list[Row], meta: dict) -> dict:
    """The table and the numbers behind it, for comparing a later run with this one."""
    keep = ("t_err_pct", "r_err_deg_per_100m", "ate_rmse_m", "ate_max_m", "rpe_trans_m_mean",
            "rpe_rot_deg_mean", "path_length_m", "est_path_length_m", "kitti_segments", "note")
    out_rows = []
    for r in rows:
        out_rows.append({
            "sequence": r.sequence, "system": r.system, "frames": r.frames,
            **{k: r.metrics.get(k) for k in keep},
            "loops_accepted": r.loops_accepted, "loops_correct": r.loops_correct,
            "loop_score": r.metrics.get("loop_score"),
            "fps": r.fps, "wall_s": r.wall_s, "peak_mb": max(r.peak_mb) if r.peak_mb else None,
            "peak_mb_runs": r.peak_mb, "error": r.error, "skipped": r.skipped,
            "notes": r.notes,
            "cells": dict(zip(HEADER, cells(r))),
        })
    return {**meta, "columns": list(HEADER), "rows": out_rows}


# ---------------------------------------------------------------------------------- main


def parse_config_for(items: list[str]) -> dict[str, Path]:
    """SEQNAME=FILE pairs; the files must exist."""
    out = {}
    for item in items:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            sys.exit(f"--config-for expects SEQNAME=FILE, got {item!r}")
        if not Path(path).is_file():
            sys.exit(f"--config-for {name}: {path} does not exist")
        out[name] = Path(path).resolve()  # the runs start in their own folders
    return out


def load_sequence(path: str, start: int, n_scans: int | None, configs: dict[str, Path]) -> Sequence:
    """Open a sequence and cut its ground truth to the benchmarked frames, in the first frame."""
    src = open_source(path)
    if start >= len(src):
        sys.exit(f"{path}: --start {start} is past the last scan ({len(src)} scans)")
    n = len(src) - start if n_scans is None else min(n_scans, len(src) - start)
    gt = None
    if src.ground_truth is not None:
        gt = src.ground_truth[start:start + n]
        gt = inverse(gt[0]) @ gt
    return Sequence(Path(path).resolve(), src.name, start, n, gt, configs.get(src.name),
                    src.ground_truth, np.asarray(src.stamps, dtype=float))


def warm_page_cache(path: Path) -> tuple[float, float]:
    """Read every file of a sequence once, untimed, so the first system timed does not pay the
    disk alone (a cold 2.5 GB simulated sequence cost lidar-slam, which runs first, ~30 s).
    Returns (MB read, seconds)."""
    t0, total = time.perf_counter(), 0
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    for f in files:
        with open(f, "rb") as fh:
            while chunk := fh.read(1 << 24):
                total += len(chunk)
    return total / 1e6, time.perf_counter() - t0


def prepare_rko_lio(rows: dict[str, Row], seq: Sequence, seq_dir: Path,
                    lio: dict | None = None) -> None:
    """Write rko_lio's input for seq (untimed), or mark its row skipped (no IMU) or failed;
    warns on every row when a simulated sequence's README.txt states another T_lidar_imu than
    the lidar-slam config (both systems would be given the wrong extrinsic)."""
    from lidar_slam.config import load_config

    row = rows["rko-lio"]
    t0 = time.perf_counter()
    try:
        row.skipped = write_rko_lio_input(seq, seq_dir / "rko-lio" / "input", lio)
    except LidarSlamError as exc:
        row.error = f"input for rko_lio: {exc}"
        return
    if row.skipped:
        print(f"{seq.name}: {LABELS['rko-lio']}: {row.skipped}", flush=True)
        return
    print(f"{seq.name}: wrote rko_lio's input in {time.perf_counter() - t0:.1f} s", flush=True)
    settings = (f"its settings {lio}, its own defaults otherwise" if lio else
                "its own defaults otherwise (initialization_phase off: it would assume a "
                "start at rest)")
    row.notes.append("input written once beforehand (untimed) in rko_lio's raw format: "
                     f"lidar/<stamp ns>.ply, imu.csv, transforms.yaml (base = lidar frame); "
                     f"{settings}")
    stated = readme_extrinsic(seq.path)
    used = load_config(seq.config).imu.T_lidar_imu_matrix()
    if stated is not None and not np.allclose(stated, used, atol=1e-6):
        for r in rows.values():
            r.notes.append("README.txt states another T_lidar_imu than the lidar-slam config "
                           "(imu.T_lidar_imu); pass the right one with --config-for")


def write_truth_files(seq: Sequence, seq_dir: Path) -> tuple[Path | None, Path | None]:
    """seq's truth as KITTI files in seq_dir: at the stamps (for lidar-slam) and at each
    sweep's last point (for the peers that report that instant; the stamps' when the scans
    have no per-point times); (None, None) without truth."""
    if seq.gt is None:
        return None, None
    gt_file = gt_end_file = seq_dir / "ground_truth_kitti.txt"
    write_kitti_poses(gt_file, seq.gt)
    gt_end = sweep_end_truth(seq)
    if gt_end is not None:
        gt_end_file = seq_dir / "ground_truth_sweep_end_kitti.txt"
        write_kitti_poses(gt_end_file, gt_end)
    return gt_file, gt_end_file


def run_once(row: Row, seq: Sequence, seq_dir: Path, label: str) -> None:
    """One timed run of row's system on seq in seq_dir/<system> (nothing when the row already
    failed or was skipped): its wall time and peak MB appended to the row, or the row's error."""
    if row.error or row.skipped:
        return
    s = row.system
    out = seq_dir / s
    out.mkdir(exist_ok=True)
    if s == "rko-lio":  # it numbers its outputs; one run's only
        shutil.rmtree(out / "results", ignore_errors=True)
    wall, mb, code = timed(command(s, seq, out), out / "log.txt", cwd=out)
    print(f"{seq.name} {LABELS[s]} {label}: {wall:.2f} s, {mb:.0f} MB"
          + (f", exit {code}" if code else ""), flush=True)
    if code != 0:
        row.error = f"exit code {code}, see {out / 'log.txt'}"
        return
    row.wall_s.append(wall)
    row.peak_mb.append(mb)


def compile_ours() -> str:
    """Byte-compile the lidar_slam package the timed runs will import (this environment's,
    PYTHONPATH included), before anything is timed, as `pip install` does for every
    installed package; returns the package directory. An editable install writes no bytecode
    when PYTHONDONTWRITEBYTECODE is set (as on the benchmark VMs), and then every run compiled
    all ~80 of lidar_slam's modules from source, in its main process and again in its loop
    worker (~0.3 s of a 4.5 s hand-held walk,
    docs/benchmarks/2026-12-06j-speed-handheld.md), while the peers' packages ran from pip's
    bytecode. Python still reads bytecode written here when that variable is set."""
    code = ("import compileall, pathlib, lidar_slam; "
            "p = pathlib.Path(lidar_slam.__file__).parent; "
            "ok = compileall.compile_dir(str(p), quiet=1); print(p); "
            "raise SystemExit(0 if ok else 1)")
    # from a neutral directory, as the runs start in their output folders: the same import
    done = subprocess.run([sys.executable, "-c", code], text=True, capture_output=True,
                          cwd=tempfile.gettempdir())
    if done.returncode:
        sys.exit(f"benchmark: could not byte-compile lidar_slam: {done.stderr.strip()[-300:]}")
    return done.stdout.strip()


def git_commit() -> str:
    try:
        sha = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=HERE, text=True,
                             capture_output=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=HERE, text=True, capture_output=True).stdout.strip()
        return sha + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequences", nargs="+", help="scan folders, KITTI sequences or bags")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--config-for", action="append", default=[], metavar="SEQNAME=FILE",
                    help="lidar-slam config overlay for the sequence named SEQNAME (folder name)")
    ap.add_argument("--systems", default=",".join(SYSTEMS),
                    help=f"comma-separated subset of {','.join(SYSTEMS)}")
    ap.add_argument("--start", type=int, default=0, help="first scan of every sequence")
    ap.add_argument("--n-scans", type=int, default=None, help="scans per sequence (default all)")
    args = ap.parse_args(argv)
    systems = [s.strip() for s in args.systems.split(",") if s.strip()]
    unknown = sorted(set(systems) - set(SYSTEMS))
    if unknown or args.repeats < 1:
        sys.exit(f"unknown systems {unknown} (choose from {SYSTEMS})" if unknown
                 else "--repeats must be at least 1")
    systems = [s for s in systems if available(s)]
    configs = parse_config_for(args.config_for)
    try:
        seqs = [load_sequence(p, args.start, args.n_scans, configs) for p in args.sequences]
    except LidarSlamError as exc:
        sys.exit(f"benchmark: {exc}")
    missing = sorted(set(configs) - {s.name for s in seqs})
    if missing:
        sys.exit(f"--config-for names {missing} match no sequence ({[s.name for s in seqs]})")

    bytecode = compile_ours() if any(s in OURS for s in systems) else None
    rows: list[Row] = []
    for seq in seqs:
        seq_dir = args.out / seq.name
        seq_dir.mkdir(parents=True, exist_ok=True)
        gt_file, gt_end_file = write_truth_files(seq, seq_dir)
        seq_rows = {s: Row(seq.name, s, seq.n) for s in systems}
        if "rko-lio" in seq_rows:
            prepare_rko_lio(seq_rows, seq, seq_dir)
        mb_read, secs = warm_page_cache(seq.path)
        print(f"{seq.name}: read {mb_read:.0f} MB in {secs:.1f} s to warm the page cache",
              flush=True)
        for rep in range(args.repeats):  # interleaved so every system sees the same load
            for row in seq_rows.values():
                run_once(row, seq, seq_dir, f"repeat {rep + 1}/{args.repeats}")
        for s, row in seq_rows.items():
            if not row.error and not row.skipped:
                evaluate_row(row, seq, seq_dir / s, gt_file if s in OURS else gt_end_file)
            rows.append(row)

    ratios: dict[str, dict[str, float]] = {}
    for seq in seqs:
        by = {r.system: r for r in rows if r.sequence == seq.name and r.fps}
        base = next((b for b in SPEED_BASELINES if b in by), None)
        if base is not None:
            ratios[seq.name] = {"baseline": base, **{s: r.fps / by[base].fps
                                                     for s, r in by.items() if s != base}}
    meta = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "commit": git_commit(),
            "cpus": os.cpu_count(), "repeats": args.repeats, "start": args.start,
            "n_scans": args.n_scans, "systems": systems,
            "configs": {k: str(v) for k, v in configs.items()}, "fps_vs_kiss_icp": ratios,
            "bytecode_compiled": bytecode}
    args.out.mkdir(parents=True, exist_ok=True)
    ours = [r for r in rows if r.system == "lidar-slam"]
    if ours:  # lidar-slam's runs as one batch results table (the last repeat of each)
        table = [r.result or results.error_row(r.sequence, r.error or "no result") for r in ours]
        results.write_results(args.out / "lidar-slam", table, sum(r.wall_s[-1] for r in ours
                                                                  if r.wall_s),
                              notes=[f"tools/benchmark.py, {args.repeats} repeat(s); fps: the "
                                     f"last repeat's own wall time (benchmark.md: whole "
                                     f"process, median of the repeats)"])
    md = markdown(rows, meta)
    (args.out / "benchmark.md").write_text(md)
    (args.out / "benchmark.json").write_text(json.dumps(as_json(rows, meta), indent=2) + "\n")
    print()
    print(md, end="")
    print(f"wrote {args.out / 'benchmark.md'} and {args.out / 'benchmark.json'}")
    return 1 if any(r.error for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
