"""Signals as flags: handlers only set an event, the owner's loop polls it.

Used by the daemon (stop, reload), `netpose replay` and `netpose monitor` (stop). The previous
handlers are restored when the `with` block ends, so a library or test that installed its own
keeps them.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

# The stop reason of an in-process restart (`netpose run`'s web page).
RESTART = "restart"


class SignalFlags:
    """Set by signal handlers, polled by a loop (handlers do nothing else)."""

    def __init__(self) -> None:
        self.stop = threading.Event()
        self.reload = threading.Event()
        self.stop_signal: str | None = None
        # Set by a real signal and never cleared: what a stop the owner clears to go on (the
        # web page's in-process restart) must not swallow.
        self.signalled = threading.Event()

    def request_stop(self, name: str) -> None:
        """A stop for `name`; the first reason given is kept, except that a signal replaces a
        restart (the process must end, not come back)."""
        if self.stop_signal is None or self.stop_signal == RESTART:
            self.stop_signal = name
        self.stop.set()

    def signal_stop(self, name: str) -> None:
        self.signalled.set()
        self.request_stop(name)


class EarlySignals:
    """Signals that come while the service is still starting (importing numpy and OpenCV,
    reading its configuration: a few hundred ms), kept for `handle_signals` to act on. Without
    it a `systemctl reload` right after a start ended the process (SIGHUP's default), and a
    stop there ended it with 143 instead of a clean exit."""

    WATCHED = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)

    def __init__(self) -> None:
        self.pending: list[signal.Signals] = []
        self._previous: dict[signal.Signals, Any] = {}

    def install(self) -> EarlySignals:
        if threading.current_thread() is threading.main_thread():
            self._previous = {sig: signal.signal(sig, self._keep) for sig in self.WATCHED}
        return self

    def _keep(self, signum: int, _frame: FrameType | None) -> None:
        self.pending.append(signal.Signals(signum))

    def hand_over(self) -> list[signal.Signals]:
        """The signals kept, with the handlers from before `install` back in place."""
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous = {}
        return self.pending


@contextmanager
def handle_signals(flags: SignalFlags, *, reload: bool = False,
                   early: EarlySignals | None = None) -> Iterator[SignalFlags]:
    """SIGTERM and SIGINT request a stop; SIGHUP a reload when `reload` is set. `early`: the
    signals that came during start-up are acted on now.

    A second Ctrl-C while a stop is already under way interrupts at once (KeyboardInterrupt).
    Outside the main thread (where Python cannot handle signals) nothing is installed.
    """
    pending = early.hand_over() if early is not None else []
    if threading.current_thread() is not threading.main_thread():
        yield flags
        return

    def on_stop(signum: int, _frame: FrameType | None) -> None:
        if flags.stop.is_set() and signum == signal.SIGINT:
            raise KeyboardInterrupt
        flags.signal_stop(signal.Signals(signum).name)

    def on_hup(_signum: int, _frame: FrameType | None) -> None:
        flags.reload.set()

    handlers: list[tuple[signal.Signals, Any]] = [(signal.SIGTERM, on_stop),
                                                  (signal.SIGINT, on_stop)]
    if reload:
        handlers.append((signal.SIGHUP, on_hup))
    previous = {sig: signal.signal(sig, handler) for sig, handler in handlers}
    for sig in pending:
        if sig == signal.SIGHUP:
            if reload:
                flags.reload.set()
        else:
            flags.signal_stop(sig.name)
    try:
        yield flags
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
