"""The `lidar-slam` command: maps library errors to one-line messages and exit codes."""

from __future__ import annotations

import contextlib
import functools
import logging
import shutil
import signal
import sys
import time
from enum import Enum
from pathlib import Path
from typing import Optional

import typer

from lidar_slam.errors import LidarSlamError

app = typer.Typer(add_completion=False, pretty_exceptions_enable=False,
                  help="Lidar SLAM: odometry, loop closure, pose graph, map and metrics.")
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130
log = logging.getLogger("lidar_slam")


def _fail(message: str, code: int = EXIT_BAD_INPUT) -> typer.Exit:
    typer.echo(f"lidar-slam: error: {message}", err=True)
    return typer.Exit(code)


def reports_errors(fn):
    """Turn typed library errors (and Ctrl-C) into one line on stderr and an exit code."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except LidarSlamError as exc:
            raise _fail(str(exc)) from None
        except KeyboardInterrupt:
            raise _fail("interrupted", EXIT_INTERRUPTED) from None
        except OSError as exc:  # e.g. an output path that cannot be created or written
            where = exc.filename if exc.filename is not None else "output"
            raise _fail(f"{where}: {exc.strerror or exc}") from None

    return wrapper


@app.callback()
def main(verbose: bool = typer.Option(False, "--verbose", "-v", help="Debug logging.")) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)


UNITS = {"wall_s": "s", "fps": "frames/s", "peak_rss_mb": "MB", "path_length_m": "m",
         "map_points": "points", "rpe_trans_m_mean": "m", "rpe_rot_deg_mean": "deg",
         "end_drift_pct": "%", "ate_rmse_m": "m", "odometry_ate_rmse_m": "m",
         "odometry_ms_per_frame": "ms", "loops_ms_per_frame": "ms",
         "loop_worker_ms_per_frame": "ms", "loop_wait_ms_per_frame": "ms",
         "backend_ms_per_loop_max": "ms"}


def _summary_table(summary: dict) -> str:
    """The run summary as an aligned two-column table, every number with its unit."""
    rows = []
    for key, value in summary.items():
        text = f"{value:.4g}" if isinstance(value, float) else str(value)
        rows.append((key, f"{text} {UNITS.get(key, '')}".strip()))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)


class _StopSignals:
    """While active, Ctrl-C and SIGTERM (kill, timeout, docker stop, a batch scheduler) ask the
    run to stop after the scan in hand, so the frames computed so far are kept and written; a
    second one stops at once (KeyboardInterrupt). deferred(): signals are only noted, so the
    outputs being written are finished first."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self.received = False
        self._old: dict = {}

    def _request(self, signum, frame):
        if self.received:
            raise KeyboardInterrupt
        self.received = True

    def _note(self, signum, frame):
        self.received = True

    def _install(self, handler) -> None:
        try:
            for sig in self.SIGNALS:
                self._old[sig] = signal.signal(sig, handler)
        except ValueError:  # not the main thread (embedded use): leave signals alone
            self._restore()

    def _restore(self) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)
        self._old = {}

    def __enter__(self):
        self._install(self._request)
        return self

    def __exit__(self, *exc) -> None:
        self._restore()

    @contextlib.contextmanager
    def deferred(self):
        self._install(self._note)
        try:
            yield
        finally:
            self._restore()


# Every file and folder `run` writes into --out: --overwrite deletes these and nothing else.
RUN_OUTPUTS = ("poses_kitti.txt", "poses_tum.txt", "odometry_kitti.txt", "map.ply", "loops.csv",
               "graph.g2o", "config.yaml", "summary.json", "error_traceback.txt", "keyframes",
               "checkpoint")


SIMULATE_OUTPUTS = ("velodyne", "velodyne_times", "poses.txt", "times.txt", "calib.txt",
                    "README.txt")


