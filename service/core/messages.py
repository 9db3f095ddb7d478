"""Typed telemetry messages: one frozen dataclass per payload, serialised once at the edge.

Every payload netpose publishes (Zenoh, the web page, recordings) is one of the messages below.
They are built from typed values by the application and turned into JSON only by `to_json` /
`encode`, called by the transport that sends them. There is one rounding policy for every float
(`FLOAT_DECIMALS` places: micrometres, microseconds, micro-degrees), and a value that is unknown
or not finite is `null` (strict JSON has no NaN).

The documentation of every key lives here, in each field's metadata; `schema_markdown()` renders
it, docs/telemetry.md carries that rendering, and a test keeps the two identical.

Wire conventions: every message carries `schema` (SCHEMA_VERSION) and `kind` first. The version
is bumped when a key changes meaning or disappears; adding keys keeps it, so readers ignore keys
they do not know.
"""

from __future__ import annotations

import dataclasses
import enum
import inspect
import json
import math
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

SCHEMA_VERSION = 2
FLOAT_DECIMALS = 6

# Key expressions below the per-vehicle prefix `<key_prefix>/<vehicle>`.
ESTIMATE_SUFFIX = "estimate"
STATUS_SUFFIX = "status"
PREVIEW_SUFFIX = "preview"
STATE_SUFFIX = "state"
DAMAGE_SUFFIX = "damage"
# A Zenoh liveliness token, not a message: present while the daemon's session is up.
ALIVE_SUFFIX = "alive"

Vec3 = tuple[float, float, float]

# States a status section can report (docs/telemetry.md explains each).
FRAME_SOURCE_STATES = ("starting", "streaming", "reconnecting", "ended", "stopped")
AUTOPILOT_STATES = ("disabled", "waiting", "connected", "lost")
SERVICE_STATES = ("starting", "running", "degraded", "stopping")


def doc(text: str, default: Any = dataclasses.MISSING) -> Any:
    """A message field with its documentation (rendered into docs/telemetry.md)."""
    if default is dataclasses.MISSING:
        return field(metadata={"doc": text})
    if isinstance(default, dict | list):
        value = default
        return field(default_factory=lambda: type(value)(value), metadata={"doc": text})
    return field(default=default, metadata={"doc": text})


# -- estimate -------------------------------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class FilteredView:
    """The tracking filter's view of the net after this frame."""

    valid: bool = doc("the filter believes its distance (TRACKING, or COASTING briefly)")
    autopilot: str = doc(
        "what the autopilot is told: `good` (distance sent), `too_close` (a reading below the "
        "rangefinder minimum is sent), `none` (nothing is sent)"
    )
    autopilot_distance_m: float | None = doc(
        "the distance handed to the autopilot with this frame (DISTANCE_SENSOR carries it, in "
        "cm, while the link sends): `range_m` or `distance_m`, as `autopilot_along` says; null "
        "unless `autopilot` is `good`", None)
    autopilot_along: str | None = doc(
        "which distance the autopilot gets (`service.autopilot_distance` for this frame): "
        "`optical_axis` (along the camera's axis) or `perpendicular` (to the net plane)", None)
    state: str = doc("`tracking`, `coasting` or `lost`")
    measurement: str = doc(
        "fate of this frame's measurement: `accepted`, `rejected`, `none` or `reset`"
    )
    distance_m: float | None = doc("filtered perpendicular distance to the net plane", None)
    sigma_distance_m: float | None = doc(
        "its one-sigma uncertainty from the image alone (its precision; the mesh size's and "
        "the calibration's errors are not in it)", None)
    sigma_distance_total_m: float | None = doc(
        "one sigma of `distance_m` as a measurement of the world: `sigma_distance_m` with the "
        "scale's error (`mesh.bar_length_tolerance`, `camera.focal_tolerance`), which is the "
        "same in every frame and does not shrink as the filter averages them; "
        "DISTANCE_SENSOR's covariance carries the one of the distance `autopilot_along` "
        "names", None)
    range_m: float | None = doc("filtered distance along the optical axis", None)
    sigma_range_m: float | None = doc(
        "its one-sigma uncertainty from the image alone (its precision; the mesh size's and "
        "the calibration's errors are not in it)", None)
    sigma_range_total_m: float | None = doc(
        "one sigma of `range_m` as a measurement of the world: `sigma_range_m` with the scale's "
        "error (`mesh.bar_length_tolerance`, `camera.focal_tolerance`), which is the same in "
        "every frame and does not shrink as the filter averages them; DISTANCE_SENSOR's "
        "covariance carries the one of the distance `autopilot_along` names", None)
    normal: Vec3 | None = doc("filtered plane normal [x, y, z]", None)
    closing_speed_mps: float | None = doc(
        "rate at which the distance shrinks (positive = approaching the net)", None
    )
    age_s: float | None = doc("time since the filter last accepted a measurement", None)


