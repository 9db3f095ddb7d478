"""Never a confident wrong distance (issues 11 and 17): scale proofs, grids that are not nets, a
wrong opening angle, a net too close to measure, and a short seeded run of the integrity
benchmark.

Frames come from drivers.synthetic_net; non-net grids (bricks, checkerboards, tiles) are rendered
on the same plane geometry as a net, so only what the pattern looks like differs.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.synthetic_net import GroundTruth, NetPose, NetRenderer, SceneStyle
from service.benchmarks import integrity
from service.benchmarks.scenes import PAPER_MESH, bench_camera
from service.core.camera import CameraModel
from service.core.estimator import NetEstimator
from service.core.mesh import MeshGeometry
from service.core.results import NetEstimate
from tests.numeric_stack import open_case

GROSS = integrity.GROSS_RANGE


def _range_error(est: NetEstimate, truth: GroundTruth) -> float:
    assert est.range_m is not None
    return est.range_m / truth.range_m - 1.0


# -- a scale hypothesis must be proved ------------------------------------------------------------


def test_a_seed_at_a_harmonic_scale_does_not_give_its_distance() -> None:
    """The failure of issue 11: 1080p, 80 deg, a 1.5 cm mesh at 0.40 m tilted 20 deg under
    caustics was reported at 0.69 m (x sqrt 3, a lattice of the mesh's harmonics) with a sigma
    of 1.3 mm. Here the estimator is handed exactly such wrong hypotheses as the previous
    frame's estimate (x sqrt 2, sqrt 3, 2, 3 and their inverses): the answer must be the true
    distance or none, never the hypothesis."""
    w, h = 1920, 1080
    f = 0.5 * w / math.tan(math.radians(40.0))
    camera = CameraModel(width=w, height=h, fx=f, fy=f, cx=(w - 1) / 2 + 3, cy=(h - 1) / 2 - 2,
                         distortion=(-0.08, 0.05, 0.0005, -0.0003, 0.0))
    renderer = NetRenderer(camera, PAPER_MESH)
    estimator = NetEstimator(camera, PAPER_MESH)
    frame, truth = renderer.render(NetPose(0.40, 20.0, 30.0, 25.0, (0.3, 0.6)),
                                   np.random.default_rng(5), SceneStyle(caustics=0.3))
    for factor in (math.sqrt(2), math.sqrt(3), 2.0, 3.0, 1 / math.sqrt(2), 1 / math.sqrt(3)):
        wrong = NetEstimate(detected=True, confidence=0.9, normal=truth.normal,
                            distance_m=truth.distance_m * factor,
                            range_m=truth.range_m * factor)
        est = estimator.estimate(frame, prior=wrong)
        if est.detected:
            # Measured 0.03 %; the Table-1 target is 1 %.
            assert abs(_range_error(est, truth)) < 0.01, factor


@pytest.mark.parametrize("prior_age_s", [None, 0.5])
@pytest.mark.parametrize("size", [(640, 360), (1280, 720), (384, 216)])
def test_a_net_that_jumped_much_closer_is_not_tracked_at_the_old_scale(
    size: tuple[int, int], prior_age_s: float | None
) -> None:
    """The previous frame saw the net at 0.4 m; this one (frames were lost: half a second, or
    an unknown time) at 0.1-0.2 m. The tracked plane's rectification shows the mesh's 2nd or
    4th harmonic where the old mesh was: that must not come out as the old distance."""
    camera = bench_camera(*size)
    mesh = MeshGeometry(0.025)
    renderer = NetRenderer(camera, mesh)
    estimator = NetEstimator(camera, mesh)
    style = SceneStyle(focus_m=1.5, aperture_m=0.003)
    first, _ = renderer.render(NetPose(0.4, 15.0, 30.0, 10.0), np.random.default_rng(1), style)
    prior = estimator.estimate(first)
    assert prior.detected
    for z in (0.2, 0.16, 0.12, 0.1, 0.08):
        frame, truth = renderer.render(NetPose(z, 15.0, 30.0, 10.0), np.random.default_rng(1),
                                       style)
        est = estimator.estimate(frame, prior=prior, prior_age_s=prior_age_s)
        if est.detected:
            assert abs(_range_error(est, truth)) < GROSS, z


def _approach(z0: float, z1: float, frames: int) -> tuple[list[NetEstimate], list[GroundTruth]]:
    """A 640x360 camera closing in from z0 to z1 over `frames` frames at 30 frames/s, each
    frame estimated with the previous detection as prior (as `Pipeline` feeds it)."""
    camera = bench_camera(640, 360)
    renderer = NetRenderer(camera, PAPER_MESH, seed=2)
    estimator = NetEstimator(camera, PAPER_MESH)
    rng = np.random.default_rng(2)
    prior: NetEstimate | None = None
    estimates, truths = [], []
    for i in range(frames):
        z = z0 + (z1 - z0) * i / (frames - 1)
        frame, truth = renderer.render(NetPose(z, 20.0, 30.0, 10.0), rng)
        est = estimator.estimate(frame, prior=prior, prior_age_s=1.0 / 30.0)
        prior = est if est.detected else None
        estimates.append(est)
        truths.append(truth)
    return estimates, truths


def test_tracking_renews_its_proof_of_scale_on_schedule() -> None:
    """At 0.15 m/s the net cannot change scale by a harmonic factor between frames 33 ms
    apart, so a tracked frame keeps the last proof of scale, and the blind check (a full
    search) runs once every `scale_proof_frames` frames instead of on every frame."""
    every = NetEstimator(bench_camera(640, 360), PAPER_MESH).settings.scale_proof_frames
    estimates, truths = _approach(1.10, 1.00, 2 * every + 5)
    assert all(e.detected for e in estimates)
    ages = [e.frames_since_scale_proof for e in estimates]
    proved = [i for i, a in enumerate(ages) if a == 0]
    assert proved == [0, every, 2 * every], ages
    for est in estimates:
        # Only a proving frame spends time on the blind check.
        assert ("blind_check" in est.timings_ms) == (est.frames_since_scale_proof == 0 and
                                                     est is not estimates[0])
    # Skipping the check changed no answer: every range within 3 of its sigmas (Table 1: 1 %).
    for est, truth in zip(estimates, truths, strict=True):
        assert est.range_m is not None and est.sigma_range_m is not None
        assert abs(est.range_m - truth.range_m) < 3.0 * est.sigma_range_m + 1e-3


def test_a_range_that_drifted_from_the_proved_one_is_proved_again() -> None:
    """Closing from 1.2 to 0.6 m in a second: the scale is proved again each time the range
    has left the last proved one by the largest step a tracked frame may take unchecked."""
    from service.core.estimator import MAX_TRACKED_SCALE_STEP

    estimates, _ = _approach(1.2, 0.6, 30)
    proved_at: float | None = None
    for est in estimates:
        assert est.detected and est.range_m is not None, est.reason
        if est.frames_since_scale_proof == 0:
            proved_at = est.range_m
        assert proved_at is not None and est.scale_proved_range_m == pytest.approx(proved_at)
        assert abs(math.log(est.range_m / proved_at)) < math.log(MAX_TRACKED_SCALE_STEP)
    assert sum(e.frames_since_scale_proof == 0 for e in estimates) >= 3


def test_a_tracked_frame_keeps_the_priors_proof_of_twine_only_while_it_holds() -> None:
    """A tracked frame spares itself the proofs its prior made (the scale check, the twine
    profile) only while they hold: a proof of this age, at a range the net cannot have left by
    a harmonic factor since. Shown on a 16 px checkerboard, which every proof-checking path
    refuses, tracked from priors that claim a proof at the range its lattice (the squares'
    diagonal) gives: only the prior whose proof holds is believed. Only a frame that passed the
    proofs gives such a prior; a forged one shows where the proofs are carried and no further."""
    from service.core.estimator import MAX_TRACKED_SCALE_STEP

    renderer = NetRenderer(CAMERA_720P, SQUARE_25)
    frame, _ = renderer.render(
        NetPose(1.0, 0.0, 30.0, 10.0), np.random.default_rng(3),
        SceneStyle(pattern="checkerboard", pattern_size_m=16.0 / CAMERA_720P.fx,
                   grout_fraction=0.08))
    estimator = NetEstimator(CAMERA_720P, SQUARE_25)
    every = estimator.settings.scale_proof_frames
    lattice_range = math.sqrt(2.0) * SQUARE_25.bar_length_m * CAMERA_720P.fx / 16.0

    def tracked(proved_range: float, age_s: float | None, since_proof: int = 0) -> NetEstimate:
        prior = NetEstimate(
            detected=True, confidence=0.9, normal=(0.0, 0.0, -1.0), distance_m=lattice_range,
            range_m=lattice_range, sigma_range_m=0.01 * lattice_range,
            sigma_distance_m=0.01 * lattice_range, sigma_normal_deg=1.0,
            scale_proved_range_m=proved_range, frames_since_scale_proof=since_proof)
        return estimator.estimate(frame, prior=prior, prior_age_s=age_s)

    held = tracked(lattice_range, 1.0 / 30.0)
    assert held.detected and held.range_m == pytest.approx(lattice_range, rel=0.01)
    not_held = [
        tracked(lattice_range, None),  # an unknown time since the prior
        tracked(lattice_range, 0.5),  # long enough to come nearer by a harmonic factor
        tracked(lattice_range, 1.0 / 30.0, since_proof=every - 1),  # due for renewal
        tracked(lattice_range * MAX_TRACKED_SCALE_STEP * 1.05, 1.0 / 30.0),  # drifted from it
    ]
    for est in not_held:
        assert not est.detected and est.distance_m is None
        assert "checkerboard" in est.reason, est.reason


# -- grids that are not nets ----------------------------------------------------------------------


CAMERA_720P = bench_camera(1280, 720)
SQUARE_25 = MeshGeometry(0.025)


def _grid(pattern: str, period_px: float, tilt: float, grout: float = 0.08,
          mesh: MeshGeometry = SQUARE_25) -> NetEstimate:
    renderer = NetRenderer(CAMERA_720P, mesh)
    size = period_px * 1.0 / CAMERA_720P.fx  # the pattern's period at 1 m, frontal
    frame, truth = renderer.render(
        NetPose(1.0, tilt, 30.0, 10.0), np.random.default_rng(3),
        SceneStyle(pattern=pattern, pattern_size_m=size, grout_fraction=grout),
    )
    assert not truth.net_present
    return NetEstimator(CAMERA_720P, mesh).estimate(frame)


@pytest.mark.parametrize("period_px", [8, 16, 30])
@pytest.mark.parametrize("tilt", [0.0, 25.0])
def test_checkerboards_are_not_nets(period_px: int, tilt: float) -> None:
    est = _grid("checkerboard", period_px, tilt)
    assert not est.detected and est.distance_m is None and not est.too_close
    # Refused for what it is: a 50 % grid has no (1, 1) cross terms but strong (2, 1) ones.
    assert "checkerboard" in est.reason


@pytest.mark.parametrize(("period_px", "tilt"), [(30, 0.0), (30, 25.0), (60, 0.0), (60, 25.0)])
def test_brick_walls_are_not_nets(period_px: int, tilt: float) -> None:
    est = _grid("bricks", period_px, tilt)
    assert not est.detected and est.distance_m is None and not est.too_close


@pytest.mark.parametrize("period_px", [30, 60, 120])
def test_square_tiles_are_not_a_rhombic_net(period_px: int) -> None:
    """Square tiles with thin grout look exactly like a square net (documented in
    docs/estimator.md); against a rhombic mesh their shape gives them away."""
    rhombic = MeshGeometry(0.025, opening_angle_deg=60.0)
    est = _grid("tiles", period_px, 10.0, mesh=rhombic)
    assert not est.detected and est.distance_m is None and not est.too_close


# -- the video's own compression blocks ----------------------------------------------------------

BLOCKS_FRAME = Path(__file__).parent / "data" / "mpeg4-open-water-blocks.png"


def test_a_videos_compression_blocks_are_not_a_net(monkeypatch: pytest.MonkeyPatch) -> None:
    """A real codec's blocks: the soak benchmark's open-water video (the renderer's scene
    without a net, encoded by OpenCV's FFmpeg MPEG-4 at its default quality, 1280x720, frame 87,
    decoded and stored losslessly). In its dark, smooth lower half the 8x8 blocks are a square
    grid on the pixel grid, and six ROIs agreed on it: a 'net' at 2.26 m, tilt 1.4 deg,
    sigma 3 cm, confidence 0.51. Refused for what it is; without that check it is a net."""
    import cv2

    from service.core import estimator as estimator_module

    gray = cv2.imread(str(BLOCKS_FRAME), cv2.IMREAD_GRAYSCALE)
    assert gray is not None and gray.shape == (720, 1280)
    est = NetEstimator(CAMERA_720P, MeshGeometry(0.025)).estimate(gray)
    assert not est.detected and est.distance_m is None and not est.too_close
    assert "compression blocks (8 px" in est.reason
    monkeypatch.setattr(estimator_module, "_compression_grid", lambda rois, image: "")
    assert NetEstimator(CAMERA_720P, MeshGeometry(0.025)).estimate(gray).detected


@pytest.mark.parametrize("jpeg_quality", [None, 60])
def test_a_net_of_exactly_the_block_size_on_the_pixel_axes_is_still_a_net(
    jpeg_quality: int | None, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The other way round: a net facing the camera squarely, its bars along the pixel axes
    and 8 px apart, through a lens without distortion (so nothing but the image's own steps
    tells it from a block grid), at 8 mesh phases, lossless and as JPEG. The block test is
    reached on every frame, and the twine's two edges per period keep the net a net."""
    import cv2

    from service.core import estimator as estimator_module

    camera = dataclasses.replace(CAMERA_720P, distortion=tuple(0.0 for _ in
                                                               CAMERA_720P.distortion))
    mesh = MeshGeometry(0.025)
    range_m = camera.fx * mesh.bar_length_m / 8.0
    renderer = NetRenderer(camera, mesh, seed=1)
    estimator = NetEstimator(camera, mesh)
    tested: list[bool] = []
    real = estimator_module._block_edges

    def spy(*args: Any) -> bool:
        tested.append(real(*args))
        return tested[-1]

    monkeypatch.setattr(estimator_module, "_block_edges", spy)
    for k in range(8):
        pose = NetPose(range_m, 0.0, 0.0, 0.0, (k / 8, (3 * k % 8) / 8))
        frame, _ = renderer.render(pose, np.random.default_rng(k), SceneStyle())
        if jpeg_quality is not None:
            _, data = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
            decoded = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE)
            assert decoded is not None
            frame = np.asarray(decoded, dtype=np.uint8)
        est = estimator.estimate(frame)
        assert est.detected, (k, est.reason)
        assert est.range_m is not None and abs(est.range_m / range_m - 1.0) < 0.01
    assert len(tested) >= 8 and not any(tested)


