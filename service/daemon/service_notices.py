"""What the pilot must hear about netpose itself: the camera gone (and back), and netpose
stopping or restarting.

A pilot flying with Cockpit or QGroundControl sees netpose only as a rangefinder. When the
camera dies, or the service stops or restarts (the web page's Restart, an update, systemd),
that rangefinder just falls silent, which reads the same as open water; a ground station's
indicator may even keep the last number on screen. Each of these costs the autopilot its
distance for a reason the pilot can act on, so each is said as a STATUSTEXT when it happens:
the camera's loss once per `interval_s` at most (a camera that flaps does not flood the
screen), its return only after its loss was said.
"""

from __future__ import annotations

import collections

from service.daemon.ports import AutopilotLink
from service.signals import RESTART

MAV_SEVERITY_WARNING = 4
MAV_SEVERITY_INFO = 6


class ServiceNotices:
    """Tells the pilot when netpose's own state takes the distance away, and gives it back."""

    def __init__(self, link: AutopilotLink, interval_s: float = 30.0) -> None:
        self._link = link
        self.interval_s = interval_s
        self._loss_said = False
        self._last_loss_text_at = -float("inf")
        self._had_frames = False
        # The last texts said (tests and a debugger read them): a daemon runs for months.
        self.sent: collections.deque[str] = collections.deque(maxlen=32)

    def camera(self, up: bool | None, now: float) -> None:
        """The frame source's state on this pass (SourceWatch.up: None before any frame)."""
        if up:
            self._had_frames = True
            if self._loss_said:
                self._loss_said = False
                self._say("netpose: camera back", MAV_SEVERITY_INFO)
            return
        if up is False and not self._loss_said and (
                now - self._last_loss_text_at >= self.interval_s):
            self._loss_said = True
            self._last_loss_text_at = now
            self._say(self._loss_text(), MAV_SEVERITY_WARNING)

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
