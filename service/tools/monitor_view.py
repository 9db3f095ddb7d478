"""What `netpose monitor` knows and shows: received telemetry -> rates, link state, text lines.

Pure bookkeeping, no Zenoh and no terminal: the command feeds `MonitorState.ingest()` with
(key, bytes, receive time) and asks for lines to print. Times are the monitor's own monotonic
clock, so rates and staleness do not depend on the clocks of the vehicle.
"""

from __future__ import annotations

import collections
import json
import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from service.core.messages import (
    ALIVE_SUFFIX,
    DAMAGE_SUFFIX,
    ESTIMATE_SUFFIX,
    PREVIEW_SUFFIX,
    STATE_SUFFIX,
    STATUS_SUFFIX,
    schema_problems,
)

STREAMS = (ESTIMATE_SUFFIX, STATUS_SUFFIX, PREVIEW_SUFFIX)
# Confirmed holes in the net: rare events, listed rather than counted per second.
HOLES_SHOWN = 8


@dataclass
class StreamStats:
    """Arrivals of one stream (estimate, status or preview) of one vehicle."""

    window_s: float
    count: int = 0
    last_mono: float = -math.inf
    recent: collections.deque[float] = field(default_factory=collections.deque)

    def add(self, now_mono: float) -> None:
        self.count += 1
        self.last_mono = now_mono
        self.recent.append(now_mono)
        self._trim(now_mono)

    def _trim(self, now_mono: float) -> None:
        while self.recent and self.recent[0] < now_mono - self.window_s:
            self.recent.popleft()

    def rate_hz(self, now_mono: float) -> float:
        """Messages per second over the last window (0 when fewer than two arrived in it).
        A stream silent for more than two of its intervals is counted up to now: it showed its
        old rate for the whole window after it stopped."""
        self._trim(now_mono)
        if len(self.recent) < 2:
            return 0.0
        span = self.recent[-1] - self.recent[0]
        interval = span / (len(self.recent) - 1)
        if now_mono - self.recent[-1] > 2.0 * interval:
            span = now_mono - self.recent[0]
        return (len(self.recent) - 1) / span if span > 0 else 0.0


@dataclass
class VehicleView:
    """Latest values and stream statistics of one vehicle."""

    name: str
    window_s: float
    streams: dict[str, StreamStats] = field(default_factory=dict)
    estimate: dict[str, Any] | None = None
    status: dict[str, Any] | None = None
    preview_bytes: int = 0
    preview_meta: dict[str, Any] | None = None
    problems: set[str] = field(default_factory=set)
    holes: list[dict[str, Any]] = field(default_factory=list)  # newest last
    # Times the estimate's seq went backwards: once is a restart of the daemon; again and
    # again, two daemons publishing under one vehicle name.
    seq_backwards: deque[float] = field(default_factory=deque)
    last_seq: int | None = None
    # The daemon's liveliness token: True while it is there, False once withdrawn, None
    # before it was seen (an older daemon has none).
    alive: bool | None = None

    def stream(self, name: str) -> StreamStats:
        if name not in self.streams:
            self.streams[name] = StreamStats(self.window_s)
        return self.streams[name]

    def last_seen(self) -> float:
        return max((s.last_mono for s in self.streams.values()), default=-math.inf)


@dataclass(frozen=True)
class Received:
    """One message after decoding: what --save writes and the plot reads."""

    vehicle: str
    kind: str
    key: str
    payload: dict[str, Any] | None
    size: int
    meta: dict[str, Any] | None = None

    def record(self, recv_time_unix: float) -> dict[str, Any]:
        """The JSON-lines record: JSON payloads in full, previews as size and metadata."""
        record: dict[str, Any] = {
            "recv_time_unix": round(recv_time_unix, 6),
            "key": self.key,
            "kind": self.kind,
            "vehicle": self.vehicle,
        }
        if self.kind == PREVIEW_SUFFIX:
            record["bytes"] = self.size
            record["meta"] = self.meta
        else:
            record["payload"] = self.payload
        return record


def _decode_json(data: bytes | None) -> dict[str, Any] | None:
    if not data:
        return None
    try:
        value = json.loads(data)
    except (UnicodeDecodeError, ValueError):
        return None
    return value if isinstance(value, dict) else None


# The estimate's seq going backwards this often within the window: two publishers.
SEQ_BACKWARDS_LIMIT = 3
SEQ_WINDOW_S = 10.0


