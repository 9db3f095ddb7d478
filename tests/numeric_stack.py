"""Which numeric stack the suite runs on, for cases that are known to be open.

A few cases of the integrity run and of real frames are open (docs/benchmarks.md): they fail on
one stack or both. On the stack CI pins (Debian bookworm's: `.ci/bookworm-constraints.txt`)
the outcome is exact, so the mark is strict there: a case that starts to pass (mended) or to
fail (a regression) turns the run red until the list says so. The newest wheels are not
pinned, so a release can move a marginal case either way: there the mark stays lenient.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

PINNED_BOOKWORM = np.__version__ == "1.24.4" and cv2.__version__ == "4.6.0"


def failing_case(reason: str) -> pytest.MarkDecorator:
    """The mark of a case open on every stack: strict on bookworm's pinned one, lenient
    elsewhere."""
    return pytest.mark.xfail(strict=PINNED_BOOKWORM, reason=reason)


def open_case(reason: str, *, fails_on_bookworm: bool) -> list[pytest.MarkDecorator]:
    """The marks of an open case (for `pytest.param`): strict on bookworm's pinned stack (an
    expected failure where it fails there, an ordinary test where it passes), lenient
    elsewhere."""
    if PINNED_BOOKWORM and not fails_on_bookworm:
        return []  # passes there: any failure is a regression
    return [failing_case(reason)]
