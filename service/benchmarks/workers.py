"""Running a benchmark's independent chunks in worker processes, in order of completion."""

from __future__ import annotations

import multiprocessing
import sys
from collections.abc import Callable, Iterator, Sequence
from typing import TypeVar

Chunk = TypeVar("Chunk")
Part = TypeVar("Part")


def run_chunks(work: Callable[[Chunk], list[Part]], chunks: Sequence[Chunk], jobs: int,
               progress: Callable[[int], None] | None = None) -> list[Part]:
    """All parts of `work` over `chunks`, with `jobs` processes (1: in this one). The caller
    sorts: parts arrive in completion order. `work` must be a module-level function (it is
    pickled into the workers)."""
    parts: list[Part] = []
    for part in _parts(work, chunks, jobs):
        parts.extend(part)
        if progress:
            progress(len(part))
    return parts


def _parts(work: Callable[[Chunk], list[Part]], chunks: Sequence[Chunk],
           jobs: int) -> Iterator[list[Part]]:
    if jobs <= 1:
        yield from map(work, chunks)
        return
    # Not "fork": a process that already ran OpenCV (or pytest's timeout thread) holds locks
    # that a forked child inherits locked, and the pool then deadlocks.
    ctx = multiprocessing.get_context("forkserver" if sys.platform == "linux" else "spawn")
    with ctx.Pool(jobs) as pool:
        yield from pool.imap_unordered(work, chunks, chunksize=1)
