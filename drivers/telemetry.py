"""Telemetry to the topside over Zenoh: estimates, 1 Hz status, preview JPEGs and a queryable.

The publisher knows nothing about the estimator: it takes the core's typed messages
(service.core.messages) and JPEG bytes. The frame loop only appends to a bounded deque
(drop-oldest, drops counted); a worker thread owned by the publisher opens the Zenoh session,
retries with backoff while no router answers, serialises (once, here at the edge) and puts. So
a missing, slow or vanishing router can never stall the frame loop or the MAVLink path.

    TelemetryPublisher   the interface the daemon talks to
    ZenohPublisher       the real one (eclipse-zenoh >= 1.0)
    NullPublisher        telemetry disabled
    RecordingPublisher   keeps everything in memory, for tests of the daemon
"""

from __future__ import annotations

import collections
import ipaddress
import json
import logging
import math
import re
import threading
import time
from abc import abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from drivers.lifecycle import Closeable
from service.core.backoff import Backoff
from service.core.errors import ConfigError
from service.core.messages import (
    ALIVE_SUFFIX,
    DAMAGE_SUFFIX,
    ESTIMATE_SUFFIX,
    PREVIEW_SUFFIX,
    STATE_SUFFIX,
    STATUS_SUFFIX,
    DamageMessage,
    EstimateMessage,
    PreviewMeta,
    StateMessage,
    StatusMessage,
    TelemetryHealth,
    encode,
)

log = logging.getLogger(__name__)

MODES = ("peer", "client")
DEFAULT_MODE = "client"
# BlueOS runs its Zenoh router here; a client session on the vehicle connects to it.
DEFAULT_CONNECT = ("tcp/127.0.0.1:7447",)
# One key chunk: no '/', no wildcards or Zenoh's reserved characters.
_CHUNK = re.compile(r"^[A-Za-z0-9_.-]+$")
# Zenoh endpoints: <protocol>/<address>[?metadata][#config]. Protocols whose address is
# host:port, and the host forms accepted (IPv4, [IPv6], a DNS name).
_IP_PROTOCOLS = frozenset({"tcp", "udp", "tls", "quic", "ws"})
_OTHER_PROTOCOLS = frozenset({"unixsock-stream", "serial", "unixpipe", "vsock"})
_HOSTNAME = re.compile(r"^(?=.{1,253}$)[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
                       r"(\.[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*$")
