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

import numpy as np
import numpy.typing as npt

from service.core.spectrum import Peaks

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
    """Lagrange-Gauss reduction: the shortest basis of the same 2D lattice.

    Plain floats: this runs several times per ROI and numpy's per-call overhead dominates 2x2 work.
    """
    ax, ay = float(basis[0, 0]), float(basis[1, 0])
    bx, by = float(basis[0, 1]), float(basis[1, 1])
    if ax * ax + ay * ay > bx * bx + by * by:
        ax, ay, bx, by = bx, by, ax, ay
    for _ in range(32):
        aa = ax * ax + ay * ay
        mu = round((ax * bx + ay * by) / aa)
        bx, by = bx - mu * ax, by - mu * ay
        if bx * bx + by * by >= aa:
            break
        ax, ay, bx, by = bx, by, ax, ay
    # Canonical orientation: angle between k1 and k2 at most 90 degrees, right-handed.
    if ax * bx + ay * by < 0:
        bx, by = -bx, -by
    if ax * by - ay * bx < 0:
        ax, ay, bx, by = bx, by, ax, ay
    return np.array([[ax, bx], [ay, by]])


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


# The sub-lattices of index 2 and 3 of a 2D lattice, as integer bases in its coordinates.
_SUBLATTICES = (
    np.array([[2.0, 0.0], [0.0, 1.0]]),
    np.array([[1.0, 0.0], [0.0, 2.0]]),
    np.array([[1.0, 0.0], [1.0, 2.0]]),
    np.array([[3.0, 0.0], [0.0, 1.0]]),
    np.array([[1.0, 0.0], [0.0, 3.0]]),
    np.array([[1.0, 0.0], [1.0, 3.0]]),
    np.array([[1.0, 0.0], [2.0, 3.0]]),
)


_SUBLATTICE_ARR = np.stack(_SUBLATTICES)
_SUBLATTICE_INV = np.linalg.inv(_SUBLATTICE_ARR)


def _spans_unimodular(indices: I64) -> bool:
    """Do two of these integer index vectors already form a basis of Z^2 (det +-1)?

    The common case for a correct hypothesis (the fundamentals (1,0) and (0,1) are among the
    inliers), checked vectorised so the exact Hermite-normal-form search is the exception.
    """
    head = indices[:12]
    dets = np.abs(head[:, None, 0] * head[None, :, 1] - head[:, None, 1] * head[None, :, 0])
    return bool((dets == 1).any())


def inverse_2x2(m: F64) -> F64:
    """Inverse of a 2x2 matrix without LAPACK's per-call overhead (this runs per hypothesis,
    and per ROI)."""
    a, b, c, d = float(m[0, 0]), float(m[0, 1]), float(m[1, 0]), float(m[1, 1])
    det = a * d - b * c
    return np.array([[d / det, -b / det], [-c / det, a / det]])


def _inverse_2x2_many(m: F64) -> F64:
    """`inverse_2x2` of each matrix of a stack (n, 2, 2)."""
    a, b, c, d = m[:, 0, 0], m[:, 0, 1], m[:, 1, 0], m[:, 1, 1]
    det = a * d - b * c
    return np.stack([np.stack([d, -b], axis=1), np.stack([-c, a], axis=1)], axis=1) / det[
        :, None, None]


def _basis_observed(basis: F64, k: F64, tol: F64) -> bool:
    """Is k1 a peak, and is k2 (or k2 +- k1, for a rhombic mesh's weak cross term) one too?"""

    def seen(v: F64) -> bool:
        d_plus = np.hypot(k[:, 0] - v[0], k[:, 1] - v[1])
        d_minus = np.hypot(k[:, 0] + v[0], k[:, 1] + v[1])
        return bool(((d_plus < tol) | (d_minus < tol)).any())

    def seen_odd(v: F64) -> bool:
        # The fundamental may drown in the low-frequency background of a short ROI while its
        # third harmonic stands clear; folded aliases do not line up like that.
        return seen(v) or seen(3.0 * v)

    b1, b2 = basis[:, 0], basis[:, 1]
    return seen_odd(b1) and (seen_odd(b2) or seen_odd(b2 + b1) or seen_odd(b2 - b1))


