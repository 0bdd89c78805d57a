"""Progress of a run on stderr (stdout keeps the results that scripts parse)."""

from __future__ import annotations

import os
import sys
import time


def progress_interval_s() -> float:
    """Seconds between progress lines when stderr is not a terminal (LIDAR_SLAM_PROGRESS_S)."""
    try:
        return max(0.0, float(os.environ.get("LIDAR_SLAM_PROGRESS_S", "10")))
    except ValueError:
        return 10.0


class Progress:
    """On a terminal, a rich bar with the rate, elapsed time and ETA; otherwise (a log file, CI,
    nohup) one line at least every LIDAR_SLAM_PROGRESS_S seconds (10), rich not imported."""

    def __init__(self, name: str, total: int, done: int = 0, unit: str = "frames"):
        self.name, self.total, self.unit = name, total, unit
        self.done0 = self.done = done
        self.t0 = self.last = time.perf_counter()
        self.interval = progress_interval_s()
        self.bar = None
        if sys.stderr.isatty():
            from rich.console import Console
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                TextColumn,
                TimeElapsedColumn,
                TimeRemainingColumn,
            )
            from rich.progress import Progress as RichProgress

            self.bar = RichProgress(TextColumn("[bold]{task.description}"), BarColumn(),
                                    MofNCompleteColumn(),
                                    TextColumn(f"{{task.fields[rate]:.1f}} {unit}/s"),
                                    TimeElapsedColumn(), TextColumn("ETA"),
                                    TimeRemainingColumn(), console=Console(stderr=True))
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
            print(f"lidar-slam: {self.name}: {self.done}/{self.total} {self.unit} "
                  f"({100.0 * self.done / max(self.total, 1):.0f} %), {rate:.1f} "
                  f"{self.unit}/s, {now - self.t0:.0f} s elapsed, ETA {eta:.0f} s",
                  file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()


class NoProgress:
    """Progress of a run nobody watches (a batch task: `batch` reports per sequence)."""

    def tick(self, *_) -> None:
        pass

    def close(self) -> None:
        pass


def progress(name: str, total: int, done: int = 0, unit: str = "frames", shown: bool = True):
    """A Progress, or a NoProgress when not shown."""
    return Progress(name, total, done, unit) if shown else NoProgress()