def _note_seq(view: VehicleView, seq: Any, now_mono: float) -> None:
    if not isinstance(seq, int) or isinstance(seq, bool):
        return
    if view.last_seq is not None and seq < view.last_seq:
        view.seq_backwards.append(now_mono)
    view.last_seq = seq
    while view.seq_backwards and now_mono - view.seq_backwards[0] > SEQ_WINDOW_S:
        view.seq_backwards.popleft()
    if len(view.seq_backwards) >= SEQ_BACKWARDS_LIMIT:
        view.problems.add("estimate: seq goes back and forth: two daemons publish as "
                          f"'{view.name}' (give each its own telemetry.vehicle)")


class MonitorState:
    """Everything the monitor has seen, per vehicle."""

    def __init__(self, stale_after_s: float = 3.0, window_s: float = 5.0) -> None:
        self.stale_after_s = stale_after_s
        self.window_s = window_s
        self.vehicles: dict[str, VehicleView] = {}
        self.undecodable = 0

    def ingest(
        self,
        key: str,
        data: bytes,
        now_mono: float,
        attachment: bytes | None = None,
    ) -> Received | None:
        """Account for one sample on `<prefix>/<vehicle>/<kind>`; None if not ours/unreadable."""
        parts = key.split("/")
        if len(parts) < 3:
            return None
        vehicle, kind = parts[-2], parts[-1]
        if kind not in (*STREAMS, STATE_SUFFIX, DAMAGE_SUFFIX, ALIVE_SUFFIX):
            return None
        view = self.vehicles.get(vehicle)
        if view is None:
            view = self.vehicles[vehicle] = VehicleView(vehicle, self.window_s)
        if kind == ALIVE_SUFFIX:  # data: the liveliness sample's kind, b"PUT" or b"DELETE"
            token = data.decode("ascii", errors="replace")
            view.alive = token == "PUT"
            return Received(vehicle, kind, key, {"token": token}, 0)
        if kind == PREVIEW_SUFFIX:
            meta = _decode_json(attachment)
            view.stream(kind).add(now_mono)
            view.preview_bytes = len(data)
            view.preview_meta = meta
            return Received(vehicle, kind, key, None, len(data), meta)
        payload = _decode_json(data)
        if payload is None:
            self.undecodable += 1
            view.problems.add(f"{kind}: not a JSON object")
            return None
        problems = schema_problems(payload)
        view.problems.update(f"{kind}: {p}" for p in problems)
        if kind in STREAMS:
            view.stream(kind).add(now_mono)
        if any(": expected " in p for p in problems):
            # A value of the wrong type (a foreign publisher, another version): flagged, and
            # the last good message stays on screen rather than one the views trip over.
            return Received(vehicle, kind, key, payload, len(data))
        if kind == ESTIMATE_SUFFIX:
            _note_seq(view, payload.get("seq"), now_mono)
            view.estimate = payload
        elif kind == STATUS_SUFFIX:
            view.status = payload
        elif kind == DAMAGE_SUFFIX:
            view.holes.append(payload)
        return Received(vehicle, kind, key, payload, len(data))

    def link_state(self, now_mono: float, vehicle: str | None = None) -> str:
        """'waiting' (nothing yet), 'live', or 'stale' (silent for stale_after_s); for one
        vehicle whose daemon withdrew its liveliness token, 'stopped' when its last status
        said so, 'gone' when it did not (a crash, a cut tether, a dead router)."""
        if vehicle is None:
            views = list(self.vehicles.values())
        else:
            views = [self.vehicles[vehicle]] if vehicle in self.vehicles else []
        if not views:
            return "waiting"
        if vehicle is not None and views[0].alive is False:
            status = views[0].status or {}
            return "stopped" if status.get("state") == "stopping" else "gone"
        last = max(v.last_seen() for v in views)
        return "live" if now_mono - last <= self.stale_after_s else "stale"

    def rate_hz(self, vehicle: str, stream: str, now_mono: float) -> float:
        view = self.vehicles.get(vehicle)
        if view is None or stream not in view.streams:
            return 0.0
        return view.streams[stream].rate_hz(now_mono)

    # --- text ---------------------------------------------------------------------------

    def summary(self, now_mono: float) -> str:
        """One line for all vehicles (what a non-terminal stdout gets once per second)."""
        if not self.vehicles:
            return "waiting for telemetry"
        return " | ".join(self._vehicle_summary(v, now_mono) for v in self.vehicles.values())

    def estimate_silence_s(self, view: VehicleView, now_mono: float) -> float | None:
        """How long no estimate has come, when that is longer than stale_after_s (the link may
        be live on its status alone): its last values are then no distance of now."""
        stats = view.streams.get(ESTIMATE_SUFFIX)
        if stats is None or now_mono - stats.last_mono <= self.stale_after_s:
            return None
        return now_mono - stats.last_mono

    def _vehicle_summary(self, view: VehicleView, now_mono: float) -> str:
        link = self.link_state(now_mono, view.name)
        parts = [f"{view.name} {link}"]
        parts.append(f"est {self.rate_hz(view.name, ESTIMATE_SUFFIX, now_mono):.1f}Hz")
        silence = self.estimate_silence_s(view, now_mono)
        filtered = (view.estimate or {}).get("filtered") if silence is None else None
        if filtered:
            # What the autopilot was handed first (the page's header and a ground station show
            # it), then the raw estimate with each distance named.
            parts.append(f"[{filtered.get('state') or '-'}] ap: "
                         + _autopilot_text(filtered, view.status))
        parts.append(_estimate_text(view.estimate) if silence is None
                     else f"no estimate for {silence:.1f} s")
        parts.append(f"status {self.rate_hz(view.name, STATUS_SUFFIX, now_mono):.1f}Hz")
        parts.append(_status_text(view.status))
        if view.holes:
            parts.append(f"holes {len(view.holes)} (last: {hole_text(view.holes[-1])})")
        return " ".join(p for p in parts if p)

    def render(self, now_mono: float) -> list[str]:
        """A screenful of lines for a terminal."""
        lines = ["netpose monitor"]
        if not self.vehicles:
            return [*lines, "", "waiting for telemetry ..."]
        for view in self.vehicles.values():
            lines.append("")
            lines.append(f"vehicle {view.name}: link {self.link_state(now_mono, view.name)}")
            for stream in STREAMS:
                stats = view.streams.get(stream)
                if stats is None:
                    lines.append(f"  {stream:<9} none yet")
                    continue
                age = now_mono - stats.last_mono
                lines.append(
                    f"  {stream:<9} {stats.rate_hz(now_mono):6.2f} Hz  {stats.count:7d} msgs"
                    f"  last {age:5.1f} s ago"
                )
            silence = self.estimate_silence_s(view, now_mono)
            estimate = (view.estimate or {}) if silence is None else {}
            filtered = estimate.get("filtered") or {}
            if filtered:
                # First what the autopilot steers by (what the page's header and a ground
                # station show); the monitor led with the perpendicular distance, 6-18 % off it
                # at 20-35 deg of tilt, under the same letter "d" (pilot review).
                lines.append("  autopilot " + _autopilot_text(filtered, view.status))
            if silence is not None:
                # The last estimate is history: no distance, filter or autopilot of now.
                lines.append(f"  estimate  no estimate for {silence:.1f} s (last: "
                             f"{_estimate_text(view.estimate) or '-'})")
            else:
                lines.append("  estimate  " + (_estimate_text(view.estimate) or "-"))
            if filtered:
                lines.append(
                    f"  filtered  {filtered.get('state') or '-'}  valid {filtered.get('valid')}"
                    f"  perp {_fmt(filtered.get('distance_m'))}"
                    f" +/- {_fmt(sigma_of(filtered, 'distance'), 3)} m"
                    f"  closing {_fmt(filtered.get('closing_speed_mps'), 2)} m/s"
                    " (+ toward the net)"
                )
            latency = estimate.get("latency_ms") or {}
            if latency:
                lines.append(
                    f"  latency   estimator {_fmt(latency.get('estimator_total'), 1)} ms"
                    f"  frame->publish {_fmt(latency.get('frame_to_publish'), 1)} ms"
                )
            lines.append("  status    " + (_status_text(view.status) or "-"))
            if view.preview_meta is not None:
                lines.append(
                    f"  preview   {view.preview_meta.get('width')}x"
                    f"{view.preview_meta.get('height')}  {view.preview_bytes} bytes"
                )
            if view.holes:
                lines.append(f"  net damage: {len(view.holes)} hole(s) confirmed")
                for hole in view.holes[-HOLES_SHOWN:][::-1]:
                    lines.append("    " + hole_text(hole))
            for problem in sorted(view.problems):
                lines.append(f"  ! {problem}")
        return lines


