"""The intervals between consecutive frame times, over a window: how fast frames really come.

Both the filter (its coasting window, service/core/tracking.py) and the MAVLink link (its
freshness limit, drivers/distance_gate.py) judge time in units of the measured frame interval
rather than fixed seconds, so that a loaded CPU's three frames a second are not read as a
stall. Times come from the frames (capture or frame-loop time), never from a clock read here.
"""

from __future__ import annotations

import collections
import statistics
from collections.abc import Iterable


class FrameIntervals:
    """The last `window` positive intervals between the times passed to `add`; typical
    (median) and worst (max) once `min_count` of them have been measured."""

    def __init__(self, window: int, min_count: int) -> None:
        self._min_count = min_count
        self._intervals: collections.deque[float] = collections.deque(maxlen=window)
        self.last: float | None = None

    def add(self, t: float) -> None:
        """A frame at time `t`; a time not after the last one adds no interval."""
        if self.last is not None and t > self.last:
            self._intervals.append(t - self.last)
        self.last = t

    @property
    def measured(self) -> bool:
        return len(self._intervals) >= self._min_count

    def median(self) -> float | None:
        return statistics.median(self._intervals) if self.measured else None

    def max(self) -> float | None:
        return max(self._intervals) if self.measured else None

    def clear(self) -> None:
        self._intervals.clear()
        self.last = None

    def values(self) -> list[float]:
        """The intervals, oldest first (for a saved state)."""
        return list(self._intervals)

    def restore(self, values: Iterable[float], last: float | None) -> None:
        self._intervals.clear()
        self._intervals.extend(float(v) for v in values)
        self.last = None if last is None else float(last)
