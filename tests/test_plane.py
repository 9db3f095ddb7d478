"""Net plane from per-ROI mesh cell areas: exactness, robustness, degenerate input, sigmas."""

from __future__ import annotations

import itertools
import math

import numpy as np
import numpy.typing as npt
import pytest

from service.core.plane import (
    PRIOR_DOF,
    RoiTriples,
    axis_leverage,
    fit_plane,
    plane_through,
    tilt_leverage,
)

F64 = npt.NDArray[np.float64]
CELL_M2 = 0.015**2


def _unit(v: F64) -> F64:
    return np.asarray(v / np.linalg.norm(v), dtype=np.float64)


def _rays(cols: int = 5, rows: int = 3, half_x: float = 0.6, half_y: float = 0.4) -> F64:
    """Undistorted normalised rays (x, y, 1) of a grid of ROI centres, like the estimator's."""
    x, y = np.meshgrid(np.linspace(-half_x, half_x, cols), np.linspace(-half_y, half_y, rows))
    return np.stack([x.ravel(), y.ravel(), np.ones(x.size)], axis=1)


def _areas(rays: F64, normal_away: F64, distance: float) -> F64:
    """Perspective: a cell of area A on the plane n.X = d covers A (n.r)^3 / d^2 at ray r.

    The formula is checked against a direct projection of a small plane square below, so these
    expected areas do not rest on the implementation's own model."""
    return np.asarray(CELL_M2 * (rays @ normal_away) ** 3 / distance**2, dtype=np.float64)


