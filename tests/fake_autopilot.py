"""A recording fake autopilot speaking real MAVLink 2 (pymavlink's codec) over loopback sockets
or a pseudo-terminal: the stand-in for the flight controller, the one piece of hardware that
cannot exist on a test machine.

It sends HEARTBEAT (as an ArduSub: MAV_TYPE_SUBMARINE, MAV_AUTOPILOT_ARDUPILOTMEGA) and
SYSTEM_TIME (its boot clock) at `heartbeat_period_s`, records every message it decodes, answers
PARAM_REQUEST_READ from `params` (unknown names get no answer, as ArduPilot does) and
MAV_CMD_REQUEST_MESSAGE(AUTOPILOT_VERSION). With `echo=True` it reflects every received packet
back, as a router that does not filter the sender would.

Usage (also from the daemon's end-to-end tests: `from tests.fake_autopilot import ...`):

    with FakeAutopilot(UdpServerTransport()) as autopilot:
        link = MavlinkLink(MavlinkSettings(url=autopilot.url))
        ...
        autopilot.wait_for("DISTANCE_SENSOR", count=5)
"""

from __future__ import annotations

import contextlib
import os
import select
import socket
import threading
import time
import tty
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from drivers.lifecycle import Closeable
from drivers.net import free_port


def _mavlink2() -> Any:
    os.environ["MAVLINK20"] = "1"
    from pymavlink.dialects.v20 import ardupilotmega

    return ardupilotmega


class Transport(ABC):
    """The fake autopilot's end of one loopback connection."""

    url: str  # what the link under test connects to

    @abstractmethod
    def fds(self) -> list[int]: ...

    @abstractmethod
    def read(self, fd: int) -> bytes:
        """Bytes that arrived on `fd` (b'' if none); handles accepts."""

    @abstractmethod
    def write(self, data: bytes) -> None:
        """Send to the connected peer; silently nothing when there is none (like a radio)."""

    @abstractmethod
    def close(self) -> None: ...


class UdpServerTransport(Transport):
    """The autopilot listens; the link uses udpout: and is answered at its last address."""

    def __init__(self) -> None:
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind(("127.0.0.1", 0))
        self._peer: tuple[str, int] | None = None
        self.url = f"udpout:127.0.0.1:{self._sock.getsockname()[1]}"

    def fds(self) -> list[int]:
        return [self._sock.fileno()]

    def read(self, fd: int) -> bytes:
        data, self._peer = self._sock.recvfrom(65535)
        return data

    def write(self, data: bytes) -> None:
        if self._peer is not None:
            self._sock.sendto(data, self._peer)

    def close(self) -> None:
        self._sock.close()


class UdpClientTransport(Transport):
    """The link listens (udpin:) on a free port; the autopilot sends to it first."""

    def __init__(self) -> None:
        self._target = ("127.0.0.1", free_port(socket.SOCK_DGRAM))
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind(("127.0.0.1", 0))
        self.url = f"udpin:127.0.0.1:{self._target[1]}"

    def fds(self) -> list[int]:
        return [self._sock.fileno()]

    def read(self, fd: int) -> bytes:
        return self._sock.recv(65535)

    def write(self, data: bytes) -> None:
        with contextlib.suppress(ConnectionRefusedError):  # the link is not listening yet
            self._sock.sendto(data, self._target)

    def close(self) -> None:
        self._sock.close()


