"""What the pilot must hear about the view itself: the net is too close to measure, the camera
sees a regular grid that is not the configured net (a pool's tiles, a brick wall, a net of
another opening angle), or it sees the net but too little of it (bunched behind boards, one
side only) to pin the plane down to a distance. Each means "no distance" for a reason the pilot
can act on, unlike open water, so each is logged as a warning and sent as a STATUSTEXT when it
starts.

An episode must last a few frames before it is announced (one frame of a fish at the lens is
not news), and a STATUSTEXT of the same kind goes out at most once per `interval_s`, so a view
that flickers at the limit does not flood the pilot's screen. The log says when it ends. The
pilot hears an episode only once it has lasted `text_after_s` (a net too close at once): in a
60 s approach tracked 87 % of the time, episodes of under a second each sent a "no dist"
warning, which teaches a pilot to ignore them. Once an episode was said, the pilot also hears
when a distance goes to the autopilot again ("netpose: distance back").
"""

from __future__ import annotations

import collections
import enum
import logging

from service.core.estimator import refused_as_another_grid
from service.core.readings import RangeStatus
from service.core.state_log import StateLog, not_logged_note
from service.daemon.ports import AutopilotLink
from service.pipeline import PipelineResult

RECENT_TEXTS = 32  # the last pilot texts, kept to be read back (tests, a debugger)

log = logging.getLogger("netpose.daemon")

MAV_SEVERITY_WARNING = 4
MAV_SEVERITY_INFO = 6
STATUSTEXT_CHARS = 50  # MAVLink 1 STATUSTEXT: longer texts are cut by ground stations


class View(enum.Enum):
    NET = "net"  # measured, or nothing to say
    TOO_CLOSE = "too_close"
    ANOTHER_GRID = "another_grid"
    IMPRECISE = "imprecise"  # the net is seen, its plane too uncertain for a distance


def classify(result: PipelineResult) -> View:
    if result.reading.status is RangeStatus.TOO_CLOSE:
        return View.TOO_CLOSE
    if result.estimate is not None and refused_as_another_grid(result.estimate):
        return View.ANOTHER_GRID
    # Only while the autopilot gets nothing: a filter still coasting on earlier frames is
    # sending a distance, and then there is nothing to explain.
    if (result.estimate is not None and result.estimate.net_seen
            and not result.estimate.detected and result.reading.status is RangeStatus.NONE):
        return View.IMPRECISE
    return View.NET


def pilot_text(view: View, result: PipelineResult, configured_opening_deg: float) -> str:
    est = result.estimate
    if view is View.TOO_CLOSE:
        return "netpose: net too close to measure, back off"
    if view is View.IMPRECISE:
        approx = est.approx_range_m if est is not None else None
        where = f"~{approx:.1f} m" if approx is not None else "seen"
        return f"netpose: net {where}, too little in view: no dist"[:STATUSTEXT_CHARS]
    measured = est.measured_opening_deg if est is not None else None
    if measured is not None and abs(measured - configured_opening_deg) > 1.0 and (
        est is not None and est.reason.startswith("mesh opening angle")
    ):
        return (f"netpose: mesh angle {measured:.0f} deg, config {configured_opening_deg:.0f}:"
                " no dist")[:STATUSTEXT_CHARS]
    return "netpose: grid is not the configured net: no dist"


class ViewNotices:
    """Announces TOO_CLOSE, ANOTHER_GRID and IMPRECISE episodes to the log and the pilot."""

    def __init__(self, link: AutopilotLink, configured_opening_deg: float,
                 confirm_frames: int = 3, interval_s: float = 30.0,
                 states: StateLog | None = None, text_after_s: float = 1.0) -> None:
        self._link = link
        # The log lines go through the daemon's StateLog (at most one a second): a view at the
        # limit (a net seen in one frame, measured in the next) can start and end an episode
        # every few frames.
        self._states = states or StateLog()
        self.configured_opening_deg = configured_opening_deg
        self.confirm_frames = confirm_frames
        self.interval_s = interval_s
        self.text_after_s = text_after_s
        self._candidate = View.NET
        self._candidate_since = -float("inf")
        self._frames = 0
        self._announced = View.NET
        self._announced_since = -float("inf")  # the first frame of the episode announced
        self._texted = False  # the episode announced was said to the pilot
        self._back_due = False  # ... so its end, a distance again, is said too
        self._last_text_at: dict[View, float] = {}
        # The last texts sent (tests and the status read them), and how many in all: a
        # daemon runs for months, so the texts themselves are not all kept.
        self.sent: collections.deque[str] = collections.deque(maxlen=RECENT_TEXTS)
        self.sent_total = 0

    @property
    def view(self) -> View:
        """The episode announced last (NET when none is going on)."""
        return self._announced

    def update(self, result: PipelineResult, now: float) -> None:
        """One processed frame (ticks without a frame say nothing about the view)."""
        if not result.has_frame:
            return
        view = classify(result)
        if view is not self._candidate:
            self._candidate_since = now
        self._frames = self._frames + 1 if view is self._candidate else 1
        self._candidate = view
        # TOO_CLOSE comes confirmed: the pipeline asks for frames in a row before it says so.
        needed = 1 if view is View.TOO_CLOSE else self.confirm_frames
        if view is not self._announced and self._frames >= needed:
            self._announced = view
            self._announced_since = self._candidate_since
            self._texted = False
        announced = self._announced
        wait = 0.0 if announced is View.TOO_CLOSE else self.text_after_s
        if (announced is not View.NET and not self._texted
                and now - self._announced_since >= wait):
            self._texted = True  # said now, or not at all (the kind's rate limit)
            if now - self._last_text_at.get(announced, -float("inf")) >= self.interval_s:
                self._last_text_at[announced] = now
                self._say(pilot_text(announced, result, self.configured_opening_deg),
                          MAV_SEVERITY_WARNING)
                self._back_due = True
        # Only once the episode is over (confirmed, as its start was): one good frame in a
        # flicker at the limit said "distance back" in the middle of a "too close".
        if (self._back_due and self._announced is View.NET
                and result.reading.status is RangeStatus.GOOD):
            self._back_due = False
            self._say("netpose: distance back", MAV_SEVERITY_INFO)
        due, logged, between = self._states.update("view", self._announced, now)
        if not due:
            return
        if self._announced is View.NET:
            assert isinstance(logged, View)
            log.info("%s ended%s", _episode(logged), not_logged_note(between))
            return
        est = result.estimate
        reason = est.reason if est is not None else ""
        log.warning("%s: no distance to the autopilot (%s)%s", _episode(self._announced), reason,
                    not_logged_note(between))


    def repeat(self, result: PipelineResult | None) -> None:
        """The link dropped pilot texts that waited out its outage: an episode that was said and
        still goes on is said again (the pilot must hear what is true now), whatever the rate
        limit."""
        if self._announced is not View.NET and self._texted and result is not None:
            self._say(pilot_text(self._announced, result, self.configured_opening_deg),
                      MAV_SEVERITY_WARNING)
            self._back_due = True  # its end is said too

    def _say(self, text: str, severity: int) -> None:
        self.sent.append(text)
        self.sent_total += 1
        self._link.notify_pilot(text, severity)


def _episode(view: View) -> str:
    if view is View.TOO_CLOSE:
        return "net too close to measure"
    if view is View.IMPRECISE:
        return "net seen, but its plane is too uncertain for a distance"
    return "the camera sees a grid that is not the configured net"