def prepare_out_dir(out: Path, ours: tuple[str, ...], overwrite: bool, resume: bool = False
                    ) -> bool:
    """The one rule for commands that write a folder: an --out that already holds files is
    refused unless --overwrite (our files are deleted first) or --resume. Returns True when
    there is a run to resume."""
    if overwrite and resume:
        raise _fail("--overwrite and --resume exclude each other")
    if out.exists() and not out.is_dir():
        raise _fail(f"{out}: --out exists and is not a folder")
    held = sorted(p.name for p in out.iterdir()) if out.is_dir() else []
    if held and resume:
        return True
    if held and not overwrite:
        flag = "--overwrite or --resume" if ours is RUN_OUTPUTS else "--overwrite"
        raise _fail(f"{out}: --out already holds files ({', '.join(held[:3])}"
                    f"{', ...' if len(held) > 3 else ''}); pass {flag}")
    for name in held:
        if name in ours:
            path = out / name
            shutil.rmtree(path) if path.is_dir() else path.unlink()
    out.mkdir(parents=True, exist_ok=True)  # fail before the run, not after it
    return False


class _Progress:
    """A rich progress bar with frames/s on a terminal; silent otherwise (rich not imported)."""

    def __init__(self, name: str, total: int, done: int = 0):
        self.bar = None
        self.t0 = time.perf_counter()
        if sys.stderr.isatty():
            from rich.console import Console
            from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn,
                                       TimeElapsedColumn)

            self.bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(),
                                MofNCompleteColumn(), TextColumn("{task.fields[fps]:.1f} frames/s"),
                                TimeElapsedColumn(), console=Console(stderr=True))
            self.task = self.bar.add_task(name, total=total, completed=done, fps=0.0)
            self.done0 = done
            self.bar.start()

    def tick(self, _scan=None) -> None:
        if self.bar is not None:
            done = self.bar.tasks[0].completed + 1 - self.done0
            fps = done / max(time.perf_counter() - self.t0, 1e-9)
            self.bar.update(self.task, advance=1, fps=fps)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()