def _numeric_area(ray: F64, normal_away: F64, distance: float, h: float = 1e-4) -> float:
    """Image area of a small plane patch by projecting a square of side h around the hit point."""
    t = distance / float(normal_away @ ray)
    point = t * ray
    u = _unit(np.cross(normal_away, [0.0, 1.0, 0.0]))
    v = np.cross(normal_away, u)
    corners = [point + h * (su * u + sv * v) / 2 for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    img = np.array([c[:2] / c[2] for c in corners])
    x, y = img[:, 0], img[:, 1]
    shoelace = 0.5 * abs(float(x @ np.roll(y, -1) - y @ np.roll(x, -1)))
    return shoelace / h**2 * CELL_M2


POSES = [
    (np.array([0.0, 0.0, 1.0]), 0.5),
    (_unit(np.array([math.sin(math.radians(25)), 0.0, math.cos(math.radians(25))])), 1.2),
    (_unit(np.array([-0.3, 0.55, 0.78])), 2.0),  # 40 deg, oblique axis
]


def test_area_model_matches_a_numerical_projection() -> None:
    normal, distance = POSES[2]
    for ray in _rays():
        expected = _numeric_area(ray, normal, distance)
        assert _areas(ray[None, :], normal, distance)[0] == pytest.approx(expected, rel=1e-6)


@pytest.mark.parametrize(("normal", "distance"), POSES)
def test_exact_areas_give_the_exact_plane(normal: F64, distance: float) -> None:
    rays = _rays()
    fit = fit_plane(rays, _areas(rays, normal, distance), np.full(15, 0.01), CELL_M2, min_rois=4)
    assert fit is not None
    np.testing.assert_allclose(fit.normal_away, normal, atol=1e-9)
    assert fit.distance_m == pytest.approx(distance, abs=1e-9)
    assert fit.range_m == pytest.approx(distance / normal[2], abs=1e-9)
    assert fit.used.all()
    assert fit.relative_rms < 1e-9


def test_two_gross_outliers_of_fifteen_are_rejected_and_flagged() -> None:
    normal, distance = POSES[2]
    rays = _rays()
    areas = _areas(rays, normal, distance)
    # A sub-harmonic lattice (cell 2x too small) and a fish (one axis lost: 2x too large).
    areas[3] *= 0.5
    areas[11] *= 2.0
    fit = fit_plane(rays, areas, np.full(15, 0.01), CELL_M2, min_rois=4)
    assert fit is not None
    assert not fit.used[3] and not fit.used[11]
    assert int(fit.used.sum()) == 13
    np.testing.assert_allclose(fit.normal_away, normal, atol=1e-9)
    assert fit.distance_m == pytest.approx(distance, abs=1e-9)


def test_a_kept_triple_table_gives_the_same_plane_as_a_new_one() -> None:
    """The estimator keeps its table of ROI triples between fits: every triple once, in
    combinations' order (the consensus's sampling of a long table depends on it), read-only,
    and a fit with a kept table is the fit without one."""
    triples = RoiTriples()
    for k in (3, 4, 15):
        np.testing.assert_array_equal(triples(k), list(itertools.combinations(range(k), 3)))
        assert triples(k) is triples(k)
        assert not triples(k).flags.writeable
    normal, distance = POSES[2]
    rays = _rays(cols=7, rows=5)  # 35 ROIs: 6545 triples, more than the consensus samples
    areas = _areas(rays, normal, distance)
    areas[3] *= 0.5
    fresh = fit_plane(rays, areas, np.full(35, 0.01), CELL_M2, min_rois=4)
    kept = fit_plane(rays, areas, np.full(35, 0.01), CELL_M2, min_rois=4, triples=triples)
    assert fresh is not None and kept is not None
    np.testing.assert_array_equal(kept.used, fresh.used)
    assert not kept.used[3]
    assert kept.distance_m == pytest.approx(distance, abs=1e-9)


def test_small_outliers_against_noise_are_flagged_too() -> None:
    # 10 % off in area (3 % in c) among ROIs with 0.3 % noise: clearly inconsistent.
    normal, distance = POSES[1]
    rays = _rays()
    rng = np.random.default_rng(0)
    areas = _areas(rays, normal, distance) * (1 + rng.normal(0, 0.003, 15))
    areas[7] *= 1.10
    fit = fit_plane(rays, areas, np.full(15, 0.003), CELL_M2, min_rois=4)
    assert fit is not None
    assert not fit.used[7]
    assert fit.distance_m == pytest.approx(distance, rel=0.005)


def test_the_plane_through_every_roi_keeps_them_all() -> None:
    """`plane_through` is the weighted fit without choosing: exact areas give the plane, and an
    outlier that `fit_plane` leaves out pulls it (what the estimator's sigma weighs)."""
    normal, distance = POSES[2]
    rays = _rays()
    areas = _areas(rays, normal, distance)
    through = plane_through(rays, areas, np.full(15, 0.01), CELL_M2)
    assert through is not None
    np.testing.assert_allclose(through[0], normal, atol=1e-9)
    assert through[1] == pytest.approx(distance, abs=1e-9)
    areas[7] *= 1.10
    pulled = plane_through(rays, areas, np.full(15, 0.01), CELL_M2)
    assert pulled is not None and pulled[1] != pytest.approx(distance, rel=1e-4)
    assert plane_through(rays[:2], areas[:2], np.full(2, 0.01), CELL_M2) is None


def test_fewer_rois_than_required_give_no_plane() -> None:
    normal, distance = POSES[0]
    rays = _rays()[:5]
    areas = _areas(rays, normal, distance)
    assert fit_plane(rays, areas, np.full(5, 0.01), CELL_M2, min_rois=6) is None
    assert fit_plane(rays[:3], areas[:3], np.full(3, 0.01), CELL_M2, min_rois=4) is None
    # Five well-spread ROIs (four corners and the centre) are enough for min_rois=5.
    spread = _rays()[[0, 4, 7, 10, 14]]
    fit = fit_plane(
        spread, _areas(spread, normal, distance), np.full(5, 0.01), CELL_M2, min_rois=5
    )
    assert fit is not None and fit.distance_m == pytest.approx(distance, abs=1e-9)


def test_rois_on_one_line_cannot_fix_a_plane() -> None:
    # All centres on one image row: the tilt about that row is unobservable.
    normal, distance = POSES[1]
    rays = _rays(cols=8, rows=1, half_y=0.0)
    rays[:, 1] = 0.1
    fit = fit_plane(rays, _areas(rays, normal, distance), np.full(8, 0.01), CELL_M2, min_rois=4)
    assert fit is None


def test_too_many_outliers_give_no_plane() -> None:
    # Half the ROIs on one plane, half on another twice as far: no consistent net.
    rays = _rays()
    near = _areas(rays, POSES[0][0], 0.5)
    far = _areas(rays, POSES[0][0], 1.0)
    areas = np.where(np.arange(15) % 2 == 0, near, far)
    fit = fit_plane(rays, areas, np.full(15, 0.01), CELL_M2, min_rois=10)
    assert fit is None


@pytest.mark.parametrize("relative_area_noise", [0.02, 0.06])
def test_reported_sigmas_match_the_spread_of_repeated_noisy_fits(
    relative_area_noise: float,
) -> None:
    normal, distance = POSES[2]
    rays = _rays()
    exact = _areas(rays, normal, distance)
    rng = np.random.default_rng(42)
    distances, ranges, angles = [], [], []
    sigma_d, sigma_r, sigma_n = [], [], []
    for _ in range(300):
        # Outlier rejection is switched off: this checks the error propagation, and trimming
        # the tails of pure Gaussian noise would shrink the empirical spread.
        areas = exact * (1 + rng.normal(0.0, relative_area_noise, exact.size))
        fit = fit_plane(
            rays, areas, np.full(exact.size, relative_area_noise), CELL_M2, min_rois=4,
            outlier_sigma=1e6, min_relative_tolerance=1.0, consensus_tolerance=1.0,
        )
        assert fit is not None
        distances.append(fit.distance_m)
        ranges.append(fit.range_m)
        angles.append(math.degrees(math.acos(min(1.0, float(fit.normal_away @ normal)))))
        sigma_d.append(fit.sigma_distance_m)
        sigma_r.append(fit.sigma_range_m)
        sigma_n.append(fit.sigma_normal_deg)
    # Rough check: the mean reported sigma against the empirical spread within a factor 2
    # (measured ratios 1.04-1.28 for distance, range and normal at both noise levels).
    # The angle error is the length of a 2D error vector: its RMS is sqrt(2) x the per-axis
    # sigma when both axes have equal spread, 1x when one dominates; compare with the RMS / 1.2.
    empirical_d = float(np.std(distances))
    empirical_r = float(np.std(ranges))
    empirical_n = float(np.sqrt(np.mean(np.square(angles)))) / 1.2
    for reported, empirical in (
        (np.mean(sigma_d), empirical_d),
        (np.mean(sigma_r), empirical_r),
        (np.mean(sigma_n), empirical_n),
    ):
        assert 0.5 < reported / empirical < 2.0, (reported, empirical)
    # Unbiased to well within the spread.
    assert abs(float(np.mean(distances)) - distance) < 3 * empirical_d / math.sqrt(300) + 0.002


def test_four_rois_give_a_finite_sigma_that_grows_with_their_disagreement() -> None:
    """One degree of freedom: the residual alone cannot tell the scatter, so the ROIs' noise
    model counts as PRIOR_DOF degrees of freedom (a finite sigma, never below the model's), and
    a disagreement far beyond the model still shows in the sigma."""
    normal, distance = POSES[1]
    rays = _rays(2, 2)
    exact = _areas(rays, normal, distance)
    noise = np.full(4, 0.01)
    agree = fit_plane(rays, exact, noise, CELL_M2, min_rois=4)
    assert agree is not None and agree.sigma_dof == PRIOR_DOF + 1
    assert math.isfinite(agree.sigma_range_m) and agree.sigma_range_m > 0
    # 6 % off in one ROI's area (2 % in c, five times its model sigma):
    bent = exact * np.array([1.0, 1.0, 1.0, 1.06])
    disagree = fit_plane(rays, bent, noise, CELL_M2, min_rois=4,
                         outlier_sigma=1e6, min_relative_tolerance=1.0, consensus_tolerance=1.0)
    assert disagree is not None
    # The pooled variance factor: (PRIOR_DOF + chi^2) / (PRIOR_DOF + 1), chi^2 from the
    # residuals over the model sigma of c (a third of the area's, with the 0.2 % floor).
    sigma_c = math.hypot(0.01 / 3.0, 0.002)
    chi2 = 4 * disagree.relative_rms**2 / sigma_c**2
    assert chi2 > 5.0
    factor = math.sqrt((PRIOR_DOF + chi2) / (PRIOR_DOF + 1))
    assert disagree.sigma_range_m / agree.sigma_range_m == pytest.approx(factor, rel=0.1)


def test_axis_leverage_is_small_inside_the_rois_and_grows_on_one_side() -> None:
    axis = np.array([0.0, 0.0, 1.0])
    around = _rays()
    assert axis_leverage(around, axis, 0.2) < 0.1
    # The same grid shifted so that all of it lies right of the axis, at twice its half-width:
    # the axis is then ~2.5 spreads from the centroid along x (spread sqrt(0.18 + 0.2^2 / 12)).
    side = around + np.array([1.2, 0.0, 0.0])
    lever = axis_leverage(side, axis, 0.2)
    expected = 1.2**2 / (float(np.var(around[:, 0])) + 0.2**2 / 12)
    assert lever == pytest.approx(expected, rel=1e-6)
    assert lever > 4.0
    # Depth does not matter: rays are compared where they cross z = 1.
    assert axis_leverage(side * 2.0, axis * 3.0, 0.2) == pytest.approx(lever)


def test_tilt_leverage_says_how_far_an_error_common_to_one_side_tilts_the_plane() -> None:
    """A relative error in the cell sizes that grows across the view (a net bulging on one
    side) is not noise that averages over ROIs: fitted exactly, it tilts the plane by its rms
    over the ROIs' spread that way, and sqrt(tilt_leverage) bounds that for any direction."""
    rays = _rays()
    normal = _unit(np.array([0.0, 0.0, 1.0]))
    areas = _areas(rays, normal, 1.0)
    sigmas = np.full(len(rays), 0.002)
    x = rays[:, 0]
    rms = 0.01
    ramp = rms * (x - x.mean()) / x.std()
    bent = areas * (1.0 + ramp) ** 3  # c, the cube root of the area, off by `ramp`
    flat_fit = fit_plane(rays, areas, sigmas, CELL_M2)
    bent_fit = fit_plane(rays, bent, sigmas, CELL_M2)
    assert flat_fit is not None and bent_fit is not None
    tilt = math.acos(min(1.0, float(flat_fit.normal_away @ bent_fit.normal_away)))
    assert tilt == pytest.approx(rms / x.std(), rel=0.1)
    leverage = tilt_leverage(rays, 0.0)
    assert rms * math.sqrt(leverage) >= tilt
    # Larger ROIs (each a square, not a point) pin it a little better; a view twice as wide
    # both ways, four times better.
    assert tilt_leverage(rays, 0.2) < leverage
    wide = rays * np.array([2.0, 2.0, 1.0])
    assert tilt_leverage(wide, 0.0) == pytest.approx(leverage / 4.0)
    # One row of ROIs leaves the tilt across it unpinned but for the ROIs' own extent.
    row = rays[np.isclose(rays[:, 1], 0.0)]
    assert tilt_leverage(row, 0.2) > 20 * tilt_leverage(rays, 0.2)
