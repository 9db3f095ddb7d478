"""Net plane from the apparent mesh cell area in several ROIs (linear, no mirror ambiguity).

For a plane n.X = d (n pointing away from the camera) and a ray r = (x, y, 1) in undistorted
normalised coordinates, a cell of area A on the plane covers a = A (n.r)^3 / d^2 of the
normalised image. With c = (a / A)^(1/3) that is linear: c = r . m with m = n / d^(2/3).
Several ROIs spread over the image give m by weighted least squares; n = m/|m|, d = |m|^-3/2,
and the range along the optical axis is d / n_z.

How well the fit knows m: each ROI's lattice fit gives its own measurement noise (a
Cramer-Rao-like model of the peak positions), and the ROI-to-ROI residuals measure the scatter
actually present. With few ROIs the residuals alone say little (with one degree of freedom the
scatter is one squared number), so the two are pooled as a scaled-inverse-chi-square posterior:
the noise model counts as `PRIOR_DOF` prior degrees of freedom at a variance factor of one, the
residuals as `n - 3` more, s^2 = (nu0 + chi^2) / (nu0 + nu). The factor never drops below one:
residuals smaller than the model mean ROIs that share pixels (overlapping windows), not ROIs
better than their own spectra. `PlaneFit.sigma_dof` (nu0 + nu) is what a Student-t quantile of
the result must use.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]
Bools = npt.NDArray[np.bool_]

# Prior degrees of freedom of the per-ROI noise model in the pooled variance (see the module
# docstring): about what a fit with four residuals says about its own scatter. Larger trusts the
# model more; zero is the residual-only scatter, which is undefined without residuals.
PRIOR_DOF = 4.0
# How far (relative, in c) a ROI may sit off a plane and still agree with it: real nets' cells
# differ a little from place to place, so agreement is never judged tighter than this.
CONSENSUS_TOLERANCE = 0.02


def relative_sigma_c(relative_area_sigma: F64 | float) -> F64:
    """Relative sigma of a ROI's c = (a / A)^(1/3): one third of its cell area's relative
    sigma (c ~ a^(1/3)), with a model floor for net deformation and the perspective chirp inside
    a ROI."""
    return np.sqrt((np.asarray(relative_area_sigma, dtype=np.float64) / 3.0) ** 2 + 0.002**2)


@dataclass(frozen=True)
class PlaneFit:
    normal_away: F64  # unit normal, camera -> net
    distance_m: float
    range_m: float
    sigma_distance_m: float
    sigma_range_m: float
    sigma_normal_deg: float
    used: Bools  # which ROIs survived the robust fit
    relative_rms: float  # rms of (c_fit - c) / c over used ROIs
    # Degrees of freedom of the pooled variance behind the sigmas: PRIOR_DOF + used ROIs - 3.
    sigma_dof: float = PRIOR_DOF

    def c_at(self, ray: F64) -> float:
        """The plane's c = r . m at a ray (m = n / d^(2/3)): what a ROI there should show."""
        return float(ray @ self.normal_away) / self.distance_m ** (2.0 / 3.0)


