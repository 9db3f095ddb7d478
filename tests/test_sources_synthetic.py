"""`synthetic:` source: scripted trajectories, ground truth on every frame, and the estimator
recovering that truth within the estimator's own accuracy targets."""

from __future__ import annotations

import itertools
import math
import time

import numpy as np
import pytest

from drivers.sources import Frame, FrameSource, SourceState, open_source
from drivers.sources.synthetic import BUILTIN_CAMERA, SyntheticSource
from drivers.synthetic_net import GroundTruth
from service.benchmarks.accuracy import (
    TARGET_DETECTION,
    TARGET_MEAN_PCT,
    TARGET_NORMAL_DEG,
    TARGET_STD_PCT,
)
from service.core.camera import load_camera
from service.core.estimator import NetEstimator
from tests.shared_data import REAL_NET_CALIBRATION, needs_real_net_frame

pytestmark = pytest.mark.timeout(120)

REAL_CALIBRATION = REAL_NET_CALIBRATION
SMALL = "width=320&height=180&realtime=0"


def read_frames(source: FrameSource, count: int) -> list[Frame]:
    frames = []
    for _ in range(count):
        frame = source.read(5.0)
        assert frame is not None
        frames.append(frame)
    return frames


def truth_of(frame: Frame) -> GroundTruth:
    assert isinstance(frame.truth, GroundTruth)
    return frame.truth


def test_same_seed_same_frames_other_seed_other_frames() -> None:
    with open_source(f"synthetic:?{SMALL}&seed=4") as a, open_source(
        f"synthetic:?{SMALL}&seed=4"
    ) as b, open_source(f"synthetic:?{SMALL}&seed=5") as c:
        fa, fb, fc = read_frames(a, 3), read_frames(b, 3), read_frames(c, 3)
    for x, y, z in zip(fa, fb, fc, strict=True):
        assert np.array_equal(x.image, y.image)
        assert not np.array_equal(x.image, z.image)
        assert truth_of(x).range_m == truth_of(z).range_m  # same trajectory, other noise


