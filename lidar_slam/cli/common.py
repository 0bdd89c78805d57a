"""The `lidar-slam` command: maps library errors to one-line messages and exit codes."""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import shutil
import signal
import sys
import time
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Optional

import typer

from lidar_slam.errors import LidarSlamError

EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130
log = logging.getLogger("lidar_slam")


class CommandError(LidarSlamError):
    """A command's one-line error and its exit code (reports_errors prints it); raised, not
    printed, so that `batch` can turn the same error of one sequence into its row."""

    def __init__(self, message: str, code: int = EXIT_BAD_INPUT):
        super().__init__(message)
        self.exit_code = code


def _fail(message: str, code: int = EXIT_BAD_INPUT) -> CommandError:
    return CommandError(message, code)


def _exit(message: str, code: int) -> typer.Exit:
    typer.echo(f"lidar-slam: error: {message}", err=True)
    return typer.Exit(code)


def _click_exception() -> type[Exception]:
    """The class of typer's usage errors (click's ClickException), found from typer's public
    `typer.BadParameter`: typer >= 0.2x raises its own copy of click's exceptions, older typer
    click's, and neither copy is a public name of typer."""
    return next(c for c in typer.BadParameter.__mro__ if c.__name__ == "ClickException")


ClickException = _click_exception()


def _internal_error(exc: BaseException) -> int:
    """An error that is a bug, not bad input: one line naming it and the file that holds the
    traceback (also on stderr with --verbose), exit code 1."""
    import tempfile
    import traceback

    text = "".join(traceback.format_exception(exc))
    where = ""
    try:
        fd, path = tempfile.mkstemp(prefix="lidar-slam-traceback-", suffix=".txt")
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
        where = f"; traceback in {path}"
    except OSError:
        pass
    if log.isEnabledFor(logging.DEBUG):
        sys.stderr.write(text)
    first = (str(exc).strip().splitlines() or [""])[0]
    typer.echo(f"lidar-slam: error: internal error: {type(exc).__name__}: {first}".rstrip(": ")
               + f" (a bug: please report it{where})", err=True)
    return 1


class _App(typer.Typer):
    """typer.Typer whose usage errors (a bad option value, a missing argument) are one line on
    stderr and exit code 2, like every other error, instead of typer's boxed panel; a bug is
    one line and exit code 1 (_internal_error), never a traceback on the terminal."""

    def __call__(self, *args, **kwargs):
        kwargs.setdefault("prog_name", "lidar-slam")
        try:
            code = super().__call__(*args, standalone_mode=False, **kwargs)
        except typer.Exit as exc:
            sys.exit(exc.exit_code)
        except typer.Abort:
            typer.echo("lidar-slam: error: aborted", err=True)
            sys.exit(1)
        except KeyboardInterrupt:
            typer.echo("lidar-slam: error: interrupted", err=True)
            sys.exit(EXIT_INTERRUPTED)
        except ClickException as exc:
            if type(exc).__name__ == "NoArgsIsHelpError":
                exc.show()  # the help text, as for --help
                sys.exit(exc.exit_code)
            where = f" (see {exc.ctx.command_path} --help)" if getattr(exc, "ctx", None) else ""
            message = " ".join(exc.format_message().split()).rstrip(".")
            typer.echo(f"lidar-slam: error: {message}{where}", err=True)
            sys.exit(exc.exit_code)
        except Exception as exc:  # a bug: say so in one line, keep the traceback in a file
            sys.exit(_internal_error(exc))
        sys.exit(code if isinstance(code, int) else 0)


app = _App(add_completion=False, pretty_exceptions_enable=False, no_args_is_help=True,
           help="Lidar SLAM: odometry, loop closure, pose graph, map and metrics.")


def reports_errors(fn):
    """Turn typed library errors (and Ctrl-C) into one line on stderr and an exit code."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except LidarSlamError as exc:
            raise _exit(str(exc), getattr(exc, "exit_code", EXIT_BAD_INPUT)) from None
        except KeyboardInterrupt:
            raise _exit("interrupted", EXIT_INTERRUPTED) from None
        except BrokenPipeError:  # stdout closed early (`| head`): no error line, no traceback
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            raise typer.Exit(1) from None
        except OSError as exc:  # e.g. an output path that cannot be created or written
            where = exc.filename if exc.filename is not None else "output"
            raise _exit(f"{where}: {exc.strerror or exc}", EXIT_BAD_INPUT) from None

    return wrapper


def _print_version(value: bool) -> None:
    if value:
        from lidar_slam.provenance import version_line

        typer.echo(version_line())
        raise typer.Exit()


@app.callback()
def main(verbose: bool = typer.Option(False, "--verbose", "-v", help="Debug logging."),
         version: bool = typer.Option(False, "--version", callback=_print_version,
                                      is_eager=True, help="Print the version and exit.")) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)


UNITS = {"wall_s": "s", "fps": "frames/s", "peak_rss_mb": "MB", "path_length_m": "m",
         "map_points": "points", "rpe_trans_m_mean": "m", "rpe_rot_deg_mean": "deg",
         "end_drift_pct": "%", "ate_rmse_m": "m", "odometry_ate_rmse_m": "m",
         "odometry_ms_per_frame": "ms", "loops_ms_per_frame": "ms",
         "loop_worker_ms_per_frame": "ms", "loop_wait_ms_per_frame": "ms",
         "loop_wait_final_s": "s",
         "backend_ms_per_loop_max": "ms", "backend_s": "s", "backend_final_s": "s",
         "backend_share_pct": "%", "map_load_s": "s", "fps_after_load": "frames/s",
         "localize_ms_per_frame": "ms", "track_ms_per_frame": "ms",
         "relocalise_ms_per_attempt": "ms"}


def _summary_table(summary: dict) -> str:
    """The run summary as an aligned two-column table, every number with its unit."""
    rows = []
    for key, value in summary.items():
        if value is None or value == {}:  # e.g. no topic, no git commit: summary.json only
            continue
        text = f"{value:.4g}" if isinstance(value, float) else str(value)
        rows.append((key, f"{text} {UNITS.get(key, '')}".strip()))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)


class _StopSignals:
    """While active, Ctrl-C and SIGTERM (kill, timeout, docker stop, a batch scheduler) ask the
    run to stop after the scan in hand, so the frames computed so far are kept and written; a
    second one stops at once (KeyboardInterrupt). Inside deferred() every signal is only noted,
    so the outputs being written are finished first: the handler stays installed from the first
    scan to the last output (no moment where Python's default handler is back)."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self.received = False
        self.name = ""  # the first signal's name (SIGINT, SIGTERM), for summary.json
        self._deferring = False
        self._old: dict = {}

    def _handle(self, signum, frame):
        if self.received and not self._deferring:
            raise KeyboardInterrupt
        self.received = True
        self.name = self.name or signal.Signals(signum).name

    def __enter__(self):
        try:
            for sig in self.SIGNALS:
                self._old[sig] = signal.signal(sig, self._handle)
        except ValueError:  # not the main thread (embedded use): leave signals alone
            self.__exit__()
        return self

    def __exit__(self, *exc) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)
        self._old = {}

    @contextlib.contextmanager
    def deferred(self):
        self._deferring = True
        try:
            yield
        finally:
            self._deferring = False


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
        raise _fail(f"{out}: --out is a file, not a folder")
    blocker = next((p for p in out.parents if p.exists() and not p.is_dir()), None)
    if blocker is not None:
        raise _fail(f"{out}: cannot create --out: {blocker} is a file, not a folder")
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


