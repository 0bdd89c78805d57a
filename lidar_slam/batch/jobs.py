"""`lidar-slam batch`: many sequences, one Ray job each (lidar_slam.fleet), one results table
(lidar_slam.results).

Every job runs the same code as `lidar-slam run` (cli.run_sequence) into DIR/<name>/, with
`--resume` semantics: a sequence whose run folder holds a finished run of the same input, range
and config is skipped (its row is read back), a partial one (killed, interrupted) resumes from
its checkpoint. A failing sequence becomes an error row; the others go on.
"""

from __future__ import annotations

import glob
import json
import logging
import socket
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from lidar_slam.errors import InputError, LidarSlamError
from lidar_slam.results import SequenceResult, error_row, run_row, write_results

log = logging.getLogger(__name__)
SHARED_FS = ("every node of the cluster must read the inputs and write --out at the same paths "
             "(a shared file system)")
SKIPPED = "finished earlier: skipped"
INTERRUPTED = "interrupted; re-run the same command to resume"


@dataclass(frozen=True)
class BatchJob:
    """One sequence of a batch: absolute paths (Ray workers do not start in the caller's
    folder) and the options every run of the batch shares."""

    name: str
    data: str
    out: str
    config: str | None = None
    start: int = 0
    n_scans: int | None = None
    topic: str | None = None
    overrides: dict = field(default_factory=dict)
    overwrite: bool = False
    cluster: bool = False


def expand_inputs(patterns: list[str]) -> list[Path]:
    """Inputs in the given order, each glob (quoted, so the shell left it) replaced by its
    matches in natural order; a path named twice is run once. A glob without a match is an
    error; a plain path that does not exist becomes that sequence's error row."""
    from lidar_slam.io.sources import natural_key

    out: list[Path] = []
    for pattern in patterns:
        if any(c in pattern for c in "*?["):
            found = sorted(glob.glob(pattern), key=natural_key)
            if not found:
                raise InputError(pattern, "no input matches this pattern")
            paths = [Path(p) for p in found]
        else:
            paths = [Path(pattern)]
        for p in paths:
            p = p.absolute()
            if p not in out:
                out.append(p)
    return out


def sequence_names(paths: list[Path]) -> list[str]:
    """A folder name per input (a file's name without its suffix), made unique by prefixing
    the parent folders' names where two inputs share one: /a/07 and /b/07 are a_07 and b_07."""

    def name(p: Path, depth: int) -> str:
        parts = list(p.parts[-depth:])
        if p.suffix and not p.is_dir():
            parts[-1] = p.stem
        return "_".join(x.strip("/") or "root" for x in parts)

    depth = [1] * len(paths)
    while True:
        names = [name(p, d) for p, d in zip(paths, depth)]
        clash = [i for i, n in enumerate(names) if names.count(n) > 1]
        if not clash or all(depth[i] >= len(paths[i].parts) for i in clash):
            break
        for i in clash:
            depth[i] += 1
    seen: dict[str, int] = {}
    for i, n in enumerate(names):  # the same path twice was removed; this is a last resort
        seen[n] = seen.get(n, 0) + 1
        names[i] = n if seen[n] == 1 else f"{n}-{seen[n]}"
    return names


def finished_run(out: Path, identity: dict) -> bool:
    """Whether out holds a run that ended normally (not interrupted, not stopped by an error)
    of the same input, range and config (checkpoint/run.json)."""
    from lidar_slam import checkpoint

    summary_path = out / "summary.json"
    try:
        summary = json.loads(summary_path.read_text())
    except (OSError, ValueError):
        return False
    if summary.get("interrupted") or summary.get("stopped_by_error"):
        return False
    traceback = out / "error_traceback.txt"  # an internal error, written after the summary
    if traceback.is_file() and traceback.stat().st_mtime >= summary_path.stat().st_mtime:
        return False
    try:
        checkpoint.check_same_run(out, identity, verify_files=False)
    except InputError:
        return False
    return True


def run_job(job: BatchJob) -> SequenceResult:
    """One sequence, in a Ray worker: skip it when finished, else run (or resume) it as `run`
    does; its row, or an error row with the one-line message. The details say on which node
    and with which lidar_slam it ran."""
    import lidar_slam

    res = _run_job(job)
    res.details.update(node=socket.gethostname(), code=str(Path(lidar_slam.__file__).parent))
    return res