@dataclass(frozen=True, kw_only=True)
class EstimateLatency:
    """Where the time of one frame went."""

    stages: dict[str, float] = doc(
        "time spent in each estimator stage, ms (names are the estimator's)", {}
    )
    estimator_total: float | None = doc("estimator time for this frame, ms", None)
    frame_to_publish: float | None = doc(
        "frame capture to publication, ms, monotonic clock", None
    )


@dataclass(frozen=True, kw_only=True)
class TruthView:
    """Ground truth of a rendered frame (synthetic and `sim:` sources only)."""

    net_present: bool = doc("a net is in view")
    range_m: float | None = doc("true distance along the optical axis", None)
    distance_m: float | None = doc("true perpendicular distance", None)
    tilt_deg: float | None = doc("true angle between optical axis and net normal", None)
    normal: Vec3 | None = doc("true plane normal", None)


@dataclass(frozen=True, kw_only=True)
class Message:
    """Header of every JSON message; `schema` and `kind` are added by the encoder."""

    KIND: ClassVar[str] = ""
    vehicle: str = doc("vehicle name, as in the key expression")
    time_unix: float = doc("vehicle wall clock when the message was built, s since 1970 (UTC)")
    time_mono: float = doc("vehicle monotonic clock when the message was built, s")


@dataclass(frozen=True, kw_only=True)
class EstimateMessage(Message):
    """One processed frame: the estimator's answer and the filter's."""

    KIND: ClassVar[str] = ESTIMATE_SUFFIX
    seq: int = doc("number of this estimate in the service run (1, 2, ... with no gaps: a "
                   "gap a subscriber sees is a message lost on the way; frames the camera "
                   "dropped are counted in status `frame_source.dropped`)")
    frame_time_unix: float | None = doc("wall-clock capture time of the frame", None)
    frame_time_mono: float | None = doc("monotonic capture time of the frame", None)
    detected: bool = doc("a net lattice was found in this frame", False)
    confidence: float = doc("detection confidence 0..1", 0.0)
    range_m: float | None = doc("distance to the net plane along the optical axis", None)
    sigma_range_m: float | None = doc(
        "its one-sigma uncertainty from the image alone (its precision; the mesh size's and "
        "the calibration's errors are not in it)", None)
    sigma_range_total_m: float | None = doc(
        "one sigma of `range_m` as a measurement of the world: `sigma_range_m` with the scale's "
        "error (`mesh.bar_length_tolerance`, `camera.focal_tolerance`: docs/estimator.md, "
        "Limits)", None)
    distance_m: float | None = doc("perpendicular distance from the camera to the plane", None)
    sigma_distance_m: float | None = doc(
        "its one-sigma uncertainty from the image alone (its precision; the mesh size's and "
        "the calibration's errors are not in it)", None)
    sigma_distance_total_m: float | None = doc(
        "one sigma of `distance_m` as a measurement of the world: `sigma_distance_m` with the "
        "scale's error (`mesh.bar_length_tolerance`, `camera.focal_tolerance`: "
        "docs/estimator.md, Limits)", None)
    normal: Vec3 | None = doc(
        "unit normal of the net plane [x, y, z], from the net to the camera (camera frame)", None
    )
    tilt_deg: float | None = doc("angle between optical axis and net normal (0 = square)", None)
    sigma_normal_deg: float | None = doc("uncertainty of the normal direction", None)
    rois: int = doc("regions of interest analysed in this frame", 0)
    rois_used: int = doc("regions whose lattice entered the plane fit", 0)
    reason: str = doc("why nothing was detected (empty when detected)", "")
    net_seen: bool = doc(
        "a net is in view: detected, or recognised with a range too uncertain to give", False)
    approx_range_m: float | None = doc(
        "for a net seen but not detected: the range along the optical axis that was refused "
        "as too uncertain (never sent to the autopilot)", None)
    approx_sigma_range_m: float | None = doc("its one-sigma uncertainty", None)
    budget_level: int = doc(
        "estimator work level of this frame: 0 full work, up to 3 the leanest (slow CPU)", 0
    )
    measured: bool = doc(
        "false: the frame was read but not given to the estimator (no net in view for a while:"
        " a paced search, `budget.search_hz`)", True)
    inspected: bool | None = doc(
        "net inspection searched this frame for holes (or tried: it failed); false: its time "
        "budget skipped it; null: not a frame to search (no valid track, inspection off)", None)
    filtered: FilteredView | None = doc("the tracking filter's view (null without a filter)", None)
    latency_ms: EstimateLatency = doc("per-stage latency", EstimateLatency())
    truth: TruthView | None = doc("ground truth of a rendered frame, else null", None)


