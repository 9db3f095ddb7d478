"""CPU load for the status payload: system load average and this process's share of a core."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import Any

from service.telemetry_schema import cpu_status


class CpuMeter:
    """Measures process CPU use between two `sample()` calls (call it at the status rate)."""

    def __init__(
        self,
        *,
        wall: Callable[[], float] = time.monotonic,
        cpu: Callable[[], float] = time.process_time,
    ) -> None:
        self._wall = wall
        self._cpu = cpu
        self._last = (wall(), cpu())

    def sample(self) -> dict[str, Any]:
        """`cpu_status(...)` for the interval since the previous sample (or construction)."""
        now = (self._wall(), self._cpu())
        elapsed = now[0] - self._last[0]
        used = now[1] - self._last[1]
        self._last = now
        percent = 100.0 * used / elapsed if elapsed > 0 else None
        try:
            load_1m: float | None = os.getloadavg()[0]
        except OSError:  # not available on every platform
            load_1m = None
        return cpu_status(cores=os.cpu_count(), load_1m=load_1m, process_percent=percent)