def finished_result(job: BatchJob, since: float | None = None) -> SequenceResult | None:
    """The row of job's run folder when it holds a finished run of this job (None otherwise);
    it counts as computed by this batch when summary.json is newer than `since` (a time)."""
    from lidar_slam import checkpoint
    from lidar_slam.config import load_config
    from lidar_slam.io.sources import open_source

    data, out = Path(job.data), Path(job.out)
    cfg = load_config(job.config, job.overrides)
    if not finished_run(out, checkpoint.describe_run(data, job.start, job.n_scans, job.topic,
                                                     cfg)):
        return None
    now = since is not None and (out / "summary.json").stat().st_mtime >= since
    source = open_source(data, topic=job.topic,
                         kitti_vertical_correction=cfg.data.kitti_vertical_correction)
    return run_row(job.name, out, source.ground_truth, "" if now else SKIPPED, computed_now=now)


def _run_job(job: BatchJob) -> SequenceResult:
    from lidar_slam.cli import run_sequence

    data, out = Path(job.data), Path(job.out)
    node = socket.gethostname()
    try:
        if not out.parent.is_dir():
            raise InputError(out.parent, f"--out is not visible on node {node}: {SHARED_FS}")
        if job.cluster and not data.exists():
            raise InputError(data, f"does not exist on node {node}: {SHARED_FS}")
        found = None if job.overwrite else finished_result(job)
        if found is not None:
            return found
        outcome = run_sequence(
            data, out, config=Path(job.config) if job.config else None, start=job.start,
            n_scans=job.n_scans, topic=job.topic, overrides=job.overrides,
            overwrite=job.overwrite, resume=not job.overwrite, progress=False)
    except LidarSlamError as exc:
        return error_row(job.name, str(exc))
    except OSError as exc:  # e.g. a run folder that cannot be written
        return error_row(job.name, f"{exc.filename or out}: {exc.strerror or exc}")
    if outcome.failure is not None:
        return error_row(job.name, str(outcome.failure), outcome.summary)
    resumed = outcome.summary.get("resumed_at_frame", 0)
    return run_row(job.name, out, outcome.ground_truth,
                   f"resumed at frame {resumed}" if resumed else "")


def _lines(path: Path) -> int:
    try:
        with open(path, "rb") as fh:
            return fh.read().count(b"\n")
    except OSError:
        return 0


class JobProgress:
    """Progress of many jobs on stderr, as lines (so also in a log file, CI or nohup): one when
    a job ends, and every `interval_s` the jobs done / running / failed, with the frames the
    running batch computed and the aggregate frames/s when there are frames to count."""

    def __init__(self, label: str, names: list[str], interval_s: float,
                 run_dirs: list[Path] | None = None, echo: Callable[[str], None] | None = None):
        self.label, self.names = label, names
        self.interval_s = max(interval_s, 1.0)  # lines, not a flood, even with an interval of 0
        self.run_dirs = run_dirs
        self.echo = echo or (lambda line: print(line, file=sys.stderr, flush=True))
        self.t0 = self.last = time.monotonic()
        self.t0_wall = time.time()
        self.done = self.failed = 0
        self.frames_done = 0  # frames computed by jobs that ended
        self.baseline = [_lines(d / "odometry_kitti.txt") for d in run_dirs] if run_dirs else []

    def restart_clock(self) -> None:
        """Count time from now (Ray has started: its start-up is not the jobs' time)."""
        self.t0 = self.last = time.monotonic()

    def _running(self, in_flight: set[int]) -> tuple[int, int]:
        """(jobs started, frames they computed so far): a run has started once it wrote into
        its folder (the odometry is streamed there line by line)."""
        if not self.run_dirs:
            return len(in_flight), 0
        started = frames = 0
        for i in in_flight:
            odo = self.run_dirs[i] / "odometry_kitti.txt"
            try:
                if odo.stat().st_mtime >= self.t0_wall - 1.0:
                    started += 1
                    frames += max(0, _lines(odo) - self.baseline[i])
            except OSError:
                pass
        return started, frames

    def waiting(self, in_flight: set[int]) -> None:
        now = time.monotonic()
        if now - self.last < self.interval_s:
            return
        self.last = now
        started, frames = self._running(in_flight)
        queued = len(self.names) - self.done - started
        line = (f"lidar-slam: {self.label}: {self.done}/{len(self.names)} done, {self.failed} "
                f"failed, {started} running, {queued} queued")
        if self.run_dirs:
            total = self.frames_done + frames
            line += f"; {total} frames, {total / max(now - self.t0, 1e-9):.1f} frames/s"
        self.echo(f"{line}; {now - self.t0:.0f} s elapsed")

    def finished(self, index: int, ok: bool, text: str, frames: int = 0) -> None:
        self.done += 1
        self.failed += not ok
        self.frames_done += frames
        self.echo(f"lidar-slam: {self.label}: {self.names[index]}: {text} "
                  f"({self.done}/{len(self.names)} done, {self.failed} failed)")


