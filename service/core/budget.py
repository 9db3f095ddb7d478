"""How much work per frame the estimator may do: the budget level, chosen from measured time.

On a busy Raspberry Pi the full estimator can take longer than the camera's frame interval.
The loop then only ever sees the newest frame (older ones are dropped), so every frame costs
its capture-to-result latency plus a whole processing time of age before the next one: the
autopilot's distance goes stale, and ArduPilot drops a rangefinder after 500 ms. Fresh
readings matter more than processing every frame at full precision, so when the loop falls
behind the camera the estimator is asked for less (`NetEstimator.estimate(budget=...)`: skipped
second rectified pass, fewer ROIs, a coarser pyramid level; docs/estimator.md).

"Behind" means both: a frame takes more than `load` of the camera's interval, and the source
drops frames for it (a source that renders or reads on demand, such as `sim:`, never drops
one; it only runs slower, and less work would buy nothing). A configured CPU share
(`max_cpu`) is a second limit: a tracked frame may take at most that share of the camera's
interval, dropped frames or not, so the loop leaves the rest of the core to BlueOS's video
stream.

A leaner level must keep seeing the net: one whose share of frames with a net falls well
below a richer level's is left at once for the next richer level, one step (not straight back
to the richer level it was judged against: on a CPU that could only afford the leaner level, a
frame of several levels' more work stalls the distance for a second), and it and the leaner
levels are blocked for a while (doubling each time it happens again). If the next level loses
the net too, it steps again.

The controller is pure: the daemon hands it each processed frame's capture time, frame number
and the loop time that frame took (a measurement), and uses the level it returns for the next
frame. The level is recorded in every estimate message, so a replay can tell which work each
frame got. Under a test's fake clock the measured time is zero and the level stays put.

Hysteresis keeps the level from hunting: up only when the current level has been measured on
a few frames and is over budget for a second, and then straight to the first level predicted
to fit; down one level at a time, only after a longer hold, and only when the richer level is
predicted to fit with a margin. A prediction is the level's own measured cost when recent,
else the current cost scaled by a typical step ratio per level.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass
from typing import Literal

from service.core.errors import ConfigError

# The estimator's levels: 0 = full work ... LEVELS - 1 = least work.
LEVELS = 4
FRAMES_TO_JUDGE = 3  # frames measured at a level before it is judged
UP_HOLD_S = 1.0  # a level is kept at least this long before more is cut
DOWN_HOLD_S = 5.0  # ... and this long before work is added back
DOWN_MARGIN = 0.7  # a richer level must be predicted to use at most this share of the budget
STEP_RATIO = 1.6  # assumed cost ratio between neighbouring levels when not measured lately
COST_MEMORY_S = 30.0  # a level's measured cost is trusted this long after it was last used
COST_SMOOTHING = 0.25  # weight of a new frame in a level's running cost
# Weight of a new frame in a level's running share of frames with a net: about ten frames'
# memory. At 0.25 (four frames), three misses in a row read as a loss (0.42); a lean level
# that saw 98 % of the soak benchmark's frames misses a few in a row where the net is far,
# and was left and blocked for 30 s, costing a capped loop its CPU share. Against a richer
# level that saw every frame, five misses in a row read as a loss (0.59); the price is a
# slower exit from a level that really lost the net: five to seven frames instead of three,
# half a second at the 11 frames/s of a quarter of a core.
DETECTION_SMOOTHING = 0.1
INTERVAL_WINDOW = 31  # frames over which the camera's frame interval is taken (median)


@dataclass(frozen=True)
class BudgetSettings:
    """`[budget]`: work per frame on a slow or busy CPU (docs/daemon.md)."""

    # "auto": the daemon lowers the work when it falls behind the camera and raises it when
    # there is room; "fixed": always `level`.
    mode: Literal["auto", "fixed"] = "auto"
    # The fixed level, or where "auto" starts (0 = full work, 3 = least).
    level: int = 0
    # The most "auto" may cut.
    max_level: int = LEVELS - 1
    # Share of the camera's frame interval a frame may take before the loop counts as behind.
    load: float = 0.9
    # While no net has been in view for a while, the estimator looks at this many frames a
    # second at most (0: every frame). Open water costs as much CPU as a net (a cold search,
    # 12-15 ms a frame on a desktop core, 3-5 times that on a Pi) and buys nothing but an
    # acquisition up to 1/search_hz s sooner; the CPU is BlueOS's video stream's
    # (service/daemon/search_pace.py).
    search_hz: float = 5.0
    # Share of one CPU core the frame loop may spend on a tracked net (1.0: as much as keeping
    # up with the camera takes). Below that, the work per frame is cut until a tracked frame
    # (its loop time, inspection and publishing included; searches are not capped) takes at
    # most this share of the camera's frame interval, whether or not the loop keeps up:
    # BlueOS's video stream and services share the Pi's cores.
    max_cpu: float = 1.0

    def __post_init__(self) -> None:
        if self.mode not in ("auto", "fixed"):
            raise ConfigError("budget.mode", "must be \"auto\" or \"fixed\"")
        if not 0 <= self.level < LEVELS:
            raise ConfigError("budget.level", f"must be 0..{LEVELS - 1}")
        if not 0 <= self.max_level < LEVELS:
            raise ConfigError("budget.max_level", f"must be 0..{LEVELS - 1}")
        if self.mode == "auto" and self.level > self.max_level:
            raise ConfigError("budget.level", "must not exceed budget.max_level")
        if not 0.3 <= self.load <= 1.0:
            raise ConfigError("budget.load", "must be 0.3..1.0")
        if not (self.search_hz == 0.0 or 0.5 <= self.search_hz <= 120.0):
            raise ConfigError("budget.search_hz", "must be 0 (every frame) or 0.5..120")
        if not 0.05 <= self.max_cpu <= 1.0:
            raise ConfigError("budget.max_cpu", "must be 0.05..1.0 (a share of one core)")


@dataclass
class _Cost:
    seconds: float  # running loop time of this level's tracked frames (NaN until one came)
    timed: int  # tracked frames measured since the level was last judged
    frames: int  # frames of any kind since then
    last_t: float
    detected: float  # running share of this level's frames with a net
    seen: int = 0  # frames with a net at this level: a yardstick must have seen the net


# A level whose running detection share falls this far below a richer level's, while that
# one saw the net at least MIN_DETECTED of the time, loses the net: it and the leaner levels
# are not used for BLOCK_S, doubled each time the same level loses it again up to MAX_BLOCK_S
# (a leaner estimate that finds nothing keeps no distance fresh; retrying it costs frames).
DETECTION_LOSS = 0.4
MIN_DETECTED = 0.5
BLOCK_S = 30.0
MAX_BLOCK_S = 600.0


class BudgetController:
    """Picks the estimator's budget level from measured frame times (see the module doc)."""

    def __init__(self, settings: BudgetSettings) -> None:
        self.settings = settings
        self.level = settings.level
        self._costs: dict[int, _Cost] = {}
        self._intervals: collections.deque[float] = collections.deque(maxlen=INTERVAL_WINDOW)
        self._last: tuple[float, int] | None = None
        self._drops: collections.deque[int] = collections.deque(maxlen=2 * FRAMES_TO_JUDGE)
        self._changed_at: float | None = None
        self._blocked: dict[int, tuple[float, float]] = {}  # level: (until, block length)
        self.changes = 0
        self.why = ""  # the reason for the last change, for the log

    @property
    def frame_interval_s(self) -> float | None:
        """The camera's frame interval (median over recent frames), None until known."""
        if not self._intervals:
            return None
        ordered = sorted(self._intervals)
        return ordered[len(ordered) // 2]

    def cost_s(self, level: int) -> float | None:
        """The measured loop time per tracked frame at `level` (None if never measured)."""
        cost = self._costs.get(level)
        return None if cost is None or not math.isfinite(cost.seconds) else cost.seconds

    def frame(self, t_capture: float, index: int, work_s: float, detected: bool = True,
              tracked: bool = True) -> int:
        """One processed frame at the current level: its capture time, the source's frame
        number, the loop time it took, whether the estimator saw the net and whether it tracked
        it (no scale search ran: `NetEstimate.searched` false). Returns the level for the next
        frame.

        Only tracked frames' times judge the level: they are the frames whose distance the
        autopilot flies on. A cold search (the net not found yet, or found again) costs two to
        ten times as much and gives the autopilot nothing fresh whatever the level; judged by
        its frames, the start of `make run` dropped to the leanest level for its first 30 s on
        a desktop core. Every frame counts for whether a level keeps seeing the net."""
        self._note_interval(t_capture, index)
        if math.isfinite(work_s) and work_s >= 0.0:
            cost = self._costs.get(self.level)
            if cost is None or t_capture - cost.last_t > COST_MEMORY_S:
                # A level new to this view is taken to see the net until its own frames say
                # otherwise: started from its first frame alone, a level entered on a miss
                # would read as having lost the net at once.
                cost = _Cost(math.nan, 0, 0, t_capture, 1.0)
                self._costs[self.level] = cost
            cost.detected += DETECTION_SMOOTHING * (float(detected) - cost.detected)
            cost.seen += int(detected)
            cost.frames += 1
            cost.last_t = t_capture
            if tracked:
                cost.seconds = work_s if not math.isfinite(cost.seconds) else (
                    cost.seconds + COST_SMOOTHING * (work_s - cost.seconds))
                cost.timed += 1
        if self._changed_at is None:
            self._changed_at = t_capture
        if self.settings.mode == "auto":
            self._decide(t_capture)
        return self.level

    def skipped(self, t_capture: float, index: int) -> None:
        """A frame the loop chose not to measure (service/daemon/search_pace.py): the next
        measured frame's gap starts here, so frames skipped by choice are not taken for frames
        the source dropped because the loop was behind."""
        self._last = (t_capture, index)

    def reset(self, settings: BudgetSettings) -> None:
        """New settings (a reload): measured costs stay, the level starts over."""
        self.settings = settings
        self._set(settings.level, self._changed_at or 0.0)

    # -- internals -------------------------------------------------------------------------
    def _note_interval(self, t: float, index: int) -> None:
        if self._last is not None:
            t0, i0 = self._last
            if index > i0 and t > t0:
                # Frames dropped while the loop was busy still count: index - i0 camera frames.
                self._intervals.append((t - t0) / (index - i0))
                self._drops.append(index - i0 - 1)
        self._last = (t, index)

    def _decide(self, t: float) -> None:
        interval = self.frame_interval_s
        cost = self._costs.get(self.level)
        if interval is None or cost is None or cost.frames < FRAMES_TO_JUDGE:
            return
        # A tracked frame may take `load` of the camera's interval before the loop is behind,
        # and `max_cpu` of it before the loop holds more of a core than it was given.
        behind_at = self.settings.load * interval
        cap = self.settings.max_cpu * interval if self.settings.max_cpu < 1.0 else math.inf
        budget = min(behind_at, cap)
        held = t - (self._changed_at if self._changed_at is not None else t)
        # The nearest richer level measured lately: the yardstick of this one's detections.
        richer_level = next((k for k in range(self.level - 1, -1, -1)
                             if k in self._costs and t - self._costs[k].last_t <= COST_MEMORY_S),
                            None)
        if richer_level is not None:
            richer = self._costs[richer_level]
            if (richer.detected >= MIN_DETECTED and richer.seen >= FRAMES_TO_JUDGE
                    and cost.detected < richer.detected - DETECTION_LOSS):
                block = self._block_from(self.level, t)
                self._set(self.level - 1, t,
                          f"level {self.level} loses the net (detected {cost.detected:.0%} of "
                          f"frames, {richer.detected:.0%} at level {richer_level}); not used "
                          f"for {block:.0f} s")
                return
        if cost.timed < FRAMES_TO_JUDGE:
            return  # no tracked frames at this level to judge its cost by (see `frame`)
        highest = min([self.settings.max_level]
                      + [k - 1 for k, (until, _) in self._blocked.items() if t < until])
        # Behind the camera: over budget, and the source is dropping frames for it. A source
        # that renders or reads frames on demand never drops one: the loop only runs slower.
        behind = cost.seconds > behind_at and sum(self._drops) > 0
        over_cap = cost.seconds > cap
        if (behind or over_cap) and self.level < highest:
            if held >= UP_HOLD_S:
                # Far behind (a Pi core at a quarter of its time): straight to the first level
                # predicted to fit, not one step per second while the distance goes stale.
                target = self.level + 1
                while target < highest and self._predicted(target, t, cost.seconds) > budget:
                    target += 1
                why = (f"the camera gives one every {interval * 1e3:.0f} ms" if behind else
                       f"budget.max_cpu {self.settings.max_cpu:g} of a core allows "
                       f"{cap * 1e3:.0f} ms of the camera's {interval * 1e3:.0f} ms")
                self._set(target, t, f"a frame takes {cost.seconds * 1e3:.0f} ms at level "
                          f"{self.level}, {why}")
            return
        if self.level > 0 and held >= DOWN_HOLD_S and (
            self._predicted(self.level - 1, t, cost.seconds) <= DOWN_MARGIN * budget
        ):
            self._set(self.level - 1, t, f"room again: a frame takes {cost.seconds * 1e3:.0f} "
                      f"ms at level {self.level} of the camera's {interval * 1e3:.0f} ms")

    def _block_from(self, level: int, t: float) -> float:
        """Block `level` and every leaner one; returns how long `level` is blocked."""
        for k in range(level, LEVELS):
            previous = self._blocked.get(k)
            length = BLOCK_S if previous is None else min(2.0 * previous[1], MAX_BLOCK_S)
            self._blocked[k] = (t + length, length)
        return self._blocked[level][1]

    def _predicted(self, level: int, t: float, current_s: float) -> float:
        """A level's cost per frame: measured, when recently; else scaled from the current."""
        known = self._costs.get(level)
        if known is not None and t - known.last_t <= COST_MEMORY_S and math.isfinite(
                known.seconds):
            return known.seconds
        return current_s * STEP_RATIO ** (self.level - level)

    def _set(self, level: int, t: float, why: str = "") -> None:
        if level != self.level:
            self.changes += 1
            self.why = why
            # The new level is judged on its own frames only.
            stale = self._costs.get(level)
            if stale is not None:
                stale.frames = stale.timed = 0
        self.level = level
        self._changed_at = t
