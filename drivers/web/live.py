"""The hand-over from the frame loop to the page's event loop, and what each page is sent.

The frame loop calls `LiveFeed.put_*` (a lock, an append, at most one wake-up of the event loop
per batch: microseconds). The event loop takes everything in one go, keeps the plot history,
and fills each client's slots. A client's slots hold only the newest estimate, status, frame
and recording state, plus a short bounded list of one-off events: a page that reads slowly or
not at all loses old data, never memory, and never delays the loop or the other pages.
"""

from __future__ import annotations

import asyncio
import math
import threading
from collections import deque
from collections.abc import Callable
from typing import Any

from service.core.messages import DamageMessage, EstimateMessage, StatusMessage

# Estimates waiting for the event loop; more arrive only if it stalls (then the oldest go).
PENDING_ESTIMATES = 256
# Plot history: at most one point per this many seconds, plus every change of detection or
# filter validity (so the gaps stay where they were).
HISTORY_STEP_S = 0.2
EVENTS_PER_CLIENT = 16


class LiveFeed:
    """Thread-safe inbox filled by the frame loop and emptied by the event loop."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._estimates: deque[EstimateMessage] = deque(maxlen=PENDING_ESTIMATES)
        self._status: StatusMessage | None = None
        self._damage: list[DamageMessage] = []
        self._frame: tuple[Any, Any, EstimateMessage] | None = None
        self._wake: Callable[[], None] | None = None
        self._wake_pending = False

    def attach(self, wake: Callable[[], None] | None) -> None:
        """`wake` is called (from the loop thread) when something new arrived; it must only
        schedule work (loop.call_soon_threadsafe)."""
        with self._lock:
            self._wake = wake
            self._wake_pending = False

    def put_frame(self, frame: Any, result: Any, message: EstimateMessage) -> None:
        with self._lock:
            self._estimates.append(message)
            self._frame = (frame, result, message)
            wake = self._take_wake()
        if wake is not None:
            wake()

    def put_status(self, message: StatusMessage) -> None:
        with self._lock:
            self._status = message
            wake = self._take_wake()
        if wake is not None:
            wake()

    def put_damage(self, message: DamageMessage) -> None:
        with self._lock:
            self._damage.append(message)
            wake = self._take_wake()
        if wake is not None:
            wake()

    def take_damage(self) -> list[DamageMessage]:
        """Holes confirmed since the last call (the event loop takes them with the rest)."""
        with self._lock:
            holes, self._damage = self._damage, []
            return holes

    def take(self) -> tuple[list[EstimateMessage], StatusMessage | None,
                            tuple[Any, Any, EstimateMessage] | None]:
        """Everything new since the last call (the newest frame is kept for the renderer)."""
        with self._lock:
            estimates = list(self._estimates)
            self._estimates.clear()
            status, self._status = self._status, None
            self._wake_pending = False
            return estimates, status, self._frame

    def newest_frame(self) -> tuple[Any, Any, EstimateMessage] | None:
        with self._lock:
            return self._frame

    def _take_wake(self) -> Callable[[], None] | None:
        if self._wake is None or self._wake_pending:
            return None
        self._wake_pending = True
        return self._wake


def _tilt_of(normal: tuple[float, float, float] | None) -> float | None:
    if normal is None:
        return None
    z = abs(normal[2])
    return math.degrees(math.acos(min(1.0, z))) if math.isfinite(z) else None


def plot_point(message: EstimateMessage) -> list[float | str | None]:
    """[capture time (monotonic s), raw distance, raw tilt, distance sent to the autopilot,
    filtered tilt, seen range, which distance]: None where there is nothing to plot.

    The distances are the one the autopilot gets (`filtered.autopilot_along`, which follows
    `service.autopilot_distance`): the raw estimate's range along the camera axis or its
    perpendicular distance, and the distance this frame handed to the autopilot (None when
    nothing was: no net, the filter does not believe its value, too close). The seen range is a
    net seen but too uncertain for a distance (its refused range along the axis; the page draws
    it hollow). The last place names the distance ("optical_axis", "perpendicular"; None
    without a filter: then the perpendicular one). The page's `plotPoint` builds the same."""
    f = message.filtered
    valid = f is not None and f.valid
    along = f.autopilot_along if f is not None else None
    raw = message.range_m if along == "optical_axis" else message.distance_m
    t = message.frame_time_mono if message.frame_time_mono is not None else message.time_mono
    seen = not message.detected and message.net_seen
    return [
        round(t, 3),
        raw if message.detected else None,
        message.tilt_deg if message.detected else None,
        f.autopilot_distance_m if f is not None else None,
        _tilt_of(f.normal) if valid and f is not None else None,
        message.approx_range_m if seen else None,
        along,
    ]


def _time_of(point: list[float | str | None]) -> float:
    t = point[0]
    return t if isinstance(t, float) else 0.0


class PlotHistory:
    """The last `span_s` seconds of plot points, thinned to about 1 / HISTORY_STEP_S per s."""

    def __init__(self, span_s: float) -> None:
        self.span_s = span_s
        self._points: deque[list[float | str | None]] = deque()
        self._last_kept: list[float | str | None] | None = None

    def add(self, message: EstimateMessage) -> None:
        point = plot_point(message)
        last = self._last_kept
        t = point[0]
        assert isinstance(t, float)
        if last is not None:
            last_t = last[0]
            assert isinstance(last_t, float)
            # Where a gap starts or ends, and where the distance sent changes kind (a reload).
            same_gaps = (all((point[i] is None) == (last[i] is None) for i in (1, 3, 5))
                         and point[6] == last[6])
            if same_gaps and t - last_t < HISTORY_STEP_S:
                return
        self._points.append(point)
        self._last_kept = point
        while self._points and _time_of(self._points[0]) < t - self.span_s:
            self._points.popleft()

    def points(self) -> list[list[float | str | None]]:
        return list(self._points)


class ClientSlots:
    """What is waiting to be sent to one page: the newest of each kind, and a few events."""

    def __init__(self) -> None:
        self.texts: dict[str, str] = {}
        self.events: deque[str] = deque(maxlen=EVENTS_PER_CLIENT)
        self.jpeg: bytes | None = None
        self.wake = asyncio.Event()
        self.frames_sent = 0
        self.frames_replaced = 0

    def set_text(self, kind: str, text: str) -> None:
        self.texts[kind] = text
        self.wake.set()

    def add_event(self, text: str) -> None:
        self.events.append(text)
        self.wake.set()

    def set_jpeg(self, jpeg: bytes) -> None:
        if self.jpeg is not None:
            self.frames_replaced += 1
        self.jpeg = jpeg
        self.wake.set()

    def take(self) -> tuple[list[str], bytes | None]:
        texts = list(self.events) + list(self.texts.values())
        self.events.clear()
        self.texts.clear()
        jpeg, self.jpeg = self.jpeg, None
        self.wake.clear()
        return texts, jpeg
