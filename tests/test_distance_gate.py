"""The link's send decision: a freshness limit that follows the measured frames, hysteresis
that keeps a wavering reading from flipping the autopilot's rangefinder, and an immediate stop
when nothing is believed."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from drivers.distance_gate import DistanceGate
from service.core.readings import RangeReading, RangeStatus

PERIOD = 0.1  # 10 Hz sends


def good(t_capture: float) -> RangeReading:
    return RangeReading(RangeStatus.GOOD, t_capture, distance_m=1.0, sigma_m=0.01, quality=0.9)


def test_the_freshness_limit_follows_a_slow_frame_rate() -> None:
    """A loaded Pi: 3 frames/s, 0.15 s from capture to the link. A fixed 0.3 s limit would stop
    between frames; the gate's limit covers latency + interval, and the output never gaps."""
    gate = DistanceGate(ceiling_s=1.0, send_period_s=PERIOD)
    sends, t, frame_t = [], 0.0, 0.0
    reading = good(0.0)
    gate.observe(reading, 0.15)
    while t < 10.0:
        if t >= frame_t + 1 / 3 + 0.15:  # the next frame reaches the link
            frame_t += 1 / 3
            reading = good(frame_t)
            gate.observe(reading, t)
        sends.append(gate.decide(reading, t))
        t += PERIOD
    # 1.5 x (latency 0.25 + interval 0.33) + two send periods, under the 1 s ceiling
    assert 0.85 <= gate.freshness_s <= 1.0
    assert all(sends[5:]) and gate.changes == 1


def test_a_frozen_fast_camera_stops_the_distance_after_its_own_measured_limit() -> None:
    """A camera at 30 frames/s, 20 ms from capture to the link, freezes: the newest distance
    is repeated for 1.5 x (latency + interval) + two send periods, about 0.28 s, not for the
    ceiling's 0.8 s that a slow machine would need."""
    gate = DistanceGate(ceiling_s=0.8, send_period_s=PERIOD)
    interval, latency = 1 / 30, 0.02
    frame = 0
    reading = good(0.0)
    for step in range(1, 300):  # 3 s of the loop at 100 Hz
        t = step / 100
        while (frame + 1) * interval + latency <= t and (frame + 1) * interval < 2.0:
            frame += 1
            reading = good(frame * interval)
            gate.observe(reading, frame * interval + latency)
        if gate.decide(reading, t):
            last_sent = t
    expected = 1.5 * (latency + interval) + 2 * PERIOD
    assert gate.freshness_s == pytest.approx(expected, rel=1e-6)
    frozen_at = frame * interval  # the last frame's capture time
    assert last_sent - frozen_at == pytest.approx(expected, abs=0.011)  # the loop's 10 ms step


def test_a_wavering_reading_flips_the_output_at_most_once_a_second() -> None:
    """Readings whose age hovers around the limit (a frame rate that comes and goes): without
    hysteresis the rangefinder would come and go every 100-200 ms."""
    gate = DistanceGate(ceiling_s=0.3, send_period_s=PERIOD, floor_s=0.3, settle_s=0.3)
    rng = np.random.default_rng(3)
    t, changes_at = 0.0, []
    last_changes = 0
    while t < 30.0:
        # Stretches well inside the limit (long enough to settle), then ages beyond it: the
        # reading would start and stop the output about every 0.6 s without the rule.
        age = 0.1 if (t % 1.2) < 0.6 else 0.3 + rng.uniform(0.01, 0.12)
        gate.decide(good(t - age), t)
        if gate.changes != last_changes:
            changes_at.append(t)
            last_changes = gate.changes
        t += PERIOD
    assert len(changes_at) >= 10  # it did go on and off, so the spacing below is tested
    # A stale distance stops at once (the safety rule); what the rule limits is the starts:
    # each one (every other change, from the first) a second or more after the stop before
    # it, so the output goes on and off at most once a second.
    starts = changes_at[2::2]
    stops_before = changes_at[1::2]
    assert all(start - stop >= 1.0 - 1e-9
               for stop, start in zip(stops_before, starts, strict=False))
    assert all(b - a >= 1.0 - 1e-9 for a, b in itertools.pairwise(changes_at[::2]))


def test_nothing_believed_stops_at_once_and_restarts_only_after_a_second() -> None:
    gate = DistanceGate(ceiling_s=1.0, send_period_s=PERIOD)
    assert gate.decide(good(0.0), 0.05)
    assert not gate.decide(RangeReading.none(0.1), 0.1)  # immediate: the safety rule
    sends = [gate.decide(good(t / 10), t / 10 + 0.05) for t in range(2, 20)]
    first = 2 + sends.index(True)
    assert 1.0 <= first / 10 + 0.05 - 0.1 <= 1.1  # a second after the stop, settled by then
    assert gate.changes == 3


def test_a_stale_reading_is_not_repeated_beyond_the_ceiling() -> None:
    gate = DistanceGate(ceiling_s=0.4, send_period_s=PERIOD)
    gate.observe(good(0.0), 0.05)
    sending = [gate.decide(good(0.0), t / 100) for t in range(5, 100, 10)]
    last_sent = max(t / 100 for t, s in zip(range(5, 100, 10), sending, strict=True) if s)
    assert last_sent <= 0.4


def test_the_frame_interval_is_the_typical_spacing_of_capture_times() -> None:
    """What the link spaces its sends on arrival by: the median interval between the capture
    times of consecutive readings (one dropped frame does not move it), once four are known;
    the loop's jitter in handing them over does not enter."""
    gate = DistanceGate(ceiling_s=1.0, send_period_s=PERIOD)
    rng = np.random.default_rng(3)
    captures = [i / 30.0 for i in range(12) if i != 6]  # frame 6 dropped
    for i, t in enumerate(captures):
        if i == 4:
            assert gate.frame_interval_s is None  # three intervals: not yet measured
        gate.observe(good(t), t + 0.02 + 0.03 * float(rng.random()))
    interval = gate.frame_interval_s
    assert interval is not None and abs(interval - 1 / 30.0) < 1e-9
