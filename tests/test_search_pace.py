"""The paced search of open water: which frames the estimator looks at
(service/daemon/search_pace.py). The daemon's own use of it, on rendered frames, is in
tests/test_daemon.py; the real daemon's, in tests/test_soak.py."""

from __future__ import annotations

import pytest

from service.core.readings import RangeReading
from service.core.results import NetEstimate
from service.core.tracking import Outcome, TrackOutput, TrackState
from service.daemon.search_pace import DUE_SHARE, HOLD_S, SearchPacer
from service.pipeline import PipelineResult

FPS = 30.0


def result(t: float, estimate: NetEstimate | None, state: TrackState = TrackState.LOST
           ) -> PipelineResult:
    track = TrackOutput(state=state, distance_m=None, distance_rate_mps=None, range_m=None,
                        yaw_deg=None, pitch_deg=None, normal=None, sigma_distance_m=None,
                        measurement=Outcome.NONE, mahalanobis=None, consecutive_rejects=0,
                        since_accepted_s=None, valid=False)
    return PipelineResult(t=t, index=round(t * FPS), estimate=estimate, track=track,
                          reading=RangeReading.none(t))


NOTHING = NetEstimate(detected=False, confidence=0.0, reason="0 of 15 ROIs show a lattice")
SEEN = NetEstimate(detected=False, confidence=0.2, reason="plane too uncertain",
                   approx_range_m=0.8, approx_sigma_range_m=0.03)
TOO_CLOSE = NetEstimate(detected=False, confidence=0.0, reason="too close", too_close=True)


def measured_times(pacer: SearchPacer, seconds: float, estimate: NetEstimate | None,
                   state: TrackState = TrackState.LOST) -> list[float]:
    times = []
    for k in range(round(seconds * FPS)):
        t = k / FPS
        if pacer.due(t):
            pacer.measured(result(t, estimate, state))
            times.append(t)
    return times


def test_nothing_in_view_is_measured_at_the_camera_rate_then_at_search_hz() -> None:
    pacer = SearchPacer(5.0)
    times = measured_times(pacer, 6.0, NOTHING)
    assert len([t for t in times if t < HOLD_S]) == round(HOLD_S * FPS)
    late = [t for t in times if t >= HOLD_S]
    assert len(late) == pytest.approx(5.0 * (6.0 - HOLD_S), abs=1)
    assert pacer.pacing
    # The reason given for a frame not measured says how long by now: it said "for 2 s" (the
    # hold) 11 s into the loss (pilot review).
    assert pacer.why(6.0) == "not measured: no net in view for 6 s, searching at 5 frames/s"
    assert pacer.why(11.4) == "not measured: no net in view for 11 s, searching at 5 frames/s"


@pytest.mark.parametrize("estimate,state", [
    (SEEN, TrackState.LOST), (TOO_CLOSE, TrackState.LOST), (NOTHING, TrackState.COASTING),
    (None, TrackState.TRACKING),
], ids=["net seen without a distance", "too close", "track coasting", "track valid"])
def test_a_sign_of_the_net_keeps_every_frame_measured(
    estimate: NetEstimate | None, state: TrackState
) -> None:
    pacer = SearchPacer(5.0)
    assert len(measured_times(pacer, 6.0, estimate, state)) == round(6.0 * FPS)
    assert not pacer.pacing


def test_the_first_sign_ends_the_pacing_at_once() -> None:
    pacer = SearchPacer(5.0)
    measured_times(pacer, 4.0, NOTHING)
    t = 4.0
    while not pacer.due(t):
        t += 1 / FPS
    assert t - 4.0 <= DUE_SHARE / 5.0 + 1 / FPS
    pacer.measured(result(t, SEEN))
    assert pacer.due(t + 1 / FPS) and not pacer.pacing


def test_search_hz_0_measures_every_frame() -> None:
    pacer = SearchPacer(0.0)
    assert len(measured_times(pacer, 5.0, NOTHING)) == round(5.0 * FPS)
