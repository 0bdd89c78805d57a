"""Loop detection off the critical path: keyframes are submitted as the odometry makes them, a
worker thread runs detection and verification, and results are collected in keyframe order.

Determinism does not depend on the worker's speed: what the detector computes for a keyframe is
fixed once the keyframe is stored (see LoopDetector), and the pipeline collects the result of
keyframe k at a fixed point of the run (when keyframe k + lag is made, or at the end), waiting
for it if the worker is behind. So a run on the same input gives the same graph, updated in the
same order, whatever the machine's load.

A thread, not a process: the heavy parts (ICP, KD-trees, kiss-icp's registration) run in C++
and NumPy, and a process would need its own copy of the libraries and of the keyframe cache.
"""

from __future__ import annotations

import os
import threading
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor

from lidar_slam.loop.closer import LoopDetector, LoopResult


def _lower_this_threads_priority(niceness: int = 10) -> None:
    """Run the calling thread at a lower priority (Linux: threads have their own nice value),
    so that the odometry's registration threads get the cores first and detection uses what is
    left; the results are waited for at fixed keyframes, so this changes timing, not results."""
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), niceness)
    except (AttributeError, OSError):  # not Linux, or not allowed: run at the same priority
        pass


class LoopWorker:
    """submit(kf_id) in keyframe order; collect(upto) returns the results of keyframes <= upto,
    in order, waiting for them if needed. inline=True runs detection inside submit()."""

    def __init__(self, detector: LoopDetector, inline: bool = False):
        self.detector = detector
        self._pool = None if inline else ThreadPoolExecutor(1, thread_name_prefix="loops")
        self._pending: deque[tuple[int, Future | LoopResult]] = deque()
        self._niced = inline  # the inline detector keeps the caller's priority
        self.busy_s = 0.0  # time the detector spent (worker thread or inline)
        self.wait_s = 0.0  # time the caller waited for results

    def _run(self, kf_id: int) -> LoopResult:
        if not self._niced:
            _lower_this_threads_priority()
            self._niced = True
        t0 = time.perf_counter()
        try:
            return self.detector.process(kf_id)
        finally:
            self.busy_s += time.perf_counter() - t0

    def submit(self, kf_id: int) -> None:
        """Queue keyframe kf_id (already in the store) for detection."""
        job = self._run(kf_id) if self._pool is None else self._pool.submit(self._run, kf_id)
        self._pending.append((kf_id, job))

    def collect(self, upto: int) -> list[LoopResult]:
        """Results of every submitted keyframe with id <= upto, in keyframe order (each once);
        a detection error is raised here."""
        out = []
        t0 = time.perf_counter()
        while self._pending and self._pending[0][0] <= upto:
            _, job = self._pending.popleft()
            out.append(job.result() if isinstance(job, Future) else job)
        self.wait_s += time.perf_counter() - t0
        return out

    def close(self) -> None:
        """Stop the worker (queued keyframes not yet started are dropped)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        self.detector.index.close()
