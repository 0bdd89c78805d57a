"""The run driver: one input into one run folder, as `lidar-slam run` and every `batch` task do.

run_sequence applies the --out rules, resumes from a checkpoint, feeds the scans to the
pipeline until the end, a signal or an error (keeping the frames so far), and writes the
outputs. It prints nothing: the summary comes back in a RunOutcome, and a run that stopped
early carries its one-line RunFailed (a run that wrote nothing raises it).
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidar_slam.errors import EXIT_INTERRUPTED, LidarSlamError, RunFailed
from lidar_slam.run.outdir import (
    RUN_OUTPUTS,
    check_rrd,
    discard_run,
    prepare_out_dir,
    refuse_input_as_out,
    refuse_out_among_scans,
    say_short_range,
    scan_range,
)
from lidar_slam.run.progress import progress as make_progress
from lidar_slam.run.signals import StopSignals

log = logging.getLogger("lidar_slam")


def _has_display() -> bool:
    """Whether a window can open (the rerun viewer): always on macOS and Windows, elsewhere
    when an X11 or Wayland display is set."""
    if sys.platform in ("darwin", "win32"):
        return True
    return any(os.environ.get(v) for v in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET"))


def open_viewer(viz: bool, rrd: Path | None):
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
    """How the scan loop of a run ended: a bad-input or an internal error (traceback), and
    how many scans it read, how many with per-point times."""

    error: str | None = None
    internal_error: str | None = None
    n_read: int = 0
    n_timed: int = 0


def _process_scans(pipe, scans, out: Path, stop: StopSignals, progress) -> _LoopEnd:
    """Feed the scans to the pipeline until the end, a signal or an error, streaming the
    odometry and writing checkpoints; errors are kept, so the frames so far can be written."""
    import traceback

    from lidar_slam.run import checkpoint
    from lidar_slam.run.outputs import OdometryStream

    end = _LoopEnd()
    stream = OdometryStream(out, pipe.result.odom_poses[:pipe.settled_frames])
    streamed = pipe.settled_frames
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
            # frames whose pose a later scan no longer changes (Pipeline.settled_frames)
            for T in pipe.result.odom_poses[streamed:pipe.settled_frames]:
                stream.append(T)
            streamed = pipe.settled_frames
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
        for T in pipe.result.odom_poses[streamed:]:
            stream.append(T)
        stream.close()
    if every and (stop.received or end.error) and not end.internal_error and len(pipe.result.store):
        # Stopped by a signal or a bad scan: a checkpoint of every frame so far, so that
        # --resume goes on from here instead of from the last periodic one (or the start).
        with stop.deferred():
            checkpoint.save(out, pipe, pipe.loops_applied_upto)
    return end


def _nothing_written(end: _LoopEnd, interrupted: bool, out: Path, data: Path, frames: int,
                     cfg) -> RunFailed:
    """The one line for a run that ended without a frame worth writing (nothing was written)."""
    if end.internal_error:
        from lidar_slam.io.atomic import write_text_atomic

        out.mkdir(parents=True, exist_ok=True)
        write_text_atomic(out / "error_traceback.txt", end.internal_error)
        return RunFailed(f"internal error before the first scan (traceback in "
                         f"{out / 'error_traceback.txt'})", 1)
    if end.error:
        return RunFailed(end.error)
    if interrupted:
        return RunFailed("interrupted before the first scan; nothing written", EXIT_INTERRUPTED)
    return RunFailed(f"{data}: no valid points in any of the {frames} scans read (all empty, "
                     f"NaN, fewer than data.min_points {cfg.data.min_points}, or outside "
                     f"data.min_range_m..max_range_m {cfg.data.min_range_m:g}.."
                     f"{cfg.data.max_range_m:g} m); nothing written")


def _stop_reason(end: _LoopEnd, stop: StopSignals) -> str:
    """Why the scan loop ended, for summary.json: the input's end, a signal, or an error."""
    if end.internal_error:
        return "internal error (traceback in error_traceback.txt)"
    if end.error:
        return f"input error: {end.error}"
    if stop.received:
        return f"interrupted ({stop.name or 'KeyboardInterrupt'})"
    return "end of input"


def _failure(end: _LoopEnd, stop: StopSignals, out: Path, frames: int) -> RunFailed | None:
    """The one line of a run that stopped early (its frames so far written), or None."""
    if end.internal_error:
        return RunFailed(f"internal error (traceback in {out / 'error_traceback.txt'}); the "
                         f"{frames} frames so far written to {out}", 1)
    if end.error:
        return RunFailed(f"{end.error} (stopped there; frames so far written to {out})")
    if stop.received:
        return RunFailed(f"interrupted; the {frames} frames so far written to {out}",
                         EXIT_INTERRUPTED)
    return None


