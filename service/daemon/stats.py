"""Counters of the frame loop: only ever added to, read without being reset.

Reports over a period (the 1 Hz status, the summary line) take two snapshots and subtract;
latencies are kept in a bounded window with their times, so "the last period" is a query, not a
reset. Memory stays flat however long the service runs.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass

import numpy as np

from service.pipeline import PipelineResult

# Latencies kept for percentiles: at 30 frames/s, over four minutes.
LATENCY_WINDOW = 8192


@dataclass(frozen=True)
class StatsSnapshot:
    frames: int  # measured by the estimator
    skipped: int  # dropped before the loop could take them
    detected: int
    errors: int
    paced: int = 0  # taken, but not measured: a paced search in open water

    def minus(self, earlier: StatsSnapshot) -> StatsSnapshot:
        return StatsSnapshot(
            frames=self.frames - earlier.frames,
            skipped=self.skipped - earlier.skipped,
            detected=self.detected - earlier.detected,
            errors=self.errors - earlier.errors,
            paced=self.paced - earlier.paced,
        )


@dataclass(frozen=True)
class LatencyStats:
    count: int
    mean_ms: float | None
    p50_ms: float | None
    p99_ms: float | None
    max_ms: float | None


class LoopStats:
    """What the loop did: frames, gaps, detections, estimator errors, latencies."""

    def __init__(self) -> None:
        self.frames = 0
        self.skipped = 0
        self.detected = 0
        self.errors = 0
        self.paced = 0
        # Net inspection: frames searched for holes and the cells judged in them.
        self.inspected = 0
        self.judged_cells = 0
        self.last_error = ""
        self._last_index: int | None = None
        # (time the result was handed to the outputs, capture -> hand-over in ms)
        self._latencies: collections.deque[tuple[float, float]] = collections.deque(
            maxlen=LATENCY_WINDOW
        )

    def record(self, result: PipelineResult, handed_over: float) -> None:
        if result.index is None:
            return
        if self._last_index is not None and result.index > self._last_index + 1:
            self.skipped += result.index - self._last_index - 1
        self._last_index = result.index
        if result.unmeasured:
            self.paced += 1
            return
        self.frames += 1
        self.detected += result.detected
        damage = result.damage
        if damage is not None and damage.inspected:
            self.inspected += 1
            self.judged_cells += damage.scan.inspected_cells if damage.scan is not None else 0
        if result.error:
            self.errors += 1
            self.last_error = result.error
        self._latencies.append((handed_over, (handed_over - result.t) * 1e3))

    def snapshot(self) -> StatsSnapshot:
        return StatsSnapshot(self.frames, self.skipped, self.detected, self.errors, self.paced)

    def latency_since(self, since: float) -> LatencyStats:
        """Latency of the frames handed over after `since` (within the kept window)."""
        values = [ms for t, ms in self._latencies if t > since]
        if not values:
            return LatencyStats(0, None, None, None, None)
        arr = np.asarray(values)
        return LatencyStats(
            count=len(values),
            mean_ms=float(arr.mean()),
            p50_ms=float(np.percentile(arr, 50)),
            p99_ms=float(np.percentile(arr, 99)),
            max_ms=float(arr.max()),
        )
