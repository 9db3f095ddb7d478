"""Hold a process to a share of one CPU core, as a busy Raspberry Pi would.

The first choice is a CPU quota on a control group with a short period (10 ms), which throttles
the process smoothly and exactly: cgroup v2 (`cpu.max`) or v1 (`cpu.cfs_quota_us`). Where no
cgroup can be created, the process is pinned to one core with busy competitors pinned beside
it, which gives it about 1/(competitors + 1) of that core.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from pathlib import Path

PERIOD_US = 10_000
_V2_ROOTS = (Path("/sys/fs/cgroup"), Path("/sys/fs/cgroup/unified"))
_V1_ROOT = Path("/sys/fs/cgroup/cpu")
_BUSY = "while True: pass"


class CpuLimit:
    """Limits one process (all its threads) to `share` of a core until `close()`."""

    def __init__(self, share: float) -> None:
        if not 0.0 < share < 1.0:
            raise ValueError(f"share must be in (0, 1), got {share}")
        self.share = share
        self._group: Path | None = None
        self._competitors: list[subprocess.Popen[bytes]] = []
        self.how = ""

    def attach(self, pid: int) -> str:
        """Apply the limit to process `pid`; returns how it is held."""
        quota = round(self.share * PERIOD_US)
        for root in _V2_ROOTS:
            if (root / "cgroup.controllers").is_file() and "cpu" in (
                    root / "cgroup.controllers").read_text():
                how = f"cgroup v2 cpu.max {quota}/{PERIOD_US} us"
                if self._group_for(root / f"netpose-soak-{pid}", how, (
                        ("cpu.max", f"{quota} {PERIOD_US}\n"), ("cgroup.procs", f"{pid}\n"))):
                    return self.how
        if (_V1_ROOT / "cpu.cfs_quota_us").is_file():
            how = f"cgroup v1 cfs quota {quota}/{PERIOD_US} us"
            if self._group_for(_V1_ROOT / f"netpose-soak-{pid}", how, (
                    ("cpu.cfs_period_us", f"{PERIOD_US}\n"), ("cpu.cfs_quota_us", f"{quota}\n"),
                    ("cgroup.procs", f"{pid}\n"))):
                return self.how
        return self._competitors_for(pid)

    def _group_for(self, group: Path, how: str,
                   writes: tuple[tuple[str, str], ...]) -> bool:
        """Make `group` with `writes` (the process last); a group that cannot be made whole
        is removed again, not left behind."""
        try:
            group.mkdir()
        except OSError:
            return False
        try:
            for name, value in writes:
                (group / name).write_text(value)
        except OSError:
            with contextlib.suppress(OSError):
                group.rmdir()  # empty: the process was the last write
            return False
        self._group = group
        self.how = how
        return True

    def _competitors_for(self, pid: int) -> str:
        cpu = sorted(os.sched_getaffinity(0))[-1]
        for task in Path(f"/proc/{pid}/task").iterdir():
            with contextlib.suppress(OSError):
                os.sched_setaffinity(int(task.name), {cpu})
        count = max(1, round(1.0 / self.share) - 1)
        for _ in range(count):
            proc = subprocess.Popen([sys.executable, "-c", _BUSY])
            self._competitors.append(proc)  # owned before anything else can fail
            os.sched_setaffinity(proc.pid, {cpu})
        self.how = f"pinned to CPU {cpu} with {count} busy competitor(s) (no cgroup here)"
        return self.how

    def close(self) -> None:
        for proc in self._competitors:
            proc.kill()
            proc.wait()
        self._competitors.clear()
        if self._group is not None:
            with contextlib.suppress(OSError):
                self._group.rmdir()  # empty once the process has ended
            self._group = None