def _sums(roi: I64, n: int, a: F64, b: F64) -> F64:
    """Per ROI, the 2x2 sum over its rows of outer(a_row, b_row): (n, 2, 2)."""
    out = np.empty((n, 2, 2))
    for r in range(2):
        for c in range(2):
            out[:, r, c] = np.bincount(roi, a[:, r] * b[:, c], n)
    return out


def _spans_unimodular_many(idx: I64, inl: npt.NDArray[np.bool_], roi: I64, n: int
                           ) -> npt.NDArray[np.bool_]:
    """`_spans_unimodular` of each ROI's inlier indices (its first 12, in peak order)."""
    sel = np.nonzero(inl)[0]
    r = roi[sel]
    starts = np.searchsorted(r, np.arange(n))
    rank = np.arange(sel.size) - starts[r]
    keep = rank < 12
    head = np.zeros((n, 12, 2), dtype=np.int64)
    head[r[keep], rank[keep]] = idx[sel[keep]]
    dets = np.abs(head[:, :, None, 0] * head[:, None, :, 1]
                  - head[:, :, None, 1] * head[:, None, :, 0])
    return np.asarray((dets == 1).any(axis=(1, 2)), dtype=bool)


def _basis_observed_many(basis: F64, k: F64, tol: F64, roi: I64, n: int
                         ) -> npt.NDArray[np.bool_]:
    """`_basis_observed` of one basis among each ROI's peaks."""
    b1, b2 = basis[:, 0], basis[:, 1]
    vectors = np.array([b1, 3.0 * b1, b2, 3.0 * b2, b2 + b1, 3.0 * (b2 + b1), b2 - b1,
                        3.0 * (b2 - b1)])  # (8, 2)
    d_plus = np.hypot(k[:, None, 0] - vectors[None, :, 0], k[:, None, 1] - vectors[None, :, 1])
    d_minus = np.hypot(k[:, None, 0] + vectors[None, :, 0], k[:, None, 1] + vectors[None, :, 1])
    near = (d_plus < tol[:, None]) | (d_minus < tol[:, None])  # (m, 8)
    seen = np.zeros((n, 8), dtype=bool)
    np.logical_or.at(seen, roi, near)
    odd = seen[:, 0::2] | seen[:, 1::2]  # each vector or its third harmonic: b1, b2, b2+b1, b2-b1
    return np.asarray(odd[:, 0] & (odd[:, 1] | odd[:, 2] | odd[:, 3]), dtype=bool)