def _progress_interval_s() -> float:
    """Seconds between progress lines when stderr is not a terminal (LIDAR_SLAM_PROGRESS_S)."""
    try:
        return max(0.0, float(os.environ.get("LIDAR_SLAM_PROGRESS_S", "10")))
    except ValueError:
        return 10.0


class _Progress:
    """Progress on stderr (stdout keeps the results that scripts parse): on a terminal, a rich
    bar with the rate, elapsed time and ETA; otherwise (a log file, CI, nohup) one line at least
    every LIDAR_SLAM_PROGRESS_S seconds (10), rich not imported."""

    def __init__(self, name: str, total: int, done: int = 0, unit: str = "frames"):
        self.name, self.total, self.unit = name, total, unit
        self.done0 = self.done = done
        self.t0 = self.last = time.perf_counter()
        self.interval = _progress_interval_s()
        self.bar = None
        if sys.stderr.isatty():
            from rich.console import Console
            from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn,
                                       TimeElapsedColumn, TimeRemainingColumn)

            self.bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(),
                                MofNCompleteColumn(),
                                TextColumn(f"{{task.fields[rate]:.1f}} {unit}/s"),
                                TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(),
                                console=Console(stderr=True))
            self.task = self.bar.add_task(name, total=total, completed=done, rate=0.0)
            self.bar.start()

    def tick(self, *_) -> None:
        self.done += 1
        now = time.perf_counter()
        rate = (self.done - self.done0) / max(now - self.t0, 1e-9)
        if self.bar is not None:
            self.bar.update(self.task, advance=1, rate=rate)
        elif now - self.last >= self.interval:
            self.last = now
            eta = (self.total - self.done) / rate if rate > 0 else float("nan")
            typer.echo(f"lidar-slam: {self.name}: {self.done}/{self.total} {self.unit} "
                       f"({100.0 * self.done / max(self.total, 1):.0f} %), {rate:.1f} "
                       f"{self.unit}/s, {now - self.t0:.0f} s elapsed, ETA {eta:.0f} s",
                       err=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()


def _has_display() -> bool:
    """Whether a window can open (the rerun viewer): always on macOS and Windows, elsewhere
    when an X11 or Wayland display is set."""
    if sys.platform in ("darwin", "win32"):
        return True
    return any(os.environ.get(v) for v in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET"))


def _open_viewer(viz: bool, rrd: Path | None):
    """The rerun logger for --viz / --rrd, or None. Without a display --viz is dropped with one
    warning (the viewer would fail, and rerun would end the run in a traceback)."""
    if viz and not _has_display():
        log.warning("--viz: no display (DISPLAY / WAYLAND_DISPLAY unset), so no viewer; the run "
                    "goes on (record with --rrd FILE and open it with `rerun FILE` elsewhere)")
        viz = False
    if not viz and rrd is None:
        return None
    from lidar_slam.viz import RerunViz

    return RerunViz(spawn=viz, rrd_path=rrd)


def _discard_run(out: Path, created: bool) -> None:
    """Remove what a run that produced no frame wrote (and --out itself if the run made it), so
    no 0-frame run folder is left behind."""
    for name in RUN_OUTPUTS:
        if name == "error_traceback.txt":
            continue
        path = out / name
        if path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
        elif path.exists():
            path.unlink()
    if created and out.is_dir() and not any(out.iterdir()):
        out.rmdir()


def _deskew_state(cfg, n_timed: int, n_read: int) -> str:
    """What deskew did, for summary.json: on, off by config, or off for lack of point times."""
    if not cfg.data.deskew:
        return "off (--no-deskew or data.deskew: false)"
    if n_timed == 0:
        return "off (the scans carry no per-point times)"
    if n_timed < n_read:
        return f"on for the {n_timed} of {n_read} scans with per-point times"
    return "on"


@dataclass
class _LoopEnd:
    """How the scan loop of `run` ended: a bad-input or an internal error (traceback), and
    how many scans it read, how many with per-point times."""

    error: str | None = None
    internal_error: str | None = None
    n_read: int = 0
    n_timed: int = 0


def _process_scans(pipe, scans, out: Path, stop: _StopSignals, progress: _Progress) -> _LoopEnd:
    """Feed the scans to the pipeline until the end, a signal or an error, streaming the
    odometry and writing checkpoints; errors are kept, so the frames so far can be written."""
    import traceback

    from lidar_slam import checkpoint
    from lidar_slam.outputs import OdometryStream

    end = _LoopEnd()
    stream = OdometryStream(out, pipe.result.odom_poses)
    every = pipe.cfg.checkpoint.every_keyframes
    try:
        for scan in scans:
            if stop.received:
                break
            n_kf = len(pipe.result.store)
            pipe.process(scan)
            end.n_read += 1
            end.n_timed += scan.point_times is not None
            progress.tick()
            stream.append(pipe.result.odom_poses[-1])
            if every and len(pipe.result.store) != n_kf and len(pipe.result.store) % every == 0:
                checkpoint.save(out, pipe, pipe.loops_applied_upto)
    except KeyboardInterrupt:
        stop.received = True
    except LidarSlamError as exc:
        end.error = str(exc)
    except Exception:  # a bug must not cost the frames already computed: keep them, report it
        end.internal_error = traceback.format_exc()
        log.error("internal error after %d frames", len(pipe.result.indices))
    finally:
        progress.close()
        stream.close()
    return end


def _nothing_written(end: _LoopEnd, interrupted: bool, out: Path, data: Path, frames: int,
                     cfg) -> CommandError:
    """The one line for a run that ended without a frame worth writing (nothing was written)."""
    if end.internal_error:
        from lidar_slam.io.atomic import write_text_atomic

        out.mkdir(parents=True, exist_ok=True)
        write_text_atomic(out / "error_traceback.txt", end.internal_error)
        return _fail(f"internal error before the first scan (traceback in "
                     f"{out / 'error_traceback.txt'})", 1)
    if end.error:
        return _fail(end.error)
    if interrupted:
        return _fail("interrupted before the first scan; nothing written", EXIT_INTERRUPTED)
    return _fail(f"{data}: no valid points in any of the {frames} scans read (all empty, NaN, "
                 f"fewer than data.min_points {cfg.data.min_points}, or outside "
                 f"data.min_range_m..max_range_m {cfg.data.min_range_m:g}.."
                 f"{cfg.data.max_range_m:g} m); nothing written")


def _stop_reason(end: _LoopEnd, stop: _StopSignals) -> str:
    """Why the scan loop ended, for summary.json: the input's end, a signal, or an error."""
    if end.internal_error:
        return "internal error (traceback in error_traceback.txt)"
    if end.error:
        return f"input error: {end.error}"
    if stop.received:
        return f"interrupted ({stop.name or 'KeyboardInterrupt'})"
    return "end of input"


class _NoProgress:
    """Progress of a run nobody watches (a batch task: `batch` reports per sequence)."""

    def tick(self, *_) -> None:
        pass

    def close(self) -> None:
        pass


@dataclass
class RunOutcome:
    """What run_sequence wrote: the summary, the source's ground truth (all input scans, or
    None), and the one-line error of a run that stopped early (its frames so far written)."""

    summary: dict
    ground_truth: object | None
    failure: CommandError | None = None


def run_sequence(data: Path, out: Path, *, config: Path | None = None, start: int = 0,
                 n_scans: int | None = None, topic: str | None = None,
                 overrides: dict | None = None, viz: bool = False, rrd: Path | None = None,
                 overwrite: bool = False, resume: bool = False,
                 progress: bool = True) -> RunOutcome:
    """Everything `lidar-slam run` does for one input, without printing: the run-folder rules,
    resume, signals, the pipeline and the outputs. `run` and every `batch` task call this.
    Raises CommandError when nothing was written."""
    from lidar_slam import __version__, checkpoint
    from lidar_slam.config import load_config
    from lidar_slam.io.atomic import write_text_atomic
    from lidar_slam.io.sources import open_source, read_ahead
    from lidar_slam.outputs import write_run
    from lidar_slam.pipeline import Pipeline
    from lidar_slam.provenance import git_commit

    cfg = load_config(config, overrides)
    source = open_source(data, topic=topic,
                         kitti_vertical_correction=cfg.data.kitti_vertical_correction)
    if start >= len(source):
        raise _fail(f"{data}: --start {start} is past the last scan ({len(source)} scans)")
    total = len(source) - start if n_scans is None else min(n_scans, len(source) - start)
    created = not out.exists()
    resuming = prepare_out_dir(out, RUN_OUTPUTS, overwrite, resume)
    identity = checkpoint.describe_run(data, start, n_scans, topic, cfg)
    if resuming and not checkpoint.has_checkpoint(out):
        if (out / "checkpoint" / "run.json").is_file():
            checkpoint.check_same_run(out, identity)
        prepare_out_dir(out, RUN_OUTPUTS, overwrite=True)  # killed before its first checkpoint
        resuming = False
    elif resuming:
        checkpoint.check_same_run(out, identity)
    visualizer = _open_viewer(viz, rrd)
    t0 = time.perf_counter()
    stop = _StopSignals()
    with stop:  # from here on, a signal stops the run after the scan in hand
        pipe = Pipeline(cfg, out, visualizer, resume=resuming)
        pipe.frames_total = total
        done = 0
        if resuming:
            done = checkpoint.restore(out, pipe)
            log.warning("resuming %s at frame %d of %d", out, done, total)
        else:
            checkpoint.start_run(out, identity)
        label = f"{source.name}:{source.topic}" if source.topic else source.name
        end = _process_scans(pipe, read_ahead(source.scans(start + done, total - done)), out,
                             stop, _Progress(label, total, done) if progress else _NoProgress())
        with stop.deferred():  # a signal now waits until the outputs are written
            frames = len(pipe.result.indices)
            skipped = pipe.result.skipped_empty + pipe.result.skipped_small
            if frames == skipped:  # no frame, or no scan with enough valid points
                pipe.close()
                _discard_run(out, created)
                raise _nothing_written(end, stop.received, out, data, frames, cfg)
            result = pipe.finish()
            status = {"interrupted": stop.received, "stopped": _stop_reason(end, stop),
                      "frames_requested": total}
            if end.error:
                status["stopped_by_error"] = end.error
            run_info = {"input": str(data), "input_kind": source.kind, "topic": source.topic,
                        "config_overlay": str(config) if config is not None else None,
                        "deskew": _deskew_state(cfg, end.n_timed, end.n_read),
                        "input_notes": source.input_notes, "start": start,
                        "resumed_at_frame": done, "version": __version__,
                        "git_commit": git_commit()}
            summary = write_run(out, result, cfg, source.ground_truth, time.perf_counter() - t0,
                                extra={**status, **run_info})
            pipe.close()
            if end.internal_error:
                write_text_atomic(out / "error_traceback.txt", end.internal_error)
    if visualizer is not None:
        visualizer.finish(result, out / "map.ply")
    failure = None
    if end.internal_error:
        failure = _fail(f"internal error (traceback in {out / 'error_traceback.txt'}); the "
                        f"{summary['frames']} frames so far written to {out}", 1)
    elif end.error:
        failure = _fail(f"{end.error} (stopped there; frames so far written to {out})")
    elif stop.received:
        failure = _fail(f"interrupted; the {summary['frames']} frames so far written to {out}",
                        EXIT_INTERRUPTED)
    return RunOutcome(summary, source.ground_truth, failure)


@app.command()
@reports_errors
def run(
    data: Path = typer.Argument(..., help="Folder of scans, one scan file, KITTI sequence, KITTI "
                                          "raw drive, or rosbag/mcap."),
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
    """Run SLAM on DATA and write poses, map, config and summary into --out.

    DATA: a folder of scans (.bin/.pcd/.ply/.npy), one scan file, a KITTI sequence or raw
    drive, or a rosbag (.bag, ROS2 bag folder, .mcap).
    """
    outcome = run_sequence(data, out, config=config, start=start, n_scans=n_scans, topic=topic,
                           overrides=_run_overrides(no_loops, no_deskew), viz=viz, rrd=rrd,
                           overwrite=overwrite, resume=resume)
    typer.echo(_summary_table(outcome.summary))
    typer.echo(f"wrote {out}")
    if outcome.failure is not None:
        raise outcome.failure


def _run_overrides(no_loops: bool, no_deskew: bool) -> dict:
    """The config overrides of --no-loops and --no-deskew."""
    overrides: dict = {}
    if no_loops:
        overrides["loop"] = {"enabled": False}
    if no_deskew:
        overrides["data"] = {"deskew": False}
    return overrides


@app.command()
@reports_errors
def batch(
    data: list[str] = typer.Argument(..., help="Sequences, each as `run` takes it, or quoted "
                                               "globs ('/data/sequences/*')."),
    out: Path = typer.Option(..., "--out", "-o", help="Folder of the run folders (DIR/<name>/) "
                                                      "and results.md/.json/.csv."),
    address: Optional[str] = typer.Option(None, "--address",
                                          help="Ray cluster: auto (one started with `ray "
                                               "start`) or ray://HOST:PORT. Default: Ray "
                                               "inside this command, on this machine."),
    workers: Optional[int] = typer.Option(None, "--workers", min=1,
                                          help="Sequences at once (default: CPU count / "
                                               "--cpus-per-run; with --address: as many as "
                                               "the cluster's CPUs allow)."),
    cpus_per_run: int = typer.Option(1, "--cpus-per-run", min=1,
                                     help="CPUs each run reserves, and its kiss-icp threads "
                                          "(odometry.max_num_threads)."),
    config: Optional[Path] = typer.Option(None, "--config", "-c",
                                          help="YAML config overlay for every run."),
    start: int = typer.Option(0, "--start", min=0, help="First scan of every sequence."),
    n_scans: Optional[int] = typer.Option(None, "--n-scans", min=1,
                                          help="Scans per sequence (default: all)."),
    topic: Optional[str] = typer.Option(None, "--topic", help="PointCloud2 topic of the bags."),
    no_loops: bool = typer.Option(False, "--no-loops", help="Odometry only."),
    no_deskew: bool = typer.Option(False, "--no-deskew", help="Do not deskew."),
    overwrite: bool = typer.Option(False, "--overwrite",
                                   help="Run every sequence again (by default finished ones are "
                                        "skipped and partial ones resumed)."),
) -> None:
    """Run SLAM on many sequences, one Ray task each, and write one results table.

    Each sequence is run as `lidar-slam run DATA --out DIR/<name> --resume` would, so
    re-running the same command skips the finished sequences and resumes the partial ones.
    Exit code 0 when every sequence is ok, 1 when some failed, 130 after Ctrl-C.
    """
    from lidar_slam import __version__
    from lidar_slam.batch import BatchJob, expand_inputs, run_batch, sequence_names
    from lidar_slam.fleet import INSTALL, Fleet, ray_installed
    from lidar_slam.provenance import git_commit
    from lidar_slam.results import as_markdown

    if not ray_installed():
        raise _fail(f"batch runs on Ray, which is not installed: {INSTALL}")
    if out.exists() and not out.is_dir():
        raise _fail(f"{out}: --out is a file, not a folder")
    if config is not None and not config.is_file():
        raise _fail(f"{config}: config file does not exist")
    paths = expand_inputs(data)
    names = sequence_names(paths)
    overrides = _run_overrides(no_loops, no_deskew)
    overrides["odometry"] = {"max_num_threads": cpus_per_run}
    jobs = [BatchJob(name, str(path), str((out / name).absolute()),
                     str(config.absolute()) if config else None, start, n_scans, topic,
                     overrides, overwrite, cluster=address is not None)
            for name, path in zip(names, paths)]
    fleet = Fleet(address, workers, cpus_per_run)
    meta = {"command": "lidar-slam batch " + " ".join(sys.argv[2:]), "version": __version__,
            "git_commit": git_commit(), "address": address or "embedded",
            "cpus_per_run": cpus_per_run, "workers": workers}
    report = run_batch(jobs, out, fleet, _progress_interval_s(), meta)
    typer.echo(as_markdown(report.rows), nl=False)
    typer.echo(f"wrote {out / 'results.md'}, results.json and results.csv")
    n, finished = len(report.results), len(report.results) - report.failed
    if report.interrupted:
        raise _fail(f"interrupted; {finished} of {n} sequences finished and kept in {out}; "
                    f"re-run the same command to resume the others", EXIT_INTERRUPTED)
    if report.failed:
        raise _fail(f"{report.failed} of {n} sequences failed, {finished} ok (see "
                    f"{out / 'results.md'})", 1)


class Robust(str, Enum):
    huber = "huber"
    gnc = "gnc"
    none = "none"


class Init(str, Enum):
    auto = "auto"
    file = "file"
    chordal = "chordal"


class Certify(str, Enum):
    auto = "auto"
    on = "on"
    off = "off"


class Weights(str, Enum):
    file = "file"
    sesync = "sesync"


class TrajFormat(str, Enum):
    auto = "auto"
    kitti = "kitti"
    tum = "tum"


@app.command()
@reports_errors
def optimize(
    graph: Path = typer.Argument(..., help="Input g2o (2D SE2 or 3D SE3:QUAT)."),
    out: Path = typer.Option(..., "--out", "-o", help="Optimised g2o to write."),
    robust: Robust = typer.Option(Robust.none, "--robust",
                                  help="Kernel on loop edges; gnc: graduated non-convexity "
                                       "(truncated least squares), odometry edges known inliers."),
    huber_k: float = typer.Option(1.345, "--huber-k", help="Huber threshold (whitened)."),
    init: Init = typer.Option(Init.auto, "--init",
                              help="Start: the file's poses, a global initialisation (chordal in "
                                   "3D, LAGO in 2D), or auto: both, the lower final error kept "
                                   "(with --robust gnc: the odometry chain)."),
    certify: Certify = typer.Option(Certify.auto, "--certify",
                                    help="Shonan rotation certificate (auto: graphs up to "
                                         "6000 nodes)."),
    weights: Weights = typer.Option(Weights.file, "--weights",
                                    help="sesync: SE-Sync's isotropic weights instead of the "
                                         "file's information (its optimum is SE-Sync's p*)."),
    max_iterations: int = typer.Option(100, "--max-iterations", min=1,
                                       help="Levenberg-Marquardt iterations at most."),
) -> None:
    """Optimise a pose graph with GTSAM (prior on the first pose): LM, Huber or GNC."""
    from lidar_slam.backend.g2o_optimize import optimize_g2o

    if robust == Robust.huber and not huber_k > 0:
        raise _fail(f"--huber-k must be positive, got {huber_k}")
    rep = optimize_g2o(graph, out, robust=robust.value, huber_k=huber_k,
                       max_iterations=max_iterations, init=init.value, certify=certify.value,
                       weights=weights.value)
    typer.echo(f"graph={graph} dims={rep.dims} vertices={rep.n_vertices} edges={rep.n_edges} "
               f"loop_edges={rep.n_loop_edges} robust={rep.robust} "
               f"repaired_information={rep.n_repaired} weights={weights.value}")
    tried = ", ".join(f"{name}={'skipped (starts higher)' if err is None else f'{err:.6g}'}"
                      for name, err in rep.candidates)
    typer.echo(f"init={rep.init} ({tried})")
    typer.echo(f"initial_error={rep.initial_error:.6g}")
    typer.echo(f"final_error={rep.final_error:.6g}")
    typer.echo(f"sesync_objective={rep.sesync_objective:.6g}")
    label = "rejected" if rep.robust == "gnc" else "outside_99pct_gate"
    typer.echo(f"loops: {label}={rep.n_loops_rejected} of {rep.n_loop_edges}")
    cert = rep.certificate
    if cert is None:
        typer.echo("rotations_certified=not_run")
    elif cert.certified:
        typer.echo(f"rotations_certified=yes (ShonanAveraging{rep.dims}: rotation-only problem at "
                   f"its global optimum, lambda_min={cert.lambda_min:.3g}, "
                   f"{cert.seconds:.2f} s)")
    else:
        why = cert.note or f"lambda_min={cert.lambda_min:.3g}"
        typer.echo(f"rotations_certified=no ({why}, {cert.seconds:.2f} s)")
    iterations = "-" if rep.iterations is None else rep.iterations
    typer.echo(f"iterations={iterations} seconds={rep.seconds:.3f} "
               f"cpu_seconds={rep.cpu_seconds:.3f} load_seconds={rep.load_seconds:.3f}")
    typer.echo(f"wrote {out}")


@app.command("eval")
@reports_errors
def eval_cmd(
    est: Path = typer.Argument(..., help="Estimated trajectory (KITTI or TUM file)."),
    gt: Path = typer.Argument(..., help="Ground-truth trajectory (KITTI or TUM file)."),
    fmt: TrajFormat = typer.Option(TrajFormat.auto, "--format",
                                   help="Format of both files; auto: each told by its columns "
                                        "(12 KITTI, 8 TUM), so they may differ."),
    calib: Optional[Path] = typer.Option(None, "--calib", help="KITTI calib: GT cam0 -> lidar."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="metrics.json and plots here."),
    loops: Optional[Path] = typer.Option(None, "--loops", help="loops.csv of the run."),
    start: Optional[int] = typer.Option(None, "--start", min=0,
                                        help="The run's --start: EST line 0 is GT line START "
                                             "(and loops.csv frames count from the input's "
                                             "first scan)."),
    gt_times: Optional[Path] = typer.Option(None, "--gt-times",
                                            help="Stamps of a KITTI-format GT (times.txt), to "
                                                 "pair it with a TUM estimate by time."),
    revisit_gap: int = typer.Option(100, "--revisit-gap", min=1,
                                    help="Loop recall: frames between two passes of a place "
                                         "for the second to count as a revisit."),
    gt_label: Optional[str] = typer.Option(None, "--gt-label",
                                           help="What GT is called in the plots (default: "
                                                "'reference' where a README beside GT says it "
                                                "is not ground truth, else 'ground truth')."),
) -> None:
    """KITTI drift (t_err %, r_err deg/100 m), ATE and RPE of EST against GT.

    EST and GT: KITTI (12 numbers per line) or TUM (stamp tx ty tz qx qy qz qw) files.
    """
    from lidar_slam.evaluate import format_table, run_eval

    metrics = run_eval(est, gt, fmt=fmt.value, calib_path=calib, out_dir=out, loops_csv=loops,
                       start=start, gt_times=gt_times, revisit_gap=revisit_gap,
                       gt_label=gt_label)
    typer.echo(format_table(metrics))
    if out is not None:
        typer.echo(f"wrote {out}")


class Sensor(str, Enum):
    hdl64 = "hdl64"
    vlp16 = "vlp16"
    os1_64 = "os1-64"


@dataclass(frozen=True)
class SimulateJob:
    """One sequence of `simulate`: the pose file, the files beside it and the options."""

    poses: str
    out: str
    calib: str | None = None
    times: str | None = None
    sensor: str = "hdl64"
    start: int = 0
    n_scans: int | None = None
    seed: int = 0
    overwrite: bool = False


def simulate_one(job: SimulateJob, progress: bool = True) -> str:
    """Simulate one sequence into job.out (the --out rule applies); returns the line to print.
    A missing --calib is looked up as ../calib/<name>.txt beside POSES, as --times."""
    import numpy as np

    from lidar_slam.io.trajectory import (camera_to_lidar_poses, read_kitti_calib_tr,
                                          read_kitti_poses, read_times)
    from lidar_slam.simulate import simulate_sequence

    poses, out = Path(job.poses), Path(job.out)
    calib = Path(job.calib) if job.calib else poses.parent.parent / "calib" / poses.name
    if job.calib is None and not calib.is_file():
        raise _fail(f"{poses}: no --calib given and no {calib} beside it; pass --calib")
    prepare_out_dir(out, SIMULATE_OUTPUTS, job.overwrite)
    Tr = read_kitti_calib_tr(calib)
    poses_lidar = camera_to_lidar_poses(read_kitti_poses(poses), Tr)
    times = Path(job.times) if job.times else poses.parent.parent / "times" / poses.name
    if times.is_file():
        stamps = read_times(times)
    else:
        log.warning("%s not found: poses taken as 0.1 s apart (10 Hz); pass --times", times)
        stamps = np.arange(len(poses_lidar)) * 0.1
    if len(stamps) != len(poses_lidar):
        raise _fail(f"{times}: {len(stamps)} stamps for {len(poses_lidar)} poses")
    start, n_scans = job.start, job.n_scans
    if start >= len(poses_lidar):
        raise _fail(f"{poses}: --start {start} is past the last pose ({len(poses_lidar)})")
    total = len(poses_lidar) - start if n_scans is None else min(n_scans, len(poses_lidar) - start)
    bar = _Progress(f"simulate {out.name}", total, unit="scans") if progress else _NoProgress()
    try:
        summary = simulate_sequence(poses_lidar, stamps, out, sensor=job.sensor, seed=job.seed,
                                    start=start, n_scans=n_scans, Tr_cam_lidar=Tr,
                                    on_scan=bar.tick)
    finally:
        bar.close()
    return (f"simulated {summary.n_scans} scans ({summary.points_per_scan:.0f} points/scan, "
            f"{summary.seconds_per_scan:.3f} s/scan) into {out}")


def simulate_job(job: SimulateJob) -> tuple[bool, str]:
    """simulate_one as a job of many (a Ray task): (True, its line) or (False, its error)."""
    try:
        return True, simulate_one(job, progress=False)
    except LidarSlamError as exc:
        return False, str(exc)
    except (OSError, ValueError) as exc:
        return False, f"{job.poses}: {exc}"


def _simulate_many(jobs: list[SimulateJob], names: list[str], address: str | None,
                   workers: int | None) -> None:
    """Several sequences: in parallel on Ray when it is installed, else one after another;
    a failing one is reported and the others go on."""
    from lidar_slam.batch import JobProgress
    from lidar_slam.fleet import INSTALL, Fleet, ray_installed

    progress = JobProgress("simulate", names, _progress_interval_s())
    failed = 0

    def report(index: int, ok: bool, text: str) -> None:
        nonlocal failed
        failed += not ok
        progress.finished(index, ok, "ok" if ok else f"error: {text}")
        if ok:
            typer.echo(text)

    if ray_installed():
        with Fleet(address, workers) as fleet:
            progress.restart_clock()
            for outcome in fleet.map(simulate_job, jobs, on_wait=progress.waiting):
                ok, text = outcome.value if outcome.error is None else (False, outcome.error)
                report(outcome.index, ok, text)
    else:
        if address is not None:
            raise _fail(f"--address needs Ray, which is not installed: {INSTALL}")
        log.warning("Ray is not installed: simulating the %d sequences one after another "
                    "(for all at once: %s)", len(jobs), INSTALL)
        for i, job in enumerate(jobs):
            report(i, *simulate_job(job))
    if failed:
        raise _fail(f"{failed} of {len(jobs)} sequences failed", 1)


@app.command()
@reports_errors
def simulate(
    poses: list[Path] = typer.Argument(..., help="KITTI pose file(s) (left-camera frame, as "
                                                 "poses/XX.txt); several: one sequence each."),
    out: Path = typer.Option(..., "--out", "-o",
                             help="KITTI-layout sequence folder to write; with several POSES, "
                                  "the folder of one sequence per file (OUT/<name>)."),
    calib: Optional[Path] = typer.Option(None, "--calib",
                                         help="KITTI calib with Tr (velodyne -> cam0); "
                                              "default: ../calib/<name>.txt beside POSES."),
    times: Optional[Path] = typer.Option(None, "--times", help="Stamps (s); default: "
                                         "../times/<name>.txt beside POSES, else 10 Hz."),
    sensor: Sensor = typer.Option(Sensor.hdl64, "--sensor", help="Lidar model to simulate."),
    start: int = typer.Option(0, "--start", min=0, help="First pose to simulate (0-based)."),
    n_scans: Optional[int] = typer.Option(None, "--n-scans", min=1,
                                          help="Number of scans (default: to the last pose)."),
    seed: int = typer.Option(0, "--seed", help="World and noise seed (same seed, same bytes)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace a sequence in --out."),
    address: Optional[str] = typer.Option(None, "--address",
                                          help="Several POSES: the Ray cluster to use (as "
                                               "`batch --address`); default: this machine."),
    workers: Optional[int] = typer.Option(None, "--workers", min=1,
                                          help="Several POSES: sequences at once (default: "
                                               "the CPU count)."),
) -> None:
    """Ray-cast a lidar along a real trajectory through a procedural street world.

    POSES: KITTI pose files (left-camera frame, as poses/XX.txt). With several, each becomes
    OUT/<name>, simulated in parallel when Ray is installed (`lidar-slam[cluster]`).
    """
    if len(poses) == 1:
        typer.echo(simulate_one(SimulateJob(str(poses[0]), str(out), _str(calib), _str(times),
                                            sensor.value, start, n_scans, seed, overwrite)))
        return
    from lidar_slam.batch import sequence_names

    if times is not None:
        raise _fail("--times takes one POSES; with several, each uses ../times/<name>.txt "
                    "beside it (else 10 Hz)")
    paths = [p.absolute() for p in poses]
    names = sequence_names(paths)
    out.mkdir(parents=True, exist_ok=True)
    jobs = [SimulateJob(str(p), str((out / name).absolute()), _str(calib and calib.absolute()),
                        None, sensor.value, start, n_scans, seed, overwrite)
            for p, name in zip(paths, names)]
    _simulate_many(jobs, names, address, workers)


def _str(path: Path | None) -> str | None:
    return None if path is None else str(path)


def _parse_initial_pose(text: str | None):
    """x,y,z,yaw (m, m, m, deg) -> T_map_scan, or None."""
    if text is None:
        return None
    from lidar_slam.localize import initial_pose_matrix

    try:
        x, y, z, yaw = (float(v) for v in text.split(","))
    except ValueError:
        raise _fail(f"--initial-pose: expected x,y,z,yaw (metres, metres, metres, degrees), "
                    f"got {text!r}") from None
    return initial_pose_matrix(x, y, z, yaw)


@app.command()
@reports_errors
def localize(
    data: Path = typer.Argument(..., help="Scans to localise (any DATA that `run` reads)."),
    map_dir: Path = typer.Option(..., "--map", help="Run folder of the map (a finished `run`)."),
    out: Path = typer.Option(..., "--out", "-o", help="Folder to write."),
    config: Optional[Path] = typer.Option(None, "--config", "-c",
                                          help="YAML overlay on the map's config.yaml."),
    start: int = typer.Option(0, "--start", min=0, help="First scan (0-based)."),
    n_scans: Optional[int] = typer.Option(None, "--n-scans", min=1, help="Number of scans."),
    topic: Optional[str] = typer.Option(None, "--topic", help="PointCloud2 topic of a bag."),
    initial_pose: Optional[str] = typer.Option(None, "--initial-pose",
                                               help="x,y,z,yaw of the first scan in the map "
                                                    "frame (m, m, m, deg); else found by "
                                                    "relocalisation."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace the files in --out."),
) -> None:
    """Localise DATA in a saved map: poses in the map frame and a status per frame.

    Relocalisation (Scan Context + the loop-closure ICP gates) finds the pose without an
    initial guess; then each scan is registered against the fixed map from the motion model's
    prediction, and relocalised whenever tracking is lost.
    """
    from lidar_slam import __version__
    from lidar_slam.io.sources import open_source, read_ahead
    from lidar_slam.localize import Localizer
    from lidar_slam.outputs import LOCALIZE_OUTPUTS, write_localization
    from lidar_slam.provenance import git_commit
    from lidar_slam.saved_map import open_map

    T_init = _parse_initial_pose(initial_pose)
    t0 = time.perf_counter()
    saved = open_map(map_dir, config)
    source = open_source(data, topic=topic,
                         kitti_vertical_correction=saved.cfg.data.kitti_vertical_correction)
    if start >= len(source):
        raise _fail(f"{data}: --start {start} is past the last scan ({len(source)} scans)")
    total = len(source) - start if n_scans is None else min(n_scans, len(source) - start)
    prepare_out_dir(out, LOCALIZE_OUTPUTS, overwrite)
    loc = Localizer(saved, T_init)
    load_s = time.perf_counter() - t0
    frames: list = []
    error = None
    stop = _StopSignals()
    with stop:
        progress = _Progress(f"localize {source.name}", total)
        t1 = time.perf_counter()
        try:
            for scan in read_ahead(source.scans(start, total)):
                if stop.received:
                    break
                frames += loc.step(scan)
                progress.tick()
        except KeyboardInterrupt:
            stop.received = True
        except LidarSlamError as exc:
            error = str(exc)
        finally:
            progress.close()
        frames += loc.finish()
        loop_s = time.perf_counter() - t1
        with stop.deferred():
            saved.close()
            if not frames:
                raise _fail(error or f"{data}: no scan localised; nothing written",
                            EXIT_INTERRUPTED if stop.received and not error else EXIT_BAD_INPUT)
            st = loc.stats
            n = len(frames)
            wall_s = time.perf_counter() - t0
            summary = write_localization(out, frames, {
                "relocalisations": st.relocalisations,
                "relocalisation_attempts": st.relocalisation_attempts,
                "wall_s": wall_s, "fps": n / wall_s, "map_load_s": load_s,
                "fps_after_load": n / loop_s if loop_s > 0 else 0.0,
                "localize_ms_per_frame": 1e3 * st.compute_s() / n,
                "track_ms_per_frame": 1e3 * st.seconds["track"] / n,
                "relocalise_ms_per_attempt": (1e3 * st.seconds["relocalise"]
                                              / max(st.relocalisation_attempts, 1)),
                "map": str(map_dir), "map_keyframes": len(saved),
                "input": str(data), "input_kind": source.kind,
                "topic": source.topic, "start": start, "initial_pose": initial_pose,
                "interrupted": stop.received, "stopped_by_error": error,
                "version": __version__, "git_commit": git_commit()})
    typer.echo(_summary_table(summary))
    typer.echo(f"wrote {out}")
    if error:
        raise _fail(f"{error} (stopped there; frames so far written to {out})")
    if stop.received:
        raise _fail(f"interrupted; the {n} frames so far written to {out}", EXIT_INTERRUPTED)


def _parse_band(text: str) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise _fail(f"--band: expected LOW,HIGH in metres above the ground, got {text!r}"
                    ) from None
    if not 0 <= lo < hi:
        raise _fail(f"--band: need 0 <= LOW < HIGH, got {text!r}")
    return lo, hi


class PointFormatOption(str, Enum):
    ply = "ply"
    pcd = "pcd"
    las = "las"
    laz = "laz"


OCCUPANCY_OUTPUTS = ("map.png", "map.yaml")


@app.command()
@reports_errors
def export(
    run_dir: Path = typer.Argument(..., help="Run folder (a finished `run`)."),
    out: Optional[Path] = typer.Option(None, "--out", "-o",
                                       help="Point file to write; with --occupancy the folder "
                                            "for map.png / map.yaml (default: RUN_DIR)."),
    fmt: Optional[PointFormatOption] = typer.Option(None, "--format",
                                                    help="Point format (default: --out's "
                                                         "suffix)."),
    voxel: Optional[float] = typer.Option(None, "--voxel",
                                          help="Keep one point per voxel of this size (m)."),
    occupancy: bool = typer.Option(False, "--occupancy",
                                   help="Write a 2-D occupancy grid (ROS map_server format)."),
    resolution: float = typer.Option(0.1, "--resolution", help="Occupancy cell size (m)."),
    band: str = typer.Option("0.3,2.0", "--band",
                             help="Heights above the ground that are obstacles (m, LOW,HIGH)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace existing output."),
) -> None:
    """Export a run's map: points as PLY / PCD / LAS / LAZ, or an occupancy grid.

    Points are the keyframe clouds placed with the final poses (the frame of poses_kitti.txt),
    with intensity and the id of their keyframe.
    """
    from lidar_slam.saved_map import open_map

    for name, value in (("--voxel", voxel), ("--resolution", resolution)):
        if value is not None and not value > 0:
            raise _fail(f"{name} must be positive, got {value:g}")
    if occupancy:
        from lidar_slam.occupancy import OccupancyParams, build_grid, write_map_server

        params = OccupancyParams(resolution_m=resolution, band_m=_parse_band(band))
        folder = out if out is not None else run_dir
        saved = open_map(run_dir)
        if folder == run_dir or out is None:
            held = [n for n in OCCUPANCY_OUTPUTS if (folder / n).exists()]
            if held and not overwrite:
                raise _fail(f"{folder}: already holds {', '.join(held)}; pass --overwrite")
        else:
            prepare_out_dir(folder, OCCUPANCY_OUTPUTS, overwrite)
        try:
            grid = build_grid(saved, params)
        finally:
            saved.close()
        png, yaml_path = write_map_server(grid, folder, params)
        h, w = grid.state.shape
        typer.echo(f"wrote {png} and {yaml_path} ({w} x {h} cells of {resolution:g} m)")
        return
    from lidar_slam.export import (PointFormat, format_of, map_points, require_laspy,
                                   write_points)

    if out is None:
        raise _fail("--out FILE is needed (or --occupancy)")
    kind = format_of(out, None if fmt is None else PointFormat(fmt.value))
    if out.is_dir():
        raise _fail(f"{out}: --out is a folder, not a file")
    if out.exists() and not overwrite:
        raise _fail(f"{out}: already exists; pass --overwrite")
    if kind in (PointFormat.las, PointFormat.laz):
        require_laspy()  # before reading the map
    saved = open_map(run_dir)
    try:
        points = map_points(saved, voxel)
    finally:
        saved.close()
    out.parent.mkdir(parents=True, exist_ok=True)
    n = write_points(out, kind, points)
    typer.echo(f"wrote {n} points to {out}")


if __name__ == "__main__":
    app()
