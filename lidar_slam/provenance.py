"""What produced a run: the package version and, for a git checkout, the commit."""

from __future__ import annotations

import functools
import subprocess
from pathlib import Path

from lidar_slam import __version__

PACKAGE_DIR = Path(__file__).resolve().parent


def _git(*args: str) -> str | None:
    try:
        proc = subprocess.run(["git", "-C", str(PACKAGE_DIR.parent), *args], capture_output=True,
                              text=True, timeout=5, check=False)
    except (OSError, subprocess.SubprocessError):  # no git, or it hangs
        return None
    return proc.stdout.strip() if proc.returncode == 0 else None


@functools.cache
def git_commit() -> str | None:
    """The commit of the lidar_slam sources, with '+dirty' when lidar_slam/ has uncommitted
    changes; None when they are not a git checkout (an installed wheel) or git is missing."""
    if not (PACKAGE_DIR.parent / ".git").exists():  # a file in a worktree, a folder otherwise
        return None
    commit = _git("rev-parse", "HEAD")
    if not commit:
        return None
    dirty = _git("status", "--porcelain", "--untracked-files=no", "--", PACKAGE_DIR.name)
    return commit + ("+dirty" if dirty else "")


def version_line() -> str:
    """'lidar-slam 0.1.0' with the commit when known."""
    commit = git_commit()
    return f"lidar-slam {__version__}" + (f" (git {commit})" if commit else "")
