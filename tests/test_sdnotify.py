"""sd_notify against a real AF_UNIX datagram socket standing in for the service manager."""

from __future__ import annotations

import io
import os
import socket
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from drivers.errors import NotifyError
from drivers.sdnotify import (
    ConsoleNotifier,
    NullNotifier,
    RecordingNotifier,
    SystemdNotifier,
    notifier_from_environment,
    watchdog_interval_from_environment,
)


@pytest.fixture
def manager_socket(tmp_path: Path) -> Iterator[tuple[socket.socket, str]]:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    path = str(tmp_path / "notify.sock")
    sock.bind(path)
    sock.settimeout(2.0)
    yield sock, path
    sock.close()


def test_messages_arrive_as_datagrams(manager_socket: tuple[socket.socket, str]) -> None:
    sock, path = manager_socket
    n = SystemdNotifier(path)
    try:
        assert n.ready(status="started")
        assert sock.recv(4096) == b"READY=1\nSTATUS=started"
        assert n.status("tracking 1.23 m\nsecond line")
        assert sock.recv(4096) == b"STATUS=tracking 1.23 m second line"
        assert n.stopping()
        assert sock.recv(4096) == b"STOPPING=1"
        assert n.reloading()
        reload_msg = sock.recv(4096).decode()
        assert reload_msg.startswith("RELOADING=1\nMONOTONIC_USEC=")
        assert not n.failed
    finally:
        n.close()


def test_abstract_namespace_socket() -> None:
    name = f"netpose-test-{uuid.uuid4().hex}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)
    sock.settimeout(2.0)
    n = notifier_from_environment({"NOTIFY_SOCKET": "@" + name})
    try:
        assert isinstance(n, SystemdNotifier)
        assert n.notify("READY=1")
        assert sock.recv(4096) == b"READY=1"
    finally:
        n.close()
        sock.close()


def test_watchdog_is_rate_limited_to_half_the_interval(
    manager_socket: tuple[socket.socket, str],
) -> None:
    sock, path = manager_socket
    env = {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "2000000", "WATCHDOG_PID": str(os.getpid())}
    n = notifier_from_environment(env)
    try:
        assert n.watchdog_interval_s == pytest.approx(2.0)
        sent = [n.watchdog(now=t / 10.0) for t in range(0, 35)]  # 0 .. 3.4 s every 0.1 s
        # Pings at 0, 1.0, 2.0, 3.0 s: every half interval, never more often.
        assert [i / 10.0 for i, s in enumerate(sent) if s] == [0.0, 1.0, 2.0, 3.0]
        sock.settimeout(0.5)
        assert [sock.recv(64) for _ in range(4)] == [b"WATCHDOG=1"] * 4
    finally:
        n.close()


def test_watchdog_meant_for_another_process_is_ignored() -> None:
    assert watchdog_interval_from_environment({"WATCHDOG_USEC": "1000000",
                                               "WATCHDOG_PID": "1"}) is None
    assert watchdog_interval_from_environment({"WATCHDOG_USEC": "junk"}) is None
    assert watchdog_interval_from_environment({"WATCHDOG_USEC": "500000"}) == pytest.approx(0.5)


def test_outside_systemd_nothing_is_sent() -> None:
    n = notifier_from_environment({})
    assert isinstance(n, NullNotifier)
    assert not n.ready() and not n.watchdog()


def test_vanished_manager_does_not_raise(tmp_path: Path) -> None:
    n = SystemdNotifier(str(tmp_path / "nobody-listens.sock"))
    try:
        assert not n.ready()
        assert n.failed
    finally:
        n.close()


def test_relative_socket_path_is_refused() -> None:
    with pytest.raises(NotifyError):
        SystemdNotifier("relative/path.sock")


def test_recording_notifier_keeps_messages() -> None:
    n = RecordingNotifier(watchdog_interval_s=1.0)
    n.ready()
    n.watchdog(now=0.0)
    n.watchdog(now=0.1)
    assert n.messages == ["READY=1", "WATCHDOG=1"]


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_console_notifier_on_a_terminal_prints_status_at_most_once_a_second() -> None:
    out = _Tty()
    n = notifier_from_environment({}, console=out)
    assert isinstance(n, ConsoleNotifier)
    n.ready(status="started")
    n.status("tracking 1.20 m")  # within a second of "started": not printed
    n.stopping()
    assert out.getvalue().splitlines() == ["netpose: ready", "netpose: started",
                                           "netpose: stopping"]
    # Not a terminal (a pipe, a journal): nothing is printed.
    assert isinstance(notifier_from_environment({}, console=io.StringIO()), NullNotifier)


def test_outside_systemd_a_hung_loop_ends_the_process_for_the_container_to_restart() -> None:
    """In a container (BlueOS's extensions) no systemd watches: a frame loop hung in a
    blocking read stopped the distances for good. $NETPOSE_HANG_EXIT_S asks for the stand-in:
    no ping for that long after ready ends the process; pings keep it alive, and stopping
    disarms it (a slow close is not a hang)."""
    import threading
    import time

    from drivers.sdnotify import HangWatchdog, NullNotifier, notifier_from_environment

    assert isinstance(notifier_from_environment({"NETPOSE_HANG_EXIT_S": "30"}), HangWatchdog)
    assert not isinstance(notifier_from_environment({"NETPOSE_HANG_EXIT_S": "1"}),
                          HangWatchdog)  # out of range: ignored, said in the log
    systemd = notifier_from_environment({"NETPOSE_HANG_EXIT_S": "30",
                                         "NOTIFY_SOCKET": "/run/x.sock"})
    assert not isinstance(systemd, HangWatchdog)  # systemd's own watchdog does the job

    for case in ("hung", "pinging", "stopping"):
        hung = threading.Event()

        def on_hang(_silent_s: float, event: threading.Event = hung) -> None:
            event.set()

        dog = HangWatchdog(NullNotifier(), 1.0, on_hang=on_hang)
        dog.ready()
        end = time.monotonic() + 3.0
        if case == "stopping":
            dog.stopping()
        while time.monotonic() < end and not hung.is_set():
            if case == "pinging":
                dog.watchdog()
            time.sleep(0.05)
        dog.close()
        assert hung.is_set() == (case == "hung"), case


def test_the_hang_exit_is_a_real_exit_with_its_reason(tmp_path: Path) -> None:
    """The stand-in ends a real process, with status 70 and the reason in its log (what the
    container's log shows before the restart)."""
    import subprocess
    import sys
    import time

    code = ("import logging, time\n"
            "logging.basicConfig()\n"
            "from drivers.sdnotify import notifier_from_environment\n"
            "notifier_from_environment().ready()\n"
            "time.sleep(60)\n")
    env = {k: v for k, v in os.environ.items() if k not in ("NOTIFY_SOCKET", "WATCHDOG_USEC")}
    env["NETPOSE_HANG_EXIT_S"] = "5"
    t0 = time.monotonic()
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                          text=True, timeout=30, cwd=Path(__file__).resolve().parents[1])
    assert done.returncode == 70, done.stderr
    assert 5.0 <= time.monotonic() - t0 < 20.0
    assert "frame loop hung" in done.stderr