# -- status ---------------------------------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class FrameSourceHealth:
    """The camera or video stream."""

    state: str = doc("`starting`, `streaming`, `reconnecting`, `ended`, `stopped`")
    fps: float | None = doc("frames the loop took per second over the last period (the "
                            "camera's rate less what was dropped)", None)
    frames: int = doc("frames the loop took in total", 0)
    dropped: int = doc("frames the camera gave that the loop never took because it was busy "
                       "with an earlier one (total)", 0)
    corrupt: int = doc("frames that could not be decoded (total)", 0)
    last_frame_age_s: float | None = doc("time since the last frame", None)
    up_since_mono: float | None = doc(
        "monotonic capture time of the first frame since the source (last) came up; null "
        "before it and while the source is down", None)
    error: str = doc("why the source is not streaming (empty while it is)", "")


@dataclass(frozen=True, kw_only=True)
class AutopilotIdentity:
    """The autopilot this link talks to, from its HEARTBEAT (and AUTOPILOT_VERSION)."""

    sysid: int = doc("MAVLink system id")
    compid: int = doc("MAVLink component id")
    type: int = doc("MAV_TYPE")
    autopilot: int = doc("MAV_AUTOPILOT")
    mavlink_version: int = doc("1 or 2, from the heartbeat's framing")
    flight_sw_version: int | None = doc("AUTOPILOT_VERSION.flight_sw_version", None)


@dataclass(frozen=True, kw_only=True)
class AutopilotHealth:
    """The MAVLink link to the autopilot (the link's own status, as it is)."""

    state: str = doc("`disabled`, `waiting` (no heartbeat yet), `connected`, `lost`")
    heartbeat_age_s: float | None = doc("time since the last autopilot heartbeat", None)
    messages_sent: int = doc("MAVLink messages sent in total", 0)
    transport: str = doc("`up`, `down`, or `fake` for a stand-in", "down")
    url: str = doc("the link's endpoint, secrets removed", "")
    autopilot: AutopilotIdentity | None = doc("who answers, null before the first heartbeat", None)
    sent: dict[str, int] = doc("messages sent per MAVLink message name", {})
    received: int = doc("messages received from the vehicle", 0)
    errors: int = doc("failed opens and transport errors", 0)
    last_error: str = doc("the last of those, empty if none", "")
    reconnects: int = doc("times the transport came back after an outage", 0)
    sending_distance: bool = doc("DISTANCE_SENSOR is being sent right now", False)
    freshness_s: float | None = doc(
        "age beyond which a reading is not repeated (follows the measured frame interval)", None
    )
    sending_changes: int = doc("times sending started or stopped (total)", 0)
    texts_dropped: int = doc(
        "pilot texts (STATUSTEXT) dropped after waiting out a link outage (total)", 0)
    min_distance_m: float | None = doc(
        "the rangefinder's minimum the autopilot is told (DISTANCE_SENSOR.min_distance): it "
        "reads a distance below it as too close, not as a distance", None)
    max_distance_m: float | None = doc(
        "the rangefinder's maximum the autopilot is told (DISTANCE_SENSOR.max_distance)", None)
    sending_net_plane: bool = doc("the net plane (DEBUG_VECT NET_PLANE, for the net-hold "
                                  "applet) is being sent right now", False)
    net_plane: str = doc(
        "the net-hold applet's input in words: `off` (mavlink.send_net_plane false), `sent`, "
        "or why not (held while the autopilot's clock is unconfirmed, a zero vector while the "
        "newest frame did not confirm the net, ...)", "off")
    armed: bool | None = doc(
        "the autopilot's last HEARTBEAT said it is armed (the web page's settings and restart "
        "wait for it to be disarmed); kept while its heartbeat is lost, since a lost heartbeat "
        "is not a disarmed vehicle; null while no autopilot has been heard", None)


