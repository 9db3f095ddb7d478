"""The estimator on real fish-farm frames and real net-free scenes (shared/data/real-field/).

What is known exactly about these frames is tested exactly: whether a net is in view, and the
net-free scenes must never give a net or a "too close". The sequence's frames are consecutive
(the vehicle held a 0.57-0.63 m DVL stand-off), so its distances must be consistent with each
other within what the estimator says its uncertainty is. The issue's recall and stand-off
targets are measured and printed by `netpose bench real` (see docs/benchmarks.md).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator

import pytest

from service.benchmarks.real_frames import (
    RealResult,
    real_field_frames,
    run_frames,
    summarise,
)
from tests.shared_data import shared_data_dir

REAL_FIELD = shared_data_dir() / "real-field"

pytestmark = pytest.mark.skipif(
    not REAL_FIELD.is_dir(),
    reason=f"real-field data set not found at {REAL_FIELD} (set NETPOSE_SHARED_DATA to the "
    "folder holding real-field/)",
)


@pytest.fixture(scope="module")
def results() -> Iterator[list[RealResult]]:
    yield list(run_frames(real_field_frames(shared_data_dir())))


def test_no_net_free_scene_is_a_net_or_too_close(results: list[RealResult]) -> None:
    free = [r for r in results if r.frame.kind == "no-net"]
    assert len(free) == 18
    for r in free:
        assert not r.estimate.detected, (r.frame.name, r.estimate.range_m)
        assert r.estimate.distance_m is None
        assert not r.estimate.too_close, r.frame.name


def test_the_stills_show_a_net_at_a_plausible_distance(results: list[RealResult]) -> None:
    stills = [r for r in results if r.frame.kind == "still"]
    assert stills
    for r in stills:
        e = r.estimate
        assert e.detected, (r.frame.name, e.reason)
        assert e.range_m is not None and e.sigma_range_m is not None
        # The README: nets at ~0.4-0.5 m (close mesh) to ~1.4 m (the far recording; the
        # 27.5 mm mesh and published intrinsics put it nearer 1.7 m). Plausible, not truth.
        assert 0.3 < e.range_m < 2.5, (r.frame.name, e.range_m)
        # A distance is only given when the data pin it down.
        assert e.sigma_range_m <= 0.02 * e.range_m


def test_sequence_distances_agree_within_their_sigma(results: list[RealResult]) -> None:
    """Consecutive detections of one slow pass: each step between detected frames is within
    what the two reported sigmas allow (4 sigma of the difference), and the reported sigma is
    at least the frame-to-frame spread (issue 11, point 3)."""
    seq = [r for r in results if r.frame.kind == "sequence"]
    assert len(seq) == 44
    found = [r.estimate for r in seq if r.estimate.detected]
    for e in found:
        assert e.distance_m is not None and e.sigma_distance_m is not None
    summary = summarise(results)
    if len(found) >= 3:
        assert summary.sequence_sigma_median_m >= summary.sequence_frame_to_frame_m
    for a, b in itertools.pairwise(seq):
        ea, eb = a.estimate, b.estimate
        if not (ea.detected and eb.detected):
            continue
        assert ea.distance_m is not None and eb.distance_m is not None
        assert ea.sigma_distance_m is not None and eb.sigma_distance_m is not None
        allowed = 4.0 * math.hypot(ea.sigma_distance_m, eb.sigma_distance_m)
        assert abs(eb.distance_m - ea.distance_m) <= allowed, (a.frame.name, b.frame.name)