def _fmt(value: Any, digits: int = 2) -> str:
    if isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value):
        return f"{value:.{digits}f}"
    return "-"


def hole_text(hole: Mapping[str, Any]) -> str:
    """'hole 3: 6x4 cm, 4 cells, ahead-left at 1.10 m, conf 0.66'."""
    def cm(value: Any) -> str:
        if isinstance(value, int | float) and math.isfinite(value):
            return str(max(1, round(value * 100)))
        return "?"

    return (f"hole {hole.get('hole_id')}: {cm(hole.get('width_m'))}x{cm(hole.get('height_m'))}"
            f" cm, {hole.get('cells')} cells, {hole.get('bearing')} at "
            f"{_fmt(hole.get('range_m'))} m, conf {_fmt(hole.get('confidence'))}")


def sigma_of(message: Mapping[str, Any], quantity: str) -> Any:
    """A distance's sigma as a measurement of the world (the scale's error in it), or the
    image's alone from a daemon that does not send that yet."""
    total = message.get(f"sigma_{quantity}_total_m")
    return total if total is not None else message.get(f"sigma_{quantity}_m")


def _estimate_text(estimate: Mapping[str, Any] | None) -> str:
    if estimate is None:
        return ""
    if not estimate.get("detected"):
        reason = estimate.get("reason") or "no net"
        if estimate.get("net_seen"):
            # The net is there; its range is too uncertain to be a distance (none is sent).
            return (f"net seen, ~{_fmt(estimate.get('approx_range_m'))}+/-"
                    f"{_fmt(estimate.get('approx_sigma_range_m'))} m, no distance "
                    f"({reason.split(':')[0]})")
        return f"no net ({reason})"
    return (
        f"perp {_fmt(estimate.get('distance_m'))}+/-{_fmt(sigma_of(estimate, 'distance'), 3)} m"
        f" axis {_fmt(estimate.get('range_m'))} m tilt {_fmt(estimate.get('tilt_deg'), 1)} deg"
        f" conf {_fmt(estimate.get('confidence'))}"
    )


