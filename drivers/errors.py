"""Exceptions raised by drivers (everything that touches the outside world).

Each driver adds its own classes here, derived from DriverError, so the daemon can tell a
hardware/link problem from a bug.
"""

from __future__ import annotations

from service.core.errors import NetposeError
from service.core.redact import redact_text


class DriverError(NetposeError):
    """Base of every error a driver raises on purpose."""


class NotifyError(DriverError):
    """The systemd notification socket named in NOTIFY_SOCKET cannot be used."""


class MavlinkLinkError(DriverError):
    """The MAVLink link to the autopilot cannot be opened or was closed by the other side."""


class SourceError(DriverError):
    """A frame source cannot be opened (or re-opened); `url` names it, `reason` says why.

    Both are redacted here, once: a camera's password or an SRT passphrase in the URL (or in a
    library's error text that repeats it) never reaches a log, a status or an error line."""

    def __init__(self, url: str, reason: str) -> None:
        self.url = redact_text(url)
        self.reason = redact_text(reason)
        super().__init__(f"frame source {self.url}: {self.reason}")
