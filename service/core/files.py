"""Files the service reads and writes: small regular files read whole, and writes that must
survive a power cut, whole or not at all.

A vehicle's power is cut at the end of every dive, often within seconds of a change made from
the web page. A file written in place can be left half written; one renamed over the old can
be left empty, pointing nothing at the data that never reached the card (ext4 usually saves
the rename-over case, nothing guarantees it). So the new content goes to a temporary file
beside the target, is flushed to the card, renamed over the target, and the rename itself is
flushed with the folder. After a cut the target is the old file or the new one.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import stat
from collections.abc import Callable
from pathlib import Path


def read_small(path: str | Path, max_bytes: int) -> bytes:
    """The bytes of a regular file of at most `max_bytes`; OSError otherwise.

    Files named by settings (a calibration, a key) are read whole: a device named instead
    (/dev/zero) would fill the memory, and a FIFO or a tty would block the reader for good
    (with it the settings page, and the service's stop). Neither is read: a device is refused
    before it is opened, and the file opened is judged again without waiting on it (a FIFO
    put there in between)."""
    p = Path(path)
    if not stat.S_ISREG(p.stat().st_mode):  # follows a link, as open() would
        raise OSError(f"{p} is not a regular file")
    # Opened without waiting (a FIFO put there since the look above would block open()) and
    # judged again by what was opened.
    fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK)
    with open(fd, "rb") as fh:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise OSError(f"{p} is not a regular file")
        data = fh.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise OSError(f"{p} is larger than {max_bytes} bytes: not a file of this kind")
    return data


def write_atomically(path: str | Path, data: bytes, *,
                     check: Callable[[Path], object] | None = None, durable: bool = True) -> None:
    """Replace `path` with `data`: whole or not at all, on the card when this returns.

    `check` sees the new file (beside the target) before it replaces anything; an exception
    from it leaves the target as it was. An existing target's permissions are kept. `durable`
    False skips the flushes, for files that only a viewer reads (a preview image).
    """
    # A link (a configuration kept elsewhere) is followed: the file it names is the one
    # replaced, and the link stays.
    target = Path(path).resolve() if Path(path).is_symlink() else Path(path)
    # One scratch file per write: two writers of one file (processes, threads) must not write
    # into each other's.
    temporary = target.with_name(f".{target.name}.{os.getpid()}.{os.urandom(4).hex()}.new")
    try:
        with open(temporary, "wb") as out:
            out.write(data)
            out.flush()
            if durable:
                os.fsync(out.fileno())
        if check is not None:
            check(temporary)
        if target.exists():
            shutil.copymode(target, temporary)
        os.replace(temporary, target)
    finally:
        # Gone after the rename; after a failure, a cleanup that fails too (a read-only
        # folder) must not hide why the write failed.
        with contextlib.suppress(OSError):
            temporary.unlink(missing_ok=True)
    if durable:
        _sync_folder(target.parent)


def _sync_folder(folder: Path) -> None:
    # A folder cannot be opened for writing; read-only is what fsync of a directory needs.
    # Some filesystems (a FAT card, a network share) refuse it: the rename is then as durable
    # as they make it.
    fd = os.open(folder, os.O_RDONLY)
    try:
        with contextlib.suppress(OSError):
            os.fsync(fd)
    finally:
        os.close(fd)
