"""Typed errors; cli.py turns them into one-line messages and exit codes."""

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