@app.command()
@reports_errors
def run(
    data: Path = typer.Argument(..., help="Folder of scans, KITTI sequence, or rosbag/mcap."),
    out: Path = typer.Option(..., "--out", "-o", help="Run folder to write."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="YAML config overlay."),
    start: int = typer.Option(0, "--start", min=0, help="First scan (0-based)."),
    n_scans: Optional[int] = typer.Option(None, "--n-scans", min=1, help="Number of scans."),
    topic: Optional[str] = typer.Option(None, "--topic", help="PointCloud2 topic of a bag."),
    no_loops: bool = typer.Option(False, "--no-loops", help="Odometry only."),
    no_deskew: bool = typer.Option(False, "--no-deskew", help="Do not deskew."),
    viz: bool = typer.Option(False, "--viz", help="Open the rerun viewer."),
    rrd: Optional[Path] = typer.Option(None, "--rrd", help="Record a rerun .rrd file."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace a previous run in --out."),
    resume: bool = typer.Option(False, "--resume",
                                help="Continue the killed run in --out from its checkpoint."),
) -> None:
    """Run SLAM on DATA and write poses, map, config and summary into --out."""
    import traceback

    from lidar_slam import checkpoint
    from lidar_slam.config import load_config
    from lidar_slam.io.sources import open_source, read_ahead
    from lidar_slam.outputs import OdometryStream, write_run
    from lidar_slam.pipeline import Pipeline

    overrides: dict = {}
    if no_loops:
        overrides["loop"] = {"enabled": False}
    if no_deskew:
        overrides["data"] = {"deskew": False}
    cfg = load_config(config, overrides)
    resuming = prepare_out_dir(out, RUN_OUTPUTS, overwrite, resume)
    source = open_source(data, topic=topic,
                         kitti_vertical_correction=cfg.data.kitti_vertical_correction)
    if start >= len(source):
        raise _fail(f"{data}: --start {start} is past the last scan ({len(source)} scans)")
    total = len(source) - start if n_scans is None else min(n_scans, len(source) - start)
    identity = checkpoint.describe_run(data, start, n_scans, topic, cfg)
    if resuming and not checkpoint.has_checkpoint(out):
        if (out / "checkpoint" / "run.json").is_file():
            checkpoint.check_same_run(out, identity)
        prepare_out_dir(out, RUN_OUTPUTS, overwrite=True)  # killed before its first checkpoint
        resuming = False
    elif resuming:
        checkpoint.check_same_run(out, identity)
    visualizer = None
    if viz or rrd is not None:
        from lidar_slam.viz import RerunViz

        visualizer = RerunViz(spawn=viz, rrd_path=rrd)
    t0 = time.perf_counter()
    pipe = Pipeline(cfg, out, visualizer, resume=resuming)
    done = 0
    if resuming:
        done = checkpoint.restore(out, pipe)
        log.warning("resuming %s at frame %d of %d", out, done, total)
    else:
        checkpoint.start_run(out, identity)
    progress = _Progress(source.name, total, done)
    stream = OdometryStream(out, pipe.result.odom_poses)
    every = cfg.checkpoint.every_keyframes
    stop = _StopSignals()
    error = internal_error = None
    with stop:
        try:
            for scan in read_ahead(source.scans(start + done, total - done)):
                n_kf = len(pipe.result.store)
                pipe.process(scan)
                progress.tick(scan)
                stream.append(pipe.result.odom_poses[-1])
                if every and len(pipe.result.store) != n_kf and len(pipe.result.store) % every == 0:
                    checkpoint.save(out, pipe, pipe.loops_applied_upto)
                if stop.received:
                    break
        except KeyboardInterrupt:
            stop.received = True
        except LidarSlamError as exc:
            error = str(exc)
        except Exception:  # a bug must not cost the frames already computed: keep them, report it
            internal_error = traceback.format_exc()
            log.error("internal error after %d frames", len(pipe.result.indices))
        finally:
            progress.close()
            stream.close()
    with stop.deferred():  # a signal now waits until the outputs are written
        result = pipe.finish()
        status = {"interrupted": stop.received}
        if error:
            status["stopped_by_error"] = error
        summary = write_run(out, result, cfg, source.ground_truth, time.perf_counter() - t0,
                            extra={**status, "input": str(data), "start": start,
                                   "resumed_at_frame": done})
        pipe.close()
    if visualizer is not None:
        visualizer.finish(result, out / "map.ply")
    typer.echo(_summary_table(summary))
    typer.echo(f"wrote {out}")
    if internal_error:
        (out / "error_traceback.txt").write_text(internal_error)
        raise _fail(f"internal error (traceback in {out / 'error_traceback.txt'}); the "
                    f"{summary['frames']} frames so far written to {out}", 1)
    if error:
        raise _fail(f"{error} (stopped there; frames so far written to {out})")
    if stop.received:
        raise _fail(f"interrupted; the {summary['frames']} frames so far written to {out}",
                    EXIT_INTERRUPTED)


class Robust(str, Enum):
    huber = "huber"
    none = "none"


class TrajFormat(str, Enum):
    kitti = "kitti"
    tum = "tum"


@app.command()
@reports_errors
def optimize(
    graph: Path = typer.Argument(..., help="Input g2o (2D SE2 or 3D SE3:QUAT)."),
    out: Path = typer.Option(..., "--out", "-o", help="Optimised g2o to write."),
    robust: Robust = typer.Option(Robust.none, "--robust", help="Kernel on loop edges."),
    huber_k: float = typer.Option(1.345, "--huber-k", help="Huber threshold (whitened)."),
    max_iterations: int = typer.Option(100, "--max-iterations", min=1),
) -> None:
    """Optimise a pose graph with GTSAM Levenberg-Marquardt (prior on the first pose)."""
    from lidar_slam.backend.g2o_optimize import optimize_g2o

    if robust == Robust.huber and not huber_k > 0:
        raise _fail(f"--huber-k must be positive, got {huber_k}")
    rep = optimize_g2o(graph, out, robust=robust.value, huber_k=huber_k,
                       max_iterations=max_iterations)
    typer.echo(f"graph={graph} dims={rep.dims} vertices={rep.n_vertices} edges={rep.n_edges} "
               f"loop_edges={rep.n_loop_edges} robust={rep.robust}")
    typer.echo(f"initial_error={rep.initial_error:.6g}")
    typer.echo(f"final_error={rep.final_error:.6g}")
    typer.echo(f"iterations={rep.iterations} seconds={rep.seconds:.3f}")
    typer.echo(f"wrote {out}")


@app.command("eval")
@reports_errors
def eval_cmd(
    est: Path = typer.Argument(..., help="Estimated trajectory."),
    gt: Path = typer.Argument(..., help="Ground-truth trajectory."),
    fmt: TrajFormat = typer.Option(TrajFormat.kitti, "--format", help="File format of both."),
    calib: Optional[Path] = typer.Option(None, "--calib", help="KITTI calib: GT cam0 -> lidar."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="metrics.json and plots here."),
    loops: Optional[Path] = typer.Option(None, "--loops", help="loops.csv of the run."),
) -> None:
    """KITTI drift (t_err %, r_err deg/100 m), ATE and RPE of EST against GT."""
    from lidar_slam.evaluate import format_table, run_eval

    metrics = run_eval(est, gt, fmt=fmt.value, calib_path=calib, out_dir=out, loops_csv=loops)
    typer.echo(format_table(metrics))
    if out is not None:
        typer.echo(f"wrote {out}")


class Sensor(str, Enum):
    hdl64 = "hdl64"
    vlp16 = "vlp16"
    os1_64 = "os1-64"


@app.command()
@reports_errors
def simulate(
    poses: Path = typer.Argument(..., help="KITTI pose file (left-camera frame, as poses/XX.txt)."),
    calib: Path = typer.Option(..., "--calib", help="KITTI calib with Tr (velodyne -> cam0)."),
    out: Path = typer.Option(..., "--out", "-o", help="KITTI-layout sequence folder to write."),
    times: Optional[Path] = typer.Option(None, "--times", help="Stamps (s); default: "
                                         "../times/<name>.txt beside POSES, else 10 Hz."),
    sensor: Sensor = typer.Option(Sensor.hdl64, "--sensor"),
    start: int = typer.Option(0, "--start", min=0),
    n_scans: Optional[int] = typer.Option(None, "--n-scans", min=1),
    seed: int = typer.Option(0, "--seed"),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace a sequence in --out."),
) -> None:
    """Ray-cast a lidar along a real trajectory through a procedural street world."""
    import numpy as np

    from lidar_slam.io.trajectory import (camera_to_lidar_poses, read_kitti_calib_tr,
                                          read_kitti_poses, read_times)
    from lidar_slam.simulate import simulate_sequence

    prepare_out_dir(out, SIMULATE_OUTPUTS, overwrite)
    Tr = read_kitti_calib_tr(calib)
    poses_lidar = camera_to_lidar_poses(read_kitti_poses(poses), Tr)
    times = times or poses.parent.parent / "times" / poses.name
    stamps = read_times(times) if times.is_file() else np.arange(len(poses_lidar)) * 0.1
    if len(stamps) != len(poses_lidar):
        raise _fail(f"{times}: {len(stamps)} stamps for {len(poses_lidar)} poses")
    if start >= len(poses_lidar):
        raise _fail(f"{poses}: --start {start} is past the last pose ({len(poses_lidar)})")
    summary = simulate_sequence(poses_lidar, stamps, out, sensor=sensor.value, seed=seed,
                                start=start, n_scans=n_scans, Tr_cam_lidar=Tr)
    typer.echo(f"simulated {summary.n_scans} scans ({summary.points_per_scan:.0f} points/scan, "
               f"{summary.seconds_per_scan:.3f} s/scan) into {out}")


if __name__ == "__main__":
    app()