@dataclass
class BatchReport:
    """The rows of a batch (in input order), its wall time and whether Ctrl-C stopped it."""

    results: list[SequenceResult]
    rows: list[dict]  # the table: a row per sequence, TOTAL last
    wall_s: float
    interrupted: bool

    @property
    def failed(self) -> int:
        return sum(1 for r in self.results if not r.ok)


_WARNED_CODE: set[str] = set()


def _check_same_code(res: SequenceResult) -> None:
    """Warn (once per folder) when a worker imported lidar_slam from elsewhere than this
    process did: a cluster node with another install may run other code."""
    import lidar_slam

    here, there = str(Path(lidar_slam.__file__).parent), res.details.get("code")
    if there and there != here and there not in _WARNED_CODE:
        _WARNED_CODE.add(there)
        log.warning("node %s runs lidar_slam from %s, this process from %s: install the same "
                    "version on every node (or share the source folder)",
                    res.details.get("node"), there, here)


def _read_back(job: BatchJob, since: float) -> SequenceResult | None:
    """After Ctrl-C: the row of a run that finished (read from its folder), else None."""
    try:
        return finished_result(job, since)
    except (LidarSlamError, OSError, ValueError) as exc:  # e.g. an input this node cannot read
        log.debug("%s: not read back: %s", job.name, exc)
        return None


def _describe(res: SequenceResult) -> str:
    row = res.row
    if not res.ok:
        return f"error: {row['message']}"
    if not res.details.get("computed_now", True):
        return f"{SKIPPED} ({row['frames']} frames)"
    return f"ok, {row['frames']} frames, {row['fps']:.1f} frames/s"


def run_batch(jobs: list[BatchJob], out_dir: Path, fleet, interval_s: float,
              meta: dict | None = None) -> BatchReport:
    """Run every job on the fleet and write DIR/results.{md,json,csv}, also after Ctrl-C (the
    sequences not finished then are error rows that say to re-run)."""
    progress = JobProgress("batch", [j.name for j in jobs], interval_s,
                           [Path(j.out) for j in jobs])
    t0 = t_up = time.perf_counter()
    results: dict[int, SequenceResult] = {}
    interrupted = False

    def write() -> tuple[list[SequenceResult], list[dict], float]:
        t1 = time.perf_counter()
        if interrupted:  # runs that ended while their result was on its way
            for i, job in enumerate(jobs):
                if i not in results:
                    results[i] = _read_back(job, progress.t0_wall)
        ordered = [results.get(i) or error_row(j.name, INTERRUPTED) for i, j in enumerate(jobs)]
        # TOTAL frames/s counts from the moment Ray is up: its start-up (seconds, the same for
        # any number of sequences) is in results.json as ray_start_s.
        notes = [f"{len(jobs)} sequences in {t1 - t0:.1f} s, {t_up - t0:.1f} s of it starting "
                 f"or joining Ray (not in TOTAL fps)" + ("; interrupted" if interrupted else "")]
        rows = write_results(out_dir, ordered, t1 - t_up,
                             {**(meta or {}), "wall_s_total": t1 - t0, "ray_start_s": t_up - t0},
                             notes)
        return ordered, rows, t1 - t0

    written = None
    try:
        with fleet:
            t_up = time.perf_counter()
            out_dir.mkdir(parents=True, exist_ok=True)  # once Ray is up: no empty DIR left
            progress.restart_clock()
            try:
                for outcome in fleet.map(run_job, jobs, on_wait=progress.waiting):
                    res = outcome.value if outcome.error is None else error_row(
                        jobs[outcome.index].name, outcome.error)
                    results[outcome.index] = res
                    _check_same_code(res)
                    progress.finished(outcome.index, res.ok, _describe(res),
                                      res.details.get("frames_computed", 0))
            except KeyboardInterrupt:
                interrupted = True
            written = write()  # before Ray stops: stopping it may take a while, or fail
    except KeyboardInterrupt:  # while Ray started or stopped
        interrupted = True
    if written is None:
        written = write()
    ordered, rows, wall_s = written
    return BatchReport(ordered, rows, wall_s, interrupted)