def fit_plane(
    rays: F64,
    cell_area_norm: F64,
    relative_area_sigma: F64,
    mesh_cell_area_m2: float,
    min_rois: int = 4,
    outlier_sigma: float = 3.5,
    min_relative_tolerance: float = 0.01,
    consensus_tolerance: float = CONSENSUS_TOLERANCE,
    triples: RoiTriples | None = None,
) -> PlaneFit | None:
    """Robust weighted plane fit; None when too few consistent ROIs or a degenerate layout.
    `triples`: the caller's table of ROI triples, kept between fits (a new one otherwise)."""
    if rays.shape[0] < min_rois:
        return None
    c = np.cbrt(cell_area_norm / mesh_cell_area_m2)
    rel_sigma_c = relative_sigma_c(relative_area_sigma)
    # A ROI joins the consensus within 3 sigma of its own measurement, but never tighter than
    # `consensus_tolerance`: weak lattices (few cycles, faint peaks) are known less well.
    used = _consensus(rays, c, np.maximum(consensus_tolerance, 3.0 * rel_sigma_c),
                      triples if triples is not None else RoiTriples())
    if used is None:
        return None
    m = np.zeros(3)
    cov = np.eye(3)
    dof = 0
    # Backward elimination: drop the worst ROI while it is an outlier against the robust spread
    # of the rest (a fish, a wrong lattice), then re-admit any ROI the final plane explains.
    for _ in range(rays.shape[0]):
        fitted = _solve(rays[used], c[used], rel_sigma_c[used])
        if fitted is None:
            return None
        m, cov, dof = fitted
        rel = (rays @ m - c) / c
        spread = 1.4826 * float(np.median(np.abs(rel[used] - np.median(rel[used]))))
        limit = max(outlier_sigma * spread, min_relative_tolerance)
        candidates = np.where(used, np.abs(rel), -1.0)
        worst = int(np.argmax(candidates))
        if candidates[worst] <= limit:
            readmit = used | (np.abs(rel) <= limit)
            if not np.array_equal(readmit, used):
                used = readmit
                continue
            break
        used[worst] = False
        if int(used.sum()) < min_rois:
            return None
    if int(used.sum()) < min_rois:
        return None
    norm = float(np.linalg.norm(m))
    if norm <= 0 or m[2] <= 0:
        return None
    n = m / norm
    d = norm**-1.5
    rng = d / float(n[2])
    # First-order propagation of cov(m).
    g_d = -1.5 * norm**-2.5 * n
    g_r = -0.5 * norm**-2.5 * m / m[2] - norm**-0.5 / m[2] ** 2 * np.array([0.0, 0.0, 1.0])
    proj = np.eye(3) - np.outer(n, n)
    ang_var = float(np.trace(proj @ cov @ proj)) / norm**2
    rel = (rays[used] @ m - c[used]) / c[used]
    return PlaneFit(
        normal_away=n,
        distance_m=float(d),
        range_m=float(rng),
        sigma_distance_m=math.sqrt(max(0.0, float(g_d @ cov @ g_d))),
        sigma_range_m=math.sqrt(max(0.0, float(g_r @ cov @ g_r))),
        sigma_normal_deg=math.degrees(math.sqrt(max(0.0, ang_var))),
        used=used,
        relative_rms=float(np.sqrt(np.mean(rel**2))),
        sigma_dof=PRIOR_DOF + dof,
    )


def plane_through(rays: F64, cell_area_norm: F64, relative_area_sigma: F64,
                  mesh_cell_area_m2: float) -> tuple[F64, float] | None:
    """The weighted least-squares plane through every ROI given, none left out: its unit
    normal (camera -> net) and distance; None for a degenerate layout."""
    if rays.shape[0] < 3:
        return None
    c = np.cbrt(cell_area_norm / mesh_cell_area_m2)
    fitted = _solve(rays, c, relative_sigma_c(relative_area_sigma))
    if fitted is None:
        return None
    m = fitted[0]
    norm = float(np.linalg.norm(m))
    if norm <= 0 or m[2] <= 0:
        return None
    return m / norm, norm**-1.5


def _solve(rays: F64, c: F64, rel_sigma_c: F64) -> tuple[F64, F64, int] | None:
    """Weighted least squares for c = r . m; the covariance scaled by the pooled variance
    factor (the noise model as PRIOR_DOF prior degrees of freedom, the residuals' chi-square as
    the rest; never below the model), and the residual degrees of freedom."""
    # Rows scaled so each residual is (r.m - c) / (sigma_rel * c).
    a = rays / (rel_sigma_c * c)[:, None]
    b = 1.0 / rel_sigma_c
    ata = a.T @ a
    if np.linalg.cond(ata) > 1e9:
        return None
    m = np.linalg.solve(ata, a.T @ b)
    dof = max(0, rays.shape[0] - 3)
    chi2 = float(((a @ m - b) ** 2).sum())
    scale = max(1.0, (PRIOR_DOF + chi2) / (PRIOR_DOF + dof))
    return (np.asarray(m, dtype=np.float64),
            np.asarray(np.linalg.inv(ata) * scale, dtype=np.float64), dof)


def _layout_spread(rays: F64, extent: float) -> tuple[F64, F64]:
    """The ROI centres where their rays cross z = 1, and their covariance with each ROI counted
    as a square of side `extent` (uniform over it: variance extent^2 / 12 each way)."""
    xy = rays[:, :2] / rays[:, 2:3]
    return xy, np.cov(xy.T, bias=True) + np.eye(2) * extent * extent / 12.0


