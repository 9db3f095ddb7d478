"""What every driver resource shares: `with resource:` closes it when the block is left."""

from __future__ import annotations

from abc import ABC, abstractmethod
from types import TracebackType


class Closeable(ABC):
    """A resource with an owner-visible `close()`; leaving a `with` block always closes it.

    Each interface says what entering does (a link starts, a source opens), so `__enter__` stays
    with the interface; only the exit is the same everywhere.
    """

    @abstractmethod
    def close(self) -> None:
        """Stop every thread and release every handle; idempotent."""

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