def _load_inertial(source, cfg, imu_topic: str | None, gnss_topic: str | None,
                   start: int = 0, count: int | None = None):
    """The input's own IMU and GNSS (source.inertial: beside the scans, in the bag, or in the
    dataset's or pcap's files), checked against the scan stamps and reported in summary.json:
    the IMU deskews and predicts in the front-end (Pipeline(inertial=)), both go into the back-end's
    final solve (Pipeline.finish). The IMU's clock offset and mounting the config and the input
    do not give are found from the data (lidar_slam.imu_calibration, over the run's first
    scans: start, count): returns (cfg with the values used, the input)."""
    from lidar_slam import imu_calibration as calib

    offset_auto = calib.offset_is_auto(cfg, source)
    mount_auto = calib.mount_is_auto(cfg)
    inertial = source.inertial(imu_enabled=cfg.imu.enabled, gnss_enabled=cfg.gnss.enabled,
                               imu_offset_s=None if offset_auto else cfg.imu.time_offset_s,
                               gnss_offset_s=cfg.gnss.time_offset_s, imu_topic=imu_topic,
                               gnss_topic=gnss_topic)
    if source.scan_clock is None:  # a single file: nothing to calibrate with
        offset_auto = mount_auto = False
    return calib.resolve(cfg, source, inertial, offset_auto, mount_auto, start, count)


def _mounting_from_input(cfg, source, imu_topic: str | None):
    """The config with the IMU mounting the input's own calibration gives (a public dataset's,
    io.datasets; an Ouster pcap's metadata; a bag's /tf_static), when the config does not give
    one itself (a value in the config always wins), and from where ("" when not taken)."""
    if not cfg.imu.enabled or "T_lidar_imu" in cfg.imu.model_fields_set:
        return cfg, ""
    T, where = source.own_mounting(imu_topic)
    if T is None or not np.isfinite(T).all():
        return cfg, ""
    values = [round(float(v), 9) + 0.0 for v in T.ravel()]
    imu = cfg.imu.model_copy(update={"T_lidar_imu": values})
    return cfg.model_copy(update={"imu": imu}), where


@dataclass
class RunOutcome:
    """What run_sequence wrote: the summary, the source's ground truth (all input scans, or
    None), and the one-line error of a run that stopped early (its frames so far written)."""

    summary: dict
    ground_truth: object | None
    failure: RunFailed | None = None
    finished_before: bool = False  # --resume of a run that had already finished: nothing done