def _autopilot_text(filtered: Mapping[str, Any],
                    status: Mapping[str, Any] | None = None) -> str:
    """What the autopilot was handed with this frame: the estimate's `perp` is the
    perpendicular distance, and the autopilot may get the one along the camera's axis
    (service.autopilot_distance), the estimate's `axis`.
    With the link to the autopilot down, or none heard, what is handed over reaches nothing,
    and that is said with it (the daemon's latest status)."""
    told = _handed_text(filtered)
    link = (status or {}).get("autopilot") or {}
    # The net-hold applet's input beside the distance: "TRACKING, 1.00 m" said nothing of
    # why net hold did not act while its plane was held (pilot review).
    plane = link.get("net_plane")
    net_hold = f"; net hold input: {plane}" if isinstance(plane, str) and plane != "off" else ""
    if told == "nothing sent" or not link:
        return told + net_hold
    if link.get("state") == "lost":
        return f"{told}, NOT reaching it: autopilot link lost{net_hold}"
    if link.get("state") == "waiting":
        return f"{told}, NOT reaching one: no autopilot heard{net_hold}"
    if link.get("sending_distance") is False:
        return f"{told}, NOT being sent now{net_hold}"
    return told + net_hold


def _handed_text(filtered: Mapping[str, Any]) -> str:
    told = filtered.get("autopilot")
    if told == "good":
        along = filtered.get("autopilot_along")
        if along is None:  # a daemon from before the key: it says only that one is sent
            return "a distance is sent"
        kind = {"optical_axis": "along the camera axis",
                "perpendicular": "perpendicular to the net"}.get(str(along), str(along))
        return f"{_fmt(filtered.get('autopilot_distance_m'))} m {kind}"
    if told == "too_close":
        return "too close (below the rangefinder minimum)"
    return "nothing sent"


def _status_text(status: Mapping[str, Any] | None) -> str:
    if status is None:
        return ""
    camera = status.get("frame_source") or {}
    autopilot = status.get("autopilot") or {}
    telemetry = status.get("telemetry") or {}
    cpu = status.get("cpu") or {}
    text = (
        f"{status.get('state')} cam {camera.get('state')} {_fmt(camera.get('fps'), 1)} fps"
        f" dropped {camera.get('dropped')} ap {autopilot.get('state')}"
        f" cpu {_fmt(cpu.get('process_percent'), 0)}%"
    )
    searching = (status.get("estimator") or {}).get("searching_hz")
    if searching:
        text += f" searching {_fmt(searching, 0)}/s (no net)"
    inspection = status.get("inspection")
    if isinstance(inspection, Mapping):
        # How much was looked at, beside the holes: none reported is no proof of an intact net.
        text += (f" inspected {inspection.get('inspected_frames')} frames"
                 f" ({inspection.get('judged_cells')} cells), {inspection.get('holes')} holes")
    if telemetry.get("queue_dropped"):
        text += f" tx-dropped {telemetry.get('queue_dropped')}"
    return text