# A client re-connects to a returning router on this schedule (Zenoh's own default waits up
# to 4 s between attempts; a vehicle's links mostly drop for seconds).
RECONNECT_RETRY = {"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2}


def endpoint_problem(endpoint: str, listening: bool) -> str | None:
    """Why `endpoint` is not a usable Zenoh endpoint, or None. Zenoh itself accepts any string
    at configuration time and then retries it forever, so the check happens here."""
    protocol, slash, rest = endpoint.partition("/")
    address = rest.split("?", 1)[0].split("#", 1)[0]
    if not slash or not address:
        return "is not an endpoint like tcp/127.0.0.1:7447"
    if protocol in _OTHER_PROTOCOLS:
        return None
    if protocol not in _IP_PROTOCOLS:
        known = ", ".join(sorted(_IP_PROTOCOLS | _OTHER_PROTOCOLS))
        return f"has an unknown protocol {protocol!r} (known: {known})"
    host, colon, port = address.rpartition(":")
    if not colon or not port.isdigit():
        return "needs a port (like tcp/127.0.0.1:7447)"
    low = 0 if listening else 1
    if not low <= int(port) <= 65535:
        return f"has port {port} outside {low}..65535"
    if host.startswith("[") and host.endswith("]"):
        try:
            ipaddress.IPv6Address(host[1:-1])
        except ValueError:
            return f"has an invalid IPv6 address {host}"
        return None
    try:
        ipaddress.IPv4Address(host)
        return None
    except ValueError:
        pass
    if host.replace(".", "").isdigit():
        return f"has an invalid IPv4 address {host}"
    if not _HOSTNAME.match(host):
        return f"has an invalid host {host!r}"
    return None


@dataclass(frozen=True)
class TelemetrySettings:
    """Section [telemetry] of the configuration; the field names are the TOML keys.

    `mode`, `listen`, `connect` and `scouting` left as None take their value from `config_file`
    when one is given (so TLS endpoints written there are not overridden), else the defaults:
    client mode, connect to BlueOS's router at tcp/127.0.0.1:7447, no listen, no scouting.
    """

    enabled: bool = True
    vehicle: str = "rov"
    key_prefix: str = "netpose"
    mode: str | None = None
    listen: tuple[str, ...] | None = None
    connect: tuple[str, ...] | None = None
    scouting: bool | None = None
    config_file: str | None = None
    preview_hz: float = 0.5
    preview_width: int = 320
    preview_quality: int = 70
    queue_size: int = 64
    retry_initial_s: float = 0.5
    retry_max_s: float = 10.0

    def __post_init__(self) -> None:
        def bad(key: str, problem: str) -> ConfigError:
            return ConfigError(f"telemetry.{key}", problem)

        for key in ("vehicle", "key_prefix"):
            value = getattr(self, key)
            if not isinstance(value, str) or not _CHUNK.match(value):
                raise bad(key, f"{value!r} must be one word of letters, digits, '_', '.', '-'")
        if self.mode is not None and self.mode not in MODES:
            raise bad("mode", f"{self.mode!r} is not one of {', '.join(MODES)}")
        for key in ("listen", "connect"):
            for endpoint in getattr(self, key) or ():
                problem = endpoint_problem(endpoint, listening=key == "listen")
                if problem is not None:
                    raise bad(key, f"{endpoint!r} {problem}")
        for key in ("preview_hz", "retry_initial_s", "retry_max_s"):
            if getattr(self, key) < 0:
                raise bad(key, "must be >= 0")
        if not self.retry_initial_s > 0:
            raise bad("retry_initial_s", f"must be > 0, got {self.retry_initial_s}")
        if self.retry_max_s < self.retry_initial_s:
            raise bad("retry_max_s", "must be at least retry_initial_s")
        for key, low, high in (
            ("preview_width", 32, 4096),
            ("preview_quality", 1, 100),
            ("queue_size", 1, 100_000),
        ):
            if not low <= getattr(self, key) <= high:
                raise bad(key, f"must be an integer from {low} to {high}")

    @property
    def key_root(self) -> str:
        """`<key_prefix>/<vehicle>`: every key this service publishes lives below it."""
        return f"{self.key_prefix}/{self.vehicle}"

    def key(self, suffix: str) -> str:
        return f"{self.key_root}/{suffix}"


def build_zenoh_config(settings: TelemetrySettings) -> zenoh.Config:
    """The Zenoh configuration: `config_file` as the base, explicit settings on top.

    Raises ConfigError naming the telemetry key when Zenoh rejects a value or the file.
    """
    from_file = settings.config_file is not None
    if settings.config_file is not None:
        path = Path(settings.config_file)
        if not path.is_file():
            raise ConfigError("telemetry.config_file", f"{path} does not exist")
        try:
            config = zenoh.Config.from_file(str(path))
        except zenoh.ZError as exc:
            raise ConfigError("telemetry.config_file",
                              f"{path}: {zenoh_error_text(exc)}") from None
    else:
        config = zenoh.Config()

    def insert(key: str, zenoh_key: str, value: Any, default: Any) -> None:
        if value is None:
            if from_file:
                return  # the file decides
            value = default
        try:
            config.insert_json5(zenoh_key, json.dumps(value))
        except zenoh.ZError as exc:
            raise ConfigError(f"telemetry.{key}", zenoh_error_text(exc)) from None

    insert("mode", "mode", settings.mode, DEFAULT_MODE)
    listen = None if settings.listen is None else list(settings.listen)
    insert("listen", "listen/endpoints", listen, [])
    insert(
        "connect",
        "connect/endpoints",
        None if settings.connect is None else list(settings.connect),
        list(DEFAULT_CONNECT),
    )
    insert("scouting", "scouting/multicast/enabled", settings.scouting, False)
    if not from_file or json.loads(config.get_json("connect/retry")) is None:
        config.insert_json5("connect/retry", json.dumps(RECONNECT_RETRY))
    return config


class TelemetryPublisher(Closeable):
    """What the daemon sees of telemetry. Every method returns at once and never raises for a
    network problem."""

    def __init__(self, settings: TelemetrySettings) -> None:
        self.settings = settings
        self._last_preview_at = -math.inf

    @abstractmethod
    def start(self) -> None:
        """Begin publishing (a real publisher connects in the background)."""

    @abstractmethod
    def publish_estimate(self, message: EstimateMessage) -> None:
        """Queue one estimate."""

    @abstractmethod
    def publish_status(self, message: StatusMessage) -> None:
        """Queue a status."""

    @abstractmethod
    def publish_preview(self, jpeg: bytes, meta: PreviewMeta) -> None:
        """Queue a preview JPEG; `meta` travels as its attachment."""

    @abstractmethod
    def publish_damage(self, message: DamageMessage) -> None:
        """Queue a confirmed hole in the net (`damage` key, once per hole)."""

    @abstractmethod
    def set_state(self, message: StateMessage) -> None:
        """What the `state` queryable answers from now on."""

    @abstractmethod
    def close(self) -> None:
        """Stop the worker and close the session; idempotent."""

    @abstractmethod
    def status(self) -> TelemetryHealth:
        """Counters and link state of the publisher itself (goes into the status message)."""

    @property
    def online(self) -> bool:
        """True when published data can leave the process."""
        return False

    def wants_preview(self, now_mono: float) -> bool:
        """True at most once per 1/preview_hz, and only while someone can receive a preview,
        so the frame loop draws and encodes no JPEG for nobody."""
        if self.settings.preview_hz <= 0 or not self.online:
            return False
        period = 1.0 / self.settings.preview_hz
        # Due on a grid of the period, not a period after the frame that drew the last one:
        # that way a frame a hair early (a 10 frames/s camera at 5 Hz) waited for the next,
        # and the rate came out 12-20 % short. After a pause the grid starts again from now.
        due = self._last_preview_at + period
        if now_mono < due - 0.01 * period:
            return False
        self._last_preview_at = due if now_mono - due < period else now_mono
        return self._preview_has_audience()

    def _preview_has_audience(self) -> bool:
        return True

    def __enter__(self) -> TelemetryPublisher:
        self.start()
        return self


class NullPublisher(TelemetryPublisher):
    """Telemetry disabled: accepts everything, sends nothing."""

    def start(self) -> None:
        pass

    def publish_estimate(self, message: EstimateMessage) -> None:
        pass

    def publish_status(self, message: StatusMessage) -> None:
        pass

    def publish_preview(self, jpeg: bytes, meta: PreviewMeta) -> None:
        pass

    def publish_damage(self, message: DamageMessage) -> None:
        pass

    def set_state(self, message: StateMessage) -> None:
        pass

    def close(self) -> None:
        pass

    def status(self) -> TelemetryHealth:
        return TelemetryHealth(state="disabled", key_root=self.settings.key_root)


@dataclass
class RecordingPublisher(TelemetryPublisher):
    """Keeps what would be published, for tests of code that publishes (the daemon's)."""

    settings: TelemetrySettings = field(default_factory=TelemetrySettings)
    is_online: bool = True
    estimates: list[EstimateMessage] = field(default_factory=list)
    statuses: list[StatusMessage] = field(default_factory=list)
    previews: list[tuple[bytes, PreviewMeta]] = field(default_factory=list)
    damages: list[DamageMessage] = field(default_factory=list)
    state: StateMessage | None = None
    started: bool = False
    closed: bool = False

    def __post_init__(self) -> None:
        super().__init__(self.settings)

    @property
    def online(self) -> bool:
        return self.is_online and self.started and not self.closed

    def start(self) -> None:
        self.started = True

    def publish_estimate(self, message: EstimateMessage) -> None:
        self.estimates.append(message)

    def publish_status(self, message: StatusMessage) -> None:
        self.statuses.append(message)

    def publish_preview(self, jpeg: bytes, meta: PreviewMeta) -> None:
        self.previews.append((jpeg, meta))

    def publish_damage(self, message: DamageMessage) -> None:
        self.damages.append(message)

    def set_state(self, message: StateMessage) -> None:
        self.state = message

    def close(self) -> None:
        self.closed = True

    def status(self) -> TelemetryHealth:
        return TelemetryHealth(
            state="online" if self.online else "offline",
            key_root=self.settings.key_root,
            sent={"estimate": len(self.estimates), "status": len(self.statuses),
                  "preview": len(self.previews), "damage": len(self.damages)},
        )


@dataclass(frozen=True)
class _Outgoing:
    suffix: str
    message: EstimateMessage | StatusMessage | DamageMessage | None = None
    jpeg: bytes = b""
    meta: PreviewMeta | None = None


_STREAMS = (ESTIMATE_SUFFIX, STATUS_SUFFIX, PREVIEW_SUFFIX, DAMAGE_SUFFIX)
# Confirmed holes kept while no session is open (a pass along a whole pen finds a few).
DAMAGE_BACKLOG = 256
# At stop, queued messages still go for this long (the daemon's last status among them).
FLUSH_S = 0.5
TOKEN_AFTER_FLUSH_S = 0.1


def token_change(sample: zenoh.Sample) -> str:
    """A liveliness sample as "PUT" (the token came) or "DELETE" (it went)."""
    return "PUT" if sample.kind == zenoh.SampleKind.PUT else "DELETE"


def zenoh_error_text(exc: BaseException) -> str:
    """Zenoh's error message on one line, without the Rust source locations it appends
    (" at /...rs:12") and the backtrace lines some errors carry."""
    lines = [line.split(" at /")[0].strip() for line in str(exc).splitlines()]
    lines = [line for line in lines if line and not line.startswith(("at ", "Caused by"))]
    return " ".join(" ".join(lines).split()) or type(exc).__name__


class ZenohPublisher(TelemetryPublisher):
    """The real publisher: one Zenoh session owned by one worker thread.

    States: "idle" (before start), "connecting" (opening; retried with backoff while it fails),
    "online" (session open; a client session re-connects to a returning router by itself),
    "closed". Messages handed over while not online are counted as `skipped_offline` and not
    kept: an estimate that waited for a router is no longer news. A confirmed hole is: it is
    reported once, so it waits (up to DAMAGE_BACKLOG of them) in its own queue, which neither
    going offline nor a flood of estimates empties, and leaves once a subscriber to the damage
    key can hear it (no session, no router or nobody listening: it waits).
    """

    def __init__(
        self,
        settings: TelemetrySettings,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(settings)
        self._clock = clock
        self._queue: collections.deque[_Outgoing] = collections.deque(maxlen=settings.queue_size)
        self._damage: collections.deque[DamageMessage] = collections.deque()
        # Every hole of this run (the newest DAMAGE_BACKLOG), sent or waiting: what a `get` on
        # the damage key answers, for a dashboard that joined late or restarted.
        self._holes: collections.deque[DamageMessage] = collections.deque(maxlen=DAMAGE_BACKLOG)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._lock = threading.Lock()  # counters and query state, shared with zenoh's threads
        self._thread: threading.Thread | None = None
        self._state = "idle"
        self._online = False
        self._sent = dict.fromkeys(_STREAMS, 0)
        self._queue_dropped = 0
        self._skipped_offline = 0
        self._errors = 0
        self._queries = 0
        self._open_attempts = 0
        self._last_error = ""
        self._session_info: zenoh.SessionInfo | None = None
        self._preview_publisher: zenoh.Publisher | None = None
        self._state_message: StateMessage | None = None
        self._backoff = Backoff(settings.retry_initial_s, settings.retry_max_s)
        # Built now, so a bad configuration (a json5 file Zenoh refuses) stops the service at
        # start-up and `netpose run --check` sees it too.
        self._config = build_zenoh_config(settings)

    # --- frame-loop side: O(microseconds), never blocks on the network -------------------

    @property
    def online(self) -> bool:
        return self._online

    def start(self) -> None:
        """Connect in the background (the configuration was checked at construction)."""
        if self._thread is not None:
            return
        self._state = "connecting"
        self._thread = threading.Thread(target=self._run, name="netpose-telemetry", daemon=True)
        self._thread.start()

    def _enqueue(self, item: _Outgoing) -> None:
        if not self._online:
            with self._lock:
                self._skipped_offline += 1
            return
        if len(self._queue) == self._queue.maxlen:
            with self._lock:
                self._queue_dropped += 1  # deque(maxlen) drops the oldest on append
        self._queue.append(item)
        self._wake.set()

    def publish_estimate(self, message: EstimateMessage) -> None:
        self._enqueue(_Outgoing(ESTIMATE_SUFFIX, message))

    def publish_status(self, message: StatusMessage) -> None:
        self._enqueue(_Outgoing(STATUS_SUFFIX, message))

    def publish_preview(self, jpeg: bytes, meta: PreviewMeta) -> None:
        self._enqueue(_Outgoing(PREVIEW_SUFFIX, jpeg=bytes(jpeg), meta=meta))

    def publish_damage(self, message: DamageMessage) -> None:
        with self._lock:
            if len(self._damage) >= DAMAGE_BACKLOG:
                # Only after hundreds of holes with no session: the newest are kept.
                self._damage.popleft()
                self._queue_dropped += 1
            self._damage.append(message)
            self._holes.append(message)
        self._wake.set()

    def set_state(self, message: StateMessage) -> None:
        with self._lock:
            self._state_message = message

    def _preview_has_audience(self) -> bool:
        """Whether a subscriber matches the preview key (Zenoh tracks this, also through a
        router): about a microsecond, checked once per preview period."""
        publisher = self._preview_publisher
        return publisher is not None and _has_audience(publisher)

    def status(self) -> TelemetryHealth:
        routers = peers = links = None
        info = self._session_info
        if info is not None and self._online:
            try:
                routers = len(info.routers_zid())
                peers = len(info.peers_zid())
                # transports() also counts clients connected to us (zenoh >= 1.1 has it).
                transports = getattr(info, "transports", None)
                links = len(transports()) if transports is not None else routers + peers
            except Exception:  # a session closing under us: counts are just unknown
                pass
        with self._lock:
            return TelemetryHealth(
                state=self._state,
                key_root=self.settings.key_root,
                routers=routers,
                peers=peers,
                links=links,
                # Online but nobody to talk to (router gone, no subscriber peer): data is lost.
                linked=None if links is None else links > 0,
                sent=dict(self._sent),
                queue_dropped=self._queue_dropped,
                skipped_offline=self._skipped_offline,
                damage_waiting=len(self._damage),
                errors=self._errors,
                queries=self._queries,
                open_attempts=self._open_attempts,
                last_error=self._last_error,
            )

    def close(self, timeout: float = FLUSH_S + 0.5) -> None:
        """Stop and join the worker, which first sends what is queued (the daemon's last
        status among it) for up to FLUSH_S. If it is stuck inside a Zenoh open (bounded by
        Zenoh's open timeout) or a put, this waits at most `timeout`; the daemon thread then
        ends on its own."""
        self._stop.set()
        self._wake.set()
        thread = self._thread
        if thread is not None:
            thread.join(timeout)
            if thread.is_alive():
                doing = "opening a Zenoh session" if self._state != "online" else (
                    "sending or closing (a congested link?)")
                log.warning("telemetry worker still %s; not waiting longer", doing)
        with self._lock:
            unsent = len(self._damage)
        if unsent:
            # Each was logged when confirmed; that it never reached the topside is said too.
            log.warning("telemetry: %d confirmed hole(s) never reached a subscriber of the "
                        "damage key (each is in the log above)", unsent)
        self._online = False
        self._state = "closed"

    # --- worker thread ------------------------------------------------------------------

    def _run(self) -> None:
        session = None
        try:
            session = self._connect()
            if session is None:
                return
            declared = self._declare(session)
            alive = self._declare_alive(session)
            self._preview_publisher = declared[0][PREVIEW_SUFFIX]
            self._online = True
            self._state = "online"
            self._drain_until_stopped(*declared)
            if alive is not None:
                # The token's withdrawal travels ahead of data (Zenoh sends declarations
                # first); a moment lets the flushed messages leave before it, so on an idle
                # link the topside reads the last status before the token goes.
                time.sleep(TOKEN_AFTER_FLUSH_S)
                alive.undeclare()
        except Exception as exc:  # keep the service alive: telemetry is not worth a crash
            log.exception("telemetry worker failed; telemetry is off from now on")
            with self._lock:
                self._errors += 1
                self._last_error = str(exc)
            self._state = "failed"
        finally:
            self._online = False
            self._preview_publisher = None
            if session is not None:
                try:
                    session.close()
                except Exception as exc:  # closing is best effort at shutdown
                    log.debug("closing Zenoh session: %s", exc)

    def _connect(self) -> zenoh.Session | None:
        """Open the session, retrying with backoff; None when asked to stop first."""
        logged = False
        while not self._stop.is_set():
            self._open_attempts += 1
            try:
                session = zenoh.open(self._config)
            except zenoh.ZError as exc:
                message = zenoh_error_text(exc)
                with self._lock:
                    self._last_error = message
                if not logged:  # once, not every retry: a missing router is a normal condition
                    log.warning(
                        "telemetry: cannot open Zenoh session (%s); retrying in the background",
                        message,
                    )
                    logged = True
                self._stop.wait(self._backoff.next_delay(self._clock()))
                continue
            if self._stop.is_set():
                session.close()
                return None
            self._backoff.reset()
            self._session_info = session.info
            log.info(
                "telemetry: Zenoh session open (attempt %d), publishing under %s/",
                self._open_attempts,
                self.settings.key_root,
            )
            return session
        return None

    def _declare(
        self, session: zenoh.Session
    ) -> tuple[dict[str, zenoh.Publisher], list[zenoh.Queryable[None]]]:
        json_enc = zenoh.Encoding.APPLICATION_JSON
        drop = zenoh.CongestionControl.DROP  # never wait for a slow link
        publishers = {
            ESTIMATE_SUFFIX: session.declare_publisher(
                self.settings.key(ESTIMATE_SUFFIX),
                encoding=json_enc,
                congestion_control=drop,
                priority=zenoh.Priority.DATA_HIGH,
                express=True,
            ),
            STATUS_SUFFIX: session.declare_publisher(
                self.settings.key(STATUS_SUFFIX), encoding=json_enc, congestion_control=drop
            ),
            PREVIEW_SUFFIX: session.declare_publisher(
                self.settings.key(PREVIEW_SUFFIX),
                encoding=zenoh.Encoding.IMAGE_JPEG,
                congestion_control=drop,
                priority=zenoh.Priority.DATA_LOW,
            ),
            # A hole is rare news that must not be dropped for a busy link: the worker thread
            # may wait for it (the frame loop never does).
            DAMAGE_SUFFIX: session.declare_publisher(
                self.settings.key(DAMAGE_SUFFIX), encoding=json_enc,
                congestion_control=zenoh.CongestionControl.BLOCK,
            ),
        }
        queryables = [
            session.declare_queryable(self.settings.key(STATE_SUFFIX), self._answer_query),
            # `<prefix>/<vehicle>/damage/*`: one key per hole, since replies on one key are
            # consolidated to the last by a default `get`.
            session.declare_queryable(self.settings.key(DAMAGE_SUFFIX) + "/*",
                                      self._answer_holes),
        ]
        return publishers, queryables

    def _declare_alive(self, session: zenoh.Session) -> zenoh.LivelinessToken | None:
        """The liveliness token `<prefix>/<vehicle>/alive`, held while the session is up.
        Zenoh withdraws it when the session closes or its link is lost (a crash, a cut
        tether): a topside that sees it go without a `stopping` status knows which it was."""
        try:
            return session.liveliness().declare_token(self.settings.key(ALIVE_SUFFIX))
        except (zenoh.ZError, AttributeError) as exc:  # AttributeError: zenoh 1.0.0 has none
            log.warning("telemetry: no liveliness token (%s); topside sees only the data",
                        zenoh_error_text(exc))
            return None

    def _drain_until_stopped(
        self, publishers: dict[str, zenoh.Publisher], queryables: list[zenoh.Queryable[None]]
    ) -> None:
        failures_logged: set[str] = set()
        while not self._stop.is_set():
            self._wake.wait(0.5)
            self._wake.clear()
            # Holes wait until a subscriber can hear them (checked again every half second).
            while self._damage and not self._stop.is_set() and _has_audience(
                publishers[DAMAGE_SUFFIX]
            ):
                with self._lock:
                    message = self._damage.popleft()
                self._put(publishers, _Outgoing(DAMAGE_SUFFIX, message), failures_logged)
            while self._queue and not self._stop.is_set():
                self._put(publishers, self._queue.popleft(), failures_logged)
        # Stopping: what is queued still goes (the daemon's last status is among it), for a
        # bounded time; holes that wait for a subscriber are said in the log at close.
        flush_until = self._clock() + FLUSH_S
        while self._queue and self._clock() < flush_until:
            self._put(publishers, self._queue.popleft(), failures_logged)
        for queryable in queryables:
            queryable.undeclare()
        for publisher in publishers.values():
            publisher.undeclare()

    def _put(self, publishers: dict[str, zenoh.Publisher], item: _Outgoing,
             failures_logged: set[str]) -> None:
        try:
            if item.message is None:
                attachment = None if item.meta is None else encode(item.meta)
                publishers[item.suffix].put(item.jpeg, attachment=attachment)
            else:
                publishers[item.suffix].put(encode(item.message))
        except (ValueError, TypeError, zenoh.ZError) as exc:
            # A message that cannot be encoded, or a put refused: count it, say it once per
            # kind of failure, keep going with the next one.
            with self._lock:
                self._errors += 1
                self._last_error = f"{item.suffix}: {exc}"
            key = f"{item.suffix}:{type(exc).__name__}"
            if key not in failures_logged:
                failures_logged.add(key)
                log.warning("telemetry: cannot publish %s: %s", item.suffix, exc)
            return
        with self._lock:
            self._sent[item.suffix] += 1

    def _answer_holes(self, query: zenoh.Query) -> None:
        """Runs on a Zenoh thread: one reply per hole of this run that the query's key
        matches, on `<prefix>/<vehicle>/damage/<hole_id>`, oldest first (each as it was
        published, crop included). Never raises into Zenoh."""
        with self._lock:
            self._queries += 1
            holes = list(self._holes)
        try:
            for message in holes:
                key = f"{self.settings.key(DAMAGE_SUFFIX)}/{message.hole_id}"
                if query.key_expr.intersects(zenoh.KeyExpr(key)):
                    query.reply(key, encode(message), encoding=zenoh.Encoding.APPLICATION_JSON)
        except Exception as exc:
            log.warning("telemetry: cannot answer query %s: %s", query.selector, exc)
            with self._lock:
                self._errors += 1

    def _answer_query(self, query: zenoh.Query) -> None:
        """Runs on a Zenoh thread: reply with the latest state, never raise into Zenoh."""
        with self._lock:
            self._queries += 1
            message = self._state_message
        if message is None:
            return  # nothing to say before the first status
        try:
            query.reply(self.settings.key(STATE_SUFFIX), encode(message),
                        encoding=zenoh.Encoding.APPLICATION_JSON)
        except Exception as exc:
            log.warning("telemetry: cannot answer query %s: %s", query.selector, exc)
            with self._lock:
                self._errors += 1


def _has_audience(publisher: zenoh.Publisher) -> bool:
    """Whether a subscriber matches the publisher's key (Zenoh tracks this, also through a
    router); when Zenoh cannot say, assume one."""
    try:
        status: Any = publisher.matching_status
    except Exception:  # unknown: err on the side of sending
        return True
    # Typed as bool in the stubs; zenoh 1.10 returns a MatchingStatus with `.matching`.
    return bool(getattr(status, "matching", status))


def make_publisher(settings: TelemetrySettings) -> TelemetryPublisher:
    """The publisher the configuration asks for: Zenoh when enabled, else a NullPublisher."""
    return ZenohPublisher(settings) if settings.enabled else NullPublisher(settings)