def test_frames_carry_the_wall_clock_as_it_is_set_mid_run(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A Pi without a real-time clock starts in 1970; NTP sets the clock mid-run. Frames of a
    file, image or rendered source kept the wall time of the source's open() plus the media
    offset: 56 years off every message's time to the end of the run (field review). They say
    the wall clock of now, as live cameras' frames do."""
    real_time = time.time
    shift = {"s": -1_795_000_000.0}  # 1970-ish, at open
    monkeypatch.setattr(time, "time", lambda: real_time() + shift["s"])
    with open_source(f"synthetic:?{SMALL}&seed=4") as source:
        before = read_frames(source, 3)
        shift["s"] = 0.0  # NTP steps the clock
        after = read_frames(source, 3)
    assert all(f.t_wall < 1e8 for f in before)
    assert all(abs(f.t_wall - real_time()) < 60.0 for f in after), [f.t_wall for f in after]
    gaps = [b.t_monotonic - a.t_monotonic for a, b in itertools.pairwise(after)]
    assert all(g > 0 for g in gaps)  # the monotonic clock is untouched


def test_approach_trajectory_truth_follows_the_script() -> None:
    url = f"synthetic:?{SMALL}&trajectory=approach&near=0.7&far=1.9&period=2&fps=10&tilt=15"
    with open_source(url) as source:
        frames = read_frames(source, 21)
    ranges = [truth_of(f).range_m for f in frames]
    expected = [1.3 + 0.6 * math.cos(2 * math.pi * f.index / 10 / 2) for f in frames]
    assert np.allclose(ranges, expected, atol=1e-12)
    assert ranges[0] == pytest.approx(1.9) and ranges[10] == pytest.approx(0.7)
    for frame in frames:
        truth = truth_of(frame)
        # Perpendicular distance = range along the axis x cos(tilt) for a plane tilted 15 deg.
        assert truth.distance_m == pytest.approx(truth.range_m * math.cos(math.radians(15)))
        assert truth.tilt_deg == pytest.approx(15.0)
        assert math.degrees(math.acos(truth.normal[2] * -1)) == pytest.approx(15.0, abs=1e-9)
    steps = np.diff([f.t_monotonic for f in frames])
    assert np.allclose(steps, 0.1, atol=1e-9)


def test_sweep_swings_the_tilt_and_gap_removes_the_net() -> None:
    url = f"synthetic:?{SMALL}&trajectory=sweep&range=1.1&tilt=30&period=4&fps=4&gap=1-2"
    with open_source(url) as source:
        frames = read_frames(source, 16)
    tilts = [truth_of(f).pose.tilt_deg for f in frames]
    assert np.allclose(tilts, [30 * math.sin(2 * math.pi * f.index / 4 / 4) for f in frames])
    assert max(tilts) == pytest.approx(30.0) and min(tilts) == pytest.approx(-30.0)
    present = [truth_of(f).net_present for f in frames]
    assert present == [not (1.0 <= f.index / 4 < 2.0) for f in frames]
    assert present.count(False) == 4


def test_duration_ends_and_loop_repeats() -> None:
    with open_source(f"synthetic:?{SMALL}&fps=10&duration=0.5") as source:
        frames = []
        while (frame := source.read(1.0)) is not None:
            frames.append(frame)
        assert source.state is SourceState.ENDED
    assert [f.index for f in frames] == [0, 1, 2, 3, 4]
    with open_source(f"synthetic:?{SMALL}&fps=10&duration=0.5&loop=1") as source:
        looped = read_frames(source, 12)
    assert [f.index for f in looped] == list(range(12))
    assert np.array_equal(looped[7].image, frames[2].image)  # frame 2 again, second pass


@needs_real_net_frame
def test_built_in_camera_and_calibration_file() -> None:
    source = SyntheticSource("synthetic:")
    assert (source.camera.width, source.camera.height) == (960, 540)
    assert source.camera.fx == pytest.approx(BUILTIN_CAMERA.fx * 0.75)
    # 82 degrees horizontal field of view, as documented.
    hfov = 2 * math.degrees(math.atan(BUILTIN_CAMERA.width / 2 / BUILTIN_CAMERA.fx))
    assert hfov == pytest.approx(82.0, abs=0.1)
    assert source.realtime and not source.loop
    source.close()
    calibrated = SyntheticSource(
        f"synthetic:?calibration={REAL_CALIBRATION}&width=640&height=360&realtime=0"
    )
    assert calibrated.camera == load_camera(REAL_CALIBRATION).scaled_to(640, 360)
    with calibrated:
        frame = calibrated.read(5.0)
    assert frame is not None and frame.image.shape == (360, 640)


def test_estimator_recovers_the_ground_truth_within_its_targets() -> None:
    # The default scene (960x540, square 25 mm mesh) along an approach from 2.0 m to 0.6 m and
    # back, sampled at 2 frames per second over one 20 s period, with a net-absent gap.
    url = "synthetic:?realtime=0&fps=2&gap=4-5.5&seed=11"
    with open_source(url) as source:
        assert isinstance(source, SyntheticSource)
        estimator = NetEstimator(source.camera, source.mesh)
        errors_pct, normal_errors, detected, present, false_positives = [], [], 0, 0, 0
        for frame in read_frames(source, 40):
            truth = truth_of(frame)
            estimate = estimator.estimate(frame.image)
            if not truth.net_present:
                false_positives += int(estimate.detected)
                continue
            present += 1
            if not estimate.detected:
                continue
            detected += 1
            assert estimate.range_m is not None and estimate.normal is not None
            errors_pct.append((estimate.range_m / truth.range_m - 1.0) * 100.0)
            cos = float(np.clip(np.dot(estimate.normal, truth.normal), -1.0, 1.0))
            normal_errors.append(math.degrees(math.acos(cos)))
    assert present == 37 and false_positives == 0
    assert detected / present >= TARGET_DETECTION
    assert abs(float(np.mean(errors_pct))) <= TARGET_MEAN_PCT
    assert float(np.std(errors_pct, ddof=1)) <= TARGET_STD_PCT
    assert float(np.mean(normal_errors)) <= TARGET_NORMAL_DEG


def test_realtime_renderer_slower_than_the_frame_rate_still_delivers_current_frames() -> None:
    # A 640x360 render takes milliseconds to tens of milliseconds; at 240 fps frames come due
    # faster than they can be drawn. The source must jump to the frame due now, not render every
    # missed frame (it would fall further behind with each one).
    fps = 240.0
    url = f"synthetic:?width=640&height=360&fps={fps:g}&realtime=1&trajectory=approach&period=2"
    with open_source(url) as source:
        assert isinstance(source, SyntheticSource)
        t0 = source.read(2.0)
        assert t0 is not None
        frames = []
        for _ in range(5):
            started = time.monotonic()
            frame = source.read(2.0)
            assert frame is not None
            # The frame handed out was due when the read started (not one from the backlog).
            assert frame.t_monotonic > started - 1.0 / fps - 1e-6
            frames.append(frame)
        stats = source.stats()
    indices = [f.index for f in frames]
    assert indices == sorted(set(indices))
    assert indices[-1] - t0.index > len(frames)  # frames were skipped
    assert stats.drops == indices[-1] + 1 - stats.frames
    for frame in frames:
        # The truth belongs to the frame's own time on the trajectory.
        assert truth_of(frame).range_m == pytest.approx(
            source.trajectory.pose_at(frame.index / fps).range_m
        )