# -- wrong opening angle --------------------------------------------------------------------------


def test_a_45_degree_net_measured_as_square_gives_no_distance_and_says_why() -> None:
    """Issue 17, item 3: a 45 deg rhombic net with the default 90 deg gave +19 % with a tiny
    sigma. Now: no distance, the measured opening angle in the estimate and in `reason`."""
    rhombic = MeshGeometry(0.015, opening_angle_deg=45.0)
    renderer = NetRenderer(CAMERA_720P, rhombic)
    frame, _ = renderer.render(NetPose(1.2, 20.0, 60.0, 15.0), np.random.default_rng(4))
    right = NetEstimator(CAMERA_720P, rhombic).estimate(frame)
    assert right.detected, right.reason
    wrong = NetEstimator(CAMERA_720P, MeshGeometry(0.015)).estimate(frame)
    assert not wrong.detected and wrong.distance_m is None
    assert wrong.measured_opening_deg == pytest.approx(45.0, abs=3.0)
    assert "opening angle measured 4" in wrong.reason


# -- too close to measure -------------------------------------------------------------------------


@pytest.mark.parametrize("size", [(640, 360), (1280, 720), (384, 216)])
def test_approaching_the_net_ends_in_too_close_not_in_no_net(size: tuple[int, int]) -> None:
    """Issue 17, item 4: an ROV closing in on a 2.5 cm mesh (82 deg camera, defocused up close)
    is measured down to about 0.25 m; closer, the estimate says "too close" (no distance),
    never "no net"."""
    camera = bench_camera(*size)
    mesh = MeshGeometry(0.025)
    renderer = NetRenderer(camera, mesh)
    estimator = NetEstimator(camera, mesh)
    style = SceneStyle(focus_m=1.5, aperture_m=0.003)
    prior: NetEstimate | None = None
    states = []
    for z in (0.4, 0.3, 0.25, 0.2, 0.16, 0.12, 0.1, 0.08):
        frame, truth = renderer.render(NetPose(z, 15.0, 30.0, 10.0), np.random.default_rng(1),
                                       style)
        est = estimator.estimate(frame, prior=prior)
        if est.detected:
            assert abs(_range_error(est, truth)) < 0.01
            assert not est.too_close
            prior = est
        else:
            assert est.distance_m is None
        states.append("D" if est.detected else "C" if est.too_close else "-")
    assert states[:2] == ["D", "D"], states  # 0.4 m and 0.3 m are measured
    # Below the measurable range every frame is "too close" (measured: from 0.2 m on).
    assert set(states[4:]) == {"C"}, states