class TcpServerTransport(Transport):
    """A TCP server like the BlueOS router (tcp:127.0.0.1:5777); one client at a time."""

    def __init__(self, port: int = 0) -> None:
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listener.bind(("127.0.0.1", port))
        self._listener.listen(1)
        self.port = int(self._listener.getsockname()[1])
        self._client: socket.socket | None = None
        self.accepted = 0
        self.url = f"tcp:127.0.0.1:{self.port}"

    def fds(self) -> list[int]:
        fds = [self._listener.fileno()]
        if self._client is not None:
            fds.append(self._client.fileno())
        return fds

    def read(self, fd: int) -> bytes:
        if fd == self._listener.fileno():
            client, _ = self._listener.accept()
            self.drop_client()
            self._client = client
            self.accepted += 1
            return b""
        if self._client is None:
            return b""
        try:
            data = self._client.recv(65535)
        except OSError:
            data = b""
        if not data:
            self.drop_client()
        return data

    def write(self, data: bytes) -> None:
        if self._client is not None:
            try:
                self._client.sendall(data)
            except OSError:
                self.drop_client()

    def drop_client(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None

    def close(self) -> None:
        self.drop_client()
        self._listener.close()


class PtyTransport(Transport):
    """A pseudo-terminal pair: the link opens the slave device, the autopilot holds the master."""

    def __init__(self) -> None:
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no line editing: a byte pipe like a UART
        self.url = os.ttyname(self._slave)

    def fds(self) -> list[int]:
        return [self._master]

    def read(self, fd: int) -> bytes:
        try:
            return os.read(self._master, 65535)
        except OSError:
            return b""  # EIO while nobody has the slave open

    def write(self, data: bytes) -> None:
        os.write(self._master, data)

    def close(self) -> None:
        os.close(self._master)
        os.close(self._slave)


@dataclass(frozen=True)
class Received:
    t: float  # time.monotonic() at decode
    msg: Any

    @property
    def src(self) -> tuple[int, int]:
        return (self.msg.get_srcSystem(), self.msg.get_srcComponent())


class _Writer:
    """File-like sink that pymavlink's MAVLink object writes packed messages to."""

    def __init__(self, transport: Transport) -> None:
        self.transport = transport

    def write(self, data: bytes) -> None:
        self.transport.write(bytes(data))


class FakeAutopilot(Closeable):
    """See the module docstring. Thread-safe accessors; stop with close() (joins)."""

    MAV_TYPE_SUBMARINE = 12
    MAV_AUTOPILOT_ARDUPILOTMEGA = 3

    def __init__(
        self,
        transport: Transport,
        *,
        sysid: int = 1,
        compid: int = 1,
        heartbeat_period_s: float = 0.1,
        params: Mapping[str, float] | None = None,
        boot_offset_s: float = 123.0,
        flight_sw_version: int = (4 << 24) | (5 << 16) | (3 << 8) | 255,  # 4.5.3 official
        signing_key: bytes | None = None,
        echo: bool = False,
        param_queue: int | None = None,
        param_answer_s: float = 0.005,
    ) -> None:
        """`param_queue`: as ArduPilot (GCS_Param.cpp), PARAM_REQUEST_READ goes to a queue of
        that many, answered one per `param_answer_s` from this object's thread; a request that
        finds the queue full is dropped. None: every request is answered at once."""
        self.transport = transport
        self.sysid = sysid
        self.compid = compid
        self.heartbeat_period_s = heartbeat_period_s
        self.params = dict(params or {})
        self.flight_sw_version = flight_sw_version
        self.echo = echo
        self.heartbeats_enabled = True
        self.armed = False  # its HEARTBEAT's base_mode says so (MAV_MODE_FLAG_SAFETY_ARMED)
        # SYSTEM_TIME with each heartbeat (ArduSub streams it; a rebooted one only after a
        # while, `reboot`), and answers to TIMESYNC requests (as GCS_MAVLINK does).
        self.system_time_enabled = True
        self.timesync_enabled = True
        self._boot = time.monotonic() - boot_offset_s
        m = _mavlink2()
        self.mavlink = m
        self._mav = m.MAVLink(_Writer(transport), srcSystem=sysid, srcComponent=compid)
        self._mav.robust_parsing = True
        if signing_key is not None:
            # Unsigned or wrongly signed messages are then rejected, as by a signing ArduPilot.
            self._mav.signing.secret_key = signing_key
            self._mav.signing.sign_outgoing = True
            self._mav.signing.link_id = 0
            self._mav.signing.timestamp = int((time.time() - 1420070400) * 1e5)
        self._lock = threading.Lock()
        self._received: list[Received] = []
        self.param_requests: list[str] = []
        self._param_queue_size = param_queue
        self._param_answer_s = param_answer_s
        self._param_queue: list[str] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        return self.transport.url

    def boot_ms(self, t: float | None = None) -> int:
        """The autopilot's time_boot_ms at monotonic time t (now by default)."""
        return int(((time.monotonic() if t is None else t) - self._boot) * 1000)

    def reboot(self, down_s: float, streams_after_s: float) -> None:
        """Silent for `down_s` (rebooting), then up with a new boot clock: heartbeats at once,
        SYSTEM_TIME only `streams_after_s` later (ArduSub SITL: 1.2 s). Blocks until then."""
        self.heartbeats_enabled, self.system_time_enabled, self.timesync_enabled = (
            False, False, False)
        time.sleep(down_s)
        self._boot = time.monotonic()
        self.heartbeats_enabled = self.timesync_enabled = True
        time.sleep(streams_after_s)
        self.system_time_enabled = True

    # ---- lifecycle --------------------------------------------------------------------------

    def start(self) -> FakeAutopilot:
        self._thread = threading.Thread(target=self._run, name="fake-autopilot", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self.transport.close()

    def __enter__(self) -> FakeAutopilot:
        return self.start()


    # ---- recorded traffic -------------------------------------------------------------------

    def received(self, kind: str | None = None) -> list[Received]:
        with self._lock:
            return [r for r in self._received if kind is None or r.msg.get_type() == kind]

    def clear(self) -> None:
        with self._lock:
            self._received.clear()

    def wait_for(
        self,
        kind: str,
        count: int = 1,
        timeout: float = 5.0,
        where: Callable[[Received], bool] | None = None,
    ) -> list[Received]:
        """The first `count` matching messages; AssertionError after `timeout` seconds."""
        deadline = time.monotonic() + timeout
        while True:
            found = [r for r in self.received(kind) if where is None or where(r)]
            if len(found) >= count:
                return found[:count]
            if time.monotonic() > deadline:
                raise AssertionError(f"got {len(found)} of {count} {kind} within {timeout} s")
            time.sleep(0.01)

    # ---- sending as someone else (e.g. a ground station on the same router) ----------------

    def send_heartbeat_as(self, sysid: int, compid: int, mav_type: int, autopilot: int) -> None:
        other = self.mavlink.MAVLink(_Writer(self.transport), srcSystem=sysid, srcComponent=compid)
        other.heartbeat_send(mav_type, autopilot, 0, 0, 4)

    # ---- thread -----------------------------------------------------------------------------

    def _run(self) -> None:
        next_heartbeat = time.monotonic()
        next_param = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_heartbeat:
                if self.heartbeats_enabled:
                    self._send_heartbeat()
                next_heartbeat = now + self.heartbeat_period_s
            if self._param_queue and now >= next_param:
                self._send_param(self._param_queue.pop(0))
                next_param = now + self._param_answer_s
            try:
                ready, _, _ = select.select(self.transport.fds(), [], [],
                                            0.002 if self._param_queue else 0.02)
            except (OSError, ValueError):
                continue  # a client socket closed under us; the next turn lists the new fds
            for fd in ready:
                try:
                    data = self.transport.read(fd)
                except OSError:
                    continue
                if data:
                    self._consume(data)

    def _send_param(self, name: str) -> None:
        """PARAM_VALUE for a parameter this autopilot has; nothing for one it has not."""
        if name in self.params:
            index = sorted(self.params).index(name)
            self._mav.param_value_send(
                name.encode("ascii"), float(self.params[name]),
                self.mavlink.MAV_PARAM_TYPE_REAL32, len(self.params), index,
            )

    def _send_heartbeat(self) -> None:
        # base_mode: MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, and SAFETY_ARMED when armed (ArduSub's).
        self._mav.heartbeat_send(
            self.MAV_TYPE_SUBMARINE, self.MAV_AUTOPILOT_ARDUPILOTMEGA,
            1 | (128 if self.armed else 0), 0, 4 if self.armed else 3
        )
        if self.system_time_enabled:
            self._mav.system_time_send(int(time.time() * 1e6), self.boot_ms())

    def _consume(self, data: bytes) -> None:
        msgs = self._mav.parse_buffer(data) or []
        now = time.monotonic()
        for msg in msgs:
            if msg.get_type() == "BAD_DATA":
                continue
            with self._lock:
                self._received.append(Received(now, msg))
            if self.echo:
                self.transport.write(bytes(msg.get_msgbuf()))
            self._answer(msg)

    def _answer(self, msg: Any) -> None:
        kind = msg.get_type()
        m = self.mavlink
        if kind == "TIMESYNC" and msg.tc1 == 0 and self.timesync_enabled:
            # GCS_MAVLINK::handle_timesync: our boot clock in ns, their ts1 echoed.
            self._mav.timesync_send(self.boot_ms() * 1_000_000, msg.ts1)
            return
        if kind == "PARAM_REQUEST_READ" and msg.target_system == self.sysid:
            name = msg.param_id
            with self._lock:
                self.param_requests.append(name)
            if self._param_queue_size is None:
                self._send_param(name)
            elif len(self._param_queue) < self._param_queue_size:
                self._param_queue.append(name)
        elif kind == "COMMAND_LONG" and msg.target_system == self.sysid:
            wants_version = (
                msg.command == m.MAV_CMD_REQUEST_MESSAGE
                and int(msg.param1) == m.MAVLINK_MSG_ID_AUTOPILOT_VERSION
            ) or msg.command == m.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES
            result = m.MAV_RESULT_ACCEPTED if wants_version else m.MAV_RESULT_UNSUPPORTED
            self._mav.command_ack_send(msg.command, result)
            if wants_version:
                self._mav.autopilot_version_send(
                    m.MAV_PROTOCOL_CAPABILITY_MAVLINK2, self.flight_sw_version, 0, 0, 0,
                    b"\x00" * 8, b"\x00" * 8, b"\x00" * 8, 0x1209, 0x5740, 0x0140,
                )
