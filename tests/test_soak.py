"""The soak benchmark's machinery, briefly: the real daemon on a pre-rendered video, a MAVLink
peer playing the autopilot's clock, a Zenoh subscriber, and the CPU limit. The figures the
targets are judged by come from `netpose bench soak` (docs/benchmarks.md); here only what the
bench measures must be measured, and the limit must hold."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from service.benchmarks import soak

pytestmark = pytest.mark.timeout(300)


@pytest.fixture
def video(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[Path, Path]:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    return soak.prepare_video(640, 360, 15.0)


def test_a_short_soak_measures_what_it_reports(video: tuple[Path, Path]) -> None:
    path, calibration = video
    free = soak.run_case(soak.SoakCase("free", None), path, calibration, duration_s=12.0)
    held = soak.run_case(soak.SoakCase("held", 0.25), path, calibration, duration_s=12.0)
    for report in (free, held):
        assert report.exit_status == 0, report.notes
        assert math.isfinite(report.rss_mb)
        # The split is of the same sample: anonymous and file pages add up to the RSS, less
        # only shared memory (none here) and the kernel's rounding to whole pages.
        assert report.rss_anon_mb > 0 and report.rss_file_mb > 0
        assert abs(report.rss_anon_mb + report.rss_file_mb - report.rss_mb) <= 1.0
    # A quarter of a core may still be importing and on its first cold frames after 12 s
    # (bookworm's stack, a busy CI machine): its rates are the benchmark's, over minutes.
    assert free.frames_per_s > 0 and free.detected_fraction > 0.8 and free.budget_levels
    # What the autopilot got is measured where there is something to measure (whether a
    # quarter of a core keeps the distance fresh is the benchmark's figure, not this test's).
    assert free.distance_rate_hz > 5.0  # the link repeats readings at 10 Hz
    # Latency from the frames' own capture stamps, read on the autopilot's clock: positive and
    # below the link's freshness ceiling (0.8 s), or the link would not have sent it.
    assert 0.0 < free.latency_ms_median < 800.0 and math.isfinite(free.latency_ms_p99)
    # Start-up: the first distance comes after the first frame, which comes after launch.
    assert 0.0 < free.startup_s < free.launch_s
    assert held.how  # cgroup quota or pinned competitors, named in the report
    # The limit holds: a quarter of a core (and the scheduler's slack). Its frame rate is not
    # compared with the free one: at 640x360 and 15 frames/s a quarter of a core keeps up
    # with every frame since a missed frame no longer starts a whole-frame search at once
    # (measured 15.2 against 15.2 frames/s).
    assert held.cpu_percent <= 25.0 + 7.0


def test_open_water_sends_nothing_and_is_searched_at_search_hz(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The real daemon on the same scenes without the net: no DISTANCE_SENSOR at all, every
    frame read and published, and after the first HOLD_S the estimator measures `search_hz`
    of them a second (service/daemon/search_pace.py)."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    path, calibration = soak.prepare_video(640, 360, 15.0, net=False)
    water = soak.run_case(soak.SoakCase("open water", None, net=False), path, calibration,
                          duration_s=12.0, extra_overrides=["budget.search_hz=5"])
    assert water.exit_status == 0, water.notes
    assert water.distance_messages == 0
    assert water.detected_fraction == 0.0
    # The steady state starts 5 s after the first frame, past the 2 s at the camera's rate.
    assert water.frames_per_s > 10.0
    assert 3.0 <= water.measured_per_s <= 5.5
