"""SIGINT and SIGTERM turned into a request to stop that a long loop checks between messages,
so that an interrupted replay ends where it is and finalises its output (readable by every MCAP
reader, its metadata saying it is partial) instead of dying inside a write.

A second signal of the same run stops at once (SIGINT: ``KeyboardInterrupt``; SIGTERM:
``SystemExit(143)``), for a loop that does not get to check.
"""
from __future__ import annotations

import signal
import threading
from typing import Any

__all__ = ['StopRequest', 'EXIT_CODES', 'signal_name']

#: Exit status of a run stopped by a signal: 128 + its number (the shell's convention).
EXIT_CODES: dict[int, int] = {signal.SIGINT: 130, signal.SIGTERM: 143}


def signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f'signal {signum}'


class StopRequest:
    """``with StopRequest() as stop:`` -- SIGINT/SIGTERM set ``stop.signum`` (the first one
    received) instead of ending the process; the previous handlers come back on exit. Outside
    the main thread (where Python cannot install handlers) it does nothing."""

    def __init__(self, signals=(signal.SIGINT, signal.SIGTERM)):
        self.signals = tuple(signals)
        self.signum: int | None = None
        self._previous: dict[int, Any] = {}

    def __bool__(self) -> bool:
        return self.signum is not None

    @property
    def exit_code(self) -> int:
        return EXIT_CODES.get(self.signum, 1) if self.signum is not None else 0

    @property
    def name(self) -> str:
        return signal_name(self.signum) if self.signum is not None else ''

    def _handler(self, signum, frame) -> None:
        if self.signum is not None:
            if signum == signal.SIGINT:
                raise KeyboardInterrupt
            raise SystemExit(EXIT_CODES.get(signum, 1))
        self.signum = signum

    def __enter__(self) -> StopRequest:
        if threading.current_thread() is threading.main_thread():
            for signum in self.signals:
                self._previous[signum] = signal.signal(signum, self._handler)
        return self

    def __exit__(self, *exc: Any) -> None:
        for signum, previous in self._previous.items():
            signal.signal(signum, previous)
        self._previous.clear()
