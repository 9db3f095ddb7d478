"""`netpose bench soak`'s CPU limit leaves nothing behind when a step of it fails."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from service.benchmarks import cpu_limit
from service.benchmarks.cpu_limit import CpuLimit


def test_a_cgroup_that_cannot_be_set_up_is_removed_and_the_competitors_are_owned(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A cgroup made but refused its quota stayed behind as netpose-soak-PID (and the limit
    fell back to competitors without saying the group was not used)."""
    root = tmp_path / "cgroup"
    root.mkdir()
    (root / "cgroup.controllers").write_text("cpuset cpu io memory\n")
    monkeypatch.setattr(cpu_limit, "_V2_ROOTS", (root,))
    monkeypatch.setattr(cpu_limit, "_V1_ROOT", tmp_path / "no-v1")
    real_write_text = Path.write_text

    def refusing_the_quota(self: Path, *args: object, **kwargs: object) -> int:
        if self.name == "cpu.max":
            raise PermissionError(13, "Permission denied")  # a delegated tree that says no
        return real_write_text(self, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(Path, "write_text", refusing_the_quota)
    target = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    limit = CpuLimit(0.5)
    try:
        how = limit.attach(target.pid)
        assert "competitor" in how
        assert not list(root.glob("netpose-soak-*"))  # the half-made group is gone
    finally:
        limit.close()
        target.kill()
        target.wait()
