"""The estimator on real fish-farm frames and real net-free scenes (shared/data/real-field/).

What is known exactly about these frames is tested exactly: whether a net is in view, and the
net-free scenes must never give a net or a "too close". The sequence's frames are consecutive
(the vehicle held a 0.57-0.63 m DVL stand-off), so its distances must be consistent with each
other within what the estimator says its uncertainty is. The issue's recall and stand-off
targets are measured and printed by `netpose bench real` (see docs/benchmarks.md).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Iterator

import numpy as np
import pytest

from service.benchmarks.real_frames import (
    RealResult,
    real_field_frames,
    run_frames,
)
from service.core.camera import load_camera
from service.core.estimator import NetEstimator
from service.core.grey import decode_gray
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
        assert not r.estimate.net_seen, (r.frame.name, r.estimate.approx_range_m)


def test_the_stills_give_a_plausible_distance_or_say_why_not(results: list[RealResult]) -> None:
    stills = [r for r in results if r.frame.kind == "still"]
    assert stills
    for r in stills:
        e = r.estimate
        if not e.detected:
            # Refused, and why: on these stills the ROIs that agree do not pin the plane down
            # to the 2 % a distance needs (see docs/benchmarks.md).
            assert e.reason and e.distance_m is None
            continue
        assert e.range_m is not None and e.sigma_range_m is not None
        # The README: nets at ~0.4-0.5 m (close mesh) to ~1.4 m (the far recording; the
        # 27.5 mm mesh and published intrinsics put it nearer 1.7 m). Plausible, not truth.
        assert 0.3 < e.range_m < 2.5, (r.frame.name, e.range_m)
        assert e.sigma_range_m <= 0.02 * e.range_m
    # The clean, fully visible net of real-net-frame/ is measured.
    clean = [r for r in stills if r.frame.name == "real-net-frame"]
    if clean:
        assert clean[0].estimate.detected, clean[0].estimate.reason


def test_sequence_distances_agree_within_their_sigma(results: list[RealResult]) -> None:
    """Consecutive detections of one slow pass: each step between detected frames is within
    what the two reported sigmas allow (4 sigma of the difference), and the steps together are
    consistent with the sigmas (issue 11, point 3)."""
    seq = [r for r in results if r.frame.kind == "sequence"]
    assert len(seq) == 44
    found = [r.estimate for r in seq if r.estimate.detected]
    for e in found:
        assert e.distance_m is not None and e.sigma_distance_m is not None
    steps, sigmas = [], []
    for a, b in itertools.pairwise(seq):
        ea, eb = a.estimate, b.estimate
        if not (ea.detected and eb.detected):
            continue
        assert ea.distance_m is not None and eb.distance_m is not None
        assert ea.sigma_distance_m is not None and eb.sigma_distance_m is not None
        allowed = 4.0 * math.hypot(ea.sigma_distance_m, eb.sigma_distance_m)
        assert abs(eb.distance_m - ea.distance_m) <= allowed, (a.frame.name, b.frame.name)
        steps.append(eb.distance_m - ea.distance_m)
        sigmas.append(math.hypot(ea.sigma_distance_m, eb.sigma_distance_m))
    if len(steps) >= 3:
        # The steps together, against their reported sigmas: chi-square of the steps about their
        # mean (the pass's slow motion) within its 99.9 % quantile. With 3-6 steps the spread
        # itself is too uncertain to be compared with the median sigma as a pass/fail test
        # (`netpose bench real` prints that comparison; measured: sigma 1.3 cm against a spread
        # of 1.1 cm with numpy 2 / OpenCV 5, 1.1 cm against 1.9 cm on bookworm's stack).
        from scipy.stats import chi2

        z = (np.array(steps) - np.mean(steps)) / np.array(sigmas)
        assert float(np.sum(z**2)) <= chi2.ppf(0.999, len(steps) - 1), (steps, sigmas)


def test_a_net_seen_without_a_distance_is_where_its_measured_neighbours_are(
    results: list[RealResult],
) -> None:
    """Frames refused only for precision ("plane too uncertain") still say a net is in view,
    with the range that was refused and its sigma, and never a distance. That range must be
    honest: within 3 of its own sigmas, plus the pass's drift (0.70 to 0.97 m over 43 frames:
    under 1 cm a frame), of the nearest frame of the sequence that was measured."""
    seq = [r.estimate for r in results if r.frame.kind == "sequence"]
    measured = [(i, e) for i, e in enumerate(seq) if e.detected]
    seen = [(i, e) for i, e in enumerate(seq) if e.net_seen and not e.detected]
    assert measured and seen  # both kinds occur on this pass (bench real prints how many)
    for i, e in seen:
        assert e.distance_m is None and e.range_m is None and e.normal is None
        assert e.approx_range_m is not None and e.approx_sigma_range_m is not None
        assert e.reason.startswith("plane too uncertain")
        j, near = min(measured, key=lambda m: abs(m[0] - i))
        assert near.range_m is not None and near.sigma_range_m is not None
        allowed = 3.0 * math.hypot(e.approx_sigma_range_m, near.sigma_range_m) + 0.01 * abs(i - j)
        assert abs(e.approx_range_m - near.range_m) <= allowed, (i, j, e.approx_range_m,
                                                                near.range_m)


def test_crops_of_a_real_frame_agree_with_it_within_their_sigmas() -> None:
    """The real net frame whole and through five crops of 70 % of it (the corners and the
    centre, the calibration's principal point moved with each crop): one net, one camera, so
    one plane. Each crop that gives a distance agrees with the whole frame's range and normal
    within 3 of their combined sigmas (the normal's sigma is the total over both axes, so a
    Gaussian error exceeds 3 of it once in 8,000). Issue 11: crops of a real frame once spread
    over 17 deg against a claimed +-0.5 deg; here the fit's own sigma alone claimed 0.5-0.8 deg
    where the crops differ by 2-3 deg."""
    frames = [f for f in real_field_frames(shared_data_dir()) if f.name == "real-net-frame"]
    if not frames:
        pytest.skip("shared/data/real-net-frame/ not found")
    frame = frames[0]
    gray, _ = decode_gray(frame.image.read_bytes())
    camera = load_camera(frame.calibration)
    whole = NetEstimator(camera, frame.mesh).estimate(gray)
    assert whole.detected and whole.normal is not None
    assert whole.range_m is not None and whole.sigma_range_m is not None
    assert whole.sigma_normal_deg is not None
    h, w = gray.shape
    cw, ch = int(0.7 * w), int(0.7 * h)
    measured = 0
    for x0, y0 in ((0, 0), (w - cw, 0), (0, h - ch), (w - cw, h - ch),
                   ((w - cw) // 2, (h - ch) // 2)):
        crop_camera = dataclasses.replace(camera, width=cw, height=ch, cx=camera.cx - x0,
                                          cy=camera.cy - y0)
        crop = NetEstimator(crop_camera, frame.mesh).estimate(
            np.ascontiguousarray(gray[y0 : y0 + ch, x0 : x0 + cw]))
        if not crop.detected:
            continue
        measured += 1
        assert crop.range_m is not None and crop.sigma_range_m is not None
        assert crop.normal is not None and crop.sigma_normal_deg is not None
        assert abs(crop.range_m - whole.range_m) <= 3.0 * math.hypot(
            crop.sigma_range_m, whole.sigma_range_m), (x0, y0)
        angle = math.degrees(math.acos(min(1.0, abs(float(np.dot(crop.normal, whole.normal))))))
        assert angle <= 3.0 * math.hypot(crop.sigma_normal_deg, whole.sigma_normal_deg), (
            x0, y0, angle, crop.sigma_normal_deg, whole.sigma_normal_deg)
    assert measured >= 3  # the net fills this frame: most crops measure it


def test_the_tracked_run_measures_what_the_cold_run_does(results: list[RealResult]) -> None:
    """`netpose bench real`'s second run, as the daemon tracks: each sequence frame gets the
    previous detection as its prior (it once stopped the whole benchmark with a calibration
    error, a still's prior mapped through the strip's lens). It covers every frame, tracking
    never makes a net-free scene a net, and where both runs give a distance they agree within
    their sigmas."""
    tracked = list(run_frames(real_field_frames(shared_data_dir()), tracking=True))
    assert [r.frame for r in tracked] == [r.frame for r in results]
    for cold, warm in zip(results, tracked, strict=True):
        if warm.estimate.detected and warm.frame.kind == "no-net":
            pytest.fail(f"{warm.frame.name}: a net-free scene tracked as a net")
        if cold.estimate.detected and warm.estimate.detected:
            a, b = cold.estimate, warm.estimate
            assert a.range_m is not None and b.range_m is not None
            assert a.sigma_range_m is not None and b.sigma_range_m is not None
            assert abs(a.range_m - b.range_m) <= 3.0 * math.hypot(a.sigma_range_m,
                                                                  b.sigma_range_m)