def _finished(out: Path, identity: dict) -> dict | None:
    """The summary of the run in out when it is this same run (input, range, config), finished
    at the input's end; else None."""
    from lidar_slam.run import checkpoint

    try:
        summary = json.loads((out / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    if not (isinstance(summary, dict) and summary.get("stopped") == "end of input"
            and (out / "poses_kitti.txt").is_file()
            and (out / "checkpoint" / "run.json").is_file()
            and not checkpoint.has_checkpoint(out)):
        return None
    checkpoint.check_same_run(out, identity)  # another input or config: refused, as ever
    return summary


def _resuming(out: Path, identity: dict, overwrite: bool, resume: bool) -> bool:
    """Apply the --out rules; whether there is a checkpoint of this same run to resume."""
    from lidar_slam.run import checkpoint

    resuming = prepare_out_dir(out, RUN_OUTPUTS, overwrite, resume)
    if resume and not resuming:  # a missing or empty --out: nothing was ever run there
        log.warning("--resume: %s holds no run; starting from the first scan", out)
    if resuming and not checkpoint.has_checkpoint(out):
        if not (out / "checkpoint" / "run.json").is_file():
            # Files, but not a run of ours: starting over would delete those named like ours.
            raise RunFailed(f"{out}: --resume: holds files but no lidar-slam run (no "
                            f"checkpoint/run.json); pass another --out, or --overwrite to "
                            f"replace the files named like a run's")
        checkpoint.check_same_run(out, identity)
        # Killed before its first checkpoint (every checkpoint.every_keyframes keyframes), or
        # a run that ended before it: the same run again from the start, said in one line.
        log.warning("--resume: no checkpoint in %s (the run there stopped before its first: "
                    "one every checkpoint.every_keyframes keyframes); starting over from the "
                    "first scan", out)
        prepare_out_dir(out, RUN_OUTPUTS, overwrite=True)
        return False
    if resuming:
        checkpoint.check_same_run(out, identity)
    return resuming


def run_sequence(data: Path, out: Path, *, config: Path | None = None, start: int = 0,
                 n_scans: int | None = None, topic: str | None = None,
                 imu_topic: str | None = None, gnss_topic: str | None = None,
                 meta: Path | None = None,
                 overrides: dict | None = None, viz: bool = False, rrd: Path | None = None,
                 overwrite: bool = False, resume: bool = False,
                 progress: bool = True) -> RunOutcome:
    """Everything `lidar-slam run` does for one input, without printing: the run-folder rules,
    resume, signals, the pipeline and the outputs. `run` and every `batch` task call this.
    Raises RunFailed when nothing was written."""
    from lidar_slam import __version__
    from lidar_slam.config import load_config
    from lidar_slam.io.atomic import write_text_atomic
    from lidar_slam.io.sources import open_source, read_ahead
    from lidar_slam.pipeline import Pipeline
    from lidar_slam.provenance import git_commit
    from lidar_slam.run import checkpoint
    from lidar_slam.run.outputs import write_run
    from lidar_slam.run.painter import TopViewPainter

    refuse_input_as_out(out, {"input": data})
    cfg = load_config(config, overrides)
    source = open_source(data, topic=topic,
                         kitti_vertical_correction=cfg.data.kitti_vertical_correction, meta=meta)
    scan_files = getattr(source, "files", None)
    refuse_out_among_scans(out, scan_files)
    check_rrd(rrd, out, [data, *(scan_files or [])], overwrite, resume)
    total = scan_range(data, start, n_scans, len(source))
    say_short_range(data, start, n_scans, len(source))
    own_mounting, mounting_from = _mounting_from_input(cfg, source, imu_topic)
    resolved, inertial = _load_inertial(source, own_mounting, imu_topic, gnss_topic, start,
                                        total)
    if mounting_from and "imu" in inertial.summary:
        inertial.summary["imu"]["T_lidar_imu_from"] = (f"the input's own calibration "
                                                       f"({mounting_from})")
    cfg = resolved
    created = not out.exists()
    identity = checkpoint.describe_run(data, start, n_scans, topic, cfg, imu_topic, gnss_topic)
    if meta is not None:
        identity["meta"] = str(Path(meta).resolve())
    if resume and (summary := _finished(out, identity)) is not None:
        log.warning("--resume: the run in %s had already finished (its summary.json: end of "
                    "input); nothing to do (--overwrite runs it again)", out)
        return RunOutcome(summary, source.ground_truth, finished_before=True)
    painter = TopViewPainter.start()  # imports matplotlib beside the run, draws at its end
    try:
        resuming = _resuming(out, identity, overwrite, resume)
        if not resuming:
            # What the run is, before any other file of it: a run stopped at any instant after
            # this (a batch's worker killed while its pipeline starts) is one --resume knows.
            checkpoint.start_run(out, identity)
        visualizer = open_viewer(viz, rrd)
        t0 = time.perf_counter()
        stop = StopSignals()
        with stop:  # from here on, a signal stops the run after the scan in hand
            pipe = Pipeline(cfg, out, visualizer, resume=resuming, inertial=inertial)
            pipe.frames_total = total
            done = 0
            if resuming:
                done = checkpoint.restore(out, pipe)
                log.warning("resuming %s at frame %d of %d", out, done, total)
            label = f"{source.name}:{source.topic}" if source.topic else source.name
            end = _process_scans(pipe, read_ahead(source.scans(start + done, total - done)), out,
                                 stop, make_progress(label, total, done, shown=progress))
            with stop.deferred():  # a signal now waits until the outputs are written
                frames = len(pipe.result.indices)
                skipped = pipe.result.skipped_empty + pipe.result.skipped_small
                if frames == skipped:  # no frame, or no scan with enough valid points
                    pipe.close()
                    discard_run(out, created)
                    raise _nothing_written(end, stop.received, out, data, frames, cfg)
                result = pipe.finish()
                inertial = pipe.input  # as the IMU check left it
                status = {"interrupted": stop.received, "stopped": _stop_reason(end, stop),
                          "frames_requested": total}
                if end.error:
                    status["stopped_by_error"] = end.error
                run_info = {"input": str(data), "input_kind": source.kind, "topic": source.topic,
                            "config_overlay": str(config) if config is not None else None,
                            "deskew": _deskew_state(cfg, end.n_timed, end.n_read),
                            "input_notes": source.input_notes, **inertial.summary,
                            **({} if pipe.inertial is None
                               else {"imu_frontend": pipe.inertial.summary(),
                                     "imu_check": pipe.inertial.check.summary()}),
                            "start": start, "n_scans": n_scans,  # as asked (None: all)
                            "resumed_at_frame": done, "version": __version__,
                            "git_commit": git_commit()}
                summary = write_run(out, result, cfg, source.ground_truth, time.perf_counter() - t0,
                                    extra={**status, **run_info}, painter=painter)
                painter.close()
                pipe.close()
                if end.internal_error:
                    write_text_atomic(out / "error_traceback.txt", end.internal_error)
        if visualizer is not None:
            visualizer.finish(result, out / "map.ply")
        return RunOutcome(summary, source.ground_truth,
                          _failure(end, stop, out, summary["frames"]))
    finally:  # a run that stops by an exception ends its helper here, not in a finalizer
        painter.close()
