"""Retry delays for every link that can go away: camera streams, MAVLink, Zenoh.

A plain exponential backoff (0.5, 1, 2, 4, 8 s ...) makes recovery slow after a short outage:
a router restarted after 6 s is found only when the 8 s wait ends. A vehicle's links mostly
drop for seconds (a cable re-seated, a service restarted), so the cap on one wait grows with
the age of the outage: while an outage is young the link probes often (probing is one cheap
connect attempt), and only an outage that has lasted minutes backs off to the configured
maximum.

    cap(age) = clamp(age * AGE_FRACTION, young_cap_s, max_s)

With the defaults, a peer that returns within the first ~20 s of an outage is found within
`young_cap_s` (1 s) plus the time one attempt takes.

Time is passed in, never read here, so a schedule can be replayed exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

# The longest wait is this fraction of the outage's age (above the young cap).
AGE_FRACTION = 0.05


@dataclass
class Backoff:
    """Delays between attempts of one outage. `reset()` when the link is up again."""

    initial_s: float = 0.25
    max_s: float = 10.0
    young_cap_s: float = 1.0

    def __post_init__(self) -> None:
        if not 0.0 < self.initial_s <= self.max_s:
            raise ValueError(f"need 0 < initial_s <= max_s, got {self.initial_s}, {self.max_s}")
        self._next = self.initial_s
        self._outage_started: float | None = None

    def reset(self) -> None:
        self._next = self.initial_s
        self._outage_started = None

    @property
    def in_outage(self) -> bool:
        return self._outage_started is not None

    def next_delay(self, now: float) -> float:
        """The wait before the next attempt, after an attempt failed at `now`."""
        if self._outage_started is None:
            self._outage_started = now
        age = now - self._outage_started
        cap = min(self.max_s, max(self.young_cap_s, age * AGE_FRACTION))
        delay = min(self._next, cap)
        self._next = min(self._next * 2.0, self.max_s)
        return delay
