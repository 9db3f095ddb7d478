"""Telemetry payloads: pure builders of the JSON documents netpose publishes over Zenoh.

Every payload is a plain dict of JSON types (no NaN or infinity: those become null, because
strict JSON readers reject them) carrying `"schema": SCHEMA_VERSION` and `"kind"`. The keys are
documented in docs/telemetry.md; `ESTIMATE_KEYS` / `STATUS_KEYS` / `STATE_KEYS` list them so the
monitor and the tests can check a received payload against the documentation.

Inputs are plain values so the daemon can feed them from whatever it holds: the estimator's
`NetEstimate.to_json_dict()`, the filter state, counters. Nothing here reads a clock or a file.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from collections.abc import Mapping, Sequence
from typing import Any

# Bump when a key changes meaning or disappears; adding keys keeps the version (readers ignore
# keys they do not know).
SCHEMA_VERSION = 1

# Key expressions below the per-vehicle prefix `<key_prefix>/<vehicle>`.
ESTIMATE_SUFFIX = "estimate"
STATUS_SUFFIX = "status"
PREVIEW_SUFFIX = "preview"
STATE_SUFFIX = "state"

COMMON_KEYS = frozenset({"schema", "kind", "vehicle", "time_unix", "time_mono"})
ESTIMATE_KEYS = COMMON_KEYS | frozenset(
    {
        "seq",
        "frame_time_unix",
        "frame_time_mono",
        "detected",
        "confidence",
        "range_m",
        "sigma_range_m",
        "distance_m",
        "sigma_distance_m",
        "normal",
        "tilt_deg",
        "sigma_normal_deg",
        "rois",
        "rois_used",
        "reason",
        "filtered",
        "latency_ms",
    }
)
FILTERED_KEYS = frozenset(
    {
        "valid",
        "distance_m",
        "sigma_distance_m",
        "range_m",
        "sigma_range_m",
        "normal",
        "closing_speed_mps",
        "age_s",
    }
)
LATENCY_KEYS = frozenset({"stages", "estimator_total", "frame_to_publish"})
STATUS_KEYS = COMMON_KEYS | frozenset(
    {
        "version",
        "state",
        "uptime_s",
        "config_digest",
        "frame_source",
        "autopilot",
        "estimator",
        "cpu",
        "telemetry",
    }
)
FRAME_SOURCE_KEYS = frozenset({"state", "fps", "frames", "dropped", "last_frame_age_s"})
AUTOPILOT_KEYS = frozenset({"state", "heartbeat_age_s", "messages_sent"})
ESTIMATOR_KEYS = frozenset(
    {"fps", "frames", "detected_fraction", "latency_ms_mean", "latency_ms_max"}
)
CPU_KEYS = frozenset({"cores", "load_1m", "process_percent"})
STATE_KEYS = COMMON_KEYS | frozenset({"status", "config", "estimate"})

PREVIEW_META_KEYS = frozenset({"schema", "kind", "vehicle", "seq", "time_unix", "width", "height"})

# Values a component can report for its link state (docs/telemetry.md explains each).
FRAME_SOURCE_STATES = ("starting", "streaming", "reconnecting", "stopped", "failed")
AUTOPILOT_STATES = ("disabled", "waiting", "connected", "lost")
SERVICE_STATES = ("starting", "running", "degraded", "stopping")

# Configuration keys whose values are never published: a key whose last component matches.
_SECRET_KEY = re.compile(
    r"(password|passwd|passphrase|secret|token|api[_-]?key|private[_-]?key|credential)", re.I
)
# user:password@ inside URLs (rtsp://user:pw@camera/...), the usual way cameras take credentials.
_URL_PASSWORD = re.compile(r"(?P<scheme>[a-z][a-z0-9+.-]*://)(?P<user>[^:/@\s]*):[^@/\s]*@", re.I)
REDACTED = "<redacted>"


def _number(value: Any, digits: int) -> float | None:
    """A finite float rounded to `digits`, or None (JSON has no NaN or infinity)."""
    if value is None or isinstance(value, bool):
        return None
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return round(number, digits) if math.isfinite(number) else None


def _count(value: Any) -> int | None:
    if value is None or isinstance(value, bool):
        return None
    try:
        return int(value)
    except (TypeError, ValueError, OverflowError):
        return None


def _vector(value: Any, digits: int) -> list[float] | None:
    if value is None:
        return None
    components = [_number(v, digits) for v in value]
    if len(components) != 3 or any(c is None for c in components):
        return None
    return [c for c in components if c is not None]


def _header(kind: str, vehicle: str, now_unix: float, now_mono: float) -> dict[str, Any]:
    return {
        "schema": SCHEMA_VERSION,
        "kind": kind,
        "vehicle": vehicle,
        "time_unix": _number(now_unix, 6),
        "time_mono": _number(now_mono, 6),
    }


def filtered_payload(
    *,
    valid: bool,
    distance_m: float | None = None,
    sigma_distance_m: float | None = None,
    range_m: float | None = None,
    sigma_range_m: float | None = None,
    normal: Sequence[float] | None = None,
    closing_speed_mps: float | None = None,
    age_s: float | None = None,
) -> dict[str, Any]:
    """The filter's view: smoothed values and whether the filter trusts them (`valid`)."""
    return {
        "valid": bool(valid),
        "distance_m": _number(distance_m, 5),
        "sigma_distance_m": _number(sigma_distance_m, 5),
        "range_m": _number(range_m, 5),
        "sigma_range_m": _number(sigma_range_m, 5),
        "normal": _vector(normal, 6),
        "closing_speed_mps": _number(closing_speed_mps, 5),
        "age_s": _number(age_s, 4),
    }


