"""Which frames the estimator looks at while no net is in view.

With a net in view every frame is measured: the distance is what the autopilot flies on. In
open water (the start of a dive, a turn away from the net, a pass under the cage) there is
nothing to measure, yet a cold search costs as much as a tracked frame or more (12-15 ms a
frame on a desktop core, 3-5 times that on a Pi 4), so at 30 frames/s the search alone would
hold a Pi core that BlueOS's video stream and router need. After `HOLD_S` of frames that
showed no sign of a net, the estimator looks at `search_hz` frames a second at most; the others
are read (the source, its watchdog, a recording see every frame) and passed to the filter as
time without a measurement. The first frame that shows a sign of the net (measured, seen
without a distance, or too close) ends the pacing: its successor is measured, tracked, at the
camera's rate. A net that comes into view is thus found at most 1/search_hz later.

Pure: time is the frames' capture time, so a replay paces exactly as the daemon did.
"""

from __future__ import annotations

from service.core.tracking import TrackState
from service.pipeline import PipelineResult

# Frames keep being measured at the camera's rate for this long after the last sign of a net:
# a net lost behind a passing fish, or for a turn of the vehicle, comes back at once.
HOLD_S = 2.0
# A frame is due when at least this share of the search interval has passed since the last
# measured frame: capture stamps jitter, and 30 frames/s at 10 Hz must be every third frame,
# not every fourth.
DUE_SHARE = 0.9


class SearchPacer:
    """Says, frame by frame, whether the estimator should look (see the module doc)."""

    def __init__(self, search_hz: float, hold_s: float = HOLD_S) -> None:
        self.search_hz = search_hz
        self.hold_s = hold_s
        self._sign_t: float | None = None  # capture time of the last frame with a sign of a net
        self._measured_t: float | None = None  # capture time of the last measured frame
        self.pacing = False  # whether the last frame asked about fell in a paced search

    def due(self, t: float) -> bool:
        """Whether the frame captured at `t` is to be measured."""
        if self.search_hz <= 0.0:
            self.pacing = False
            return True
        if self._sign_t is None:
            self._sign_t = t  # the service just started: search at full rate for a while
        self.pacing = t - self._sign_t >= self.hold_s
        if not self.pacing or self._measured_t is None:
            return True
        return t - self._measured_t >= DUE_SHARE / self.search_hz

    def measured(self, result: PipelineResult) -> None:
        """The pipeline's result of a frame that was measured."""
        self._measured_t = result.t
        estimate = result.estimate
        sign = result.track.state is not TrackState.LOST or (
            estimate is not None and (estimate.net_seen or estimate.too_close))
        if sign:
            self._sign_t = result.t
            self.pacing = False

    def why(self, t: float) -> str:
        """The reason given for the frame captured at `t`, not measured: how long the net has
        been out of view by now (it said "for 2 s", the hold, however long it had been)."""
        gone_s = self.hold_s if self._sign_t is None else max(self.hold_s, t - self._sign_t)
        return (f"not measured: no net in view for {gone_s:.0f} s, searching at "
                f"{self.search_hz:g} frames/s")