@dataclass(frozen=True, kw_only=True)
class EstimatorHealth:
    """Processing over the last status period."""

    fps: float | None = doc("frames measured per second", None)
    frames: int = doc("frames measured in the last period", 0)
    detected_fraction: float | None = doc("share of them with a net, 0..1", None)
    latency_ms_mean: float | None = doc("frame capture to result, mean, ms", None)
    latency_ms_max: float | None = doc("frame capture to result, max, ms", None)
    errors: int = doc("frames the estimator could not use (total)", 0)
    last_error: str = doc("why, for the last of them (empty if none)", "")
    budget_level: int = doc(
        "work per frame in use: 0 full ... 3 least (`[budget]`, lowered when frames take longer"
        " than the camera's interval)", 0)
    frame_interval_ms: float | None = doc("the camera's frame interval (median), ms", None)
    frame_work_ms: float | None = doc(
        "the loop's time per tracked frame at that level (what judges the level), ms", None)
    searching_hz: float | None = doc(
        "no net in view for a while: the estimator looks at this many frames a second at most"
        " (`budget.search_hz`); null while it measures every frame", None)


@dataclass(frozen=True, kw_only=True)
class CpuHealth:
    """CPU load."""

    cores: int | None = doc("CPU count", None)
    load_1m: float | None = doc("system 1-minute load average", None)
    process_percent: float | None = doc(
        "this process's CPU time over the period, % of one core", None
    )
    rss_mb: float | None = doc("resident memory of this process, MB", None)


@dataclass(frozen=True, kw_only=True)
class TelemetryHealth:
    """The Zenoh publisher's own counters."""

    state: str = doc("`idle`, `connecting`, `online`, `closed`, `failed`, `disabled`")
    key_root: str = doc("`<key_prefix>/<vehicle>`", "")
    routers: int | None = doc("Zenoh routers connected", None)
    peers: int | None = doc("Zenoh peers connected", None)
    links: int | None = doc("Zenoh transports open (routers, peers and clients)", None)
    linked: bool | None = doc("at least one link: published data can reach someone", None)
    sent: dict[str, int] = doc("messages put per stream", {})
    queue_dropped: int = doc("oldest messages dropped because the link could not keep up", 0)
    skipped_offline: int = doc("messages handed over while no session was open", 0)
    damage_waiting: int = doc("confirmed holes kept until a subscriber to `damage` can hear "
                              "them", 0)
    errors: int = doc("payloads that could not be put, failed queries", 0)
    queries: int = doc("queries answered", 0)
    open_attempts: int = doc("session open attempts", 0)
    last_error: str = doc("the last error, empty if none", "")


@dataclass(frozen=True, kw_only=True)
class FilterHealth:
    """The tracking filter."""

    state: str = doc("`tracking`, `coasting` or `lost`")
    accepted: int = doc("measurements accepted (total)", 0)
    rejected: int = doc("measurements rejected by the gate (total)", 0)
    resets: int = doc("track restarts (total)", 0)


@dataclass(frozen=True, kw_only=True)
class StatusLatency:
    """Frame capture to the hand-over to the autopilot link."""

    capture_to_link_p50: float | None = doc("median over the last period, ms", None)
    capture_to_link_p99: float | None = doc("99th percentile over the last period, ms", None)


@dataclass(frozen=True)
class InspectionHealth:
    """Net inspection since the service started: how much of the net was looked at. No hole
    reported is no proof of an intact net (docs/inspection.md, Limits)."""

    inspected_frames: int = doc("frames searched for holes", 0)
    judged_cells: int = doc("mesh cells whose bars were judged in them (overlaps counted)", 0)
    holes: int = doc("holes confirmed", 0)