@pytest.mark.parametrize("seed", range(6))
def test_never_too_close_without_a_net(seed: int) -> None:
    renderer = NetRenderer(bench_camera(640, 360), MeshGeometry(0.025))
    estimator = NetEstimator(bench_camera(640, 360), MeshGeometry(0.025))
    rng = np.random.default_rng(seed)
    style = SceneStyle.realistic(rng, net_present=False, fish_front_cover=0.2 * (seed % 2))
    frame, truth = renderer.render(NetPose(0.3), rng, style)
    assert not truth.net_present
    est = estimator.estimate(frame)
    assert not est.detected and not est.too_close


# -- gross errors found by the integrity benchmark, as regression tests --------------------------


# (seed, group, index) of `netpose bench integrity` frames that once gave a valid distance more
# than 5 % off. Each was a plane fitted to a few ROIs on one side of the image and carried to
# the optical axis: a billowing net (11, 13, 1: 7 ROIs at 5-7 px periods on the near side, +5.6 %
# at sigma 1 %), or a steep view whose far side is unresolved (5, 60, 11: -9.9 %; 5, 72, 5:
# -5.8 %; 5, 34, 10: -5.7 %, with the pooled variance before the lever term). (1, 995, 7): a
# 46 deg rhombic mesh at 1.91 m, 4.8 px at the centre, billowing, -5.6 % at sigma 1.0 %: only
# the ROIs whose own (noisy) period measured at least `min_source_period_px` were kept, so near
# that limit the coarser readings were selected and the plane came out nearer; the period the
# seed plane predicts at each ROI must now pass that limit too. Judged on the prediction alone
# (a trial of 2026-11-25), three other frames of that run went wrong, all rhombic, billowing
# nets near 5 px whose fine, biased ROIs were then let in: (1, 48, 2) -6.8 %, (1, 751, 2)
# +5.8 %, (1, 877, 5) +5.7 %.
GROSS_CASES = [(11, 13, 1), (5, 60, 11), (5, 72, 5), (5, 34, 10), (11, 13, 4), (1, 995, 7),
               (1, 48, 2), (1, 751, 2), (1, 877, 5)]


