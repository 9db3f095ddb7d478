"""The frame-interval window shared by the filter's coasting window and the link's freshness."""

from __future__ import annotations

import pytest

from service.core.frame_intervals import FrameIntervals


def test_typical_and_worst_only_once_measured_and_only_forward_steps() -> None:
    w = FrameIntervals(window=3, min_count=2)
    w.add(1.0)
    w.add(1.0)  # a repeated time (the same frame handed over twice) is no interval
    assert w.median() is None and w.max() is None
    w.add(1.25)
    w.add(1.0)  # backwards: a new clock or a replay's seek, not an interval either
    assert w.median() is None
    w.add(1.5)
    assert w.median() == pytest.approx(0.375) and w.max() == pytest.approx(0.5)
    for t in (1.6, 1.7, 1.8):  # the window keeps the last three
        w.add(t)
    assert w.values() == pytest.approx([0.1, 0.1, 0.1]) and w.last == pytest.approx(1.8)


def test_restore_and_clear() -> None:
    w = FrameIntervals(window=8, min_count=2)
    w.restore([0.2, 0.4, 0.3], 5.0)
    assert w.median() == pytest.approx(0.3) and w.last == 5.0
    w.add(5.1)
    assert w.max() == pytest.approx(0.4)
    w.clear()
    assert w.median() is None and w.last is None
