"""`netpose bench real`'s verdicts on its targets, without the data set: a target that one run
cannot evaluate says so instead of reading as missed or met."""

from __future__ import annotations

import dataclasses
import math

from service.benchmarks.real_frames import RealSummary

SUMMARY = RealSummary(
    stills=4, stills_detected=4, sequence=44, sequence_detected=5, sequence_seen=23, no_net=18,
    false_nets=0, false_too_close=0, sequence_distance_median_m=0.77,
    sequence_range_median_m=0.78, sequence_frame_to_frame_m=0.014,
    sequence_sigma_median_m=0.013,
)
SPREAD = "sequence sigma >= frame-to-frame spread"


def test_the_spread_target_is_judged_when_the_spread_was_measured() -> None:
    assert SUMMARY.targets[SPREAD] is False
    wider = dataclasses.replace(SUMMARY, sequence_sigma_median_m=0.015)
    assert wider.targets[SPREAD] is True


def test_the_spread_target_is_not_measurable_without_two_steps() -> None:
    # One pair of consecutive measured frames (or none) leaves the spread undefined.
    single = dataclasses.replace(SUMMARY, sequence_frame_to_frame_m=math.nan)
    assert single.targets[SPREAD] is None
    assert single.targets["all stills detected"] is True


SEEN_SPREAD = "sequence sigma >= frame-to-frame spread, ranges measured or seen"


def test_the_spread_of_seen_ranges_is_judged_on_its_own_sigmas() -> None:
    """The refused ranges a pilot reads ("net seen, ~0.8 m") have sigmas too: judged against
    their own frame-to-frame spread, whatever the measured frames' verdict."""
    seen = dataclasses.replace(SUMMARY, sequence_seen_frame_to_frame_m=0.03,
                               sequence_seen_sigma_median_m=0.02)
    assert seen.targets[SEEN_SPREAD] is False
    assert dataclasses.replace(seen, sequence_seen_sigma_median_m=0.035).targets[SEEN_SPREAD]
    assert SUMMARY.targets[SEEN_SPREAD] is None  # no two consecutive ranges: not measurable