def _estimate_case(seed: int, group: int, index: int) -> tuple[NetEstimate, GroundTruth]:
    """One frame of `netpose bench integrity`, rendered again and estimated cold."""
    case = integrity.build_case(seed, group, index)
    frame, truth = integrity.render_case(case)
    return NetEstimator(case.camera, case.mesh).estimate(frame), truth


@pytest.mark.parametrize(("seed", "group", "index"), GROSS_CASES)
def test_former_gross_errors_give_no_distance_or_an_honest_one(
    seed: int, group: int, index: int
) -> None:
    est, truth = _estimate_case(seed, group, index)
    if not est.detected:
        assert est.distance_m is None and est.reason
        return
    assert est.sigma_range_m is not None
    _assert_not_gross(est, truth)
    assert abs(_range_error(est, truth)) * truth.range_m <= 3.0 * est.sigma_range_m


def _assert_not_gross(est: NetEstimate, truth: GroundTruth) -> None:
    """A valid output within the integrity benchmark's gross limits (range and normal)."""
    assert est.normal is not None
    normal_error = math.degrees(math.acos(min(1.0, float(np.dot(est.normal, truth.normal)))))
    assert abs(_range_error(est, truth)) <= GROSS
    assert normal_error <= integrity.GROSS_NORMAL_DEG


