"""Ctrl-C and SIGTERM during a run: stop after the scan in hand, keep what was computed."""

from __future__ import annotations

import contextlib
import signal


class StopSignals:
    """While active, Ctrl-C and SIGTERM (kill, timeout, docker stop, a batch scheduler) ask the
    run to stop after the scan in hand, so the frames computed so far are kept and written; a
    second one stops at once (KeyboardInterrupt). Inside deferred() every signal is only noted,
    so the outputs being written are finished first: the handler stays installed from the first
    scan to the last output (no moment where Python's default handler is back)."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self.received = False
        self.name = ""  # the first signal's name (SIGINT, SIGTERM), for summary.json
        self._deferring = False
        self._old: dict = {}

    def _handle(self, signum, frame):
        if self.received and not self._deferring:
            raise KeyboardInterrupt
        self.received = True
        self.name = self.name or signal.Signals(signum).name

    def __enter__(self):
        try:
            for sig in self.SIGNALS:
                self._old[sig] = signal.signal(sig, self._handle)
        except ValueError:  # not the main thread (embedded use): leave signals alone
            self.__exit__()
        return self

    def __exit__(self, *exc) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)
        self._old = {}

    @contextlib.contextmanager
    def deferred(self):
        self._deferring = True
        try:
            yield
        finally:
            self._deferring = False
