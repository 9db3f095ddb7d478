"""The autopilot link: DISTANCE_SENSOR and the net plane (for the net-hold applet) to ArduSub.

The frame loop only calls cheap setters (`set_range`, `set_net_plane`): each stores the newest
value under a lock, a bounded queue of depth one where the newest value wins. One owned thread
(`MavlinkLink`) does all I/O with pymavlink (MAVLink 2): it connects, retries a dead transport
with backoff (service.core.backoff), sends HEARTBEAT at 1 Hz as an onboard controller, tracks
the autopilot's heartbeat (waiting -> connected -> lost -> connected), and sends DISTANCE_SENSOR
at least at `rate_hz` while the newest reading is sendable (service.core.readings.RangeStatus) and
fresh (drivers.distance_gate: a freshness limit that follows the measured frame interval and
latency, up to `max_age_s`, and start/stop hysteresis). Every message is stamped with the capture
time of the frame it describes, on the autopilot's boot clock.

When it is sent: a new reading goes out as it arrives (the frame loop wakes the link thread
through a pipe) unless the frame after it is due within the period after the last reading sent
this way (frame times are capture times: the camera's clock, without the loop's jitter). So
the frames sent are at most a period apart: every second one at 30 frames/s, every one at 15 or
fewer. The newest reading is also repeated one period after the last send, which bounds the
gap whatever the camera does. A fixed schedule alone made each reading wait up to a frame
interval for its slot (issue 13's latency).

With no believable reading it sends nothing; ArduPilot then reports the rangefinder as "no
data" after 500 ms, which is the protocol's own meaning of "invalid" for a MAVLink rangefinder.
The net plane goes out as DEBUG_VECT named `NET_PLANE` (docs/net-hold.md) on a fixed
`rate_hz` schedule (what the net-hold applet was proved with), only while the newest plane is
younger than `max_age_s` (a zero vector when that frame did not confirm the net).

`RecordingAutopilotLink` is the stand-in with the same interface for tests that need no network.
"""

from __future__ import annotations

import collections
import contextlib
import fcntl
import functools
import logging
import math
import os
import select
import sys
import threading
import time
from abc import abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from drivers.distance_gate import DistanceGate
from drivers.errors import MavlinkLinkError
from drivers.lifecycle import Closeable
from drivers.mavlink_settings import MavlinkSettings, load_signing_key, serial_device
from drivers.mavlink_wire import NET_PLANE_NAME, distance_sensor_fields
from service.core.backoff import Backoff
from service.core.messages import AutopilotHealth, AutopilotIdentity
from service.core.readings import NetPlane, RangeReading, RangeStatus
from service.core.redact import redact_text
from service.core.state_log import StateLog, not_logged_note

log = logging.getLogger(__name__)

HEARTBEAT_PERIOD_S = 1.0
# Messages with a bad signature, and none with a good one, that show the autopilot signs with
# another key (one could be a corrupted frame).
_WRONG_KEY_SIGNATURES = 3
# How long one wait for incoming data may last: bounds how late close() is noticed.
_POLL_LIMIT_S = 0.1
# Incoming messages handled per loop turn, so a flood cannot starve the send schedule.
_MAX_MESSAGES_PER_TURN = 200
# Bytes from a serial port with no MAVLink frame among them that mean a wrong baud rate (a
# heartbeat alone is 17-21 bytes; a second of a mismatched 57600 baud link is thousands).
_GARBLED_BYTES = 256
# A serial write that cannot finish in this time means the port is dead or wedged.
_SERIAL_WRITE_TIMEOUT_S = 0.2
# How long close() waits for the link thread.
CLOSE_WAIT_S = 0.2
# A jump of the autopilot's boot clock larger than this is a reboot, not network jitter.
_REBOOT_JUMP_S = 1.0
# The autopilot's clock is asked for (TIMESYNC, which ArduPilot answers with its boot time)
# this often, and a net plane goes out only while an answer (or a message's time_boot_ms) that
# agrees with the clock in use came within the last _CLOCK_CONFIRMED_S: after a reboot the old
# clock would stamp every plane hours into the new one's future until its streams start.
_CLOCK_ASK_PERIOD_S = 0.25
_CLOCK_CONFIRMED_S = 0.75
# How far two crystals may disagree (parts per million; a watch crystal is within 20-50): the
# earliest boot estimate is allowed to move later by this much per second, so stamps follow an
# autopilot clock slower than ours instead of running into its future.
_CLOCK_DRIFT_PPM = 200.0
# A new reading is sent on arrival when the one after it (a frame interval later) would come
# later than a period after the last reading sent, less this share of a frame interval: the
# margin for a camera whose frame times wobble.
_FRAME_MARGIN = 0.1