@dataclass(frozen=True, kw_only=True)
class StatusMessage(Message):
    """Health of the service, once per `service.status_interval_s`."""

    KIND: ClassVar[str] = STATUS_SUFFIX
    version: str = doc("netpose version")
    state: str = doc("`starting`, `running`, `degraded` (a part is down), `stopping`")
    uptime_s: float = doc("time since the service started")
    config_digest: str = doc(
        "`sha256:` + 16 hex digits of the effective configuration, secrets left out"
    )
    frame_source: FrameSourceHealth = doc("camera / video stream")
    autopilot: AutopilotHealth = doc("MAVLink link")
    estimator: EstimatorHealth = doc("processing over the last period")
    cpu: CpuHealth = doc("CPU and memory")
    telemetry: TelemetryHealth | None = doc("the publisher's own counters", None)
    filter: FilterHealth = doc("the tracking filter")
    latency_ms: StatusLatency = doc("frame to autopilot latency", StatusLatency())
    inspection: InspectionHealth | None = doc("net inspection's coverage (null: it is off)",
                                              None)


@dataclass(frozen=True, kw_only=True)
class StateMessage(Message):
    """The `state` queryable's answer."""

    KIND: ClassVar[str] = STATE_SUFFIX
    status: StatusMessage | None = doc("the last status message (null before the first)", None)
    config: dict[str, Any] = doc("the effective configuration, secrets redacted", {})
    estimate: EstimateMessage | None = doc(
        "the last estimate message; once frames stop it is history (its `time_mono` against "
        "the status's says how old; the status's `filter.state` is what holds now)", None)


@dataclass(frozen=True, kw_only=True)
class PreviewMeta:
    """JSON metadata sent as the Zenoh attachment of a preview JPEG."""

    KIND: ClassVar[str] = PREVIEW_SUFFIX
    vehicle: str = doc("vehicle name")
    seq: int = doc("the frame counter of the estimate it belongs to")
    time_unix: float = doc("wall clock of the estimate it belongs to (its `time_unix`)")
    width: int = doc("JPEG width, px")
    height: int = doc("JPEG height, px")
    time_mono: float | None = doc("monotonic clock of that estimate (its `time_mono`)", None)
    frame_time_mono: float | None = doc("the frame's monotonic capture time", None)
    # The frame the JPEG was scaled down from: damage pixels (image_x_px ...) are its pixels.
    frame_width: int | None = doc("the camera frame's width, px", None)
    frame_height: int | None = doc("the camera frame's height, px", None)


# -- damage ---------------------------------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class DamageMessage(Message):
    """A hole in the net, confirmed over several frames (published once per hole: see
    docs/inspection.md). Sizes are knot to knot on the net plane."""

    KIND: ClassVar[str] = DAMAGE_SUFFIX
    hole_id: int = doc("number of the hole in this service run, 1, 2, 3 in the order confirmed")
    run_started_unix: float | None = doc(
        "when this run of the service started (wall clock): hole_id starts again at 1 in the "
        "next one, so (vehicle, run_started_unix, hole_id) is a hole's key across runs", None)
    frame_time_unix: float | None = doc("wall-clock capture time of the confirming frame", None)
    frame_time_mono: float | None = doc("monotonic capture time of the confirming frame", None)
    first_seen_mono: float | None = doc("monotonic capture time of its first detection", None)
    width_m: float = doc("extent along the net plane's horizontal (the camera's right laid "
                         "onto the plane), knot to knot")
    height_m: float = doc("extent along the plane's vertical (the camera's down laid onto it)")
    cells: int = doc("mesh openings merged into the hole (2: one bar cut)")
    missing_bars: int = doc("bars missing inside it")
    image_x_px: float = doc("centre in the confirming frame, pixels from the left")
    image_y_px: float = doc("centre in the confirming frame, pixels from the top")
    image_box_px: list[float] = doc("its knots' box in that frame [x0, y0, x1, y1], pixels", [])
    frame_width_px: int | None = doc("that frame's width: the pixels above are of a frame this "
                                     "wide (scale them to draw on a preview)", None)
    frame_height_px: int | None = doc("that frame's height, px", None)
    plane_x_m: float = doc("centre on the net plane, right of the camera's foot point (the "
                           "plane's point nearest the camera)")
    plane_y_m: float = doc("centre on the net plane, below the camera's foot point")
    position_m: Vec3 = doc("centre in the camera frame [x right, y down, z forward]")
    range_m: float = doc("distance from the camera to the hole's centre")
    bearing: str = doc("where it is seen from the camera (`ahead` = along its optical axis, "
                       "whatever `mavlink.orientation` says): `ahead`, `ahead-left`, "
                       "`ahead-right`, with ` high` / ` low` when well off the optical axis")
    confidence: float = doc("0..1, from how clearly its bars are missing and how often it was "
                            "seen where it was expected")
    detections: int = doc("inspections it was found in, up to its confirmation")
    looks: int = doc("inspections that judged its place (the hole and its ring inspected), up "
                     "to its confirmation")
    crop_jpeg: str = doc("the evidence: the frame around the hole, JPEG, base64", "")


