"""The `lidar-slam` command: one module per command, each only parsing its options, calling
the library and printing. `entry` is the command's process entry point (pyproject:
lidar_slam.cli:entry); `app` is the same commands for callers in their own process.

common: the app, the one-line error handling (reports_errors) and the summary table; run,
batch, optimize, eval, simulate, localize, export, merge: the commands.
"""

import contextlib
import importlib
import signal

from lidar_slam.runtime import tune_process

# The command's process is where a run starts: tune it before anything loads NumPy (see
# lidar_slam.runtime; importing lidar_slam itself changes nothing).
tune_process()

from lidar_slam.cli.common import app, reports_errors  # noqa: E402

# Importing a command's module registers it with app; --help lists them in this order.
COMMANDS = ("run", "batch", "optimize", "eval", "simulate", "localize", "export", "merge")
for _name in COMMANDS:
    importlib.import_module(f"lidar_slam.cli.{_name}")



def entry() -> None:
    """`lidar-slam` as a process: app, then Ctrl-C and SIGTERM ignored until the process is gone.
    The command is over by then (outputs written, or its error reported), so a signal has nothing
    left to stop; Python puts the default handler back while it shuts down, and a Ctrl-C in that
    window killed the process (exit -2) after a complete run. Only here: a caller running app in
    its own process keeps its signals."""
    try:
        app()
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            with contextlib.suppress(ValueError):  # not the main thread
                signal.signal(sig, signal.SIG_IGN)


__all__ = ["COMMANDS", "app", "entry", "reports_errors"]