# Gross errors that the 20,000-frame run of 2026-11-24 (seed 1) found among 8,575 valid outputs;
# both gave the same answer with the code before that session's speed work, so they were not
# regressions of it. Kept here, strict on bookworm's pinned stack only (tests/numeric_stack.py),
# until it is mended (docs/benchmarks.md):
# - (1, 482, 19): 640x360, 0.74 m, 20 deg, four or five ROIs (the fewest a plane may have): the
#   range is right (+2 %) but the normal is off: on numpy 2 / OpenCV 5 by 8.9 deg at a sigma of
#   3.3 deg (not gross), on bookworm's stack by 12.5 deg at 3.7 deg, still gross there (with the
#   normal's deformation term of 2026-11-25; before it, 3.6 deg).
# (1, 995, 7), the other one, is mended (GROSS_CASES above).
_OPEN = "open gross error of the 20,000-frame integrity run"
OPEN_GROSS_CASES = [pytest.param(1, 482, 19, marks=open_case(_OPEN, fails_on_bookworm=True))]


@pytest.mark.parametrize(("seed", "group", "index"), OPEN_GROSS_CASES)
def test_open_gross_errors_give_no_distance_or_an_honest_one(
    seed: int, group: int, index: int
) -> None:
    test_former_gross_errors_give_no_distance_or_an_honest_one(seed, group, index)


