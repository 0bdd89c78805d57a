"""Loop detection off the critical path: keyframes are submitted as the odometry makes them, a
worker runs detection and verification, and results are collected in keyframe order. The worker
also weighs each keyframe's odometry edge (its information from the clouds), which the pipeline
hands to the back-end with the keyframe's loops: on a car's drive that is 6 ms a keyframe the
odometry no longer waits for.

Determinism does not depend on the worker's speed: what the detector computes for a keyframe is
fixed once the keyframe is stored (see LoopDetector), and the pipeline collects the result of
keyframe k at a fixed point of the run (when keyframe k + lag is made, or at the end), waiting
for it if the worker is behind. So a run on the same input gives the same graph, updated in the
same order, whatever the machine's load.

A process by default (`loop.worker: process`): kiss-icp's registration and small_gicp's ICP both
hold Python's GIL while they run, so a worker *thread* stalls the odometry for as long as each
verification ICP takes. The worker process reads keyframes from the run folder's store (only
ids cross the pipe), runs on the CPU time the odometry leaves (SCHED_IDLE; raised to the
odometry's priority while its backlog is long, see pace()), ignores Ctrl-C and SIGTERM (the main
process decides when to stop) and dies with the main process (_die_with_parent). "thread" and
"inline" (in the main flow, for debugging) remain.
"""

from __future__ import annotations

import ctypes
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections import deque
from concurrent.futures import Executor, Future, ProcessPoolExecutor, ThreadPoolExecutor
from pathlib import Path

from lidar_slam.config import SlamConfig
from lidar_slam.map.keyframes import KeyframeReader, KeyframeStore

NICENESS = 10
# The worker process runs at the odometry's priority (instead of SCHED_IDLE) while its backlog
# is at least this share of loop.collect_lag_keyframes (the odometry would soon stop and wait
# for it), or at least as many keyframes as the remaining frames would make (about one per
# KEYFRAME_FRAMES frames), so that the backlog is worked off beside the last scans on both
# cores instead of on one while the other idles after the last scan. Timing only.
URGENT_LAG_SHARE = 0.75
KEYFRAME_FRAMES = 3


def _lower_this_threads_priority(idle: bool = False) -> None:
    """Run the calling thread at a lower priority (Linux: a thread has its own policy and nice
    value), so that the odometry gets the cores first; results are waited for at fixed
    keyframes, so this changes timing, not results.

    idle (the worker process): SCHED_IDLE, the CPU time the odometry leaves. kiss-icp keeps
    about 1.65 of 2 cores busy; at nice 10 the worker still took time slices from its two
    registration threads. Full simulated 00 (261 loops), one run each beside stock
    kiss_icp_pipeline (302.2 s): nice 10 with results collected 10 keyframes later 307.4 s
    (odometry 62.7 ms/frame); SCHED_IDLE with 50 keyframes 300.9 s (59.2 ms/frame, 3.4 ms/frame
    waiting for the worker); SCHED_IDLE with 200 keyframes 296.0 s (59.8, 2.2). Not for a
    worker thread: starved while it holds the GIL, it would stall the odometry."""
    tid = threading.get_native_id()
    if idle:
        try:
            os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
            return
        except (AttributeError, OSError):  # not Linux, or not allowed: nice instead
            pass
    try:
        os.setpriority(os.PRIO_PROCESS, tid, NICENESS)
    except (AttributeError, OSError):  # not Linux, or not allowed: same priority
        pass


# -- the worker process's side -----------------------------------------------------------------

_DETECTOR = None


# Signals that reach a whole process group (Ctrl-C in a terminal; `timeout`, docker stop and
# batch schedulers send SIGTERM to the group): the main process decides when the run stops and
# still needs the worker to finish the loops of the frames it keeps, so the worker ignores them.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
PR_SET_PDEATHSIG = 1  # linux/prctl.h
PARENT_CHECK_S = 1.0


def _die_with_parent(parent_pid: int) -> None:
    """End this worker process when the run's process ends, however it ends (SIGKILL, a crash):
    on Linux the kernel sends SIGKILL on the parent's death (prctl PR_SET_PDEATHSIG); a daemon
    thread that checks the parent every second covers other systems and the moment before the
    prctl."""
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
        except (OSError, AttributeError):
            pass

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(PARENT_CHECK_S)
        os._exit(1)

    if os.getppid() != parent_pid:  # the parent died before the prctl
        os._exit(1)
    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def _start_process(cfg_json: dict, store_root: str, parent_pid: int) -> None:
    global _DETECTOR
    from lidar_slam.runtime import tune_process

    tune_process()  # a spawned process: the parent's malloc settings are not inherited
    for sig in STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
    _die_with_parent(parent_pid)
    _lower_this_threads_priority(idle=True)  # before the detector's imports: the run's start first
    from lidar_slam.loop.detector import LoopDetector

    _DETECTOR = LoopDetector(SlamConfig(**cfg_json), KeyframeReader(store_root))


def kill_pool(pool: ProcessPoolExecutor) -> None:
    """End a one-process helper pool (the loop worker, the top-view painter): its process
    killed (it ignores SIGTERM), then the pool shut down. For a helper that is idle (its
    results collected, its files written unbuffered or atomically), or whose work is no longer
    wanted: a graceful exit would only tear down its imports."""
    for proc in list(pool._processes.values()):
        proc.kill()
    # Called from the pool's own manager thread (a garbage collection there that finalizes the
    # helper's owner), waiting would join that thread from itself (RuntimeError "cannot join
    # current thread", seen once in CI): its process is killed, the thread ends by itself.
    own = getattr(pool, "_executor_manager_thread", None) is threading.current_thread()
    pool.shutdown(wait=not own, cancel_futures=True)


