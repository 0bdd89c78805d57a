"""Typed errors; the CLI (lidar_slam.cli) turns them into one-line messages and exit codes."""

from __future__ import annotations

from pathlib import Path


class LidarSlamError(Exception):
    """Base class of every error the CLI reports as a one-line message (exit code 2)."""


class InputError(LidarSlamError):
    """Bad input data: the message names the file and the problem."""

    def __init__(self, path: str | Path, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class ConfigError(LidarSlamError):
    """An invalid configuration file or value."""


class SolveError(LidarSlamError):
    """A pose-graph solve that cannot be done (e.g. a global initialisation gtsam rejects)."""


EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as a shell reports Ctrl-C


class RunFailed(LidarSlamError):
    """A run (or a command of the CLI) that stopped with a one-line message and an exit code:
    2 for bad input, 1 for a bug or a partial failure, 130 when interrupted. A run that wrote its
    frames so far says so in the message."""

    def __init__(self, message: str, exit_code: int = EXIT_BAD_INPUT):
        super().__init__(message)
        self.exit_code = exit_code
