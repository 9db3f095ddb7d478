"""Telemetry to the topside over Zenoh: estimates, 1 Hz status, preview JPEGs and a queryable.

The publisher knows nothing about the estimator: it takes plain JSON-ready dicts (built by
`service.telemetry_schema`) and JPEG bytes. The frame loop only appends to a bounded deque
(drop-oldest, drops counted); a worker thread owned by the publisher opens the Zenoh session,
retries with backoff while no router answers, serialises and puts. So a missing, slow or
vanishing router can never stall the frame loop or the MAVLink path.

    TelemetryPublisher   the interface the daemon talks to
    ZenohPublisher       the real one (eclipse-zenoh >= 1.0)
    NullPublisher        telemetry disabled
    RecordingPublisher   keeps everything in memory, for tests of the daemon
"""

from __future__ import annotations

import collections
import json
import logging
import math
import re
import threading
import time
from abc import abstractmethod
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from drivers.lifecycle import Closeable
from service.core.errors import ConfigError
from service.telemetry_schema import (
    ESTIMATE_SUFFIX,
    PREVIEW_SUFFIX,
    STATE_SUFFIX,
    STATUS_SUFFIX,
    redact_secrets,
    state_payload,
)

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger(__name__)

MODES = ("peer", "client")
DEFAULT_MODE = "client"
# BlueOS runs its Zenoh router here; a client session on the vehicle connects to it.
DEFAULT_CONNECT = ("tcp/127.0.0.1:7447",)
# One key chunk: no '/', no wildcards or Zenoh's reserved characters.
_CHUNK = re.compile(r"^[A-Za-z0-9_.-]+$")
_ENDPOINT = re.compile(r"^[a-z][a-z0-9-]*/\S+$")


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
        self.validate()

    @classmethod
    def from_mapping(cls, section: Mapping[str, Any]) -> TelemetrySettings:
        """Build from a parsed TOML table; unknown keys and wrong types are ConfigErrors."""
        known = set(cls.__dataclass_fields__)
        for key in section:
            if key not in known:
                known_list = ", ".join(sorted(known))
                raise ConfigError(f"telemetry.{key}", f"unknown key (known: {known_list})")
        values: dict[str, Any] = dict(section)
        for key in ("listen", "connect"):
            if key in values and values[key] is not None:
                endpoints = values[key]
                if isinstance(endpoints, str) or not isinstance(endpoints, Sequence):
                    raise ConfigError(f"telemetry.{key}", "must be a list of endpoint strings")
                values[key] = tuple(endpoints)
        return cls(**values)

    def validate(self) -> None:
        def bad(key: str, problem: str) -> ConfigError:
            return ConfigError(f"telemetry.{key}", problem)

        for key in ("enabled",):
            if not isinstance(getattr(self, key), bool):
                raise bad(key, "must be true or false")
        if self.scouting is not None and not isinstance(self.scouting, bool):
            raise bad("scouting", "must be true or false")
        for key in ("vehicle", "key_prefix"):
            value = getattr(self, key)
            if not isinstance(value, str) or not _CHUNK.match(value):
                raise bad(key, f"{value!r} must be one word of letters, digits, '_', '.', '-'")
        if self.mode is not None and self.mode not in MODES:
            raise bad("mode", f"{self.mode!r} is not one of {', '.join(MODES)}")
        for key in ("listen", "connect"):
            endpoints = getattr(self, key)
            if endpoints is None:
                continue
            for endpoint in endpoints:
                if not isinstance(endpoint, str) or not _ENDPOINT.match(endpoint):
                    raise bad(key, f"{endpoint!r} is not a Zenoh endpoint like tcp/127.0.0.1:7447")
        if self.config_file is not None and not isinstance(self.config_file, str):
            raise bad("config_file", "must be a path string")
        for key in ("preview_hz", "retry_initial_s", "retry_max_s"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise bad(key, "must be a number")
            if not math.isfinite(value) or value < 0:
                raise bad(key, "must be a finite number >= 0")
        if self.retry_initial_s <= 0 or self.retry_max_s < self.retry_initial_s:
            raise bad("retry_max_s", "retry_initial_s must be > 0 and <= retry_max_s")
        for key, low, high in (
            ("preview_width", 32, 4096),
            ("preview_quality", 1, 100),
            ("queue_size", 1, 100_000),
        ):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                raise bad(key, f"must be an integer from {low} to {high}")

    @property
    def key_root(self) -> str:
        """`<key_prefix>/<vehicle>`: every key this service publishes lives below it."""
        return f"{self.key_prefix}/{self.vehicle}"

    def key(self, suffix: str) -> str:
        return f"{self.key_root}/{suffix}"

    def effective(self) -> dict[str, Any]:
        """The values in force (defaults resolved), for logs and the queryable."""
        def resolved(value: Any, default: Any) -> Any:
            if value is not None:
                return list(value) if isinstance(value, tuple) else value
            return "<config_file>" if self.config_file is not None else default

        return {
            "enabled": self.enabled,
            "vehicle": self.vehicle,
            "key_prefix": self.key_prefix,
            "mode": resolved(self.mode, DEFAULT_MODE),
            "listen": resolved(self.listen, []),
            "connect": resolved(self.connect, list(DEFAULT_CONNECT)),
            "scouting": resolved(self.scouting, False),
            "config_file": self.config_file,
            "preview_hz": self.preview_hz,
            "preview_width": self.preview_width,
            "preview_quality": self.preview_quality,
            "queue_size": self.queue_size,
        }


def build_zenoh_config(settings: TelemetrySettings) -> zenoh.Config:
    """The Zenoh configuration: `config_file` as the base, explicit settings on top.

    Raises ConfigError naming the telemetry key when Zenoh rejects a value or the file.
    """
    import zenoh

    from_file = settings.config_file is not None
    if settings.config_file is not None:
        path = Path(settings.config_file)
        if not path.is_file():
            raise ConfigError("telemetry.config_file", f"{path} does not exist")
        try:
            config = zenoh.Config.from_file(str(path))
        except zenoh.ZError as exc:
            raise ConfigError("telemetry.config_file", f"{path}: {exc}") from exc
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
            raise ConfigError(f"telemetry.{key}", str(exc).split(" at /")[0]) from exc

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
    return config


class TelemetryPublisher(Closeable):
    """What the daemon sees of telemetry. Every method returns at once and never raises for a
    network problem; payload dicts handed over must not be modified afterwards."""

    def __init__(self, settings: TelemetrySettings) -> None:
        self.settings = settings
        self._last_preview_at = -math.inf

    @abstractmethod
    def start(self) -> None:
        """Begin publishing (a real publisher connects in the background)."""

    @abstractmethod
    def publish_estimate(self, payload: Mapping[str, Any]) -> None:
        """Queue one estimate payload (service.telemetry_schema.estimate_payload)."""

    @abstractmethod
    def publish_status(self, payload: Mapping[str, Any]) -> None:
        """Queue a status payload; it also becomes the status the queryable answers with."""

    @abstractmethod
    def publish_preview(self, jpeg: bytes, meta: Mapping[str, Any] | None = None) -> None:
        """Queue a preview JPEG; `meta` (telemetry_schema.preview_meta) travels as attachment."""

    @abstractmethod
    def set_query_state(self, status: Mapping[str, Any] | None, config: Mapping[str, Any]) -> None:
        """What the queryable answers: status and effective configuration (secrets removed)."""

    @abstractmethod
    def close(self) -> None:
        """Stop the worker and close the session; idempotent."""

    @abstractmethod
    def status(self) -> dict[str, Any]:
        """Counters and link state of the publisher itself (goes into the status payload)."""

    @property
    def online(self) -> bool:
        """True when published data can leave the process."""
        return False

    def wants_preview(self, now_mono: float) -> bool:
        """True at most once per 1/preview_hz, and only while someone can receive a preview,
        so the frame loop draws and encodes no JPEG for nobody."""
        if self.settings.preview_hz <= 0 or not self.online:
            return False
        if now_mono - self._last_preview_at < 1.0 / self.settings.preview_hz:
            return False
        self._last_preview_at = now_mono
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

    def publish_estimate(self, payload: Mapping[str, Any]) -> None:
        pass

    def publish_status(self, payload: Mapping[str, Any]) -> None:
        pass

    def publish_preview(self, jpeg: bytes, meta: Mapping[str, Any] | None = None) -> None:
        pass

    def set_query_state(self, status: Mapping[str, Any] | None, config: Mapping[str, Any]) -> None:
        pass

    def close(self) -> None:
        pass

    def status(self) -> dict[str, Any]:
        return {"state": "disabled"}


@dataclass
class RecordingPublisher(TelemetryPublisher):
    """Keeps what would be published, for tests of code that publishes (the daemon's)."""

    settings: TelemetrySettings = field(default_factory=TelemetrySettings)
    is_online: bool = True
    estimates: list[Mapping[str, Any]] = field(default_factory=list)
    statuses: list[Mapping[str, Any]] = field(default_factory=list)
    previews: list[tuple[bytes, Mapping[str, Any] | None]] = field(default_factory=list)
    query_status: Mapping[str, Any] | None = None
    query_config: dict[str, Any] | None = None
    started: bool = False
    closed: bool = False

    def __post_init__(self) -> None:
        super().__init__(self.settings)

    @property
    def online(self) -> bool:
        return self.is_online and self.started and not self.closed

    def start(self) -> None:
        self.started = True

    def publish_estimate(self, payload: Mapping[str, Any]) -> None:
        self.estimates.append(payload)

    def publish_status(self, payload: Mapping[str, Any]) -> None:
        self.statuses.append(payload)
        self.query_status = payload

    def publish_preview(self, jpeg: bytes, meta: Mapping[str, Any] | None = None) -> None:
        self.previews.append((jpeg, meta))

    def set_query_state(self, status: Mapping[str, Any] | None, config: Mapping[str, Any]) -> None:
        self.query_status = status
        self.query_config = redact_secrets(config)

    def close(self) -> None:
        self.closed = True

    def status(self) -> dict[str, Any]:
        return {
            "state": "online" if self.online else "offline",
            "sent": {
                "estimate": len(self.estimates),
                "status": len(self.statuses),
                "preview": len(self.previews),
            },
        }


@dataclass(frozen=True)
class _Outgoing:
    suffix: str
    payload: Mapping[str, Any] | bytes
    attachment: Mapping[str, Any] | None = None


_STREAMS = (ESTIMATE_SUFFIX, STATUS_SUFFIX, PREVIEW_SUFFIX)


class ZenohPublisher(TelemetryPublisher):
    """The real publisher: one Zenoh session owned by one worker thread.

    States: "idle" (before start), "connecting" (opening; retried with exponential backoff
    from retry_initial_s to retry_max_s while it fails), "online" (session open; a client
    session re-connects to a returning router by itself), "closed".
    Payloads handed over while not online are counted as `skipped_offline` and not kept: an
    estimate that waited for a router is no longer news.
    """

    def __init__(
        self,
        settings: TelemetrySettings,
        *,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        super().__init__(settings)
        self._clock = clock
        self._wall_clock = wall_clock
        self._queue: collections.deque[_Outgoing] = collections.deque(maxlen=settings.queue_size)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._lock = threading.Lock()  # counters and query state, shared with zenoh's threads
        self._thread: threading.Thread | None = None
        self._config: zenoh.Config | None = None
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
        self._query_status: Mapping[str, Any] | None = None
        self._query_config: dict[str, Any] | None = None
        self._last_estimate: Mapping[str, Any] | None = None

    # --- frame-loop side: O(microseconds), never blocks on the network -------------------

    @property
    def online(self) -> bool:
        return self._online

    def start(self) -> None:
        """Validate the Zenoh configuration now (ConfigError) and connect in the background."""
        if self._thread is not None:
            return
        self._config = build_zenoh_config(self.settings)
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

    def publish_estimate(self, payload: Mapping[str, Any]) -> None:
        self._last_estimate = payload
        self._enqueue(_Outgoing(ESTIMATE_SUFFIX, payload))

    def publish_status(self, payload: Mapping[str, Any]) -> None:
        self._query_status = payload
        self._enqueue(_Outgoing(STATUS_SUFFIX, payload))

    def publish_preview(self, jpeg: bytes, meta: Mapping[str, Any] | None = None) -> None:
        self._enqueue(_Outgoing(PREVIEW_SUFFIX, bytes(jpeg), meta))

    def set_query_state(self, status: Mapping[str, Any] | None, config: Mapping[str, Any]) -> None:
        redacted = redact_secrets(config)  # once here, not per query
        with self._lock:
            self._query_status = status
            self._query_config = redacted

    def _preview_has_audience(self) -> bool:
        """Whether a subscriber matches the preview key (Zenoh tracks this, also through a
        router): about a microsecond, checked once per preview period."""
        publisher = self._preview_publisher
        if publisher is None:
            return False
        try:
            status: Any = publisher.matching_status
        except Exception:  # unknown: err on the side of sending
            return True
        # Typed as bool in the stubs; zenoh 1.10 returns a MatchingStatus with `.matching`.
        return bool(getattr(status, "matching", status))

    def status(self) -> dict[str, Any]:
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
            return {
                "state": self._state,
                "key_root": self.settings.key_root,
                "routers": routers,
                "peers": peers,
                "links": links,
                # Online but nobody to talk to (router gone, no subscriber peer): data is lost.
                "linked": None if links is None else links > 0,
                "sent": dict(self._sent),
                "queue_dropped": self._queue_dropped,
                "skipped_offline": self._skipped_offline,
                "errors": self._errors,
                "queries": self._queries,
                "open_attempts": self._open_attempts,
                "last_error": self._last_error,
            }

    def close(self, timeout: float = 3.0) -> None:
        """Stop and join the worker. If it is stuck inside a Zenoh open (bounded by Zenoh's
        open timeout) this waits at most `timeout`; the daemon thread then ends on its own."""
        self._stop.set()
        self._wake.set()
        thread = self._thread
        if thread is not None:
            thread.join(timeout)
            if thread.is_alive():
                log.warning("telemetry worker still opening a Zenoh session; not waiting longer")
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
            self._preview_publisher = declared[0][PREVIEW_SUFFIX]
            self._online = True
            self._state = "online"
            self._drain_until_stopped(*declared)
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
        import zenoh

        assert self._config is not None
        delay = self.settings.retry_initial_s
        logged = False
        while not self._stop.is_set():
            self._open_attempts += 1
            try:
                session = zenoh.open(self._config)
            except zenoh.ZError as exc:
                message = str(exc).split(" at /")[0]
                with self._lock:
                    self._last_error = message
                if not logged:  # once, not every retry: a missing router is a normal condition
                    log.warning(
                        "telemetry: cannot open Zenoh session (%s); retrying in the background",
                        message,
                    )
                    logged = True
                self._stop.wait(delay)
                delay = min(delay * 2.0, self.settings.retry_max_s)
                continue
            if self._stop.is_set():
                session.close()
                return None
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
    ) -> tuple[dict[str, zenoh.Publisher], zenoh.Queryable[None]]:
        import zenoh

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
        }
        queryable = session.declare_queryable(self.settings.key(STATE_SUFFIX), self._answer_query)
        return publishers, queryable

    def _drain_until_stopped(
        self, publishers: dict[str, zenoh.Publisher], queryable: zenoh.Queryable[None]
    ) -> None:
        import zenoh

        failures_logged: set[str] = set()
        while not self._stop.is_set():
            self._wake.wait(0.5)
            self._wake.clear()
            while self._queue and not self._stop.is_set():
                item = self._queue.popleft()
                try:
                    if isinstance(item.payload, bytes):
                        attachment = None if item.attachment is None else _to_json(item.attachment)
                        publishers[item.suffix].put(item.payload, attachment=attachment)
                    else:
                        publishers[item.suffix].put(_to_json(item.payload))
                except (ValueError, TypeError, zenoh.ZError) as exc:
                    # A payload that is not JSON, or a put refused: count it, say it once per
                    # kind of failure, keep going with the next one.
                    with self._lock:
                        self._errors += 1
                        self._last_error = f"{item.suffix}: {exc}"
                    key = f"{item.suffix}:{type(exc).__name__}"
                    if key not in failures_logged:
                        failures_logged.add(key)
                        log.warning("telemetry: cannot publish %s: %s", item.suffix, exc)
                    continue
                with self._lock:
                    self._sent[item.suffix] += 1
        queryable.undeclare()
        for publisher in publishers.values():
            publisher.undeclare()

    def _answer_query(self, query: zenoh.Query) -> None:
        """Runs on a Zenoh thread: reply with the state snapshot, never raise into Zenoh."""
        import zenoh

        with self._lock:
            self._queries += 1
            status, config = self._query_status, self._query_config
        try:
            payload = state_payload(
                vehicle=self.settings.vehicle,
                now_unix=self._wall_clock(),
                now_mono=self._clock(),
                status=status,
                config=config,
                estimate=self._last_estimate,
            )
            query.reply(
                self.settings.key(STATE_SUFFIX),
                _to_json(payload),
                encoding=zenoh.Encoding.APPLICATION_JSON,
            )
        except Exception as exc:
            log.warning("telemetry: cannot answer query %s: %s", query.selector, exc)
            with self._lock:
                self._errors += 1


def _to_json(payload: Mapping[str, Any]) -> bytes:
    # allow_nan=False: NaN is not JSON; the schema builders already map it to null.
    return json.dumps(payload, separators=(",", ":"), allow_nan=False).encode("utf-8")


def make_publisher(settings: TelemetrySettings) -> TelemetryPublisher:
    """The publisher the configuration asks for: Zenoh when enabled, else a NullPublisher."""
    return ZenohPublisher(settings) if settings.enabled else NullPublisher(settings)