AnyMessage = EstimateMessage | StatusMessage | StateMessage | PreviewMeta | DamageMessage
MESSAGES: tuple[type[Any], ...] = (EstimateMessage, StatusMessage, StateMessage, PreviewMeta,
                                   DamageMessage)


# -- serialisation ----------------------------------------------------------------------------
def _valid_text(text: str) -> str:
    """`text` as valid Unicode: a file name that is not UTF-8 decodes to lone surrogates
    (Python's surrogateescape), which json.dumps writes as \\udcXX escapes that strict JSON
    parsers (serde_json) refuse, losing the whole message. They become U+FFFD."""
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return "".join("\ufffd" if 0xD800 <= ord(c) <= 0xDFFF else c for c in text)
    return text


def json_value(value: Any) -> Any:
    """A JSON value under the one rounding policy (dataclasses become objects)."""
    if value is None or isinstance(value, bool):
        return value
    if isinstance(value, str):
        return _valid_text(value)
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        # + 0.0: a zero is 0.0, never -0.0 (a negated zero, or a tiny negative rounded)
        return round(value, FLOAT_DECIMALS) + 0.0 if math.isfinite(value) else None
    if isinstance(value, enum.Enum):
        return json_value(value.value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        body = {f.name: json_value(getattr(value, f.name)) for f in dataclasses.fields(value)}
        kind = getattr(value, "KIND", "")
        # A message (also one nested in another, like the state's last status) carries its
        # header; the sections of a message do not.
        return {"schema": SCHEMA_VERSION, "kind": kind, **body} if kind else body
    if isinstance(value, Mapping):
        return {str(k): json_value(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_value(v) for v in value]
    try:  # numpy scalars and the like
        return json_value(float(value))
    except (TypeError, ValueError):
        return str(value)


def to_json(message: AnyMessage) -> dict[str, Any]:
    """The JSON object of a message: `schema`, `kind`, then its fields."""
    body = json_value(message)
    assert isinstance(body, dict)
    return body


def encode(message: AnyMessage) -> bytes:
    return json.dumps(to_json(message), separators=(",", ":"), allow_nan=False).encode("utf-8")


def keys_of(cls: type[Any]) -> frozenset[str]:
    """Top-level keys of a message class on the wire."""
    names = {f.name for f in dataclasses.fields(cls)}
    return frozenset(names | {"schema", "kind"})


def schema_problems(payload: Mapping[str, Any]) -> list[str]:
    """What is wrong with a received payload compared with this schema (empty when fine).

    Extra keys are accepted (a newer publisher may add some); missing keys, another schema
    version and values of the wrong type (a string where an object belongs: what a reader
    would trip over) are reported, the last by their path.
    """
    kinds = {cls.KIND: cls for cls in (EstimateMessage, StatusMessage, StateMessage,
                                       DamageMessage)}
    cls = kinds.get(str(payload.get("kind")))
    if cls is None:
        return [f"unknown kind {payload.get('kind')!r}"]
    problems = []
    if payload.get("schema") != SCHEMA_VERSION:
        problems.append(f"schema {payload.get('schema')!r} (this reader knows {SCHEMA_VERSION})")
    missing = sorted(keys_of(cls) - payload.keys())
    if missing:
        problems.append("missing " + ", ".join(missing))
    problems.extend(type_problems(cls, payload))
    return problems


def type_problems(cls: type[Any], payload: Mapping[str, Any], path: str = "") -> list[str]:
    """The keys of `payload` whose values do not have the type `cls` gives them (nested
    message parts checked too): 'filtered: expected object, got "x"'."""
    hints = typing.get_type_hints(cls)
    problems: list[str] = []
    for f in dataclasses.fields(cls):
        if f.name not in payload:
            continue
        where = f"{path}{f.name}"
        value = payload[f.name]
        tp = hints[f.name]
        part = _dataclass_of(tp)
        if part is not None and isinstance(value, Mapping):
            problems.extend(type_problems(part, value, where + "."))
        elif not _fits(tp, value):
            problems.append(f"{where}: expected {_type_text(tp)}, got {json.dumps(value)[:40]}")
    return problems


def _dataclass_of(tp: Any) -> type[Any] | None:
    """The message part a field holds (through Optional), if it holds one."""
    options = typing.get_args(tp) if typing.get_origin(tp) in (typing.Union,
                                                             types.UnionType) else (tp,)
    parts = [a for a in options if dataclasses.is_dataclass(a) and isinstance(a, type)]
    return parts[0] if len(parts) == 1 else None


def _fits(tp: Any, value: Any) -> bool:
    """Whether a JSON value can stand for a field of type `tp`."""
    if tp is Any:
        return True
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        return any(_fits(a, value) for a in typing.get_args(tp))
    if tp is type(None):
        return value is None
    if origin is typing.Literal:
        return value in typing.get_args(tp)
    if origin in (tuple, list):
        args = [a for a in typing.get_args(tp) if a is not Ellipsis]
        return isinstance(value, list) and all(
            any(_fits(a, v) for a in args) if args else True for v in value)
    if origin is dict or tp is dict:
        return isinstance(value, Mapping)
    if dataclasses.is_dataclass(tp):
        return isinstance(value, Mapping)
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        return value in {m.value for m in tp}
    if tp is float:
        return isinstance(value, int | float) and not isinstance(value, bool)
    if tp is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if tp in (str, bool):
        return isinstance(value, tp)
    return True  # a type this reader does not judge


# -- documentation ----------------------------------------------------------------------------
def _type_text(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        parts = [_type_text(a) for a in typing.get_args(tp) if a is not type(None)]
        nullable = type(None) in typing.get_args(tp)
        return " or ".join(parts) + (" or null" if nullable else "")
    if origin is tuple:
        return "[x, y, z]"
    if origin is list:
        return "array"
    if origin is dict:
        return "object"
    if dataclasses.is_dataclass(tp):
        return "object"
    return {bool: "bool", int: "int", float: "float", str: "string"}.get(tp, "any")


def _table(cls: type[Any]) -> list[str]:
    hints = typing.get_type_hints(cls)
    lines = ["| Key | Type | Meaning |", "|-----|------|---------|"]
    for f in dataclasses.fields(cls):
        lines.append(f"| `{f.name}` | {_type_text(hints[f.name])} | {f.metadata.get('doc', '')} |")
    return lines


def _nested(cls: type[Any], path: str) -> list[tuple[str, type[Any]]]:
    """(key path, dataclass) of the objects inside `cls`'s fields, depth first."""
    found: list[tuple[str, type[Any]]] = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        for tp in (hints[f.name], *typing.get_args(hints[f.name])):
            if dataclasses.is_dataclass(tp) and isinstance(tp, type) and tp not in MESSAGES:
                inner = f"{path}.{f.name}"
                found.append((inner, tp))
                found.extend(_nested(tp, inner))
    return found


def schema_markdown() -> str:
    """The key reference of every message, as Markdown (docs/telemetry.md carries it)."""
    out: list[str] = [f"Schema version {SCHEMA_VERSION}. Every message starts with `schema` (int) "
                      "and `kind` (string); the keys of each kind follow.", ""]
    for cls in MESSAGES:
        # cleandoc: a docstring's second and later lines lose their source indentation (four
        # spaces in front of a Markdown line are a code block or a stray indent).
        out += [f"### `{cls.KIND}`", "", inspect.cleandoc(cls.__doc__ or ""), "",
                *_table(cls), ""]
        for path, inner in _nested(cls, cls.KIND):
            out += [f"#### `{path}`", "", inspect.cleandoc(inner.__doc__ or ""), "",
                    *_table(inner), ""]
    return "\n".join(out).rstrip() + "\n"
