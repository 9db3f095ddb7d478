"""From spectral peaks to a reciprocal lattice: hypotheses, robust least squares, reduction.

A net's spectrum is a 2D lattice of peaks (fundamentals and harmonics of the two twine families).
Two peaks propose a basis; the basis that explains the most peak weight wins. A hypothesis that
is too fine (a sub-harmonic) explains every peak too, so the basis is replaced by the lattice that
the explained peaks actually generate (Hermite normal form of their integer indices). The basis is
then fitted to all inliers by weighted least squares and Lagrange-Gauss reduced, so the mesh is
the true, unsheared cell.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import combinations

import numpy as np
import numpy.typing as npt

from service.spectrum import Peaks

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]


@dataclass(frozen=True)
class LatticeFit:
    basis: F64  # 2x2, columns k1, k2 in bins (cycles per ROI), reduced
    inliers: int
    inlier_weight_fraction: float
    mean_snr: float
    rms_residual_bins: float
    relative_area_sigma: float  # 1-sigma relative uncertainty of |det basis|

    @property
    def det(self) -> float:
        return float(abs(np.linalg.det(self.basis)))


def reduce_basis(basis: F64) -> F64:
    """Lagrange-Gauss reduction: the shortest basis of the same 2D lattice."""
    a = basis[:, 0].copy()
    b = basis[:, 1].copy()
    if a @ a > b @ b:
        a, b = b, a
    for _ in range(32):
        mu = round(float(a @ b) / float(a @ a))
        b = b - mu * a
        if b @ b >= a @ a:
            break
        a, b = b, a
    # Canonical orientation: angle between k1 and k2 at most 90 degrees, right-handed.
    if a @ b < 0:
        b = -b
    if a[0] * b[1] - a[1] * b[0] < 0:
        a, b = b, a
    return np.stack([a, b], axis=1)


def _egcd(a: int, b: int) -> tuple[int, int, int]:
    x0, x1, y0, y1 = 1, 0, 0, 1
    while b:
        q, a, b = a // b, b, a % b
        x0, x1 = x1, x0 - q * x1
        y0, y1 = y1, y0 - q * y1
    return a, x0, y0


def generated_lattice(indices: I64) -> I64 | None:
    """Integer 2x2 matrix whose columns generate the same lattice as the given index rows.

    None when the indices are collinear (a 1D pattern such as a rope or stripes, not a net).
    """
    r1 = (0, 0)
    c = 0
    for x, y in indices.tolist():
        if x == 0 and y == 0:
            continue
        a, b = r1
        if a == 0 and b == 0 and x != 0:
            r1 = (x, y) if x > 0 else (-x, -y)
            continue
        if x == 0:
            c = math.gcd(c, y)
            continue
        g, s, t = _egcd(a, x)
        # New first row combines both; the remainder has a zero first coordinate.
        new = (s * a + t * x, s * b + t * y)
        rem_y = (x // g) * b - (a // g) * y
        r1 = new if new[0] > 0 else (-new[0], -new[1])
        c = math.gcd(c, rem_y)
    a, b = r1
    if a == 0 or c == 0:
        return None
    return np.array([[a, 0], [b % c, c]], dtype=np.int64)


def _assign(basis: F64, k: F64, tol: F64) -> tuple[npt.NDArray[np.bool_], I64]:
    coords = np.linalg.solve(basis, k.T).T
    idx = np.rint(coords).astype(np.int64)
    resid = np.linalg.norm(k - idx @ basis.T, axis=1)
    nonzero = np.any(idx != 0, axis=1)
    return (resid < tol) & nonzero, idx


class LatticeFinder:
    """Finds the reciprocal lattice in a set of peaks. Stateless after construction."""

    def __init__(
        self,
        hypothesis_peaks: int = 7,
        tolerance_bins: float = 0.6,
        tolerance_relative: float = 0.025,
        min_angle_deg: float = 25.0,
    ) -> None:
        self.hypothesis_peaks = hypothesis_peaks
        self.tolerance_bins = tolerance_bins
        self.tolerance_relative = tolerance_relative
        self.min_sin = math.sin(math.radians(min_angle_deg))

    def fit(self, peaks: Peaks) -> LatticeFit | None:
        if len(peaks) < 2:
            return None
        k, w = peaks.k, peaks.snr
        tol = np.maximum(self.tolerance_bins, self.tolerance_relative * np.linalg.norm(k, axis=1))
        total = float(w.sum())
        best: tuple[float, int, F64] | None = None
        top = min(len(peaks), self.hypothesis_peaks)
        for i, j in combinations(range(top), 2):
            a, b = k[i], k[j]
            cross = abs(a[0] * b[1] - a[1] * b[0])
            if cross < self.min_sin * float(np.linalg.norm(a) * np.linalg.norm(b)):
                continue
            basis = np.stack([a, b], axis=1)
            inl, idx = _assign(basis, k, tol)
            gen = generated_lattice(idx[inl])
            if gen is None:
                continue
            if abs(int(round(np.linalg.det(gen)))) != 1:
                basis = basis @ gen.astype(np.float64)
                inl, idx = _assign(basis, k, tol)
            score = float(w[inl].sum())
            count = int(inl.sum())
            if best is None or (score, count) > (best[0], best[1]):
                best = (score, count, basis)
        if best is None:
            return None
        return self._refine(best[2], k, w, tol, total)

    def _refine(self, basis: F64, k: F64, w: F64, tol: F64, total: float) -> LatticeFit | None:
        basis = reduce_basis(basis)
        for _ in range(2):
            inl, idx = _assign(basis, k, tol)
            n = idx[inl].astype(np.float64)
            if n.shape[0] < 2 or np.linalg.matrix_rank(n) < 2:
                return None
            ww = w[inl]
            # Weighted least squares for B in k = B n: B^T = (N^T W N)^-1 N^T W K.
            nw = n * ww[:, None]
            basis = np.linalg.solve(n.T @ nw, nw.T @ k[inl]).T
            basis = reduce_basis(basis)
        inl, idx = _assign(basis, k, tol)
        n = idx[inl].astype(np.float64)
        if n.shape[0] < 2 or np.linalg.matrix_rank(n) < 2:
            return None
        resid = k[inl] - n @ basis.T
        dof = max(1, 2 * n.shape[0] - 4)
        rms = float(np.sqrt((resid**2).sum() / dof)) if n.shape[0] > 2 else 0.0
        # Interpolated peaks are good to ~0.05 bin even when the fit is exact (2 peaks).
        sigma_bins = max(rms, 0.05)
        cov = np.linalg.inv(n.T @ n) * sigma_bins**2  # per-component covariance of B rows
        # d|det B|/|det B| = trace(B^-1 dB); B rows share cov -> var = sum over rows.
        binv = np.linalg.inv(basis)
        var = 0.0
        for r in range(2):
            g = binv[:, r]  # derivative of log det w.r.t. row r of B
            var += float(g @ cov @ g)
        return LatticeFit(
            basis=basis,
            inliers=int(inl.sum()),
            inlier_weight_fraction=float(w[inl].sum()) / total if total > 0 else 0.0,
            mean_snr=float(w[inl].mean()),
            rms_residual_bins=rms,
            relative_area_sigma=math.sqrt(var),
        )
