"""When the link sends the distance: fresh enough, steady, and stopped at once when in doubt.

ArduPilot drops a MAVLink rangefinder 0.5 s after its last message, so the link repeats the
newest reading at `rate_hz`. How old may that reading get before repeating it would be a lie?
A fixed limit is wrong on both sides: on a loaded Pi that processes 3 frames/s, capture-to-link
latency plus the gap between frames exceeds 0.3 s in normal operation, and a fixed 0.3 s made
the rangefinder come and go every 100-200 ms. So the limit follows what is measured:

    freshness = clamp(MARGIN * (max latency + max frame interval) + 2 send periods,
                      floor, ceiling)

where latency is capture -> hand-over to the link and the interval is between the capture
times of consecutive readings, both the worst of the last `WINDOW` readings (a few seconds:
one slow frame of a loaded machine must not cut the distance), with a margin on top; `ceiling`
is `mavlink.max_age_s`, the oldest distance the configuration ever accepts.

Until a few frame intervals have been measured the limit is the ceiling.

Sending starts and stops with hysteresis: it stops at once when the reading says nothing is
believed (`RangeStatus.NONE`: never delayed, that is the safety rule) or when it is older than
the freshness limit; it starts again only after the readings have stayed well inside the limit
(3/4 of it) for `settle_s`, and not sooner than `min_change_interval_s` after the last change.
A reading that wavers around the limit therefore flips the output at most once a second.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass, field

from service.core.frame_intervals import FrameIntervals
from service.core.readings import RangeReading

WINDOW = 64
MARGIN = 1.5
START_FRACTION = 0.75
# Frame intervals needed before the measured limit replaces the ceiling.
MIN_INTERVALS = 4


@dataclass
class DistanceGate:
    ceiling_s: float
    send_period_s: float
    floor_s: float = 0.25
    min_change_interval_s: float = 1.0
    settle_s: float = 0.5
    sending: bool = False
    changes: int = 0
    _latencies: collections.deque[float] = field(
        default_factory=lambda: collections.deque(maxlen=WINDOW))
    _intervals: FrameIntervals = field(
        default_factory=lambda: FrameIntervals(WINDOW, MIN_INTERVALS))
    _last_change: float = -float("inf")
    _fresh_since: float | None = None

    def observe(self, reading: RangeReading, handed_over: float) -> None:
        """A new reading reached the link at `handed_over` (the frame loop's clock)."""
        self._intervals.add(reading.t_capture)
        self._latencies.append(max(0.0, handed_over - reading.t_capture))

    @property
    def frame_interval_s(self) -> float | None:
        """The typical interval between readings (their capture times), once measured."""
        return self._intervals.median()

    @property
    def freshness_s(self) -> float:
        """The age beyond which the newest reading is not repeated."""
        worst_interval = self._intervals.max()
        if worst_interval is None:
            return self.ceiling_s
        worst = max(self._latencies) + worst_interval
        measured = MARGIN * worst + 2.0 * self.send_period_s
        return min(self.ceiling_s, max(self.floor_s, measured))

    def decide(self, reading: RangeReading, now: float) -> bool:
        """Whether to send `reading` at `now`; counts the changes."""
        age = now - reading.t_capture
        limit = self.freshness_s
        if self.sending:
            keep = reading.sendable and age <= limit
            if not keep:
                self.sending = False
                self._change(now)
        else:
            if reading.sendable and age <= START_FRACTION * limit:
                if self._fresh_since is None:
                    self._fresh_since = now
            else:
                self._fresh_since = None
            first = self.changes == 0  # the first start needs no settling
            settled = self._fresh_since is not None and (
                first or now - self._fresh_since >= self.settle_s)
            if settled and now - self._last_change >= self.min_change_interval_s:
                self.sending = True
                self._fresh_since = None
                self._change(now)
        return self.sending

    def _change(self, now: float) -> None:
        self.changes += 1
        self._last_change = now
