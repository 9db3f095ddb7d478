"""Exceptions raised by drivers (everything that touches the outside world).

Each driver adds its own classes here, derived from DriverError, so the daemon can tell a
hardware/link problem from a bug.
"""

from __future__ import annotations

from service.core.errors import NetposeError


class DriverError(NetposeError):
    """Base of every error a driver raises on purpose."""


class NotifyError(DriverError):
    """The systemd notification socket named in NOTIFY_SOCKET cannot be used."""


class MavlinkLinkError(DriverError):
    """The MAVLink link to the autopilot cannot be opened or was closed by the other side."""


class SourceError(DriverError):
    """A frame source cannot be opened (or re-opened); `url` names it, `reason` says why."""

    def __init__(self, url: str, reason: str) -> None:
        super().__init__(f"frame source {url}: {reason}")
        self.url = url
        self.reason = reason
