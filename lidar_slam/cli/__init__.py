"""The `lidar-slam` command: one module per command, each only parsing its options, calling
the library and printing. `app` is the entry point (pyproject: lidar_slam.cli:app).

common: the app, the one-line error handling (reports_errors) and the summary table; run,
batch, optimize, eval, simulate, localize, export, merge: the commands.
"""

import importlib

from lidar_slam.runtime import tune_process

# The command's process is where a run starts: tune it before anything loads NumPy (see
# lidar_slam.runtime; importing lidar_slam itself changes nothing).
tune_process()

from lidar_slam.cli.common import app, reports_errors  # noqa: E402

# Importing a command's module registers it with app; --help lists them in this order.
COMMANDS = ("run", "batch", "optimize", "eval", "simulate", "localize", "export", "merge")
for _name in COMMANDS:
    importlib.import_module(f"lidar_slam.cli.{_name}")

__all__ = ["COMMANDS", "app", "reports_errors"]