def estimate_payload(
    *,
    vehicle: str,
    seq: int,
    estimate: Mapping[str, Any],
    now_unix: float,
    now_mono: float,
    frame_time_unix: float | None = None,
    frame_time_mono: float | None = None,
    filtered: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """One estimate, published for every processed frame.

    `estimate` is `NetEstimate.to_json_dict()` (missing keys become null); `filtered` is a
    `filtered_payload(...)` or None when no filter runs. Stage latencies come from the
    estimate's `timings_ms`; `frame_to_publish` is the age of the frame at publication, from
    the monotonic clock, so it is immune to wall-clock steps.
    """
    stages_in = estimate.get("timings_ms") or {}
    stages = {str(name): _number(ms, 3) for name, ms in stages_in.items()}
    known = [ms for ms in stages.values() if ms is not None]
    frame_age_ms = None
    if frame_time_mono is not None:
        frame_age_ms = _number((now_mono - frame_time_mono) * 1000.0, 3)
    payload = _header("estimate", vehicle, now_unix, now_mono)
    payload.update(
        {
            "seq": int(seq),
            "frame_time_unix": _number(frame_time_unix, 6),
            "frame_time_mono": _number(frame_time_mono, 6),
            "detected": bool(estimate.get("detected", False)),
            "confidence": _number(estimate.get("confidence"), 4),
            "range_m": _number(estimate.get("range_m"), 5),
            "sigma_range_m": _number(estimate.get("sigma_range_m"), 5),
            "distance_m": _number(estimate.get("distance_m"), 5),
            "sigma_distance_m": _number(estimate.get("sigma_distance_m"), 5),
            "normal": _vector(estimate.get("normal"), 6),
            "tilt_deg": _number(estimate.get("tilt_deg"), 3),
            "sigma_normal_deg": _number(estimate.get("sigma_normal_deg"), 3),
            "rois": _count(estimate.get("rois")),
            "rois_used": _count(estimate.get("rois_used")),
            "reason": str(estimate.get("reason") or ""),
            "filtered": None if filtered is None else dict(filtered),
            "latency_ms": {
                "stages": stages,
                "estimator_total": _number(sum(known), 3) if known else None,
                "frame_to_publish": frame_age_ms,
            },
        }
    )
    return payload


def frame_source_status(
    *,
    state: str,
    fps: float | None = None,
    frames: int | None = None,
    dropped: int | None = None,
    last_frame_age_s: float | None = None,
) -> dict[str, Any]:
    """Camera / stream health; `state` is one of FRAME_SOURCE_STATES."""
    return {
        "state": str(state),
        "fps": _number(fps, 2),
        "frames": _count(frames),
        "dropped": _count(dropped),
        "last_frame_age_s": _number(last_frame_age_s, 3),
    }


def autopilot_status(
    *,
    state: str,
    heartbeat_age_s: float | None = None,
    messages_sent: int | None = None,
) -> dict[str, Any]:
    """MAVLink link health; `state` is one of AUTOPILOT_STATES."""
    return {
        "state": str(state),
        "heartbeat_age_s": _number(heartbeat_age_s, 3),
        "messages_sent": _count(messages_sent),
    }


def estimator_status(
    *,
    fps: float | None = None,
    frames: int | None = None,
    detected_fraction: float | None = None,
    latency_ms_mean: float | None = None,
    latency_ms_max: float | None = None,
) -> dict[str, Any]:
    """Processing rate and latency over the last status period."""
    return {
        "fps": _number(fps, 2),
        "frames": _count(frames),
        "detected_fraction": _number(detected_fraction, 4),
        "latency_ms_mean": _number(latency_ms_mean, 3),
        "latency_ms_max": _number(latency_ms_max, 3),
    }


def cpu_status(
    *,
    cores: int | None = None,
    load_1m: float | None = None,
    process_percent: float | None = None,
) -> dict[str, Any]:
    """CPU load: the system 1-minute load average and this process's share of one core (%)."""
    return {
        "cores": _count(cores),
        "load_1m": _number(load_1m, 2),
        "process_percent": _number(process_percent, 1),
    }


def status_payload(
    *,
    vehicle: str,
    version: str,
    state: str,
    uptime_s: float,
    config_digest: str,
    now_unix: float,
    now_mono: float,
    frame_source: Mapping[str, Any],
    autopilot: Mapping[str, Any],
    estimator: Mapping[str, Any],
    cpu: Mapping[str, Any],
    telemetry: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The 1 Hz health report; sections come from the `*_status` builders above."""
    payload = _header("status", vehicle, now_unix, now_mono)
    payload.update(
        {
            "version": str(version),
            "state": str(state),
            "uptime_s": _number(uptime_s, 3),
            "config_digest": str(config_digest),
            "frame_source": dict(frame_source),
            "autopilot": dict(autopilot),
            "estimator": dict(estimator),
            "cpu": dict(cpu),
            "telemetry": None if telemetry is None else _json_safe(telemetry),
        }
    )
    return payload


def state_payload(
    *,
    vehicle: str,
    now_unix: float,
    now_mono: float,
    status: Mapping[str, Any] | None,
    config: Mapping[str, Any] | None,
    estimate: Mapping[str, Any] | None,
) -> dict[str, Any]:
    """The queryable's answer: last status, effective configuration (redacted), last estimate."""
    payload = _header("state", vehicle, now_unix, now_mono)
    payload.update(
        {
            "status": None if status is None else dict(status),
            "config": None if config is None else redact_secrets(config),
            "estimate": None if estimate is None else dict(estimate),
        }
    )
    return payload


def preview_meta(
    *, vehicle: str, seq: int, now_unix: float, width: int, height: int
) -> dict[str, Any]:
    """JSON metadata sent as the Zenoh attachment of a preview JPEG."""
    return {
        "schema": SCHEMA_VERSION,
        "kind": "preview",
        "vehicle": vehicle,
        "seq": int(seq),
        "time_unix": _number(now_unix, 6),
        "width": int(width),
        "height": int(height),
    }


def _json_safe(value: Any) -> Any:
    """Deep copy into JSON types; non-finite floats become None, unknown objects strings."""
    if isinstance(value, Mapping):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    if isinstance(value, bool | int | str) or value is None:
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    return str(value)


def redact_secrets(config: Mapping[str, Any]) -> dict[str, Any]:
    """A JSON-safe copy of `config` with secret values replaced by REDACTED.

    Secret values are those under keys that name a password, token, key or credential, and the
    password part of `scheme://user:password@host` URLs anywhere in strings.
    """

    def scrub(key: str, value: Any) -> Any:
        if _SECRET_KEY.search(key) and value not in (None, ""):
            return REDACTED
        if isinstance(value, Mapping):
            return {str(k): scrub(str(k), v) for k, v in value.items()}
        if isinstance(value, list | tuple):
            return [scrub(key, v) for v in value]
        if isinstance(value, str):
            return _URL_PASSWORD.sub(rf"\g<scheme>\g<user>:{REDACTED}@", value)
        return _json_safe(value)

    return {str(k): scrub(str(k), v) for k, v in config.items()}


def config_digest(config: Mapping[str, Any]) -> str:
    """Short stable digest of the effective configuration (secrets excluded, key order ignored).

    Two services with the same digest run the same configuration, except possibly for secrets,
    which are left out so the digest reveals nothing about them.
    """
    canonical = json.dumps(redact_secrets(config), sort_keys=True, separators=(",", ":"))
    return "sha256:" + hashlib.sha256(canonical.encode("utf-8")).hexdigest()[:16]


def schema_problems(payload: Mapping[str, Any]) -> list[str]:
    """What is wrong with a received payload compared with this schema (empty when fine).

    Extra keys are accepted (a newer publisher may add some); missing keys and another schema
    version are reported.
    """
    expected = {
        "estimate": ESTIMATE_KEYS,
        "status": STATUS_KEYS,
        "state": STATE_KEYS,
    }.get(str(payload.get("kind")))
    if expected is None:
        return [f"unknown kind {payload.get('kind')!r}"]
    problems = []
    if payload.get("schema") != SCHEMA_VERSION:
        problems.append(f"schema {payload.get('schema')!r} (this reader knows {SCHEMA_VERSION})")
    missing = sorted(expected - payload.keys())
    if missing:
        problems.append("missing " + ", ".join(missing))
    return problems
