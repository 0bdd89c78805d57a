"""Progress of many jobs (a batch, several simulations) on stderr, as lines."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path


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