# Tracked frames (the frame after a valid one, that one as the prior: `integrity.moved_case`)
# that gave a gross error in the first 20,000-frame run with them (seed 1, 2026-11-26): 3 among
# 7,857 valid tracked outputs, none among the 8,507 cold ones of the same run. Two are just over
# the 5 % in range at 3.4 and 4.0 sigma (a fouled 480x270 net with boards, ropes and a fish at
# 0.35 m, +5.3 %; a billowing, turbid one at 0.64 m, -5.1 %), one is 11.0 deg off in the normal
# at a sigma of 2.8 deg (a billowing 1920x1080 net at 0.92 m seen through boards and a fish).
# In all three the prior did not hold and the frame was searched whole: they are gross errors
# of the cold path, on frames the run's cold draw did not contain. Open (docs/benchmarks.md).
_OPEN_TRACKED = "open gross error of a tracked frame (integrity run)"
OPEN_TRACKED_GROSS_CASES = [
    pytest.param(1, 689, 5, marks=open_case(_OPEN_TRACKED, fails_on_bookworm=False)),
    pytest.param(1, 715, 18, marks=open_case(_OPEN_TRACKED, fails_on_bookworm=True)),
    pytest.param(1, 77, 19, marks=open_case(_OPEN_TRACKED, fails_on_bookworm=True)),
]


def _estimate_tracked_case(seed: int, group: int, index: int
                           ) -> tuple[NetEstimate, GroundTruth] | None:
    """The tracked frame after one of `netpose bench integrity`'s frames, as the benchmark
    makes it; None when the first frame gives no distance to track from."""
    case = integrity.build_case(seed, group, index)
    estimator = NetEstimator(case.camera, case.mesh)
    renderer = NetRenderer(case.camera, case.mesh)
    frame, truth = integrity.render_case(case, renderer)
    first = estimator.estimate(frame)
    if not (first.detected and truth.net_present):
        return None
    _, _, truth, est, _ = integrity.estimate_tracked(case, first, renderer, estimator)
    return est, truth


