"""What the pilot must hear about netpose itself: the camera gone (and back), and netpose
stopping or restarting.

A pilot flying with Cockpit or QGroundControl sees netpose only as a rangefinder. When the
camera dies, or the service stops or restarts (the web page's Restart, an update, systemd),
that rangefinder just falls silent, which reads the same as open water; a ground station's
indicator may even keep the last number on screen. Each of these costs the autopilot its
distance for a reason the pilot can act on, so each is said as a STATUSTEXT when it happens:
the camera's loss once per `interval_s` at most (a camera that flaps does not flood the
screen), its return only after its loss was said. The outages held back by that interval are
counted and said when it allows, so a flapping camera's last word on the pilot's screen is not
"camera back" (it was, for 27 of every 30 s, while the camera dropped out 3 more times). An
outage that lasts `SUSTAINED_LOSS_S` is said whatever the interval, once per interval: a
camera that died within 30 s of an earlier text (the one a restart from the page makes, a flap)
reached the pilot's ground station 15-22 s after netpose knew, with the last distance frozen on
its indicator; a camera whose every outage lasts 6 s must not send a pair of texts for each.
"""

from __future__ import annotations

import collections

from service.daemon.ports import AutopilotLink
from service.signals import RESTART

MAV_SEVERITY_WARNING = 4
MAV_SEVERITY_INFO = 6
# Longer than the outages of a camera that flaps (a few seconds each, held to one text per
# interval), short enough for a pilot holding a distance to the net.
SUSTAINED_LOSS_S = 5.0


class ServiceNotices:
    """Tells the pilot when netpose's own state takes the distance away, and gives it back."""

    def __init__(self, link: AutopilotLink, interval_s: float = 30.0) -> None:
        self._link = link
        self.interval_s = interval_s
        self._loss_said = False
        self._last_loss_text_at = -float("inf")
        self._had_frames = False
        self._down = False
        self._down_since = 0.0
        self._last_sustained_at = -float("inf")  # the last loss said early, for lasting
        self._held = 0  # outages not said (the interval held them back) since the last text
        # The last texts said (tests and a debugger read them): a daemon runs for months.
        self.sent: collections.deque[str] = collections.deque(maxlen=32)

    def camera(self, up: bool | None, now: float) -> None:
        """The frame source's state on this pass (SourceWatch.up: None before any frame)."""
        allowed = now - self._last_loss_text_at >= self.interval_s
        if up:
            self._had_frames = True
            self._down = False
            if self._loss_said:
                self._loss_said = False
                self._say("netpose: camera back", MAV_SEVERITY_INFO)
            elif self._held and allowed:
                # Back now, but it kept dropping out: the distance comes and goes.
                self._say(f"netpose: camera unstable: lost {self._held}x in "
                          f"{now - self._last_loss_text_at:.0f} s", MAV_SEVERITY_WARNING)
                # Not a loss said: a camera that dies for good right after is said at once
                # (counting this as one held the next loss back another interval).
                self._held = 0
            return
        if up is not False:
            return
        began = not self._down
        self._down = True
        if began:
            self._down_since = now
        if self._loss_said:
            return
        sustained = (now - self._down_since >= SUSTAINED_LOSS_S
                     and now - self._last_sustained_at >= self.interval_s)
        if sustained and not allowed:
            self._last_sustained_at = now
        if allowed or sustained:
            text = self._loss_text()
            # This outage, and those held back since the last text (this one among them if
            # it began while held back).
            count = self._held + int(began)
            if count > 1:
                text = text.replace(": no distance", f" ({count}x in "
                                    f"{now - self._last_loss_text_at:.0f} s): no distance")
            self._loss_said = True
            self._last_loss_text_at = now
            self._held = 0
            self._say(text, MAV_SEVERITY_WARNING)
        elif began:
            self._held += 1

    def repeat(self) -> None:
        """The link dropped pilot texts that waited out its outage: a camera loss that was said
        and still goes on is said again."""
        if self._loss_said:
            self._say(self._loss_text(), MAV_SEVERITY_WARNING)

    def stopping(self, reason: str | None) -> None:
        """The daemon stops (a signal, the page's Restart, the end of its run): said before the
        link closes, which sends what is queued as it stops."""
        self._say("netpose: restarting: no distance for a moment" if reason == RESTART
                  else "netpose: stopping: no distance", MAV_SEVERITY_WARNING)

    def _loss_text(self) -> str:
        return ("netpose: camera lost: no distance" if self._had_frames
                else "netpose: no camera frames: no distance")

    def _say(self, text: str, severity: int) -> None:
        self.sent.append(text)
        self._link.notify_pilot(text, severity)