# MAVLink enum values used below (common.xml), spelled out to keep pymavlink out of import time.
MAV_TYPE_ONBOARD_CONTROLLER = 18
MAV_AUTOPILOT_INVALID = 8
MAV_STATE_ACTIVE = 4
MAV_COMP_ID_AUTOPILOT1 = 1
MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_SEVERITY_WARNING = 4
MAV_SEVERITY_NOTICE = 5
# STATUSTEXT.text is 50 characters; texts queued while the link is down wait, up to this many.
STATUSTEXT_LENGTH = 50
_MAX_QUEUED_TEXTS = 16
# ... and for at most this long: a pilot's text is about now ("net too close to measure, back
# off"); one that reached the GCS 20 s late, after a link outage, was a wrong instruction.
# A hole's text too: it says where the hole is from where the vehicle was (its message on Zenoh
# and the log keep it).
TEXT_MAX_WAIT_S = 5.0
# Heartbeat types that are never the autopilot even if they claim an autopilot field.
NON_AUTOPILOT_TYPES = frozenset({6, 18, 26, 27, 30})  # GCS, onboard, gimbal, ADS-B, camera

SendTimes = dict[str, int]


class AutopilotLink(Closeable):
    """What the daemon needs from an autopilot link. Setters are cheap and never block."""

    @abstractmethod
    def start(self) -> None:
        """Begin connecting and sending (returns at once)."""

    @abstractmethod
    def set_range(self, reading: RangeReading) -> None:
        """Newest reading, stamped with the capture time of its frame."""

    @abstractmethod
    def set_net_plane(self, plane: NetPlane) -> None:
        """Newest net plane, from a frame whose measurement the filter accepted."""

    @abstractmethod
    def notify_pilot(self, text: str, severity: int = MAV_SEVERITY_WARNING) -> None:
        """Queue a STATUSTEXT for the pilot's ground station (at most 50 characters are sent;
        rate limiting is the caller's: this sends what it is given, oldest first)."""

    @abstractmethod
    def status(self) -> AutopilotHealth:
        """A snapshot of the link for the status report."""

    @abstractmethod
    def close(self) -> None:
        """Stop sending and release the transport; idempotent."""

    def __enter__(self) -> AutopilotLink:
        self.start()
        return self



@dataclass
class _AutopilotIdentity:
    sysid: int
    compid: int
    mav_type: int
    autopilot: int
    mavlink_version: int
    last_heartbeat: float
    flight_sw_version: int | None = None
    armed: bool = False  # its last HEARTBEAT's base_mode


class _TransportClosedError(MavlinkLinkError):
    """The peer closed the connection or the device went away."""


def import_mavutil() -> Any:
    """pymavlink's mavutil, speaking MAVLink 2 with ArduPilot's dialect.

    Both must be chosen before mavutil is first imported, through the environment (its only
    way). pymavlink 2.4.50 otherwise loads its largest dialect ("all", the union of every
    project's messages) and, on import, the MAVLink 1 "all" module as well, for PyInstaller's
    sake: about 5 MB of resident memory on the Pi's budget (issue 13) and 40 ms of start-up,
    for messages an ArduSub never sends. pymavlink itself allows that second module to be
    missing (it catches the failed import); a None in `sys.modules` is Python's documented
    way to make that import fail, and is removed at once. A MAVLINK_DIALECT set by the user
    still wins."""
    os.environ["MAVLINK20"] = "1"
    os.environ.setdefault("MAVLINK_DIALECT", "ardupilotmega")
    blocked = "pymavlink.dialects.v10.all"
    placed = "pymavlink.mavutil" not in sys.modules and blocked not in sys.modules
    if placed:
        sys.modules[blocked] = None  # type: ignore[assignment]  # None: "cannot be imported"
    try:
        from pymavlink import mavutil
    finally:
        if placed:
            del sys.modules[blocked]

    if mavutil.mavlink.WIRE_PROTOCOL_VERSION != "2.0":
        # mavutil was imported elsewhere before MAVLINK20 was set.
        mavutil.set_dialect("ardupilotmega")
    return mavutil


