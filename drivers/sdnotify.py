"""systemd service notifications (sd_notify): READY, WATCHDOG, STATUS, STOPPING, RELOADING.

No dependency on libsystemd: the protocol is one datagram per message on the AF_UNIX socket named
by $NOTIFY_SOCKET (a leading '@' means the Linux abstract namespace). Outside systemd the variable
is absent and `notifier_from_environment()` returns a `NullNotifier` (or, on a terminal, a
`ConsoleNotifier` that prints the status lines), so the daemon code is the same everywhere.

Watchdog pings are rate-limited here (at half of $WATCHDOG_USEC, as sd_watchdog_enabled(3)
recommends) so the frame loop can call `watchdog()` every iteration for free.

Where no systemd watches (a container: BlueOS's extensions), $NETPOSE_HANG_EXIT_S asks for its
stand-in, `HangWatchdog`: a frame loop that stops pinging for that long ends the process, and
the container engine's restart policy brings it back, as systemd's watchdog would.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from typing import TextIO

from drivers.errors import NotifyError

log = logging.getLogger(__name__)


class Notifier(ABC):
    """Tells the service manager how the service is doing. Never raises during operation."""

    def __init__(self, watchdog_interval_s: float | None = None) -> None:
        # None: the service manager expects no watchdog pings.
        self.watchdog_interval_s = watchdog_interval_s
        self._last_watchdog = -float("inf")

    @abstractmethod
    def notify(self, message: str) -> bool:
        """Send one raw notification ('KEY=value' lines); True when it was delivered."""

    def ready(self, status: str | None = None) -> bool:
        return self.notify("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def status(self, text: str) -> bool:
        # STATUS is one line in `systemctl status`; newlines would start new assignments.
        return self.notify("STATUS=" + " ".join(text.splitlines()))

    def stopping(self) -> bool:
        return self.notify("STOPPING=1")

    def reloading(self) -> bool:
        # systemd >= 253 wants MONOTONIC_USEC with RELOADING=1 (Type=notify-reload); older ones
        # ignore the extra field.
        usec = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
        return self.notify(f"RELOADING=1\nMONOTONIC_USEC={usec}")

    def watchdog(self, now: float | None = None) -> bool:
        """Ping the watchdog if it is enabled and half its interval has passed since the last."""
        if self.watchdog_interval_s is None:
            return False
        t = time.monotonic() if now is None else now
        if t - self._last_watchdog < self.watchdog_interval_s / 2.0:
            return False
        self._last_watchdog = t
        return self.notify("WATCHDOG=1")

    def close(self) -> None:  # noqa: B027 - optional hook, most notifiers hold nothing
        """Release resources."""


class NullNotifier(Notifier):
    """Not started by systemd: every notification is dropped."""

    def notify(self, message: str) -> bool:
        return False


class RecordingNotifier(Notifier):
    """PC stand-in that keeps the messages in memory (for tests of the code that notifies)."""

    def __init__(self, watchdog_interval_s: float | None = None) -> None:
        super().__init__(watchdog_interval_s)
        self.messages: list[str] = []

    def notify(self, message: str) -> bool:
        self.messages.append(message)
        return True


class ConsoleNotifier(Notifier):
    """PC stand-in for an interactive run (`make run`): READY, STATUS and STOPPING become lines
    on a terminal, so the live state is visible without systemctl. STATUS is printed at most
    once per `min_interval_s` (it changes every second; a terminal should not scroll faster)."""

    def __init__(self, stream: TextIO, min_interval_s: float = 1.0) -> None:
        super().__init__(None)
        self._stream = stream
        self._min_interval_s = min_interval_s
        self._last_status = -float("inf")

    def notify(self, message: str) -> bool:
        now = time.monotonic()
        for line in message.splitlines():
            key, _, value = line.partition("=")
            if key == "STATUS":
                if now - self._last_status < self._min_interval_s:
                    continue
                self._last_status = now
                text = f"netpose: {value}"
            elif key in ("READY", "STOPPING", "RELOADING"):
                text = f"netpose: {key.lower()}"
            else:
                continue
            try:
                print(text, file=self._stream, flush=True)
            except (OSError, ValueError):  # closed terminal: nothing to tell
                return False
        return True


# The exit status of a hung frame loop ended by HangWatchdog (EX_SOFTWARE).
HUNG_EXIT_STATUS = 70


def _exit_hung(_silent_s: float) -> None:
    os._exit(HUNG_EXIT_STATUS)  # the loop's thread holds what a clean exit would wait for


class HangWatchdog(Notifier):
    """systemd's watchdog where there is none (a container): `inner` does the notifying, and a
    thread of its own ends the process (`on_hang`) when the frame loop has not pinged for
    `timeout_s` since it said ready. A loop hung in a blocking read would otherwise stop the
    distances for good without a restart (the autopilot's rangefinder times out: safe, but the
    vehicle has lost its sensor until someone restarts the extension). Stopping (`stopping`,
    `close`) disarms it: a slow close is not a hang."""

    def __init__(self, inner: Notifier, timeout_s: float,
                 on_hang: Callable[[float], None] = _exit_hung,
                 clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(inner.watchdog_interval_s)
        self.inner = inner
        self.timeout_s = timeout_s
        self._on_hang = on_hang
        self._clock = clock
        self._last_ping = clock()
        self._disarmed = threading.Event()
        self._thread: threading.Thread | None = None

    def notify(self, message: str) -> bool:
        return self.inner.notify(message)

    def ready(self, status: str | None = None) -> bool:
        self._last_ping = self._clock()
        if self._thread is None and not self._disarmed.is_set():
            self._thread = threading.Thread(target=self._watch, name="hang watchdog",
                                            daemon=True)
            self._thread.start()
        return self.inner.ready(status)

    def status(self, text: str) -> bool:
        return self.inner.status(text)

    def stopping(self) -> bool:
        self._disarmed.set()
        return self.inner.stopping()

    def reloading(self) -> bool:
        return self.inner.reloading()

    def watchdog(self, now: float | None = None) -> bool:
        self._last_ping = self._clock()  # its own clock: `now` may be a replay's
        return self.inner.watchdog(now)

    def close(self) -> None:
        self._disarmed.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self.inner.close()

    def _watch(self) -> None:
        while not self._disarmed.wait(min(1.0, self.timeout_s / 4.0)):
            silent = self._clock() - self._last_ping
            if silent > self.timeout_s:
                log.critical("frame loop hung: no pass for %.0f s (NETPOSE_HANG_EXIT_S %.0f s):"
                             " exiting with status %d so that the container restarts it",
                             silent, self.timeout_s, HUNG_EXIT_STATUS)
                self._on_hang(silent)
                return


class SystemdNotifier(Notifier):
    """The real thing: datagrams to the service manager's notification socket."""

    def __init__(self, socket_path: str, watchdog_interval_s: float | None = None) -> None:
        super().__init__(watchdog_interval_s)
        if not socket_path or socket_path[0] not in "/@":
            raise NotifyError(f"NOTIFY_SOCKET must be an absolute path or start with '@': "
                              f"{socket_path!r}")
        self._address = "\0" + socket_path[1:] if socket_path[0] == "@" else socket_path
        self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
        self._socket.setblocking(False)  # the frame loop must never wait on systemd
        self._failed_once = False

    def notify(self, message: str) -> bool:
        try:
            self._socket.sendto(message.encode("utf-8"), self._address)
        except OSError:
            # The manager is gone or the queue is full: nothing useful to do but carry on.
            # The daemon logs the first failure via `failed`.
            self._failed_once = True
            return False
        return True

    @property
    def failed(self) -> bool:
        """True once any notification could not be delivered."""
        return self._failed_once

    def close(self) -> None:
        self._socket.close()