@pytest.mark.parametrize(("seed", "group", "index"), OPEN_TRACKED_GROSS_CASES)
def test_open_tracked_gross_errors_give_no_distance_or_an_honest_one(
    seed: int, group: int, index: int
) -> None:
    tracked = _estimate_tracked_case(seed, group, index)
    assert tracked is not None
    est, truth = tracked
    if est.detected:
        _assert_not_gross(est, truth)


# Frames of a 3,000-frame run (seed 7) whose rectified passes went round between planes without
# settling (each pass fitted to the subset of ROIs that agreed in its view), on both numeric
# stacks: a 1920x1080 rhombic net at 2.6 m, 40 deg, 4 px periods, and a fouled 1280x720 net at
# 2 m, 32 deg. Once "no net"; the net is seen, its range refused with the passes' spread.
UNSETTLED_CASES = [(7, 54, 7), (7, 58, 15)]


@pytest.mark.parametrize(("seed", "group", "index"), UNSETTLED_CASES)
def test_passes_that_do_not_settle_give_a_net_seen_and_no_distance(
    seed: int, group: int, index: int
) -> None:
    est, truth = _estimate_case(seed, group, index)
    assert not est.detected and est.distance_m is None and est.range_m is None
    assert est.net_seen and "do not settle on one plane" in est.reason, est.reason
    assert est.approx_range_m is not None and est.approx_sigma_range_m is not None
    assert abs(est.approx_range_m - truth.range_m) <= 3.0 * est.approx_sigma_range_m


def test_the_t_factor_is_the_student_t_quantile_ratio() -> None:
    """The sigma's widening for a variance known to `dof` degrees of freedom: the geometric mean
    of the Student-t over normal quantiles at 1 and 3 sigma, finite from the pooled variance's
    least (4 prior degrees of freedom + 1)."""
    from scipy import stats

    from service.core.estimator import _t_factor

    p1, p3 = stats.norm.cdf(1.0), stats.norm.cdf(3.0)
    for dof in (4, 5, 6, 8, 12, 20, 50):
        exact = math.sqrt(stats.t.ppf(p1, dof) * stats.t.ppf(p3, dof) / 3.0)
        assert _t_factor(dof) == pytest.approx(exact, rel=0.01), dof
    assert _t_factor(1e6) == pytest.approx(1.0, abs=1e-4)


# -- the integrity benchmark, short ---------------------------------------------------------------


@pytest.mark.timeout(1800)  # ~5 min on two idle cores; far longer while the machine is shared
def test_short_integrity_run() -> None:
    """A short seeded run of `netpose bench integrity` over the whole envelope (frames 384x180
    to 1920x1080, 60-110 deg with distortion, square and rhombic meshes of 1-4 cm, 0.3-3 m,
    tilts to 60 deg, fouling, boards, billowing, JPEG, ...). The targets of issue 11: no gross
    error among the valid outputs, 3-sigma coverage of at least 99 %, error/sigma with a
    standard deviation within 0.7-1.5, no net-free frame taken for a net or "too close".

    1,000 frames, as the issue asks: ~450 valid outputs, so that 99 % coverage allows four
    outside 3 sigma. With 400 frames (~175 valid) one frame decides it (measured: 2 outside,
    98.9 %, where 2,000-frame runs of seeds 5 and 11 give 99.5 %).

    Each valid frame is followed by a tracked one (the next frame, that one as the prior, as
    the daemon tracks): no gross error there either. Their sigma's coverage is reported, not
    asserted: it falls short (98.2 % of 394 in this run; docs/estimator.md)."""
    rows = integrity.run_rows(frames=1000, seed=11, jobs=2)
    gross = [integrity.describe_row(r) for r in rows if r.gross]
    assert not gross, "\n".join(gross)
    tracked = integrity.summarise([r for r in rows if r.tracked])
    assert tracked.valid >= 300
    summary = integrity.summarise([r for r in rows if not r.tracked])
    assert summary.valid >= 350  # detection is measured by the benchmark; enough to judge sigma
    assert summary.coverage_3sigma >= integrity.TARGET_COVERAGE
    assert integrity.TARGET_Z_STD[0] <= summary.z_std <= integrity.TARGET_Z_STD[1]
    assert summary.false_nets == 0 and summary.false_too_close == 0
