"""Files that must survive a power cut: the configuration saved from the web page, an uploaded
or computed calibration, a recording's manifest (service/core/files.py)."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from service.core.files import write_atomically


def _fsynced(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The paths os.fsync was called on, in order (directories included)."""
    seen: list[str] = []
    real = os.fsync

    def spy(fd: int) -> None:
        seen.append(os.readlink(f"/proc/self/fd/{fd}"))
        real(fd)

    monkeypatch.setattr(os, "fsync", spy)
    return seen


def test_the_new_file_and_its_rename_reach_the_card_before_it_is_trusted(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A Pi's power is cut with the vehicle: a rename that only reached the page cache can
    leave the configuration pointing at an empty calibration, and the next boot without a
    rangefinder. The data is flushed before the rename, and the folder after it."""
    target = tmp_path / "netpose.toml"
    target.write_text("old\n")
    target.chmod(0o640)
    synced = _fsynced(monkeypatch)
    write_atomically(target, b"new\n")
    assert target.read_bytes() == b"new\n"
    assert stat.S_IMODE(target.stat().st_mode) == 0o640  # the file's mode is kept
    assert len(synced) == 2 and synced[1] == str(tmp_path)
    assert Path(synced[0]).parent == tmp_path and synced[0] != str(target)  # the temporary
    assert sorted(p.name for p in tmp_path.iterdir()) == ["netpose.toml"]


def test_a_check_that_refuses_the_new_file_leaves_the_old_one(tmp_path: Path) -> None:
    target = tmp_path / "netpose.toml"
    target.write_text("old\n")

    def refuse(candidate: Path) -> None:
        assert candidate.read_bytes() == b"bad\n"  # the check reads what would be written
        raise ValueError("no")

    with pytest.raises(ValueError):
        write_atomically(target, b"bad\n", check=refuse)
    assert target.read_text() == "old\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["netpose.toml"]


def test_a_new_file_is_created_and_a_scratch_file_need_not_be_durable(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    synced = _fsynced(monkeypatch)
    write_atomically(tmp_path / "preview.png", b"png", durable=False)
    assert (tmp_path / "preview.png").read_bytes() == b"png" and synced == []