def watchdog_interval_from_environment(env: Mapping[str, str]) -> float | None:
    """$WATCHDOG_USEC in seconds if the watchdog is meant for this process (sd_watchdog_enabled)."""
    usec = env.get("WATCHDOG_USEC")
    if not usec:
        return None
    pid = env.get("WATCHDOG_PID")
    if pid and pid.strip() != str(os.getpid()):
        return None
    try:
        value = int(usec)
    except ValueError:
        return None
    return value / 1e6 if value > 0 else None


def notifier_from_environment(
    env: Mapping[str, str] | None = None, console: TextIO | None = None
) -> Notifier:
    """The notifier systemd asked for through the environment; outside systemd a
    ConsoleNotifier on `console` if that is a terminal, else a NullNotifier."""
    environ = os.environ if env is None else env
    path = environ.get("NOTIFY_SOCKET", "")
    interval = watchdog_interval_from_environment(environ)
    if path:
        return SystemdNotifier(path, interval)
    inner: Notifier = (ConsoleNotifier(console) if console is not None and console.isatty()
                       else NullNotifier(interval))
    hang_s = _hang_exit_s(environ)
    return HangWatchdog(inner, hang_s) if hang_s is not None else inner


def _hang_exit_s(environ: Mapping[str, str]) -> float | None:
    """$NETPOSE_HANG_EXIT_S in seconds (5..3600), None when unset or not such a number (said
    once in the log: the variable is the image's, not the user's)."""
    text = environ.get("NETPOSE_HANG_EXIT_S", "").strip()
    if not text:
        return None
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 5.0 <= value <= 3600.0:
        log.warning("NETPOSE_HANG_EXIT_S=%r ignored: must be 5..3600 s", text)
        return None
    return value
