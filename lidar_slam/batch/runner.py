"""A batch: every job on the Ray fleet, progress per job, and one results table at the end.

fan_out is the one loop that hands jobs to a Fleet and their outcomes back (`batch` and a
`simulate` of several sequences both use it); run_batch adds the results table, also after
Ctrl-C.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from lidar_slam.batch.fleet import JobOutcome
from lidar_slam.batch.jobs import SKIPPED, BatchJob, finished_result, run_job
from lidar_slam.batch.progress import JobProgress
from lidar_slam.batch.results import SequenceResult, error_row, write_results
from lidar_slam.errors import LidarSlamError

log = logging.getLogger(__name__)
INTERRUPTED = "interrupted; re-run the same command to resume"


def fan_out(fleet, fn: Callable, jobs: list, progress: JobProgress,
            on_outcome: Callable[[JobOutcome], None], on_up: Callable[[], None] | None = None,
            before_stop: Callable[[bool], None] | None = None) -> bool:
    """fn(job) for every job on the fleet (a lidar_slam.batch.fleet.Fleet, entered here):
    on_outcome(outcome) as each ends, on_up() once Ray is up, before_stop(interrupted) after
    the last job or Ctrl-C but before Ray stops (stopping it may take a while, or fail).
    Returns whether Ctrl-C (or SIGTERM) stopped it."""
    interrupted = False
    try:
        with fleet:
            if on_up is not None:
                on_up()
            progress.restart_clock()
            try:
                for outcome in fleet.map(fn, jobs, on_wait=progress.waiting):
                    on_outcome(outcome)
            except KeyboardInterrupt:
                interrupted = True
            if before_stop is not None:
                before_stop(interrupted)
    except KeyboardInterrupt:  # while Ray started or stopped
        interrupted = True
    return interrupted


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
    written = None

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

    def up() -> None:
        nonlocal t_up
        t_up = time.perf_counter()
        out_dir.mkdir(parents=True, exist_ok=True)  # once Ray is up: no empty DIR left

    def record(outcome: JobOutcome) -> None:
        res = outcome.value if outcome.error is None else error_row(
            jobs[outcome.index].name, outcome.error)
        results[outcome.index] = res
        _check_same_code(res)
        progress.finished(outcome.index, res.ok, _describe(res),
                          res.details.get("frames_computed", 0))

    def before_stop(stopped: bool) -> None:
        nonlocal interrupted, written
        interrupted = stopped
        written = write()  # before Ray stops: stopping it may take a while, or fail

    interrupted = fan_out(fleet, run_job, jobs, progress, record, up, before_stop)
    if written is None:
        written = write()
    ordered, rows, wall_s = written
    return BatchReport(ordered, rows, wall_s, interrupted)
