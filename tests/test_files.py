"""Files that must survive a power cut: the configuration saved from the web page, an uploaded
or computed calibration, a recording's manifest (service/core/files.py)."""

from __future__ import annotations

import os
import stat
import threading
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


def test_a_linked_configuration_is_written_where_the_link_points(tmp_path: Path) -> None:
    """/etc/netpose/netpose.toml may be a link to a file kept elsewhere: the link was replaced
    by a plain file, and the file it named kept the old settings."""
    kept = tmp_path / "kept"
    kept.mkdir()
    (kept / "netpose.toml").write_text("old\n")
    link = tmp_path / "netpose.toml"
    link.symlink_to(kept / "netpose.toml")
    write_atomically(link, b"new\n")
    assert link.is_symlink() and (kept / "netpose.toml").read_text() == "new\n"


def test_a_failed_write_says_why_and_two_writers_do_not_share_a_scratch_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The scratch file beside the target had one fixed name, so two writers of one file
    wrote into each other's; and a cleanup that failed too (a read-only folder) replaced the
    write's own error with its own."""
    names: list[str] = []
    real_replace = os.replace

    def spy(src: str | Path, dst: str | Path) -> None:
        names.append(Path(src).name)
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", spy)
    write_atomically(tmp_path / "a.toml", b"1")
    other = threading.Thread(target=write_atomically, args=(tmp_path / "a.toml", b"2"))
    other.start()
    other.join()
    assert len(set(names)) == 2, names  # this thread's scratch file and the other's

    def refuse(*_args: object) -> None:
        raise OSError(30, "Read-only file system")

    monkeypatch.setattr(os, "replace", refuse)
    def cannot_clean(*_args: object, **_kwargs: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(Path, "unlink", cannot_clean)
    with pytest.raises(OSError, match="Read-only"):
        write_atomically(tmp_path / "a.toml", b"3")