def axis_leverage(rays: F64, axis: F64, extent: float) -> float:
    """How far the fit extrapolates to `axis`: the squared Mahalanobis distance of the axis's
    image point from the cloud of ROI centres (rays and axis as (x, y, z) in one camera frame,
    compared at z = 1), each ROI counted as a square of side `extent` (same units), not a point.

    About 0 to 1 when the ROIs surround the axis; large when they sit on one side of it, which
    a marker board or a steep view can leave. A plane is known best at its ROIs' centroid, and
    the range on the optical axis is then the plane carried across that distance: any tilt the
    ROIs did not see (a net that billows) enters in proportion to the lever, so the variance it
    adds grows with this number.
    """
    xy, spread = _layout_spread(rays, extent)
    offset = axis[:2] / axis[2] - xy.mean(axis=0)
    try:
        return float(offset @ np.linalg.solve(spread, offset))
    except np.linalg.LinAlgError:
        return math.inf


def tilt_leverage(rays: F64, extent: float) -> float:
    """How weakly the ROIs' layout pins the tilt: the trace of the inverse covariance of the
    ROI centres (rays compared at z = 1, each ROI a square of side `extent`), so that a
    relative error e in the cell areas, common to a side of the view rather than independent
    per ROI, tilts the fitted plane by about e * sqrt(this) radians. Small when the ROIs span
    the view both ways; large when they sit in a row (one direction unpinned) or a bunch."""
    _, spread = _layout_spread(rays, extent)
    try:
        return float(np.trace(np.linalg.inv(spread)))
    except np.linalg.LinAlgError:
        return math.inf


class RoiTriples:
    """Every (a, b, c) with a < b < c < k, in the order itertools.combinations gives them,
    per ROI count k: built by numpy (a Python list of them cost about as much as the RANSAC
    itself) and kept, read-only, by its owner (an estimator): a tracked frame fits the same
    number of ROIs as the last, and building the table was a third of the consensus's time."""

    # ROI counts kept: an estimator sees a few (its grid, minus what a frame rejects).
    MAX_COUNTS = 64

    def __init__(self) -> None:
        self._tables: dict[int, npt.NDArray[np.int64]] = {}

    def __call__(self, k: int) -> npt.NDArray[np.int64]:
        table = self._tables.get(k)
        if table is None:
            if len(self._tables) >= self.MAX_COUNTS:
                del self._tables[next(iter(self._tables))]
            a, b, c = np.meshgrid(*(np.arange(k, dtype=np.int64),) * 3, indexing="ij")
            ordered = (a < b) & (b < c)
            table = np.stack([a[ordered], b[ordered], c[ordered]], axis=1)
            table.flags.writeable = False
            self._tables[k] = table
        return table


def _consensus(rays: F64, c: F64, tolerance: F64, all_triples: RoiTriples,
               max_triples: int = 600) -> Bools | None:
    """Exhaustive RANSAC over ROI triples: the plane most ROIs agree with seeds the fit.

    A wrong lattice in one ROI (a sub- or super-lattice, a fish) is off by a factor of at least
    2^(1/3) in c, far outside the tolerance, so it cannot join a consensus of correct ROIs.
    """
    k = rays.shape[0]
    triples = all_triples(k)
    if triples.shape[0] > max_triples:
        step = triples.shape[0] / max_triples
        triples = triples[(np.arange(max_triples) * step).astype(np.int64)]
    a = rays[triples]  # (t, 3, 3)
    b = c[triples]  # (t, 3)
    dets = np.linalg.det(a)
    ok = np.abs(dets) > 1e-6
    if not ok.any():
        return None
    m = np.linalg.solve(a[ok], b[ok][..., None])[..., 0]  # (t, 3)
    rel = np.abs(m @ rays.T - c[None, :]) / c[None, :]  # (t, k)
    inliers = rel < tolerance[None, :]
    counts = inliers.sum(axis=1)
    # Among the largest consensus sets, the one with the smallest total residual.
    best = int(np.argmin(np.where(counts == counts.max(), (rel * inliers).sum(axis=1), np.inf)))
    return np.asarray(inliers[best], dtype=bool)