def is_urgent(backlog: int, lag: int, frames_left: int | None) -> bool:
    """Whether a backlog of unfinished keyframes needs the odometry's priority (see
    URGENT_LAG_SHARE)."""
    return backlog > 0 and (backlog >= URGENT_LAG_SHARE * max(lag, 1) or (
        frames_left is not None and backlog * KEYFRAME_FRAMES >= frames_left))


def _set_priority(pid: int, urgent: bool) -> bool:
    """The worker process (single-threaded: its pid is its thread) at the normal or the idle
    policy; False when the system does not allow it (leaving SCHED_IDLE needs RLIMIT_NICE room
    or CAP_SYS_NICE): the worker then keeps its priority, which changes timing only."""
    try:
        if urgent:
            os.sched_setscheduler(pid, os.SCHED_OTHER, os.sched_param(0))
        else:
            os.sched_setscheduler(pid, os.SCHED_IDLE, os.sched_param(0))
        return True
    except (AttributeError, OSError):
        return False


def _timed_process(kf_id: int):
    t0 = time.perf_counter()
    return _DETECTOR.process(kf_id), time.perf_counter() - t0


def _reindex(upto: int) -> None:
    _DETECTOR.reindex(upto)


# -- the pipeline's side -------------------------------------------------------------------------


class LoopWorker:
    """submit(kf_id) in keyframe order; collect(upto) returns the results of keyframes <= upto,
    in order, waiting for them if needed."""

    def __init__(self, cfg: SlamConfig, store: KeyframeStore, mode: str = "process"):
        self.mode = mode
        self.busy_s = 0.0  # time the detector spent
        self.wait_s = 0.0  # time the caller waited for results
        self._pending: deque[tuple[int, Future]] = deque()
        self._pool: Executor | None = None
        self.detector = None
        self.lag = cfg.loop.collect_lag_keyframes
        self._pid: int | None = None  # the worker process, while its priority can be changed
        self._urgent = False
        self.urgent_s = 0.0  # time the worker ran at the odometry's priority
        self._urgent_since = 0.0
        if mode == "process":
            ctx = multiprocessing.get_context("spawn")  # fork is unsafe with TBB threads running
            self._pool = ProcessPoolExecutor(
                1, mp_context=ctx, initializer=_start_process,
                initargs=(cfg.model_dump(mode="json"), str(Path(store.root)), os.getpid()))
            # Ctrl-C in a terminal and `timeout` reach the whole process group. Until its
            # initializer runs (a second or two of imports) the worker would die of them, and
            # the run lose its outputs (BrokenProcessPool): start it now with both blocked, a
            # mask it inherits, as multiprocessing's resource tracker does. The parent gets a
            # signal sent meanwhile as soon as it is unblocked.
            blocked = signal.pthread_sigmask(signal.SIG_BLOCK, set(STOP_SIGNALS))
            try:
                self._pool.submit(int)  # spawns the worker process, which idles until needed
            finally:
                signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
            self._pid = next(iter(self._pool._processes), None)
        else:
            from lidar_slam.loop.detector import LoopDetector

            self.detector = LoopDetector(cfg, store)
            if mode == "thread":
                self._pool = ThreadPoolExecutor(1, thread_name_prefix="loops",
                                                initializer=_lower_this_threads_priority)

    def _local(self, kf_id: int):
        t0 = time.perf_counter()
        return self.detector.process(kf_id), time.perf_counter() - t0

    def submit(self, kf_id: int) -> None:
        """Queue keyframe kf_id (already in the store, on disk) for detection and the
        information of its odometry edge (LoopResult.edge_information)."""
        if self.mode == "process":
            job = self._pool.submit(_timed_process, kf_id)
        elif self.mode == "thread":
            job = self._pool.submit(self._local, kf_id)
        else:
            job = Future()
            job.set_result(self._local(kf_id))
        self._pending.append((kf_id, job))

    def pace(self, frames_left: int | None) -> None:
        """Raise the worker process to the odometry's priority while its backlog is long (see
        URGENT_LAG_SHARE), back to idle once it is not; frames_left: scans still to come, when
        known."""
        if self._pid is None:
            return
        backlog = 0  # one worker finishes jobs in order: the unfinished ones are the newest
        for _, job in reversed(self._pending):
            if job.done():
                break
            backlog += 1
        urgent = is_urgent(backlog, self.lag, frames_left)
        if urgent == self._urgent:
            return
        if not _set_priority(self._pid, urgent):
            self._pid = None  # not allowed here: stay idle
            return
        now = time.perf_counter()
        if urgent:
            self._urgent_since = now
        else:
            self.urgent_s += now - self._urgent_since
        self._urgent = urgent

    def reindex(self, upto: int) -> None:
        """Index keyframes 0..upto from the store (resuming a run), before any submit()."""
        if self.mode == "process":
            self._pool.submit(_reindex, upto).result()
        else:
            self.detector.reindex(upto)

    def collect(self, upto: int) -> list:
        """Results (LoopResult) of every submitted keyframe with id <= upto, in keyframe order,
        each once; a detection error is raised here."""
        out = []
        t0 = time.perf_counter()
        while self._pending and self._pending[0][0] <= upto:
            _, job = self._pending.popleft()
            result, busy = job.result()
            self.busy_s += busy
            out.append(result)
        self.wait_s += time.perf_counter() - t0
        return out

    def close(self) -> None:
        """Stop the worker (queued keyframes, and one it is working on, are dropped)."""
        if self._urgent:
            self.urgent_s += time.perf_counter() - self._urgent_since
            self._urgent = False
        self._pid = None
        if self._pool is not None:
            if self.mode == "process":  # its results collected or no longer wanted (30-60 ms)
                kill_pool(self._pool)
            else:
                self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        if self.detector is not None:
            self.detector.index.close()
            self.detector = None
