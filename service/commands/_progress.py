"""A one-line text progress bar on stderr (no dependency), for commands that chew through files."""

from __future__ import annotations

import sys
from typing import TextIO


class ProgressBar:
    """Redraws `label [#####.....] done/total` in place; silent when disabled.

    Enabled by default only when the stream is a terminal, so logs and pipes stay clean.
    """

    def __init__(
        self, label: str, *, enabled: bool | None = None, stream: TextIO | None = None,
        width: int = 30,
    ) -> None:
        self._stream = stream if stream is not None else sys.stderr
        self._enabled = self._stream.isatty() if enabled is None else enabled
        self._label = label
        self._width = width
        self._drawn = False

    def update(self, done: int, total: int) -> None:
        if not self._enabled:
            return
        total = max(total, 1)
        filled = min(self._width, self._width * done // total)
        bar = "#" * filled + "." * (self._width - filled)
        self._stream.write(f"\r{self._label} [{bar}] {done}/{total}")
        self._stream.flush()
        self._drawn = True

    def close(self) -> None:
        if self._enabled and self._drawn:
            self._stream.write("\n")
            self._stream.flush()
        self._drawn = False

    def __enter__(self) -> ProgressBar:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
