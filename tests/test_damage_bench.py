"""The short, seeded version of `netpose bench damage` (the full one: docs/inspection.md).

A few rendered passes (realistic scenes, as the benchmark draws them) through the pipeline and
the real frames of shared/data: the machinery that the benchmark's figures come from, and the
two targets a short run can check exactly: no false hole confirmed on an intact net, and no
candidate at all on the real frames (none of which shows a hole).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from service.benchmarks import damage
from tests.shared_data import needs_real_field, shared_data_dir

PASSES = 4
FRAMES = 12  # shorter passes than the benchmark's, to keep the suite quick
WIDTH, HEIGHT = 960, 540


@pytest.fixture(scope="module")
def results() -> list[damage.PassResult]:
    return damage.run_passes(damage.BenchSpec(PASSES, seed=3, width=WIDTH, height=HEIGHT,
                                              keep_misses=True, frames=FRAMES), jobs=1)


def test_passes_are_scored_frame_by_frame(results: list[damage.PassResult]) -> None:
    assert [r.case_index for r in results] == list(range(PASSES))
    for res in results:
        frames = {row.frame for row in res.rows}
        assert frames == set(range(FRAMES))
        case = damage.draw_pass(3, res.case_index, WIDTH, HEIGHT, frames=FRAMES)
        assert len(res.holes) == len(case.holes) == res.case_index % 2
        for row in res.rows:
            assert row.estimate_ms > 0 and math.isfinite(row.range_m)
            if row.inspected:
                assert row.inspect_ms > 0
            if row.hole_cells:
                # Scored only where the frame shows the hole, with its contrast over the noise.
                assert row.cnr > 0 and (row.detected or row.why)


def test_no_false_hole_is_confirmed_on_an_intact_net(results: list[damage.PassResult]) -> None:
    intact = [r for r in results if not r.holes]
    assert intact
    assert sum(r.confirmed_false for r in intact) == 0


def test_confirmed_holes_are_measured_within_20_percent(
        results: list[damage.PassResult]) -> None:
    for res in results:
        for _, width_error, height_error in res.confirmed_true:
            assert abs(width_error) <= damage.TARGET_SIZE_ERROR
            assert abs(height_error) <= damage.TARGET_SIZE_ERROR


def test_the_report_states_every_target(results: list[damage.PassResult]) -> None:
    lines = damage.format_report(results, [])
    text = "\n".join(lines)
    assert "confirmed holes by size and distance" in text and "false holes confirmed" in text
    assert "inspection / estimator time" in text
    summary = damage.summarise(results, [])
    assert summary.intact_frames == FRAMES * sum(not r.holes for r in results)
    assert len(summary.targets) == 5


def test_a_target_a_run_could_not_measure_is_not_judged() -> None:
    """No hole confirmed (a short run) leaves the size error unknown, no hole that counts
    leaves recall unknown, and `--no-real` judges no real frame: each says so, instead of
    reading as missed (or, for the real frames, as met)."""
    nothing = damage.Summary(
        recall_confirmed={}, recall_frames={}, size_errors=[], intact_frames=48,
        intact_false_confirmed=0, intact_false_candidates=0, damaged_false_confirmed=0,
        real_candidates=0, real_frames=0, cost_ratio=0.5, inspect_ms_median=5.0,
        estimate_ms_median=10.0)
    verdicts = list(nothing.targets.values())
    assert verdicts == [None, None, True, None, False]
    measured = replace(nothing, recall_confirmed={("2 cells", "0.4-0.8"): (1, 2)},
                       size_errors=[0.01, 0.3], real_frames=8, real_candidates=1)
    assert list(measured.targets.values()) == [False, False, True, False, False]


@needs_real_field
def test_no_candidate_on_the_real_frames() -> None:
    data = shared_data_dir()
    rows = damage.run_real(data)
    # How many real frames the estimator measures is `netpose bench real`'s business; here:
    # wherever a valid track let inspection run, nothing was taken for a hole.
    inspected = [r for r in rows if r.inspected_cells > 0]
    assert inspected and all(r.detected for r in inspected)
    assert [(r.name, r.candidates) for r in rows if r.candidates] == []


def test_a_hole_outside_this_frames_window_is_missed_for_that_reason() -> None:
    """The account of misses tells a hole the frame's window did not cover (the view is
    inspected a window at a time) from one outside the inspectable view."""
    from types import SimpleNamespace

    from drivers.synthetic_damage import HoleTruth, cut_bar
    from service.core.damage import DamageScan
    from service.core.damage_track import DamageReport

    truth = HoleTruth(cut_bar((0, 0), 1, np.random.default_rng(0)), 0.04, 0.02, (800.0, 400.0),
                      (790.0, 395.0, 810.0, 405.0), 1.0)
    left_half = ((0.0, 0.0), (400.0, 0.0), (400.0, 719.0), (0.0, 719.0))
    for windows, expected in ((3, "outside this frame's window"),
                              (1, "outside the inspected region")):
        scan = DamageScan(inspected_cells=900, outline_px=left_half, windows=windows)
        res = SimpleNamespace(damage=DamageReport(True, "", scan), estimate=None)
        assert damage._why_missed(res, truth, 5.0).startswith(expected)


def test_a_fouled_patch_that_dims_the_bars_around_it_is_not_a_hole() -> None:
    """A false hole the 3.6 s passes confirmed (seed 1, intact pass 76, frame 13: a fouled patch
    over light twine at 0.55 m). Its bars lose their contrast as a cut bar's would, but the
    patch fades out over cells, so the bars bounding it are dimmed too (0.6 of their
    neighbours'), where a cut leaves them whole. Judged without that test, it is a hole."""
    from drivers.synthetic_net import NetRenderer
    from service.core.damage import DamageDetector, DamageSettings
    from service.core.estimator import NetEstimator

    case = damage.draw_pass(1, 76)
    assert not case.holes and case.style.fouling > 0.2 and case.style.net_seed is not None
    k = 13
    image, _ = NetRenderer(case.camera, case.mesh).render(case.pose_at(k), case.frame_rng(k),
                                                          case.style)
    estimate = NetEstimator(case.camera, case.mesh).estimate(image)
    assert estimate.detected, estimate.reason
    # Where a lenient judge finds a hole in this frame (the benchmark confirmed one at (973,
    # 240) before the estimator used the measured opening angle, 2026-11-28: the same fouled
    # patches, judged at another place).
    patch = (412.0, 345.0)

    def near(p: tuple[float, float]) -> bool:
        return abs(p[0] - patch[0]) < 60 and abs(p[1] - patch[1]) < 60

    whole_view = DamageSettings(max_cells_inspected=100_000)
    lenient = DamageDetector(case.camera, case.mesh, replace(whole_view, min_ring_ratio=0.0))
    assert [c.cells for c in lenient.inspect(image, estimate).candidates
            if near(c.centre_px)] != []
    scan = DamageDetector(case.camera, case.mesh, whole_view).inspect(image, estimate)
    assert scan.inspected_cells > 500
    assert [c.centre_px for c in scan.candidates if near(c.centre_px)] == []
    assert any("dimmed" in why for at, _, why in scan.rejected if near(at))
