"""What every command of `lidar-slam` shares: the app (usage errors and bugs as one line),
reports_errors (library errors as one line and an exit code) and the summary table."""

from __future__ import annotations

import functools
import logging
import os
import sys

import typer

from lidar_slam.errors import EXIT_BAD_INPUT, EXIT_INTERRUPTED, LidarSlamError, RunFailed

log = logging.getLogger("lidar_slam")


def fail(message: str, code: int = EXIT_BAD_INPUT) -> RunFailed:
    """A command's one-line error and its exit code, to raise (reports_errors prints it)."""
    return RunFailed(message, code)


def _exit(message: str, code: int) -> typer.Exit:
    typer.echo(f"lidar-slam: error: {message}", err=True)
    return typer.Exit(code)


def _click_exception() -> type[Exception]:
    """The class of typer's usage errors (click's ClickException), found from typer's public
    `typer.BadParameter`: typer >= 0.2x raises its own copy of click's exceptions, older typer
    click's, and neither copy is a public name of typer."""
    return next(c for c in typer.BadParameter.__mro__ if c.__name__ == "ClickException")


ClickException = _click_exception()


def _internal_error(exc: BaseException) -> int:
    """An error that is a bug, not bad input: one line naming it and the file that holds the
    traceback (also on stderr with --verbose), exit code 1."""
    import tempfile
    import traceback

    text = "".join(traceback.format_exception(exc))
    where = ""
    try:
        fd, path = tempfile.mkstemp(prefix="lidar-slam-traceback-", suffix=".txt")
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
        where = f"; traceback in {path}"
    except OSError:
        pass
    if log.isEnabledFor(logging.DEBUG):
        sys.stderr.write(text)
    first = (str(exc).strip().splitlines() or [""])[0]
    typer.echo(f"lidar-slam: error: internal error: {type(exc).__name__}: {first}".rstrip(": ")
               + f" (a bug: please report it{where})", err=True)
    return 1


class _App(typer.Typer):
    """typer.Typer whose usage errors (a bad option value, a missing argument) are one line on
    stderr and exit code 2, like every other error, instead of typer's boxed panel; a bug is
    one line and exit code 1 (_internal_error), never a traceback on the terminal."""

    def __call__(self, *args, **kwargs):
        kwargs.setdefault("prog_name", "lidar-slam")
        try:
            code = super().__call__(*args, standalone_mode=False, **kwargs)
        except typer.Exit as exc:
            sys.exit(exc.exit_code)
        except typer.Abort:
            typer.echo("lidar-slam: error: aborted", err=True)
            sys.exit(1)
        except KeyboardInterrupt:
            typer.echo("lidar-slam: error: interrupted", err=True)
            sys.exit(EXIT_INTERRUPTED)
        except ClickException as exc:
            if type(exc).__name__ == "NoArgsIsHelpError":
                exc.show()  # the help text, as for --help
                sys.exit(exc.exit_code)
            where = f" (see {exc.ctx.command_path} --help)" if getattr(exc, "ctx", None) else ""
            message = " ".join(exc.format_message().split()).rstrip(".")
            typer.echo(f"lidar-slam: error: {message}{where}", err=True)
            sys.exit(exc.exit_code)
        except Exception as exc:  # a bug: say so in one line, keep the traceback in a file
            sys.exit(_internal_error(exc))
        sys.exit(code if isinstance(code, int) else 0)


app = _App(add_completion=False, pretty_exceptions_enable=False, no_args_is_help=True,
           help="Lidar SLAM: odometry, loop closure, pose graph, map and metrics.")


def reports_errors(fn):
    """Turn typed library errors (and Ctrl-C) into one line on stderr and an exit code."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except LidarSlamError as exc:
            raise _exit(str(exc), getattr(exc, "exit_code", EXIT_BAD_INPUT)) from None
        except KeyboardInterrupt:
            raise _exit("interrupted", EXIT_INTERRUPTED) from None
        except BrokenPipeError:  # stdout closed early (`| head`): no error line, no traceback
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            raise typer.Exit(1) from None
        except OSError as exc:  # e.g. an output path that cannot be created or written
            where = exc.filename if exc.filename is not None else "output"
            raise _exit(f"{where}: {exc.strerror or exc}", EXIT_BAD_INPUT) from None

    return wrapper


def _print_version(value: bool) -> None:
    if value:
        from lidar_slam.provenance import version_line

        typer.echo(version_line())
        raise typer.Exit()


@app.callback()
def main(verbose: bool = typer.Option(False, "--verbose", "-v", help="Debug logging."),
         version: bool = typer.Option(False, "--version", callback=_print_version,
                                      is_eager=True, help="Print the version and exit.")) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)


UNITS = {"wall_s": "s", "fps": "frames/s", "peak_rss_mb": "MB", "path_length_m": "m",
         "map_points": "points", "rpe_trans_m_mean": "m", "rpe_rot_deg_mean": "deg",
         "end_drift_pct": "%", "ate_rmse_m": "m", "odometry_ate_rmse_m": "m",
         "odometry_ms_per_frame": "ms", "loops_ms_per_frame": "ms",
         "loop_worker_ms_per_frame": "ms", "loop_wait_ms_per_frame": "ms",
         "loop_wait_final_s": "s",
         "backend_ms_per_loop_max": "ms", "backend_s": "s", "backend_final_s": "s",
         "backend_share_pct": "%", "map_load_s": "s", "fps_after_load": "frames/s",
         "localize_ms_per_frame": "ms", "track_ms_per_frame": "ms",
         "relocalise_ms_per_attempt": "ms"}


# Of a nested summary entry with many fields, the ones the terminal table shows.
SUMMARY_KEYS_SHOWN = ("used", "source", "samples", "rate_hz", "read_as", "reason", "verdict",
                      "fixes_used", "fixes_rejected", "fixes_unused")


def summary_table(summary: dict) -> str:
    """The run summary as an aligned two-column table, every number with its unit."""
    rows = []
    for key, value in summary.items():
        if value is None or value == {}:  # e.g. no topic, no git commit: summary.json only
            continue
        if isinstance(value, float):
            text = f"{value:.4g}"
        elif isinstance(value, dict):  # e.g. imu / gnss: the gist here, the rest in the file
            shown = {k: v for k, v in value.items() if k in SUMMARY_KEYS_SHOWN} or value
            text = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                             for k, v in shown.items())
        else:
            text = str(value)
        rows.append((key, f"{text} {UNITS.get(key, '')}".strip()))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)
