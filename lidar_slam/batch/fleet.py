"""Independent jobs (one per sequence) on Ray: the only module that imports ray.

Without an address Ray starts inside the calling process, on this machine, with as many CPUs
as the jobs may use at once (workers x CPUs per job), and stops with it. With an address
(`auto` for a cluster started with `ray start`, or `ray://HOST:PORT`) the jobs go to that
cluster and it is left running. Every job reserves its CPUs, runs in a fresh worker process
(`max_calls=1`: a job's peak RSS is its own) and is not retried (a sequence that crashes a
worker fails once, as an error of its own).

Ray is an optional extra (`pip install 'lidar-slam[cluster]'`); without it `Fleet` raises
RayMissing, one line saying what to install.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from lidar_slam.errors import LidarSlamError

log = logging.getLogger(__name__)
INSTALL = "pip install 'lidar-slam[cluster]' (or pip install 'ray>=2.9')"
# The embedded instance's shared-memory object store: jobs pass paths and small rows only.
OBJECT_STORE_BYTES = 80 * 2**20


class ClusterError(LidarSlamError):
    """Ray is missing, or the cluster cannot be reached."""


def _terminate_as_interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def ray_installed() -> bool:
    """Whether the optional Ray extra is importable here."""
    try:
        import ray  # noqa: F401
    except ImportError:
        return False
    return True


def _code_root() -> str | None:
    """The folder lidar_slam was imported from when it is a source tree (an editable install or
    PYTHONPATH), so that cluster workers import the same code where that folder is shared."""
    root = Path(__file__).resolve().parents[2]  # lidar_slam/batch/fleet.py -> the source root
    if any(part in ("site-packages", "dist-packages") for part in root.parts):
        return None
    return str(root)


@dataclass
class JobOutcome:
    """How one job ended: its return value, or the one-line error of a job that raised or
    whose worker died."""

    index: int
    value: object = None
    error: str | None = None


class Fleet:
    """`with Fleet(...) as fleet: for outcome in fleet.map(fn, jobs): ...` runs fn(job) for
    every job on Ray, outcomes in the order they finish. Leaving the block early (Ctrl-C, an
    error) stops the jobs still queued or running, with Ray (see __exit__)."""

    def __init__(self, address: str | None = None, workers: int | None = None,
                 cpus_per_job: int = 1):
        self.address = address
        self.cpus_per_job = cpus_per_job
        self.workers = workers or max(1, (os.cpu_count() or 1) // cpus_per_job)
        self.cap = workers  # jobs in flight at most (embedded: Ray's CPUs already bound them)
        self._pending: dict = {}
        self._started_here = False
        self._term_before = None  # SIGTERM's handler before ray.init, restored at the end

    @property
    def embedded(self) -> bool:
        return self.address is None

    def __enter__(self) -> Fleet:
        if not ray_installed():
            raise ClusterError(f"Ray is not installed: {INSTALL}")
        import ray

        if ray.is_initialized():  # a caller (a test, a notebook) already connected: use it
            return self
        kwargs = {"log_to_driver": False, "logging_level": logging.ERROR,
                  "include_dashboard": False}
        if self.embedded:  # "local": a new instance even where RAY_ADDRESS names a cluster
            kwargs.update(address="local", num_cpus=self.workers * self.cpus_per_job,
                          object_store_memory=OBJECT_STORE_BYTES)
        else:
            root = _code_root()
            if root is not None:
                path = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p)
                kwargs["runtime_env"] = {"env_vars": {"PYTHONPATH": path}}
            kwargs["address"] = self.address
            kwargs.pop("include_dashboard")
        # Ray's daemons start in this process group: with SIGINT and SIGTERM blocked while
        # they start (a mask they inherit), Ctrl-C in a terminal, `timeout` or docker stop
        # reach this process only, which writes the results and then stops Ray in order.
        blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
        term_before = signal.getsignal(signal.SIGTERM)
        try:
            ray.init(**kwargs)
        except (ConnectionError, TimeoutError, ValueError, RuntimeError) as exc:
            first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
            if self.embedded:
                raise ClusterError(f"cannot start Ray on this machine ({first})") from exc
            hint = "start one with `ray start --head`"
            if str(self.address).startswith("ray://"):
                hint += " (it serves Ray Client on port 10001)"
            if self.address != "auto":  # only `auto` reads the cluster's token by itself
                hint += "; with Ray's token authentication, set RAY_AUTH_MODE=token here"
            raise ClusterError(f"--address {self.address}: cannot connect to a Ray cluster "
                               f"({first}); {hint}") from exc
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
        self._started_here = True
        # ray.init makes SIGTERM end this process at once (sys.exit in the driver, its head
        # node's processes killed); here it stops the jobs like Ctrl-C, so the results of the
        # finished ones are written (the caller catches KeyboardInterrupt).
        if threading.current_thread() is threading.main_thread():
            self._term_before = term_before
            signal.signal(signal.SIGTERM, _terminate_as_interrupt)
        return self

    def __exit__(self, *exc) -> None:
        """Stop Ray (embedded) or leave the cluster: either way Ray ends this job's tasks still
        queued or running. No ray.cancel first: in Ray 2.60 a task whose reply arrives after a
        forced cancel aborts the whole driver ("Tried to complete task that was not pending"),
        which lost the results table of an interrupted batch."""
        import ray

        self._pending = {}
        if self._started_here:
            ray.shutdown()
        if self._term_before is not None:
            signal.signal(signal.SIGTERM, self._term_before)
            self._term_before = None

    def map(self, fn: Callable, jobs: list, on_wait: Callable[[set[int]], None] | None = None,
            wait_s: float = 1.0) -> Iterator[JobOutcome]:
        """fn(job) for every job, yielded as they finish; on_wait(indices in flight) is called
        at least every wait_s seconds while waiting."""
        import ray

        task = ray.remote(num_cpus=self.cpus_per_job, max_calls=1, max_retries=0)(fn)
        queue = list(enumerate(jobs))[::-1]
        limit = self.cap or len(jobs)
        while queue or self._pending:
            while queue and len(self._pending) < limit:
                i, job = queue.pop()
                self._pending[task.remote(job)] = i
            if on_wait is not None:
                on_wait(set(self._pending.values()))
            done, _ = ray.wait(list(self._pending), num_returns=1, timeout=wait_s)
            for ref in done:
                yield self._outcome(ref, self._pending.pop(ref))

    @staticmethod
    def _outcome(ref, index: int) -> JobOutcome:
        import ray

        try:
            return JobOutcome(index, ray.get(ref))
        except ray.exceptions.RayTaskError as exc:
            cause = exc.cause if getattr(exc, "cause", None) is not None else exc
            text = str(cause).strip().splitlines()
            return JobOutcome(index, error=f"internal error: {type(cause).__name__}: "
                                           f"{text[0] if text else ''}".rstrip(": "))
        except ray.exceptions.RayError as exc:  # the worker died (killed, out of memory), ...
            text = str(exc).strip().splitlines()
            return JobOutcome(index, error=f"{type(exc).__name__}: {text[0] if text else ''}")