def _assign(basis: F64, k: F64, tol: F64) -> tuple[npt.NDArray[np.bool_], I64]:
    coords = k @ inverse_2x2(basis).T
    idx = np.rint(coords).astype(np.int64)
    diff = k - idx @ basis.T
    resid2 = diff[:, 0] ** 2 + diff[:, 1] ** 2
    nonzero = (idx[:, 0] != 0) | (idx[:, 1] != 0)
    return (resid2 < tol * tol) & nonzero, idx


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
        # Index pairs of the strongest peaks, by how many there are (used for every ROI).
        self._pairs = {top: np.triu_indices(top, 1) for top in range(hypothesis_peaks + 1)}

    def fit(
        self, peaks: Peaks, expected: F64 | None = None, expected_share: float = 0.6
    ) -> LatticeFit | None:
        """The lattice of the peaks, or None. `expected` (2x2, columns k1 k2 in bins), when the
        caller knows roughly what to look for (tracking), is tried first and used if it explains
        `expected_share` of the peak weight and its basis vectors are seen; otherwise the full
        hypothesis search runs."""
        if len(peaks) < 2:
            return None
        if expected is not None:
            fitted = self.fit_guided_many([peaks], expected, expected_share)[0]
            if fitted is not None:
                return fitted
        return self._search(peaks)

    def fit_many(
        self, peaks: list[Peaks], expected: F64 | None = None, expected_share: float = 0.6
    ) -> list[LatticeFit | None]:
        """`fit` of each ROI's peaks; the guided attempt (`expected`) of all ROIs at once."""
        if expected is None:
            return [self.fit(p) for p in peaks]
        guided = self.fit_guided_many(peaks, expected, expected_share)
        return [g if g is not None else self._search(p) if len(p) >= 2 else None
                for g, p in zip(guided, peaks, strict=True)]

    def fit_guided_many(
        self, peaks: list[Peaks], expected: F64, expected_share: float
    ) -> list[LatticeFit | None]:
        """`fit`'s guided attempt for the peaks of several ROIs that expect the same lattice
        (the ROIs of one rectified pass), vectorised over all their peaks: per ROI, the fit of
        `expected` when it explains `expected_share` of the peak weight, two of its inliers
        form a basis and its basis vectors are seen; None where it does not (the caller then
        searches without it). numpy's cost per call, not the arithmetic, is what a ROI's
        handful of peaks costs one at a time."""
        n_rois = len(peaks)
        out: list[LatticeFit | None] = [None] * n_rois
        e = np.asarray(expected, dtype=np.float64)
        if abs(float(e[0, 0]) * float(e[1, 1]) - float(e[0, 1]) * float(e[1, 0])) <= 1e-9:
            return out
        usable = [i for i, p in enumerate(peaks) if len(p) >= 2]
        if not usable:
            return out
        k = np.concatenate([peaks[i].k for i in usable])
        w = np.concatenate([peaks[i].snr for i in usable])
        roi = np.repeat(np.arange(len(usable)), [len(peaks[i]) for i in usable])
        n = len(usable)
        radius = np.sqrt(k[:, 0] * k[:, 0] + k[:, 1] * k[:, 1])
        tol = np.maximum(self.tolerance_bins, self.tolerance_relative * radius)
        total = np.bincount(roi, w, n)
        basis = reduce_basis(e)
        inl, idx = _assign(basis, k, tol)
        ok = np.bincount(roi, w * inl, n) >= expected_share * total
        ok &= _spans_unimodular_many(idx, inl, roi, n)
        ok &= _basis_observed_many(basis, k, tol, roi, n)
        if not ok.any():
            return out
        # One weighted least-squares step from `basis`: B^T = (N^T W N)^-1 N^T W K per ROI.
        nf = idx.astype(np.float64) * inl[:, None]
        wn = nf * w[:, None]
        normal = _sums(roi, n, wn, nf)  # (n, 2, 2)
        moment = _sums(roi, n, wn, k)
        det = normal[:, 0, 0] * normal[:, 1, 1] - normal[:, 0, 1] * normal[:, 1, 0]
        ok &= np.abs(det) >= 1e-9
        bases = np.zeros((n, 2, 2))
        solvable = np.nonzero(ok)[0]
        solved = _inverse_2x2_many(normal[solvable]) @ moment[solvable]
        for j, b_t in zip(solvable.tolist(), solved, strict=True):
            bases[j] = reduce_basis(b_t.T)
        # Inliers of each ROI's own fitted basis, and the fit's statistics.
        safe = np.where(ok[:, None, None], bases, np.eye(2))
        inv = np.linalg.inv(safe)
        coords = np.einsum("mij,mj->mi", inv[roi], k)
        idx2 = np.rint(coords)
        diff = k - np.einsum("mij,mj->mi", safe[roi], idx2)
        resid2 = diff[:, 0] ** 2 + diff[:, 1] ** 2
        inl2 = (resid2 < tol * tol) & ((idx2[:, 0] != 0) | (idx2[:, 1] != 0))
        n2 = idx2 * inl2[:, None]
        gram = _sums(roi, n, n2, n2)
        count = np.bincount(roi, inl2.astype(np.float64), n)
        gdet = gram[:, 0, 0] * gram[:, 1, 1] - gram[:, 0, 1] * gram[:, 1, 0]
        ok &= (count >= 2) & (np.abs(gdet) >= 1e-9)
        sq = np.bincount(roi, resid2 * inl2, n)
        inlier_w = np.bincount(roi, w * inl2, n)
        # The relative area sigma of every ROI's fit at once: with C = (N^T N)^-1 sigma^2 the
        # covariance of each row of B, var = sum over B^-1's columns b of b^T C b.
        fitted = np.nonzero(ok)[0]
        gram_inv = _inverse_2x2_many(gram[fitted])
        basis_inv = _inverse_2x2_many(bases[fitted])
        spread = np.einsum("jkr,jkl,jlr->j", basis_inv, gram_inv, basis_inv)
        for j, spread_j in zip(fitted.tolist(), spread.tolist(), strict=True):
            m = int(count[j])
            dof = max(1, 2 * m - 4)
            rms = math.sqrt(float(sq[j]) / dof) if m > 2 else 0.0
            mean_snr = float(inlier_w[j]) / m
            sigma_bins = max(rms, 0.6 * math.exp(-0.5 * mean_snr), 0.05)
            var = spread_j * sigma_bins**2
            out[usable[j]] = LatticeFit(
                basis=bases[j],
                inliers=m,
                inlier_weight_fraction=float(inlier_w[j]) / float(total[j])
                if total[j] > 0 else 0.0,
                mean_snr=mean_snr,
                rms_residual_bins=rms,
                relative_area_sigma=math.sqrt(var),
            )
        return out

    def _search(self, peaks: Peaks) -> LatticeFit | None:
        """The lattice of the peaks without a guess: hypotheses from pairs of strong peaks."""
        k, w = peaks.k, peaks.snr
        radius = np.sqrt(k[:, 0] * k[:, 0] + k[:, 1] * k[:, 1])
        tol = np.maximum(self.tolerance_bins, self.tolerance_relative * radius)
        total = float(w.sum())
        candidates = self._hypotheses(k, w, tol, radius)
        best: tuple[float, int, F64, npt.NDArray[np.bool_]] | None = None
        for basis in candidates:
            inl, idx = _assign(basis, k, tol)
            if _spans_unimodular(idx[inl]):
                gen = None
            else:
                gen = generated_lattice(idx[inl])
                if gen is None:
                    continue
            if gen is not None and abs(round(np.linalg.det(gen))) != 1:
                # Too fine a basis (a sub-harmonic): use the lattice the peaks really generate.
                basis = basis @ gen.astype(np.float64)
                inl, idx = _assign(basis, k, tol)
            score = float(w[inl].sum())
            count = int(inl.sum())
            if best is None or (score, count) > (best[0], best[1]):
                best = (score, count, basis, inl)
        if best is None:
            return None
        basis, inl = self._admit_fractional(best[2], k, w, tol, best[3])
        basis = self._coarsen(basis, k, w, tol, inl)
        return self._refine(basis, k, w, tol, total)

    def _hypotheses(
        self, k: F64, w: F64, tol: F64, radius: F64, keep: int = 2
    ) -> list[F64]:
        """Score every basis made of two strong peaks at once (vectorised); keep the best few.
        `radius`: the peaks' distances from the origin (bins)."""
        top = min(len(k), self.hypothesis_peaks)
        ii, jj = self._pairs[top]
        a, b = k[ii], k[jj]
        det = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
        ok = np.abs(det) >= self.min_sin * radius[ii] * radius[jj]
        if not ok.any():
            return []
        a, b, det = a[ok], b[ok], det[ok]
        kx, ky = k[None, :, 0], k[None, :, 1]
        n1 = np.rint((b[:, 1:2] * kx - b[:, 0:1] * ky) / det[:, None])
        n2 = np.rint((-a[:, 1:2] * kx + a[:, 0:1] * ky) / det[:, None])
        rx = kx - n1 * a[:, 0:1] - n2 * b[:, 0:1]
        ry = ky - n1 * a[:, 1:2] - n2 * b[:, 1:2]
        inl = (np.hypot(rx, ry) < tol[None, :]) & ((n1 != 0) | (n2 != 0))
        scores = inl.astype(np.float64) @ w
        order = np.argsort(-scores)[:keep]
        return [np.stack([a[h], b[h]], axis=1) for h in order]

    @staticmethod
    def _coarsen(
        basis: F64, k: F64, w: F64, tol: F64, inl: npt.NDArray[np.bool_]
    ) -> F64:
        """Prefer a super-lattice (index 2 or 3) that explains nearly all the weight.

        A lattice twice as dense always explains at least as many peaks (noise and chirp-smeared
        harmonics find a point nearby), so density must pay: the coarser lattice wins unless the
        extra points carry real weight.
        """
        weight = float(w[inl].sum())
        for _ in range(3):
            # All sub-lattices at once: coordinates of every peak in every candidate basis.
            coords = inverse_2x2(basis) @ k.T  # (2, m) in the current basis
            idx = np.rint(_SUBLATTICE_INV @ coords)  # (s, 2, m) in each candidate basis
            cart = (basis @ _SUBLATTICE_ARR) @ idx  # (s, 2, m) back in bins
            resid2 = ((k.T[None] - cart) ** 2).sum(axis=1)
            ok = (resid2 < (tol * tol)[None]) & ((idx[:, 0] != 0) | (idx[:, 1] != 0))
            weights = ok.astype(np.float64) @ w
            good = np.nonzero(weights >= 0.9 * weight)[0]
            if good.size == 0:
                return basis
            choice = int(good[0])
            basis, weight = basis @ _SUBLATTICE_ARR[choice], float(weights[choice])
        return basis

    @staticmethod
    def _admit_fractional(
        basis: F64, k: F64, w: F64, tol: F64, inl: npt.NDArray[np.bool_]
    ) -> tuple[F64, npt.NDArray[np.bool_]]:
        """Peaks at half- or third-integer coordinates mean the basis is too coarse: refine it."""
        outliers = ~inl
        # The refined lattice must gain 20 % of weight; impossible if the outliers carry less.
        if float(w[outliers].sum()) <= 0.2 * float(w[inl].sum()):
            return basis, inl
        coords = k @ inverse_2x2(basis).T
        for denom in (2, 3):
            scaled = coords * denom
            idx = np.rint(scaled).astype(np.int64)
            fine = np.linalg.norm(k - (idx @ basis.T) / denom, axis=1) < tol
            if not (fine & outliers).any():
                continue
            gen = generated_lattice(idx[fine | inl])
            if gen is None:
                continue
            candidate = reduce_basis((basis / denom) @ gen.astype(np.float64))
            # Aliased harmonics (beyond Nyquist, folded back) also sit at fractional
            # coordinates, but a real finer lattice has peaks at its own basis vectors.
            if not _basis_observed(candidate, k, tol):
                continue
            new_inl, _ = _assign(candidate, k, tol)
            if float(w[new_inl].sum()) > 1.2 * float(w[inl].sum()):
                return candidate, new_inl
        return basis, inl

    def _refine(self, basis: F64, k: F64, w: F64, tol: F64, total: float) -> LatticeFit | None:
        basis = reduce_basis(basis)
        for _ in range(1):
            inl, idx = _assign(basis, k, tol)
            n = idx[inl].astype(np.float64)
            nw = n * w[inl][:, None]
            normal = n.T @ nw
            # Fewer than two independent peaks cannot pin a 2D lattice.
            if abs(normal[0, 0] * normal[1, 1] - normal[0, 1] * normal[1, 0]) < 1e-9:
                return None
            # Weighted least squares for B in k = B n: B^T = (N^T W N)^-1 N^T W K.
            basis = reduce_basis((inverse_2x2(normal) @ (nw.T @ k[inl])).T)
        inl, idx = _assign(basis, k, tol)
        n = idx[inl].astype(np.float64)
        gram = n.T @ n
        if n.shape[0] < 2 or abs(gram[0, 0] * gram[1, 1] - gram[0, 1] * gram[1, 0]) < 1e-9:
            return None
        resid = k[inl] - n @ basis.T
        dof = max(1, 2 * n.shape[0] - 4)
        rms = float(np.sqrt((resid**2).sum() / dof)) if n.shape[0] > 2 else 0.0
        # An interpolated peak is located to about 0.6 bin over its amplitude SNR (Hann window,
        # log-parabolic fit): ~0.05 bin for a clear peak, a few tenths for a faint one. That
        # floor holds even when the fit is exact (2 peaks).
        mean_snr = float(w[inl].mean())
        sigma_bins = max(rms, 0.6 * math.exp(-0.5 * mean_snr), 0.05)
        cov = inverse_2x2(gram) * sigma_bins**2  # covariance of each row of B
        # d log|det B| = trace(B^-1 dB): row r of B enters through column r of B^-1.
        binv = inverse_2x2(basis)
        var = float(sum(binv[:, r] @ cov @ binv[:, r] for r in range(2)))
        return LatticeFit(
            basis=basis,
            inliers=int(inl.sum()),
            inlier_weight_fraction=float(w[inl].sum()) / total if total > 0 else 0.0,
            mean_snr=mean_snr,
            rms_residual_bins=rms,
            relative_area_sigma=math.sqrt(var),
        )
