"""top_view.png drawn by a helper process that imports matplotlib while the run goes.

Importing matplotlib (~0.4 s) and drawing the top view (~0.3 s) were the largest part of what a
run does after its final solve: 13 % of a 400-scan hand-held walk's whole process. The helper
process starts with the run, imports matplotlib at SCHED_IDLE (on CPU time the odometry leaves),
and at the end draws the picture while the run writes its other outputs. The picture is the same
function's (lidar_slam.eval.evaluate.plot_run_top_view) on the same poses and map; the poses and
every other output do not depend on it. Where the helper cannot start or fails, the run draws
the picture itself, as before.

The helper ignores Ctrl-C and SIGTERM (the run decides when to stop and still writes its outputs)
and dies with the run (as the loop worker: lidar_slam.loop.worker).
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import weakref
from concurrent.futures import Future, ProcessPoolExecutor
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def _start(parent_pid: int) -> None:
    from lidar_slam.loop.worker import STOP_SIGNALS, _die_with_parent, _set_priority

    for sig in STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
    _die_with_parent(parent_pid)
    _set_priority(os.getpid(), urgent=False)  # SCHED_IDLE while it only imports


def _warm() -> None:
    """Import what the top view needs and draw a small figure once (fonts, the Agg canvas)."""
    import io

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import LogNorm  # noqa: F401 (the map density's)
    from matplotlib.figure import Figure

    import lidar_slam.eval.evaluate  # noqa: F401

    fig = Figure(figsize=(1, 1))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.plot([0, 1], [0, 1], "b-", label="x")
    ax.legend(fontsize=8)
    ax.set_title("x")
    fig.savefig(io.BytesIO(), dpi=30, format="png")


def _draw(path: str, poses: np.ndarray, map_ply: str | None) -> None:
    from lidar_slam.eval.evaluate import plot_run_top_view

    plot_run_top_view(Path(path), poses, None if map_ply is None else Path(map_ply))


def _end(pool: ProcessPoolExecutor) -> None:
    """End the helper, killed (loop.worker.kill_pool; one that drew nothing may still be
    importing at SCHED_IDLE, which on a loaded machine would keep the run's exit waiting)."""
    from lidar_slam.loop.worker import kill_pool

    kill_pool(pool)


class TopViewPainter:
    """start() at the beginning of a run; draw() at its end returns a job, finish(job) waits for
    it (or draws in this process when the helper failed); close() ends the helper."""

    def __init__(self, pool: ProcessPoolExecutor | None):
        self._pool = pool
        # a run that ends by an exception: the helper goes with it
        self._finalizer = None if pool is None else weakref.finalize(self, _end, pool)

    @classmethod
    def start(cls) -> TopViewPainter:
        """Spawn the helper (it imports matplotlib in the background); without one (the system
        does not allow it) draw() draws in this process."""
        try:
            pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"),
                                       initializer=_start, initargs=(os.getpid(),))
            # started with Ctrl-C / SIGTERM blocked (a mask it inherits) until its initializer
            # ignores them, as the loop worker
            from lidar_slam.loop.worker import STOP_SIGNALS

            blocked = signal.pthread_sigmask(signal.SIG_BLOCK, set(STOP_SIGNALS))
            try:
                pool.submit(_warm)
            finally:
                signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
        # (AssertionError: inside a daemonic process; a RuntimeError, a script without the
        # __main__ guard, is left to stop it, as the loop worker's does)
        except (OSError, AssertionError) as exc:
            log.debug("top view drawn in the run's process: %s", exc)
            pool = None
        return cls(pool)

    def draw(self, path: Path, poses: np.ndarray, map_ply: Path | None) -> tuple:
        """Start drawing plot_run_top_view(path, poses, map_ply); map_ply must be complete."""
        job = None
        if self._pool is not None:
            # The run waits for it from now on: the odometry's priority (not SCHED_IDLE, which
            # on a loaded machine would wait for an idle core), also for its imports if they
            # are not done yet.
            from lidar_slam.loop.worker import _set_priority

            for pid in list(self._pool._processes):
                _set_priority(pid, urgent=True)
            try:
                job = self._pool.submit(_draw, str(path), np.asarray(poses),
                                        None if map_ply is None else str(map_ply))
            except RuntimeError as exc:  # a broken pool
                log.debug("top view drawn in the run's process: %s", exc)
        return job, (path, poses, map_ply)

    def finish(self, drawing: tuple) -> None:
        """Wait for draw()'s picture; draw it here if the helper could not."""
        job, args = drawing
        if isinstance(job, Future):
            try:
                job.result()
                return
            except Exception as exc:  # the helper died or failed: the picture is still due
                log.debug("top view helper failed (%s): drawn in the run's process", exc)
        from lidar_slam.eval.evaluate import plot_run_top_view

        plot_run_top_view(*args)

    def close(self) -> None:
        """End the helper, killed: after a picture it is idle (the PNG is in place: written
        atomically before the job returned), and a graceful exit only tears down matplotlib
        (~0.1 s of a 4 s walk's run). Never left to the interpreter's exit: concurrent.futures'
        exit hook can race an executor shut down without waiting ("Exception ignored in:
        <module 'threading'>", OSError on its closed wake-up pipe; seen once in the full suite
        under load)."""
        if self._pool is None:
            return
        pool, self._pool = self._pool, None
        self._finalizer.detach()
        _end(pool)
