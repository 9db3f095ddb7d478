"""Exceptions raised by drivers (everything that touches the outside world).

Each driver adds its own classes here, derived from DriverError, so the daemon can tell a
hardware/link problem from a bug.
"""

from __future__ import annotations

from service.errors import NetposeError


class DriverError(NetposeError):
    """Base of every error a driver raises on purpose."""


class NotifyError(DriverError):
    """The systemd notification socket named in NOTIFY_SOCKET cannot be used."""


class MavlinkLinkError(DriverError):
    """The MAVLink link to the autopilot cannot be opened or was closed by the other side."""
