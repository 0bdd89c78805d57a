"""Process tuning for a run: one OpenBLAS thread and glibc malloc thresholds.

Importing lidar_slam changes nothing in the process; the command that starts a run calls
tune_process() first (before NumPy is imported, for the OpenBLAS part to take effect), and the
loop worker process calls it as it starts. Neither setting changes a result: runs write the same
bytes with and without them (compared on sample_scans with odometry.max_num_threads: 1); they
only change speed.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

MALLOC_DEFAULTS_ENV = "LIDAR_SLAM_MALLOC_DEFAULTS"  # set (to anything): keep glibc's defaults


def tune_process() -> None:
    """Tune this process for a run (see the module doc); idempotent.

    One OpenBLAS thread: kiss-icp's registration runs on every core (TBB); OpenBLAS threads woken
    by a large NumPy product (the deskew's (N,3) x (3,3)) then spin-wait and take those cores
    away: registration took 29.5 instead of 15.1 ms per HDL-64 scan on 2 cores. Our products are
    all (N,3) x (3,3), for which one thread is as fast. Only effective when NumPy is not yet
    imported; a user's own OPENBLAS_NUM_THREADS wins (and child processes inherit it).

    Unless LIDAR_SLAM_MALLOC_DEFAULTS is set, keep_freed_memory().
    """
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    if os.environ.get(MALLOC_DEFAULTS_ENV) is None:
        keep_freed_memory()


def keep_freed_memory() -> None:
    """Let glibc's malloc reuse freed memory instead of returning it to the OS at every free.

    Every scan allocates and frees arrays of a few MB (points, crops, selections, in NumPy and in
    kiss-icp). Above glibc's default mmap threshold each one is a fresh mmap, whose pages fault
    in one by one when touched and are unmapped again on free: in this VM that cost 25 of 61 ms
    per HDL-64E scan (tools/speed_probe.py). Raising the mmap threshold to its maximum (32 MB)
    and the trim threshold keeps those pages in the heap for the next scan; the heap stays near
    the run's working set. No-op where libc is not glibc.
    """
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return
    M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
    mallopt(M_MMAP_THRESHOLD, 32 << 20)
    mallopt(M_TRIM_THRESHOLD, 128 << 20)