def _claim_serial_port(device: str) -> int:
    """Hold the serial port alone (a descriptor holding the lock), or fail saying who may
    have it.

    A tty opened twice splits its incoming bytes between the two readers: the daemon and a
    `mavlink-check` run beside it each lost half the autopilot's messages (the check then
    advised a firmware "with rangefinder support", the daemon lost its link). The lock is the
    one pyserial's `exclusive=True` takes (flock), which pymavlink does not ask for: it keeps
    out a second netpose; other programs may not take it, hence the router advice. Taken
    before pymavlink opens the port: its open sets the baud rate, which belongs to the device,
    and a refused second netpose had already changed the service's line speed.
    """
    try:
        fd = os.open(device, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
    except OSError as exc:
        raise MavlinkLinkError(f"cannot open {device}: {exc.strerror}") from exc
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        os.close(fd)
        raise MavlinkLinkError(
            f"{device} is in use by another netpose process (the service?): a serial port "
            "has one reader; stop it, or share the autopilot through a MAVLink router "
            f"(docs/mavlink.md) ({exc.strerror})") from exc
    return fd


def _release_on_close(conn: Any, lock_fd: int) -> None:
    """Closing the connection also lets go of the port's lock (once)."""
    close = conn.close
    held = [lock_fd]

    def close_and_release(*args: Any, **kwargs: Any) -> Any:
        try:
            return close(*args, **kwargs)
        finally:
            while held:  # a descriptor closed twice could be someone else's by then
                os.close(held.pop())

    conn.close = close_and_release


def baud_hint(received_bytes: int, baud: int, key: str, missing: str = "MAVLink") -> str:
    """Why a serial port's bytes hold no `missing`: the rate (`key` names the setting) or the
    port."""
    return (f"{received_bytes} bytes arrived, none of them {missing}: is {key} ({baud}) the "
            "autopilot's SERIALn_BAUD, and is this its port?")


def _hint(message: str) -> str:
    """What to do about a failure whose cause is not in its message."""
    if "Operation not permitted" in message:
        # systemd resolves the unit's DeviceAllow= classes when it starts; a device of a class
        # whose driver loaded later stays refused until the service starts again.
        return (" - a device the service could not reach when it started: "
                "`systemctl restart netpose`")
    return ""


def open_connection(settings: MavlinkSettings, signing_key: bytes | None) -> Any:
    """Open a pymavlink connection whose failures raise instead of printing and retrying.

    pymavlink's own reconnect logic sleeps inside recv/write and reports a closed TCP peer only
    on stdout; the link needs an exception so it can back off on its own thread.
    """
    mavutil = import_mavutil()
    common = {
        "source_system": settings.source_system,
        "source_component": settings.source_component,
        "autoreconnect": False,
    }
    if settings.is_serial:
        device = serial_device(settings.url)
        lock_fd = _claim_serial_port(device)
        try:
            # Not mavlink_connection: it takes any name with a colon for UDP, and a Pi's stable
            # names for a USB autopilot (/dev/serial/by-path/...-usb-0:1.3:1.0-port0) have them.
            conn = mavutil.mavserial(device, baud=settings.baud, **common)
        except BaseException:
            os.close(lock_fd)
            raise
        _release_on_close(conn, lock_fd)
        conn.port.write_timeout = _SERIAL_WRITE_TIMEOUT_S
    elif settings.url.startswith("tcp:"):
        conn = mavutil.mavlink_connection(settings.url, retries=0, **common)

        def closed() -> None:
            raise _TransportClosedError("connection closed by the peer")

        conn.handle_eof = closed
        conn.handle_disconnect = closed
    else:
        conn = mavutil.mavlink_connection(settings.url, **common)
    if signing_key is not None:
        # Outgoing messages are signed; unsigned incoming ones are accepted because the link only
        # reads heartbeats and clocks from them and a router may forward unsigned traffic.
        conn.setup_signing(
            signing_key, sign_outgoing=True, allow_unsigned_callback=lambda _mav, _id: True
        )
    return conn


class MavlinkLink(AutopilotLink):
    """pymavlink link on its own thread; see the module docstring."""

    def __init__(
        self,
        settings: MavlinkSettings,
        clock: Callable[[], float] = time.monotonic,
        connection_factory: Callable[[MavlinkSettings, bytes | None], Any] = open_connection,
    ) -> None:
        self.settings = settings
        self._clock = clock
        self._connection_factory = connection_factory
        # Read at start-up so a bad key stops the service before anything is sent unsigned.
        self._signing_key = (
            load_signing_key(settings.signing_key_file) if settings.signing_key_file else None
        )
        self._wrong_key_said = False
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._started_at = clock()
        # Inputs, written by the frame loop.
        self._range: RangeReading = RangeReading.none(-math.inf)
        self._plane: NetPlane | None = None
        # A sendable reading arrived since the link thread last looked; the pipe wakes it.
        self._arrived = False
        self._wake: tuple[int, int] | None = None
        # Link state, written by the link thread, read by status().
        self._transport_up = False
        self._autopilot: _AutopilotIdentity | None = None
        self._autopilot_alive = False
        self._autopilot_boot: float | None = None
        self._autopilot_boot_at: float = 0.0  # our clock when that estimate was last updated
        self._clock_confirmed_at = -math.inf  # when a sample last agreed with the clock in use
        self._sent: SendTimes = dict.fromkeys(
            ("HEARTBEAT", "DISTANCE_SENSOR", "DEBUG_VECT", "STATUSTEXT", "TIMESYNC"), 0
        )
        self._texts: collections.deque[tuple[float, int, str]] = collections.deque(
            maxlen=_MAX_QUEUED_TEXTS)
        self._texts_dropped = 0
        self._received = 0
        self._errors = 0
        self._last_error: str | None = None
        self._outage_reason = ""  # the failure last logged in the current outage
        self._reconnects = 0
        self._sending_distance = False
        self._sending_net_plane = False
        self._net_plane_why = "no plane yet"  # why it is not sent (said on the page, the monitor)
        # The link's own state-change lines (sending / not sending): at most one a second per
        # output, as the daemon's (issue 13): a loaded Pi flips the net plane frame by frame.
        self._sending_log = StateLog()
        for output in ("distance", "net_plane"):
            self._sending_log.update(output, False, self._started_at)  # the state at start
        self._foreign_autopilots: set[int] = set()
        self._backoff = Backoff(settings.retry_initial_s, settings.retry_max_s)
        self._url = redact_text(settings.url)
        self._gate = DistanceGate(ceiling_s=settings.max_age_s, send_period_s=settings.period_s)

    # ---- frame-loop side: cheap, never blocks on I/O -------------------------------------

    def set_range(self, reading: RangeReading) -> None:
        now = self._clock()
        with self._lock:
            self._range = reading
            self._gate.observe(reading, now)
            self._arrived = reading.sendable
            if self._wake is not None and reading.sendable:
                # Under the lock, as close() closes the pipe: a descriptor number freed there
                # and reused by another file must never receive this byte. The write never
                # blocks; a full pipe already holds a wake-up.
                with contextlib.suppress(BlockingIOError):
                    os.write(self._wake[1], b"\0")

    def set_net_plane(self, plane: NetPlane) -> None:
        with self._lock:
            self._plane = plane

    def notify_pilot(self, text: str, severity: int = MAV_SEVERITY_WARNING) -> None:
        queued = self._clock()
        with self._lock:
            self._texts.append((queued, severity, text[:STATUSTEXT_LENGTH]))

    def start(self) -> None:
        if self._thread is not None:
            return
        if self._wake is None:
            read_end, write_end = os.pipe()
            os.set_blocking(read_end, False)
            os.set_blocking(write_end, False)
            self._wake = (read_end, write_end)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="netpose-mavlink", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            # Every turn of the thread is bounded (select <= 0.1 s, serial writes 0.2 s); only a
            # TCP connect towards a host that does not answer can take longer, and a stop must
            # not wait for it (systemd's stop budget): the daemon thread ends with the process.
            thread.join(timeout=CLOSE_WAIT_S)
            if thread.is_alive():
                log.info("MAVLink thread still connecting; not waiting for it")
                return  # its wake-up pipe ends with the process
        with self._lock:
            wake, self._wake = self._wake, None
            for fd in wake or ():
                os.close(fd)

    def status(self) -> AutopilotHealth:
        now = self._clock()
        with self._lock:
            ap = self._autopilot
            identity = None
            if ap is not None:
                identity = AutopilotIdentity(
                    sysid=ap.sysid, compid=ap.compid, type=ap.mav_type, autopilot=ap.autopilot,
                    mavlink_version=ap.mavlink_version, flight_sw_version=ap.flight_sw_version,
                )
            state = self._state_locked()
            return AutopilotHealth(
                state=state,
                heartbeat_age_s=None if ap is None else now - ap.last_heartbeat,
                messages_sent=sum(self._sent.values()),
                transport="up" if self._transport_up else "down",
                url=self._url,
                autopilot=identity,
                sent=dict(self._sent),
                received=self._received,
                errors=self._errors,
                last_error=self._last_error or "",
                reconnects=self._reconnects,
                sending_distance=self._sending_distance,
                freshness_s=self._gate.freshness_s,
                sending_changes=self._gate.changes,
                sending_net_plane=self._sending_net_plane,
                net_plane=("off" if not self.settings.send_net_plane
                           else "sent" if self._sending_net_plane else self._net_plane_why),
                min_distance_m=self.settings.min_distance_m,
                max_distance_m=self.settings.max_distance_m,
                texts_dropped=self._texts_dropped,
                # Its last heartbeat's word, kept while the heartbeat is lost: a lost heartbeat
                # (a router restarting, a tether glitch) is not a disarmed vehicle, and a mesh
                # typo saved in that gap reached the armed vehicle as ten times the distance
                # once the heartbeat came back (pilot review). A restart of netpose clears it.
                armed=ap.armed if ap is not None else None,
            )

    def _state_locked(self) -> str:
        if self._autopilot is None:
            return "waiting"
        return "connected" if self._autopilot_alive and self._transport_up else "lost"

    # ---- link thread ------------------------------------------------------------------------

    def _run(self) -> None:
        attempts = 0
        while not self._stop.is_set():
            attempts += 1
            try:
                conn = self._connection_factory(self.settings, self._signing_key)
            except Exception as exc:  # any failure to open is retried, never fatal
                self._note_failure(exc, attempts)
                self._stop.wait(self._backoff.next_delay(self._clock()))
                continue
            self._note_up(attempts)
            attempts = 0
            try:
                self._serve(conn)
            except Exception as exc:
                self._note_failure(exc, 1)
                self._stop.wait(self._backoff.next_delay(self._clock()))
            finally:
                with contextlib.suppress(Exception):
                    conn.close()
                self._transport_down()

    def _note_failure(self, exc: Exception, attempts: int) -> None:
        message = f"{type(exc).__name__}: {exc}"
        with self._lock:
            self._errors += 1
            self._last_error = message
            first = not self._backoff.in_outage
            was_up = self._transport_up
            # Without a transport there is no autopilot either; the warning below says why, so
            # the heartbeat timeout must not log a second time.
            self._autopilot_alive = False
        self._transport_down()
        if first:
            # Once per outage and reason; the retries that follow are only at DEBUG level.
            self._outage_reason = message
            log.warning(
                "MAVLink link %s %s (%s)%s; retrying with backoff up to %.1f s",
                self._url,
                "lost" if was_up else "unavailable",
                message,
                _hint(message),
                self.settings.retry_max_s,
            )
        elif message != self._outage_reason:
            # The fault changed under the same outage (the device appeared, and its open now
            # fails another way): the journal must not keep showing the first reason.
            self._outage_reason = message
            log.warning("MAVLink link %s still down, now: %s%s", self._url, message,
                        _hint(message))
        else:
            log.debug("MAVLink link %s attempt %d failed: %s", self._url, attempts, message)

    def _transport_down(self) -> None:
        """No transport: nothing goes out, and the status (the page, the monitor) says so in
        the same breath (it went on saying "sending distance", shown as "to the autopilot")."""
        with self._lock:
            self._transport_up = False
            stopped = [what for what in ("distance", "net_plane")
                       if getattr(self, f"_sending_{what}")]
            for what in stopped:
                setattr(self, f"_sending_{what}", False)
        for what in stopped:
            self._note_sending(what, False, self._clock(), "link down")

    def _note_up(self, attempts: int) -> None:
        with self._lock:
            self._transport_up = True
            reconnect = self._backoff.in_outage
            if reconnect:
                self._reconnects += 1
        self._backoff.reset()
        if reconnect:
            log.info("MAVLink link %s up again after %d attempt(s)", self._url, attempts)
        else:
            log.info("MAVLink link %s open", self._url)

    def _serve(self, conn: Any) -> None:
        now = self._clock()
        next_heartbeat = now
        next_distance = now
        next_plane = now
        next_clock_ask = now
        last_capture_sent = -math.inf
        period = self.settings.period_s
        opened = now
        # Whether bytes that are no MAVLink are still to be looked for: a serial link only,
        # until it decodes a message or has said so once.
        garbled_check = self.settings.is_serial
        decoded = 0  # MAVLink messages read on this connection (from anyone)
        while not self._stop.is_set():
            now = self._clock()
            if now >= next_heartbeat:
                self._send_heartbeat(conn)
                next_heartbeat = _advance(next_heartbeat, HEARTBEAT_PERIOD_S, now)
            # An arrival that is not sent now is not kept for later: the next frame or the
            # repeat carries the newest reading, and a send between frames only adds latency.
            arrived = self._take_arrival(last_capture_sent)
            if arrived is not None or now >= next_distance:
                self._send_distance(conn, now)
                if arrived is not None:
                    last_capture_sent = arrived
                    next_distance = now + period
                else:
                    next_distance = _advance(next_distance, period, now)
            # The net plane keeps the fixed schedule the net-hold applet was proved with in
            # SITL (its closing-speed filter counts messages, not seconds).
            if now >= next_clock_ask:
                self._ask_clock(conn, now)
                next_clock_ask = _advance(next_clock_ask, _CLOCK_ASK_PERIOD_S, now)
            if now >= next_plane:
                self._send_plane(conn, now)
                self._send_texts(conn)
                next_plane = _advance(next_plane, period, now)
            self._check_autopilot_timeout(now)
            if garbled_check:
                garbled_check = not (decoded or self._check_garbled(conn, now - opened))
            wait = min(next_heartbeat, next_distance, next_plane, next_clock_ask) - self._clock()
            if wait > 0:
                self._wait(conn, min(wait, _POLL_LIMIT_S))
            for _ in range(_MAX_MESSAGES_PER_TURN):
                msg = conn.recv_msg()
                if msg is None:
                    break
                decoded += msg.get_type() != "BAD_DATA"
                self._handle(msg, self._clock())
            self._check_signatures(conn)
        # Stopping: a text still queued (the hole the daemon confirmed in its last frames,
        # flushed as it closes) goes now, or never.
        with contextlib.suppress(Exception):
            self._send_texts(conn)

    def _check_signatures(self, conn: Any) -> None:
        """An autopilot that signs with another key rejects every message netpose signs, while
        its own (accepted here like unsigned ones, which a router may forward) kept the link
        "connected": said once, and kept as the link's last error."""
        signing = getattr(conn.mav, "signing", None)
        if self._signing_key is None or signing is None or self._wrong_key_said:
            return
        if signing.badsig_count >= _WRONG_KEY_SIGNATURES and signing.goodsig_count == 0:
            self._wrong_key_said = True
            message = ("the autopilot's messages are signed with another key than "
                       "mavlink.signing_key_file: it rejects every message netpose sends "
                       f"({signing.badsig_count} bad signatures, none good)")
            with self._lock:
                self._last_error = message
            log.warning("MAVLink: %s", message)

    def _take_arrival(self, last_capture_sent: float) -> float | None:
        """The capture time of a reading that arrived since the last look and is to go out now
        (see the module docstring), else None. Until the frame interval is measured, a reading
        half a period younger than the last one sent goes."""
        period = self.settings.period_s
        with self._lock:
            arrived, self._arrived = self._arrived, False
            capture = self._range.t_capture
            interval = self._gate.frame_interval_s
        if not arrived:
            return None
        spacing = 0.5 * period if interval is None else period - (1.0 + _FRAME_MARGIN) * interval
        return capture if capture - last_capture_sent >= spacing else None

    def _wait(self, conn: Any, timeout: float) -> None:
        """Wait up to `timeout` for incoming data or a new reading (pymavlink's own select
        where the connection has no file descriptor to wait on)."""
        fd = getattr(conn, "fd", None)
        wake = self._wake
        if fd is None or wake is None:
            conn.select(timeout)
            return
        try:
            readable, _, _ = select.select([fd, wake[0]], [], [], timeout)
        except (OSError, ValueError):
            return  # a closed descriptor: the next read says why
        if wake[0] in readable:
            with contextlib.suppress(OSError):
                os.read(wake[0], 4096)

    def _send_texts(self, conn: Any) -> None:
        while True:
            with self._lock:
                if not self._texts:
                    return
                queued, severity, text = self._texts.popleft()
            if self._clock() - queued > TEXT_MAX_WAIT_S:
                log.info("MAVLink: a text for the pilot waited %.0f s for the link and is no "
                         "longer news, not sent: %s", self._clock() - queued, text)
                with self._lock:
                    self._texts_dropped += 1  # the daemon says again what still holds
                continue
            self._send(conn, "STATUSTEXT",
                       functools.partial(conn.mav.statustext_send, severity,
                                         text.encode("utf-8")))

    def _send(self, conn: Any, name: str, send: Callable[[], None]) -> None:
        send()
        if getattr(conn, "portdead", False):
            raise _TransportClosedError(f"cannot write to {self._url}")
        with self._lock:
            self._sent[name] += 1

    def _send_heartbeat(self, conn: Any) -> None:
        self._send(
            conn,
            "HEARTBEAT",
            lambda: conn.mav.heartbeat_send(
                MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE
            ),
        )

    def _send_distance(self, conn: Any, now: float) -> None:
        with self._lock:
            reading = self._range
            fresh_range = self._gate.decide(reading, now)
            limit = self._gate.freshness_s
        why = "" if reading.sendable else "nothing believed"
        if reading.sendable and not fresh_range:
            why = f"newest reading {now - reading.t_capture:.2f} s old, limit {limit:.2f} s"
        self._note_sending("distance", fresh_range, now, why)
        if fresh_range:
            fields = distance_sensor_fields(reading, self.settings)
            time_boot_ms = self._autopilot_time_ms(reading.t_capture)
            self._send(
                conn,
                "DISTANCE_SENSOR",
                lambda: conn.mav.distance_sensor_send(
                    time_boot_ms,
                    fields.min_distance,
                    fields.max_distance,
                    fields.current_distance,
                    fields.type,
                    fields.id,
                    fields.orientation,
                    fields.covariance,
                    horizontal_fov=fields.horizontal_fov,
                    vertical_fov=fields.vertical_fov,
                    signal_quality=fields.signal_quality,
                ),
            )

    def _ask_clock(self, conn: Any, now: float) -> None:
        """TIMESYNC request (tc1 = 0): the autopilot answers with its boot clock in ns. Only
        while the net plane goes out (its stamps are what the clock is for)."""
        if not self.settings.send_net_plane or self._autopilot is None:
            return
        self._send(conn, "TIMESYNC", lambda: conn.mav.timesync_send(0, int(now * 1e9)))

    def _send_plane(self, conn: Any, now: float) -> None:
        if not self.settings.send_net_plane:
            return
        with self._lock:
            plane = self._plane
            clock_confirmed = now - self._clock_confirmed_at <= _CLOCK_CONFIRMED_S
        if not clock_confirmed:
            # Held, not stamped on a clock the autopilot may no longer have (a reboot): the
            # applet stops thrust on the silence, as it must.
            self._note_sending("net_plane", False, now,
                               "the autopilot's clock is not confirmed (not yet known, or it "
                               "rebooted): net plane held")
            with self._lock:
                self._net_plane_why = "held: the autopilot's clock is not confirmed"
            return
        max_age = self.settings.max_age_s
        # A fresh plane goes out whether it confirms the net or not (a zero vector: "no net in
        # that frame"), so the applet stops at once rather than at its timeout.
        fresh_plane = plane is not None and now - plane.t_capture <= max_age and all(
            math.isfinite(v) for v in plane.foot_m)
        if plane is None:
            plane_why = "no plane yet"
        elif not fresh_plane:
            plane_why = f"newest plane {now - plane.t_capture:.2f} s old, limit {max_age:.2f} s"
        else:
            plane_why = "the newest frame did not confirm the net: sending a zero vector"
        self._note_sending("net_plane", fresh_plane and plane is not None and plane.usable, now,
                           plane_why)
        with self._lock:
            self._net_plane_why = ("zero vector: the newest frame did not confirm the net"
                                   if fresh_plane else plane_why)
        if fresh_plane and plane is not None:
            usec = self._autopilot_time_ms(plane.t_capture) * 1000
            x, y, z = plane.foot_m
            self._send(
                conn,
                "DEBUG_VECT",
                lambda: conn.mav.debug_vect_send(NET_PLANE_NAME, usec, x, y, z),
            )

    def _note_sending(self, what: str, sending: bool, now: float, why: str = "") -> None:
        """Record whether an output is going out (status() reports it at once) and log the
        change, rate-limited: a state that flaps gives one line a second, counting the rest."""
        attribute = f"_sending_{what}"
        with self._lock:
            setattr(self, attribute, sending)
        due, _, between = self._sending_log.update(what, sending, now)
        if not due:
            return
        label = what.replace("_", " ")
        if sending:
            log.info("MAVLink: sending %s%s", label, not_logged_note(between))
        else:
            log.info("MAVLink: not sending %s (%s)%s", label, why or "not fresh",
                     not_logged_note(between))

    def _autopilot_time_ms(self, t: float) -> int:
        """Instant `t` (this host's monotonic clock) in milliseconds since the autopilot booted
        (since our own start while its clock is unknown)."""
        with self._lock:
            base = self._autopilot_boot if self._autopilot_boot is not None else self._started_at
        return int(max(0.0, t - base) * 1000.0) & 0xFFFFFFFF

    def _is_own(self, msg: Any) -> bool:
        return bool(
            msg.get_srcSystem() == self.settings.source_system
            and msg.get_srcComponent() == self.settings.source_component
        )

    def _handle(self, msg: Any, now: float) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA" or self._is_own(msg):
            return  # noise, or our own message echoed back by a router
        with self._lock:
            self._received += 1
        if kind == "HEARTBEAT":
            self._handle_heartbeat(msg, now)
            return
        ap = self._autopilot
        if ap is None or (msg.get_srcSystem(), msg.get_srcComponent()) != (ap.sysid, ap.compid):
            return
        if kind == "AUTOPILOT_VERSION":
            with self._lock:
                ap.flight_sw_version = int(msg.flight_sw_version)
        time_boot_ms = getattr(msg, "time_boot_ms", None)
        if isinstance(time_boot_ms, int):
            self._update_boot_time(now - time_boot_ms / 1000.0, now)
        elif kind == "TIMESYNC" and int(msg.tc1) > 0:
            # The answer to our request: the autopilot's boot clock when it answered, which was
            # between our request and now (the min-filter keeps the least delayed).
            self._update_boot_time(now - int(msg.tc1) / 1e9, now)

    def _update_boot_time(self, boot: float, now: float) -> None:
        """`boot`: when the autopilot booted on our clock, as one of its messages says (late by
        that message's transit)."""
        with self._lock:
            old = self._autopilot_boot
            if old is None or abs(boot - old) > _REBOOT_JUMP_S:
                self._autopilot_boot = boot
                rebooted = old is not None
            else:
                # The earliest estimate had the least transit in it; it may age later by the
                # crystals' disagreement, so a slower autopilot clock is followed.
                drift = _CLOCK_DRIFT_PPM * 1e-6 * max(0.0, now - self._autopilot_boot_at)
                self._autopilot_boot = min(old + drift, boot)
                rebooted = False
            self._autopilot_boot_at = now
            self._clock_confirmed_at = now
        if rebooted:
            log.warning("MAVLink: autopilot clock jumped by %.1f s (reboot?)", boot - (old or 0))

    def _handle_heartbeat(self, msg: Any, now: float) -> None:
        if (
            msg.autopilot == MAV_AUTOPILOT_INVALID
            or msg.type in NON_AUTOPILOT_TYPES
            or msg.get_srcComponent() != MAV_COMP_ID_AUTOPILOT1
        ):
            return
        sysid = msg.get_srcSystem()
        if sysid != self.settings.source_system:
            if sysid not in self._foreign_autopilots:
                self._foreign_autopilots.add(sysid)
                log.warning(
                    "MAVLink: ignoring autopilot with system id %d (mavlink.source_system is %d)",
                    sysid,
                    self.settings.source_system,
                )
            return
        with self._lock:
            first = self._autopilot is None
            back = not first and not self._autopilot_alive
            version = None if self._autopilot is None else self._autopilot.flight_sw_version
            self._autopilot = _AutopilotIdentity(
                sysid=sysid,
                compid=msg.get_srcComponent(),
                mav_type=msg.type,
                autopilot=msg.autopilot,
                mavlink_version=2 if msg.get_msgbuf()[0] == 0xFD else 1,
                last_heartbeat=now,
                flight_sw_version=version,
                armed=bool(int(msg.base_mode) & MAV_MODE_FLAG_SAFETY_ARMED),
            )
            self._autopilot_alive = True
        if first:
            log.info("MAVLink: autopilot %d/%d connected (type %d)", sysid, msg.get_srcComponent(),
                     msg.type)
        elif back:
            log.info("MAVLink: autopilot heartbeat back")

    def _check_garbled(self, conn: Any, open_s: float) -> bool:
        """A serial port that has delivered bytes but no MAVLink message, for longer than the
        heartbeat timeout, is at another rate than the autopilot's (or is another device): said
        once per connection, and kept as the link's last error. True once said."""
        mav = getattr(conn, "mav", None)
        received = int(getattr(mav, "total_bytes_received", 0))
        if open_s < self.settings.heartbeat_timeout_s or received < _GARBLED_BYTES:
            return False
        message = (f"{self._url}, {open_s:.1f} s: "
                   f"{baud_hint(received, self.settings.baud, 'mavlink.baud')}")
        with self._lock:
            self._last_error = message
        log.warning("MAVLink: %s", message)
        return True

    def _check_autopilot_timeout(self, now: float) -> None:
        with self._lock:
            ap = self._autopilot
            lost = (
                ap is not None
                and self._autopilot_alive
                and now - ap.last_heartbeat > self.settings.heartbeat_timeout_s
            )
            if lost:
                self._autopilot_alive = False
        if lost:
            log.warning(
                "MAVLink: autopilot heartbeat lost (none for %.1f s)",
                self.settings.heartbeat_timeout_s,
            )


def _advance(deadline: float, period: float, now: float) -> float:
    """Next deadline of a fixed-rate schedule; after a stall, restart from now, no burst."""
    deadline += period
    return deadline if deadline > now else now + period


class RecordingAutopilotLink(AutopilotLink):
    """Stand-in without I/O: records what the daemon handed over, reports a fixed status."""

    def __init__(self) -> None:
        self.started = False
        self.closed = False
        self.ranges: list[RangeReading] = []
        self.planes: list[NetPlane] = []
        self.texts: list[tuple[int, str]] = []
        self.texts_dropped = 0  # a test sets it: texts a real link dropped as stale
        self.armed: bool | None = None  # a test sets it: what the autopilot's heartbeat says
        self._lock = threading.Lock()

    def start(self) -> None:
        self.started = True

    def set_range(self, reading: RangeReading) -> None:
        with self._lock:
            self.ranges.append(reading)

    def set_net_plane(self, plane: NetPlane) -> None:
        with self._lock:
            self.planes.append(plane)

    def notify_pilot(self, text: str, severity: int = MAV_SEVERITY_WARNING) -> None:
        with self._lock:
            self.texts.append((severity, text[:STATUSTEXT_LENGTH]))

    @property
    def sent(self) -> list[RangeReading]:
        """The readings a real link would have sent (GOOD or TOO_CLOSE)."""
        with self._lock:
            return [r for r in self.ranges if r.status is not RangeStatus.NONE]

    def status(self) -> AutopilotHealth:
        return AutopilotHealth(
            state="connected" if self.started and not self.closed else "waiting",
            transport="fake",
            messages_sent=len(self.ranges),
            texts_dropped=self.texts_dropped,
            armed=self.armed,
        )

    def close(self) -> None:
        self.closed = True
