"""Net inspection: rendered damage, the one-frame detector, confirmation across frames, and
which frames are inspected (service/core/damage.py, damage_track.py, drivers/synthetic_damage.py).

Frames are rendered with the renderer's plain underwater scene (`SceneStyle()`: light gradient,
caustics, sun rays, snow, fish behind, blur, noise) at 960x540 through the benchmark's 82 deg
camera; the realistic scenes are the benchmark's (`netpose bench damage`,
tests/test_damage_bench.py).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import numpy.typing as npt
import pytest

from drivers.synthetic_damage import (
    Hole,
    NetDamage,
    bars_between,
    cell_at_pixel,
    cut_bar,
    hole_truth,
    missing_knot,
    torn_hole,
)
from drivers.synthetic_net import NetPose, NetRenderer, SceneStyle
from service.benchmarks.scenes import bench_camera
from service.core.damage import DamageDetector, DamageScan, DamageSettings
from service.core.damage_plan import InspectionPlanner
from service.core.damage_track import ConfirmedHole, HoleTracker, NetInspector
from service.core.estimator import NetEstimator
from service.core.mesh import MeshGeometry
from service.core.plane_frame import plane_axes
from service.core.results import NetEstimate
from service.core.tracking import FilterSettings, NetTracker

CAMERA = bench_camera(960, 540)
MESH = MeshGeometry(bar_length_m=0.02)
SIZE_TOLERANCE = 0.20  # the target for a hole's size


@pytest.fixture(scope="module")
def renderer() -> NetRenderer:
    return NetRenderer(CAMERA, MESH)


@pytest.fixture(scope="module")
def estimator() -> NetEstimator:
    return NetEstimator(CAMERA, MESH)


def _render(renderer: NetRenderer, pose: NetPose, seed: int, damage: NetDamage | None = None,
            style: SceneStyle | None = None) -> np.ndarray:
    image, _ = renderer.render(pose, np.random.default_rng(seed), style or SceneStyle(),
                               damage=damage)
    return image


# -- rendered damage ---------------------------------------------------------------------------
def test_holes_merge_the_cells_their_missing_bars_separated() -> None:
    rng = np.random.default_rng(0)
    bar = cut_bar((3, 4), 1, rng)
    assert bar.cells == {(2, 4), (3, 4)} and bar.bars == {(1, 3, 4)}
    knot = missing_knot((5, 5), rng)
    assert knot.cells == {(4, 4), (5, 4), (4, 5), (5, 5)} and len(knot.bars) == 4
    # A knot whose four bars are gone leaves no stub on it.
    assert all(lo == 0.0 or hi == 0.0 for _, lo, hi in knot.stubs)
    for size in range(2, 11):
        torn = torn_hole((0, 0), size, np.random.default_rng(size))
        assert len(torn.cells) == size
        # Connected: its bars join all its cells (a spanning tree needs size - 1 of them).
        assert len(torn.bars) >= size - 1 and torn.bars == bars_between(torn.cells)


def test_truth_size_is_the_cells_knot_to_knot_on_the_plane() -> None:
    """A missing knot merges 2 x 2 cells: a square mesh of 2 cm bars, facing the camera with its
    bars along the image axes, has a 4 x 4 cm hole."""
    pose = NetPose(1.0, roll_deg=0.0)
    truth = hole_truth(missing_knot((3, 2), np.random.default_rng(1)), CAMERA, pose, MESH)
    assert truth.width_m == pytest.approx(0.04, rel=1e-9)
    assert truth.height_m == pytest.approx(0.04, rel=1e-9)
    # Seen from 1 m: its centre's range and its place in the frame follow from the pose.
    assert truth.range_m == pytest.approx(math.hypot(1.0, 0.02 * math.hypot(3, 2)), rel=1e-6)


def test_damage_changes_the_frame_only_where_the_hole_is(renderer: NetRenderer) -> None:
    pose = NetPose(1.0, 10.0, 30.0, 20.0, (0.3, 0.7))
    cell = cell_at_pixel(CAMERA, pose, MESH, (480.0, 270.0))
    assert cell is not None
    damage = NetDamage([missing_knot(cell, np.random.default_rng(2))])
    holed = _render(renderer, pose, 5, damage).astype(np.int16)
    intact = _render(renderer, pose, 5).astype(np.int16)
    changed = np.abs(holed - intact) > 2
    mask = damage.masks[0]
    assert mask.any() and changed.any()
    # Every changed pixel is in the hole's cells (dilated by the blur), most of them near the
    # missing twine.
    near = np.zeros_like(mask)
    ys, xs = np.nonzero(mask)
    near[max(0, ys.min() - 3): ys.max() + 4, max(0, xs.min() - 3): xs.max() + 4] = True
    assert not (changed & ~near).any()


# -- one frame ---------------------------------------------------------------------------------
def _scene_with(renderer: NetRenderer, estimator: NetEstimator, pose: NetPose, holes: list,
                seed: int, style: SceneStyle | None = None
                ) -> tuple[DamageScan, list, NetEstimate]:
    damage = NetDamage(holes)
    image = _render(renderer, pose, seed, damage, style)
    est = estimator.estimate(image)
    assert est.detected, est.reason
    detector = DamageDetector(CAMERA, MESH, DamageSettings(max_cells_inspected=100_000))
    truths = [hole_truth(h, CAMERA, pose, MESH, damage.masks[k]) for k, h in enumerate(holes)]
    return detector.inspect(image, est), truths, est


@pytest.mark.parametrize("kind,z,tilt", [("cut_bar", 0.7, 10.0), ("missing_knot", 1.0, 25.0),
                                         ("torn", 1.3, 35.0)])
def test_a_hole_is_found_and_measured(renderer: NetRenderer, estimator: NetEstimator, kind: str,
                                      z: float, tilt: float) -> None:
    pose = NetPose(z, tilt, 40.0, 15.0, (0.2, 0.6))
    cell = cell_at_pixel(CAMERA, pose, MESH, (430.0, 300.0))
    assert cell is not None
    rng = np.random.default_rng(3)
    hole = {"cut_bar": cut_bar(cell, 1, rng), "missing_knot": missing_knot(cell, rng),
            "torn": torn_hole(cell, 6, rng)}[kind]
    scan, (truth,), _ = _scene_with(renderer, estimator, pose, [hole], 11)
    assert len(scan.candidates) == 1, [c.centre_px for c in scan.candidates]
    found = scan.candidates[0]
    x0, y0, x1, y1 = truth.box_px
    assert x0 <= found.centre_px[0] <= x1 and y0 <= found.centre_px[1] <= y1
    if kind != "torn":
        assert found.cells == truth.cells and found.missing_bars == truth.missing_bars
        assert found.width_m == pytest.approx(truth.width_m, rel=SIZE_TOLERANCE)
        assert found.height_m == pytest.approx(truth.height_m, rel=SIZE_TOLERANCE)
    else:
        # A torn edge keeps stubs of up to a third of a bar at each knot: a bar cut short in
        # the middle (here 44 % of its twine left, 3 px of gap at 6 px cells) may read as
        # intact, and the hole as one cell smaller, knot to knot.
        assert abs(found.cells - truth.cells) <= 1
        assert abs(found.missing_bars - truth.missing_bars) <= 1
        cell_m = MESH.bar_length_m
        for got, want in ((found.width_m, truth.width_m), (found.height_m, truth.height_m)):
            assert abs(got - want) <= max(SIZE_TOLERANCE * want, 1.01 * cell_m)
    assert found.range_m == pytest.approx(truth.range_m, rel=0.05)
    assert found.crop is not None and found.crop.shape[0] >= 48


@pytest.mark.parametrize("z,tilt,family", [(0.7, 10.0, 1), (1.0, 25.0, 2), (1.3, 35.0, 1)])
def test_a_cut_bar_is_found_whatever_stubs_it_leaves(renderer: NetRenderer,
                                                     estimator: NetEstimator, z: float,
                                                     tilt: float, family: int) -> None:
    """A bar cut in the middle keeps stubs of up to a third of its length on both knots: two
    thirds of its twine stay in the middle half of the bar. Its middle third is gone
    whatever the stubs, and that is where a bar is judged missing."""
    pose = NetPose(z, tilt, 40.0, 15.0, (0.2, 0.6))
    cell = cell_at_pixel(CAMERA, pose, MESH, (430.0, 300.0))
    assert cell is not None
    i, j = cell
    bar = (family, i, j)
    other = (i - 1, j) if family == 1 else (i, j - 1)
    stub = 1.0 / 3.0  # the longest stub the renderer leaves on a knot
    hole = Hole("cut_bar", frozenset({cell, other}), frozenset({bar}), ((bar, stub, stub),))
    scan, (truth,), _ = _scene_with(renderer, estimator, pose, [hole], 11)
    assert len(scan.candidates) == 1, [c.centre_px for c in scan.candidates]
    found = scan.candidates[0]
    x0, y0, x1, y1 = truth.box_px
    assert x0 <= found.centre_px[0] <= x1 and y0 <= found.centre_px[1] <= y1
    assert found.cells == 2 and found.missing_bars == 1
    assert found.width_m == pytest.approx(truth.width_m, rel=SIZE_TOLERANCE)
    assert found.height_m == pytest.approx(truth.height_m, rel=SIZE_TOLERANCE)


@pytest.mark.parametrize("what", ["plain", "fouling", "seam", "rope", "board", "fish in front"])
def test_an_intact_net_gives_no_hole(renderer: NetRenderer, estimator: NetEstimator,
                                     what: str) -> None:
    """What is not damage: fouling (less contrast, lattice kept), a seam and a rope (long and
    straight), a marker board and salmon in front (large, not enclosed by intact bars)."""
    style = {"plain": SceneStyle(), "fouling": SceneStyle(fouling=0.7, twine_fraction=0.2),
             "seam": SceneStyle(seams=1), "rope": SceneStyle(ropes=1),
             "board": SceneStyle(boards=1), "fish in front": SceneStyle(fish_front_cover=0.2)}
    for seed in range(3):
        pose = NetPose(0.6 + 0.3 * seed, 15.0 * seed, 70.0 * seed, 20.0 + seed, (0.1, 0.4))
        scan, _, _ = _scene_with(renderer, estimator, pose, [], 20 + seed, style[what])
        assert scan.inspected_cells > 500, scan.reason
        assert scan.candidates == (), [(c.centre_px, c.cells) for c in scan.candidates]


def test_plane_axes_are_the_cameras_right_and_down_on_the_net() -> None:
    h, v = plane_axes((0.0, 0.0, -1.0))
    assert np.allclose(h, [1, 0, 0]) and np.allclose(v, [0, 1, 0])
    n = np.array([0.3, -0.2, -0.93])
    h, v = plane_axes(n)
    n = n / np.linalg.norm(n)
    assert abs(h @ n) < 1e-12 and abs(v @ n) < 1e-12 and abs(h @ v) < 1e-12
    assert h[0] > 0 and v[1] > 0


def test_no_plane_no_inspection() -> None:
    scan = DamageDetector(CAMERA, MESH).inspect(np.zeros((540, 960), np.uint8),
                                                NetEstimate(detected=False, confidence=0.0))
    assert scan.candidates == () and scan.reason


# -- over frames -------------------------------------------------------------------------------
def _pass(renderer: NetRenderer, estimator: NetEstimator, frames: int, drift: float,
          holes: list, settings: DamageSettings, seed: int = 40
          ) -> tuple[list[ConfirmedHole], list, NetInspector]:
    """Frames of the camera moving along the net (the lattice drifting `drift` cells per frame)
    through a NetInspector, as the pipeline runs it (track valid, every frame inspected)."""
    inspector = NetInspector(CAMERA, MESH, settings)
    damage = NetDamage(holes)
    confirmed: list[ConfirmedHole] = []
    truths = []
    prior = None
    for k in range(frames):
        pose = NetPose(0.9, 12.0, 30.0, 10.0, (0.3 + drift * k, 0.5 + 0.5 * drift * k))
        image = _render(renderer, pose, seed + k, damage)
        est = estimator.estimate(image, prior=prior)
        prior = est if est.detected else None
        report = inspector.step(image, est, 0.1 * k, k, track_valid=True, estimate_ms=30.0)
        confirmed += report.confirmed
        truths.append([hole_truth(h, CAMERA, pose, MESH) for h in holes])
    return confirmed, truths, inspector


def test_a_hole_is_confirmed_once_while_the_camera_moves(renderer: NetRenderer,
                                                         estimator: NetEstimator) -> None:
    pose0 = NetPose(0.9, 12.0, 30.0, 10.0, (0.3, 0.5))
    cell = cell_at_pixel(CAMERA, pose0, MESH, (400.0, 260.0))
    assert cell is not None
    hole = torn_hole(cell, 5, np.random.default_rng(4))
    settings = DamageSettings(every_n_frames=1, max_cells_inspected=100_000)
    confirmed, truths, inspector = _pass(renderer, estimator, 8, 0.4, [hole], settings)
    assert len(confirmed) == 1
    hole_seen = confirmed[0]
    assert hole_seen.detections >= settings.confirm_hits
    truth = truths[-1][0]
    assert hole_seen.width_m == pytest.approx(truth.width_m, rel=SIZE_TOLERANCE)
    assert hole_seen.height_m == pytest.approx(truth.height_m, rel=SIZE_TOLERANCE)
    assert inspector.inspected_frames == 8
    text = hole_seen.pilot_text()
    assert text.startswith("net: hole ~") and len(text) <= 50 and text.endswith(" m")


def test_candidates_that_do_not_stay_put_are_not_confirmed() -> None:
    """A candidate that appears in a different place of the net each frame (a caustic, a fish)
    never gathers the detections confirmation needs."""
    from service.core.damage import HoleCandidate, NetFrame

    tracker = HoleTracker(CAMERA, DamageSettings())
    net = NetFrame(np.array([0.0, 0.0, -1.0]), 1.0, np.array([1.0, 0.0, 0.0]),
                   np.array([0.0, 1.0, 0.0]))
    confirmed = []
    rng = np.random.default_rng(5)
    for k in range(30):
        x, y = rng.uniform(-0.6, 0.6), rng.uniform(-0.3, 0.3)
        cand = HoleCandidate((480.0, 270.0), (470.0, 260.0, 490.0, 280.0), 2, 1, 0.04, 0.02,
                             (x, y), (x, y, 1.0), 1.0, 6.0, 1.0)
        outline = ((0.0, 0.0), (959.0, 0.0), (959.0, 539.0), (0.0, 539.0))
        confirmed += tracker.update(DamageScan(candidates=(cand,), outline_px=outline,
                                               geometry=net), 0.1 * k, k)
    assert confirmed == []


def _still_scan(place: tuple[float, float], found: bool, judged_left: float
                ) -> DamageScan:
    """A scan of a net 1 m straight ahead whose judged region is the frame left of
    `judged_left` px, with (or without) a candidate at `place` on the plane."""
    from service.core.damage import HoleCandidate, NetFrame

    net = NetFrame(np.array([0.0, 0.0, -1.0]), 1.0, np.array([1.0, 0.0, 0.0]),
                   np.array([0.0, 1.0, 0.0]))
    x, y = place
    px = CAMERA.project_normalized(np.array([[x, y]]))[0]
    box = (px[0] - 8.0, px[1] - 8.0, px[0] + 8.0, px[1] + 8.0)
    cand = HoleCandidate((float(px[0]), float(px[1])), box, 2, 1, 0.04, 0.02, (x, y),
                         (x, y, 1.0), 1.0, 6.0, 1.0)
    frame = ((0.0, 0.0), (959.0, 0.0), (959.0, 539.0), (0.0, 539.0))
    judged = ((0.0, 0.0), (judged_left, 0.0), (judged_left, 539.0), (0.0, 539.0))
    return DamageScan(candidates=(cand,) if found else (), outline_px=frame, geometry=net,
                      judged_px=judged)


def test_confirmation_counts_the_inspections_that_judged_the_place() -> None:
    """Found in 2 of 3 looks: confirmed. Frames whose judged region did not hold the place
    (the view is inspected a window at a time) are not looks: found in both of the two
    inspections that judged it, among four frames, is enough."""
    settings = DamageSettings(confirm_hits=2, confirm_looks=3)
    place = (-0.2, 0.0)  # left of the middle of the frame
    left_px = float(CAMERA.project_normalized(np.array([[place[0], 0.0]]))[0, 0])
    covering, elsewhere = left_px + 100.0, left_px - 100.0
    tracker = HoleTracker(CAMERA, settings)
    pattern = [(True, covering), (False, covering), (True, covering)]
    out = [tracker.update(_still_scan(place, f, edge), 0.1 * k, k)
           for k, (f, edge) in enumerate(pattern)]
    assert [len(c) for c in out] == [0, 0, 1]
    assert (out[2][0].detections, out[2][0].looks) == (2, 3)
    tracker = HoleTracker(CAMERA, settings)
    pattern = [(True, covering), (False, elsewhere), (False, elsewhere), (True, covering)]
    out = [tracker.update(_still_scan(place, f, edge), 0.1 * k, k)
           for k, (f, edge) in enumerate(pattern)]
    assert [len(c) for c in out] == [0, 0, 0, 1]
    assert (out[3][0].detections, out[3][0].looks) == (2, 2)
    # Once confirmed, further sightings of the same hole are not reported again.
    more = [tracker.update(_still_scan(place, True, covering), 0.4 + 0.1 * k, 4 + k)
            for k in range(5)]
    assert all(c == [] for c in more)


def test_a_candidate_is_dropped_when_the_looks_at_its_place_stop_finding_it() -> None:
    """Two looks in a row without it (of 2-of-3) and it can no longer be confirmed: the
    track is dropped, and a later sighting at the same place starts afresh."""
    settings = DamageSettings(confirm_hits=2, confirm_looks=3)
    place = (-0.2, 0.0)
    left_px = float(CAMERA.project_normalized(np.array([[place[0], 0.0]]))[0, 0])
    tracker = HoleTracker(CAMERA, settings)
    for k, found in enumerate([True, False, False]):
        assert tracker.update(_still_scan(place, found, left_px + 100.0), 0.1 * k, k) == []
    assert tracker.tracks == [] and tracker.open_places(0.3) == []
    assert tracker.update(_still_scan(place, True, left_px + 100.0), 0.3, 3) == []
    (view,) = tracker.tracks
    assert view.detections == 1 and not view.confirmed
    (open_place,) = tracker.open_places(0.3)
    assert open_place == pytest.approx(place)


def _scan_of_view(place: tuple[float, float], found: bool, judged_left: float,
                  view_shift_m: float = 0.0) -> DamageScan:
    """`_still_scan` with the camera moved `view_shift_m` to the right along the net: the place
    moves left in the frame (plane coordinates are the camera's), out of view beyond ~0.5 m."""
    return _still_scan((place[0] - view_shift_m, place[1]), found, judged_left)


def test_a_confirmed_hole_that_stays_in_view_is_not_reported_again() -> None:
    """Confirmed, then in view for 3 s while the inspection windows look elsewhere (a large
    view is inspected a window at a time) and the detector misses it: the next sightings are
    the same hole. Its track ran out 2 s after the last sighting, and the hole was confirmed
    and reported again, with a new number, every few seconds while the ROV held station."""
    settings = DamageSettings(confirm_hits=2, confirm_looks=3)
    place = (-0.2, 0.0)
    left_px = float(CAMERA.project_normalized(np.array([[place[0], 0.0]]))[0, 0])
    covering, elsewhere = left_px + 100.0, left_px - 100.0
    tracker = HoleTracker(CAMERA, settings)
    reports = []
    for k in range(60):  # 6 s at 10 Hz
        looked = k < 2 or k >= 32  # sighted at first, then not for 3 s, then again
        reports += tracker.update(_still_scan(place, looked, covering if looked else elsewhere),
                                  0.1 * k, k)
    assert [h.hole_id for h in reports] == [1]
    (view,) = tracker.tracks
    assert view.confirmed and view.hole_id == 1


def _moving_scan(holes: list[tuple[float, float, int]], judged_left: float = 959.0
                 ) -> DamageScan:
    """A scan of a net 1 m straight ahead with a candidate at each (x, y, cells) on the plane
    (its size: `cells` openings of 2 cm)."""
    from service.core.damage import HoleCandidate, NetFrame

    net = NetFrame(np.array([0.0, 0.0, -1.0]), 1.0, np.array([1.0, 0.0, 0.0]),
                   np.array([0.0, 1.0, 0.0]))
    cands = []
    for x, y, cells in holes:
        px = CAMERA.project_normalized(np.array([[x, y]]))[0]
        box = (px[0] - 8.0, px[1] - 8.0, px[0] + 8.0, px[1] + 8.0)
        side = 0.02 * math.sqrt(cells)
        cands.append(HoleCandidate((float(px[0]), float(px[1])), box, cells, cells, side,
                                   side, (x, y), (x, y, 1.0), 1.0, 6.0, 1.0))
    frame = ((0.0, 0.0), (959.0, 0.0), (959.0, 539.0), (0.0, 539.0))
    judged = ((0.0, 0.0), (judged_left, 0.0), (judged_left, 539.0), (0.0, 539.0))
    return DamageScan(candidates=tuple(cands), outline_px=frame, geometry=net,
                      judged_px=judged)


def test_a_confirmed_hole_does_not_take_a_neighbour_of_another_size() -> None:
    """The net passes at 7 cm/s. A 3-cell tear is confirmed, then missed for 0.9 s while a
    10-cell tear 0.2 m from it comes into view: the confirmed track, its gate grown with the
    gap, took every sighting of the larger tear, which was never reported, and the small one,
    sighted again, was reported a second time (inspection review: replay at every 2nd frame)."""
    settings = DamageSettings(confirm_hits=2, confirm_looks=3)
    tracker = HoleTracker(CAMERA, settings)
    reports = []
    for k in range(40):
        t = 0.1 * k
        shift = -0.07 * t
        small = (-0.1 + shift, 0.0, 3)
        large = (0.1 + shift, 0.05, 10)
        holes = [small] if k < 5 else [] if k < 14 else [large] if k < 20 else [small, large]
        reports += tracker.update(_moving_scan(holes, judged_left=959.0 if k >= 14 else 5.0),
                                  t, k)
    assert sorted(h.cells for h in reports) == [3, 10], [(h.hole_id, h.cells) for h in reports]


def test_a_confirmed_hole_missed_a_few_looks_in_a_row_is_still_the_same_hole() -> None:
    """A confirmed tear moving across the view is not looked at for 2.2 s (windows elsewhere),
    then fouled twine hides it for three looks: its predicted place had stopped 2 s after the
    last sighting and the track was refuted after three looks (as a candidate is), so the
    tear, found again where its speed put it, was reported again under a new number
    (inspection review, a fouled dive)."""
    settings = DamageSettings()  # 3 of 5
    tracker = HoleTracker(CAMERA, settings)
    reports = []
    for k in range(40):
        t = 0.1 * k
        place = (0.1 - 0.07 * t, 0.1, 3)
        found = k < 5 or k >= 30
        # 2.2 s of windows elsewhere (no look at its place), then three looks that miss it.
        judged = 959.0 if found or k >= 27 else 5.0
        reports += tracker.update(_moving_scan([place] if found else [], judged), t, k)
    assert [h.hole_id for h in reports] == [1]


def test_holes_are_numbered_as_confirmed_and_drawn_with_the_size_reported() -> None:
    """Candidates that came to nothing took numbers between the holes ("hole 4, hole 6": where
    is hole 5?), and the annotated video labelled a hole with its last sighting's size (8x6 cm)
    where damage.csv had the reported median (6.3x5.1)."""
    settings = DamageSettings(confirm_hits=2, confirm_looks=3)
    tracker = HoleTracker(CAMERA, settings)
    reports = []
    for k in range(3):  # a streak of light here and there: candidates, never confirmed
        reports += tracker.update(_moving_scan([(-0.3 + 0.2 * k, -0.1, 2)]), 0.1 * k, k)
    for k in range(3, 12):
        cells = 4 if k < 6 else 6  # sighted at 4 cells, later at 6 (one hole, a bar more)
        reports += tracker.update(_moving_scan([(0.2, 0.1, cells)]), 0.1 * k, k)
    assert [h.hole_id for h in reports] == [1]
    (view,) = [v for v in tracker.tracks if v.confirmed]
    assert view.hole_id == 1
    assert (view.width_m, view.height_m) == (reports[0].width_m, reports[0].height_m)


def test_a_hole_held_in_view_for_long_keeps_its_memory_bounded() -> None:
    """A confirmed hole now lives as long as it is in view: an ROV holding station on it for an
    hour (36,000 sightings at 10 a second) must not keep every sighting, each with its evidence
    crop."""
    settings = DamageSettings(confirm_hits=2, confirm_looks=3)
    place = (-0.2, 0.0)
    tracker = HoleTracker(CAMERA, settings)
    for k in range(3000):
        tracker.update(_still_scan(place, True, 959.0), 0.1 * k, k)
    (track,) = tracker._tracks
    assert track.confirmed
    assert len(track.hits) <= settings.confirm_looks
    assert len(track.record) <= settings.confirm_looks


def test_a_hole_that_left_the_view_is_a_new_hole_when_it_comes_back() -> None:
    """What is documented: once out of view for more than track_timeout_s, netpose cannot tell
    it from another hole (the net is periodic), so a sighting after that is reported anew."""
    settings = DamageSettings(confirm_hits=2, confirm_looks=3)
    place = (-0.2, 0.0)
    frame_wide = 959.0
    tracker = HoleTracker(CAMERA, settings)
    reports = []
    for k in range(50):
        away = 2 <= k < 30  # the camera 1.5 m along the net: the place is out of the frame
        scan = _scan_of_view(place, not away, frame_wide, view_shift_m=1.5 if away else 0.0)
        reports += tracker.update(scan, 0.1 * k, k)
    assert [h.hole_id for h in reports] == [1, 2]


def test_after_the_inspection_stopped_for_long_a_new_hole_is_not_taken_for_an_old_one() -> None:
    """A confirmed hole, then the net lost for 10 s (nothing inspected), then a pass that
    shows another hole 0.35 m from the first's last place: the confirmed track, kept on its
    old place and speed with its gate grown to half a metre, took the new hole for itself, and
    the farm never heard of it (found 5 times in a replay). After a gap in the inspections
    longer than a track lives, a track is looked for only where it was last seen, with the
    smallest gate: this hole is reported. The first one, still where it was after a gap of
    2.5 s (a loop behind its budget, a fish in front), is still the same hole: not reported
    again."""
    settings = DamageSettings(confirm_hits=2, confirm_looks=3)
    first, second = (-0.2, 0.0), (0.15, 0.05)
    tracker = HoleTracker(CAMERA, settings)
    reports = []
    for k in range(4):
        reports += tracker.update(_still_scan(first, True, 959.0), 0.1 * k, k)
    for k in range(4):  # 10 s later: only the second hole in view
        reports += tracker.update(_still_scan(second, True, 959.0), 10.0 + 0.1 * k, 100 + k)
    assert [h.hole_id for h in reports] == [1, 2]
    assert reports[1].plane_xy_m == pytest.approx(second)
    held = HoleTracker(CAMERA, settings)
    reports = []
    for k in range(4):
        reports += held.update(_still_scan(first, True, 959.0), 0.1 * k, k)
    for k in range(4):  # 2.5 s without an inspection, then the same hole where it was
        reports += held.update(_still_scan(first, True, 959.0), 2.8 + 0.1 * k, 30 + k)
    assert [h.hole_id for h in reports] == [1]


def test_a_retuned_inspection_keeps_its_holes_and_their_numbers() -> None:
    """A reload of [damage] (the page's Save, a SIGHUP) built a new inspector: every hole in
    view was confirmed and reported again, numbered from 1 again, although `hole_id` is the
    hole's number in this service run. Retuned, the holes carry over; with the mesh changed
    they do not (their sizes were measured with the old one), but the numbers go on; switched
    off and on, too."""
    from service.core.tracking import FilterSettings, NetTracker
    from service.pipeline import Pipeline

    settings = DamageSettings(confirm_hits=2, confirm_looks=3)
    place, other = (-0.2, 0.0), (0.2, 0.1)
    pipeline = Pipeline(NetEstimator(CAMERA, MESH), NetTracker(FilterSettings()),
                        inspector=NetInspector(CAMERA, MESH, settings))

    def looks(where: tuple[float, float], t0: float) -> list[int]:
        inspector = pipeline.inspector
        assert inspector is not None
        return [h.hole_id for k in range(3)
                for h in inspector.tracker.update(_still_scan(where, True, 959.0), t0 + 0.1 * k,
                                                  k)]

    assert looks(place, 0.0) == [1]
    pipeline.replace_inspector(NetInspector(CAMERA, MESH, DamageSettings(
        confirm_hits=2, confirm_looks=3, notify_interval_s=4.0)), keep_holes=True)
    assert looks(place, 0.3) == []  # the same hole, still in view: not again
    assert looks(other, 0.6) == [2]
    pipeline.replace_inspector(NetInspector(CAMERA, MESH, settings), keep_holes=False)
    assert looks(place, 0.9) == [3]  # measured anew with another mesh, a new number
    pipeline.replace_inspector(None, keep_holes=False)
    pipeline.replace_inspector(NetInspector(CAMERA, MESH, settings), keep_holes=False)
    assert looks(other, 1.2) == [4]


@pytest.mark.parametrize(("hits", "looks", "key"), [(0, 3, "damage.confirm_hits"),
                                                    (3, 2, "damage.confirm_looks")])
def test_confirmation_settings_are_checked(hits: int, looks: int, key: str) -> None:
    from service.core.errors import ConfigError

    with pytest.raises(ConfigError) as info:
        DamageSettings(confirm_hits=hits, confirm_looks=looks)
    assert info.value.key == key


@pytest.mark.parametrize("ratio", [-0.1, 1.0, 1.5])
def test_the_rings_strength_setting_is_checked(ratio: float) -> None:
    """A ring at full strength reads about 1 of its neighbours: a limit of 1 or more would
    refuse every hole, a negative one is a typing error."""
    from service.core.errors import ConfigError

    with pytest.raises(ConfigError) as info:
        DamageSettings(min_ring_ratio=ratio)
    assert info.value.key == "damage.min_ring_ratio"


def test_inspection_runs_only_while_tracking_and_within_its_budget(
        renderer: NetRenderer, estimator: NetEstimator) -> None:
    pose = NetPose(1.0, 10.0, 0.0, 10.0)
    image = _render(renderer, pose, 7)
    estimate = estimator.estimate(image)
    off = NetInspector(CAMERA, MESH, DamageSettings(enabled=False))
    assert not off.step(image, estimate, 0.0, 0, True, 30.0).inspected
    inspector = NetInspector(CAMERA, MESH, DamageSettings(every_n_frames=3))
    assert not inspector.step(image, estimate, 0.0, 0, False, 30.0).inspected
    ran = [inspector.step(image, estimate, 0.1 * k, k, True, 30.0).inspected for k in range(9)]
    assert ran == [True, False, False] * 3
    # By budget: an estimator that (so it is told) took 2 ms a frame leaves inspection 0.6 ms a
    # frame on average; it takes more per frame, so it runs on some frames only.
    budget = NetInspector(CAMERA, MESH, DamageSettings(max_cost_fraction=0.3))
    reports = [budget.step(image, estimate, 0.1 * k, k, True, 2.0) for k in range(60)]
    inspected = [r for r in reports if r.inspected]
    assert 0 < len(inspected) < 60
    spent = sum(r.inspect_ms for r in reports)
    assert spent <= 0.3 * 2.0 * 60 + max(r.inspect_ms for r in inspected)


def _judged_mask(scan: DamageScan) -> np.ndarray:
    import cv2

    mask = np.zeros((CAMERA.height, CAMERA.width), np.uint8)
    if len(scan.judged_px) >= 3:
        cv2.fillConvexPoly(mask, np.round(np.array(scan.judged_px)).astype(np.int32), 1)
    return mask.astype(bool)


def test_a_large_view_is_covered_a_window_at_a_time(renderer: NetRenderer,
                                                    estimator: NetEstimator) -> None:
    """A view of more cells than `max_cells_inspected` is inspected a window per frame, each
    where the view was judged longest ago: no window holds more cells than the cap, and in
    twice the number of windows the view needs (its cells over a window's judged cells) the
    windows together judged nearly all of what one whole-view inspection judges (the windows
    are squares in the lattice, the view is not). A hole is found only by windows that hold it."""
    pose = NetPose(1.0, 10.0, 40.0, 15.0, (0.2, 0.6))
    cell = cell_at_pixel(CAMERA, pose, MESH, (430.0, 300.0))
    assert cell is not None
    hole = missing_knot(cell, np.random.default_rng(6))
    whole, (truth,), est = _scene_with(renderer, estimator, pose, [hole], 12)
    assert whole.windows == 1 and len(whole.candidates) == 1
    image = _render(renderer, pose, 12, NetDamage([hole]))
    cap = 1500
    detector = DamageDetector(CAMERA, MESH, DamageSettings(max_cells_inspected=cap))
    first = detector.inspect(image, est)
    windows = first.windows
    assert 1 < windows < whole.inspected_cells / (cap // 2)
    scans = [first] + [detector.inspect(image, est) for _ in range(2 * windows - 1)]
    assert all(0 < s.inspected_cells <= cap for s in scans)
    target = _judged_mask(whole)
    covered = np.zeros_like(target)
    for s in scans:
        covered |= _judged_mask(s)
    assert (covered & target).sum() >= 0.95 * target.sum()
    holding = [k for k, s in enumerate(scans) if _judged_mask(s)[
        round(truth.centre_px[1]), round(truth.centre_px[0])]]
    found_in = [k for k, s in enumerate(scans) if s.candidates]
    assert found_in and set(found_in) <= set(holding) and len(holding) < len(scans)


def test_a_window_holds_the_open_candidates_places_first(renderer: NetRenderer,
                                                         estimator: NetEstimator) -> None:
    """Asked to revisit a candidate's place on the net, every window holds it (with its ring),
    so the hole is judged, and found, in each of those frames."""
    pose = NetPose(1.0, 10.0, 40.0, 15.0, (0.2, 0.6))
    cell = cell_at_pixel(CAMERA, pose, MESH, (430.0, 300.0))
    assert cell is not None
    hole = missing_knot(cell, np.random.default_rng(6))
    whole, (truth,), est = _scene_with(renderer, estimator, pose, [hole], 12)
    image = _render(renderer, pose, 12, NetDamage([hole]))
    detector = DamageDetector(CAMERA, MESH, DamageSettings(max_cells_inspected=1500))
    place = whole.candidates[0].plane_xy_m
    scans = [detector.inspect(image, est, revisit=[place]) for _ in range(4)]
    assert all(s.windows > 1 and s.revisits == 1 for s in scans)
    assert all(len(s.candidates) == 1 for s in scans)
    for s in scans:
        assert s.candidates[0].plane_xy_m == pytest.approx(place, abs=MESH.bar_length_m)
        assert _judged_mask(s)[round(truth.centre_px[1]), round(truth.centre_px[0])]


def test_the_detector_keeps_a_bounded_set_of_dct_matrices() -> None:
    """A daemon sees window sizes from a few cells to hundreds over hours: the detector keeps
    the matrices of the last few sizes only, and a size met again is rebuilt the same."""
    from service.core.damage import _DCT_CACHE_SIZES, _dct_matrix

    detector = DamageDetector(bench_camera(640, 360), MESH)
    for n in range(5, 5 + 4 * _DCT_CACHE_SIZES):
        assert np.array_equal(detector._dct(n), _dct_matrix(n))
    assert len(detector._dcts) == _DCT_CACHE_SIZES
    assert np.array_equal(detector._dct(5), _dct_matrix(5))


def test_a_cell_is_inspected_only_where_all_its_samples_are_valid() -> None:
    """One invalid sample (outside the frame, another pyramid level's border) takes its whole
    cell out of the judgement, and only that cell."""
    from service.core.damage import _cells_valid

    n2, n1, s = 5, 7, 4
    valid = np.ones((n2 * s, n1 * s), dtype=bool)
    assert _cells_valid(valid, n1, n2, s).all()
    valid[2 * s + 3, 4 * s] = False  # the last row, first column of cell (i=4, j=2)
    valid[0, n1 * s - 1] = False  # the first row, last column of cell (i=6, j=0)
    cells = _cells_valid(valid, n1, n2, s)
    assert cells.shape == (n2, n1)
    assert sorted(zip(*np.nonzero(~cells), strict=True)) == [(0, 6), (2, 4)]


def test_the_phase_unwrapping_dct_is_scipys_orthonormal_dct() -> None:
    """The phase is unwrapped with a DCT written as matrix products (no scipy in the frame
    loop): it must be scipy's orthonormal 2D DCT-II and its inverse, to rounding."""
    from scipy.fft import dctn

    from service.core.damage import _dct_matrix

    rng = np.random.default_rng(7)
    for shape in [(7, 9), (31, 31), (40, 25), (1, 5)]:
        a = rng.standard_normal(shape)
        c2, c1 = _dct_matrix(shape[0]), _dct_matrix(shape[1])
        d = c2 @ a @ c1.T
        assert np.max(np.abs(d - dctn(a, type=2, norm="ortho"))) < 1e-12
        assert np.max(np.abs(c2.T @ d @ c1 - a)) < 1e-12


def test_inspection_memory_starts_over_before_its_counter_overflows() -> None:
    """The planner counts inspections in int32 (memory): after 2**31 of them (two years of
    frames) it forgets what it inspected and goes on, rather than failing on the overflow."""
    planner = InspectionPlanner(0.025)
    view = np.ones((4, 5), dtype=bool)
    cells = np.stack(np.meshgrid(np.arange(5) * 0.025, np.arange(4) * 0.025), axis=-1)
    planner.choose(view, cells, 100, np.zeros((0, 2)))
    planner._count = int(np.iinfo(np.int32).max)  # two years later
    window = planner.choose(view, cells, 100, np.zeros((0, 2)))
    assert (window.n1, window.n2) == (5, 4)
    assert planner._count == 1


def test_what_a_recording_keeps_of_each_frames_search() -> None:
    """A recording keeps whether each frame was searched for holes so that a replay searches
    the same ones. A frame whose search failed was kept as "not searched": a replay skipped
    the very frame that failed on the vehicle. A frame with no valid track was kept as "not
    searched" too, and a replay with another filter had to skip it. Searched or tried: True;
    left for the time budget: False; not a frame to search: None."""
    from service.pipeline import Pipeline

    inspector = NetInspector(CAMERA, MESH, DamageSettings())
    image = np.zeros((540, 960), np.uint8)
    seen = NetEstimate(detected=True, confidence=0.9, normal=(0.0, 0.0, -1.0), distance_m=1.0,
                       range_m=1.0, sigma_distance_m=0.01, sigma_normal_deg=1.0)
    assert inspector.step(image, seen, 0.0, 0, False, 30.0).searched is None
    assert inspector.step(image, seen, 0.1, 1, True, 30.0, due=False).searched is False
    assert inspector.step(image, seen, 0.2, 2, True, 30.0, due=True).searched is True

    def broken(*_args: object, **_kwargs: object) -> None:
        raise IndexError("a bug")

    inspector.detector.inspect = broken  # type: ignore[method-assign, assignment]
    pipeline = Pipeline(NetEstimator(CAMERA, MESH), NetTracker(FilterSettings()),
                        inspector=inspector)
    measured = pipeline.measure(image, 0.3, 3)  # a blank frame: made to look tracked
    measured = dataclasses.replace(measured, estimate=seen,
                                   track=dataclasses.replace(measured.track, valid=True))
    report = pipeline.inspect(image, measured, due=True).damage
    assert report is not None and report.failed and report.searched is True


def test_a_hole_not_sighted_in_a_frame_is_drawn_where_the_net_has_carried_it() -> None:
    """The annotated video drew a confirmed hole at its last sighting's box while the net slid
    across the view between inspection windows: 18-20 px off the hole (up to 117), on intact
    net half the time (inspection report review). Not sighted, it is drawn where its speed on
    the net puts it now (a thinner box), and not once that place has left the frame."""
    from service.core.damage import NetFrame

    settings = DamageSettings(confirm_hits=2, confirm_looks=3)
    tracker = HoleTracker(CAMERA, settings)
    net = NetFrame(np.array([0.0, 0.0, -1.0]), 1.0, np.array([1.0, 0.0, 0.0]),
                   np.array([0.0, 1.0, 0.0]))

    def place(t: float) -> tuple[float, float]:
        return (0.3 - 0.1 * t, 0.05)  # the ROV moves right along the net at 0.1 m/s

    def pixel(t: float) -> npt.NDArray[np.float64]:
        return CAMERA.project_normalized(np.array([place(t)]))[0]

    reports = []
    for k in range(6):  # sighted in six inspections at 10 Hz: confirmed, its speed measured
        reports += tracker.update(_moving_scan([(*place(0.1 * k), 2)]), 0.1 * k, k)
    assert [h.hole_id for h in reports] == [1]
    (seen,) = tracker.views(0.5, net)
    assert seen.seen and seen.centre_px == pytest.approx(tuple(pixel(0.5)), abs=0.5)
    for t in (1.0, 2.0, 4.0):  # not looked at since: the windows are elsewhere
        (drawn,) = tracker.views(t, net)
        assert not drawn.seen and drawn.hole_id == 1
        assert drawn.centre_px == pytest.approx(tuple(pixel(t)), abs=2.0)
        x0, y0, x1, y1 = drawn.box_px
        assert x0 < pixel(t)[0] < x1 and y0 < pixel(t)[1] < y1
        (last,) = tracker.tracks  # the last sighting's place, which the video used to show
        assert abs(last.centre_px[0] - pixel(t)[0]) > 20.0
    assert tracker.views(14.0, net) == []  # carried out of the frame (left edge)
    assert tracker.views(1.0, None) == []  # no plane: nowhere to draw it
