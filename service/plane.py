"""Net plane from the apparent mesh cell area in several ROIs (linear, no mirror ambiguity).

For a plane n.X = d (n pointing away from the camera) and a ray r = (x, y, 1) in undistorted
normalised coordinates, a cell of area A on the plane covers a = A (n.r)^3 / d^2 of the
normalised image. With c = (a / A)^(1/3) that is linear: c = r . m with m = n / d^(2/3).
Several ROIs spread over the image give m by weighted least squares; n = m/|m|, d = |m|^-3/2,
and the range along the optical axis is d / n_z.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]
Bools = npt.NDArray[np.bool_]


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


def fit_plane(
    rays: F64,
    cell_area_norm: F64,
    relative_area_sigma: F64,
    mesh_cell_area_m2: float,
    min_rois: int = 4,
    outlier_sigma: float = 3.5,
    min_relative_tolerance: float = 0.01,
) -> PlaneFit | None:
    """Robust weighted plane fit; None when too few consistent ROIs or a degenerate layout."""
    if rays.shape[0] < min_rois:
        return None
    c = np.cbrt(cell_area_norm / mesh_cell_area_m2)
    # sigma of c: one third of the relative area sigma (c ~ a^(1/3)), with a model floor for
    # net deformation and the perspective chirp inside a ROI.
    rel_sigma_c = np.sqrt((relative_area_sigma / 3.0) ** 2 + 0.002**2)
    used = np.ones(rays.shape[0], dtype=bool)
    m = np.zeros(3)
    cov = np.eye(3)
    for _ in range(6):
        if int(used.sum()) < min_rois:
            return None
        # Rows scaled so each residual is (r.m - c) / (sigma_rel * c).
        a = rays[used] / (rel_sigma_c[used] * c[used])[:, None]
        b = 1.0 / rel_sigma_c[used]
        ata = a.T @ a
        if np.linalg.cond(ata) > 1e9:
            return None
        m = np.linalg.solve(ata, a.T @ b)
        rel = (rays @ m - c) / c
        normalised = rel / rel_sigma_c
        dof = int(used.sum()) - 3
        chi2 = float((normalised[used] ** 2).sum())
        scale = max(1.0, chi2 / dof) if dof > 0 else 1.0
        cov = np.linalg.inv(ata) * scale
        # Robust spread estimate from the used ROIs (MAD), never below the tolerance floor.
        spread = 1.4826 * float(np.median(np.abs(rel[used] - np.median(rel[used]))))
        limit = max(outlier_sigma * spread, min_relative_tolerance)
        new_used = np.abs(rel) <= np.maximum(limit, outlier_sigma * rel_sigma_c)
        if np.array_equal(new_used, used):
            break
        used = new_used
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
    )
