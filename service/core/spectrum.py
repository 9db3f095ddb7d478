"""Spectral analysis of one square region: whitened power spectrum and its sub-bin peaks.

Why each step:
- the ROI mean is removed and a Hann window applied, so the DC term and the ROI's borders do not
  leak energy over the whole spectrum (integer-bin peaks of an unwindowed FFT cost 1-3 % of scale);
- the log power is compared with a ring-shaped local background (box 11x11 minus box 5x5), which
  whitens the strong low-frequency energy of underwater scenes (light gradients, caustics) and
  makes one relative threshold work at any range;
- peaks are refined by log-parabolic (Gaussian) interpolation over the 3-point neighbourhood in
  each axis, good to a few hundredths of a bin with a Hann window.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Peaks:
    """Spectral peaks of one ROI, in bins (cycles per ROI), half-plane only, strongest first."""

    k: F64  # (m, 2): (kx, ky)
    snr: F64  # (m,): log power ratio over the local background (natural log)

    def __len__(self) -> int:
        return int(self.k.shape[0])


class SpectrumAnalyzer:
    """Everything that depends only on the ROI size is computed once here.

    The spectrum of a real patch is Hermitian, so only the half kx >= 0 is computed (a real
    FFT, half the work of a complex one). Rows are centred on ky = 0 by modulating the input
    with (-1)^y, and a few mirrored columns (kx < 0, from F(-k) = conj F(k)) are prepended so
    the local filters and the peak interpolation see a seamless spectrum around kx = 0.
    """

    MARGIN = 6  # mirrored columns: half the 11x11 background box, so kx = 0 is interior

    def __init__(
        self,
        size: int,
        min_radius_bins: float = 2.6,
        max_radius_fraction: float = 0.46,
        min_snr: float = 2.8,
        max_peaks: int = 24,
    ) -> None:
        if size < 32 or size & (size - 1):
            raise ValueError(f"ROI size must be a power of two >= 32, got {size}")
        self.size = size
        hann = np.hanning(size + 2)[1:-1]
        self.window: F32 = np.outer(hann, hann).astype(np.float32)
        rows_sign = np.where(np.arange(size) % 2 == 0, 1.0, -1.0)[:, None]
        self._modulated_window: F32 = (self.window * rows_sign).astype(np.float32)
        m = self.MARGIN
        half = size // 2
        self._mirror_rows = (size - np.arange(size)) % size
        self._mirror_cols = np.arange(m, 0, -1)  # kx = m .. 1, mirrored to -m .. -1
        ky = np.arange(size)[:, None] - half
        kx = np.arange(half + 1 + m)[None, :] - m
        radius = np.hypot(kx, ky)
        upper = (kx > 0) | ((kx == 0) & (ky > 0))
        valid = upper & (radius >= min_radius_bins) & (radius <= max_radius_fraction * size)
        # One bin of margin so the 3-point interpolation never reads outside the array.
        valid[:1, :] = False
        valid[-1:, :] = False
        valid[:, -1:] = False
        self.valid: npt.NDArray[np.bool_] = valid
        self.min_snr = min_snr
        self.max_peaks = max_peaks
        self._row0 = half
        self._col0 = m
        self._kernel = np.ones((3, 3), np.uint8)

    def index_of(self, k: npt.ArrayLike) -> tuple[int, int]:
        """(row, column) of the bin nearest wave vector k (bins) in `log_power`'s array."""
        kx, ky = (float(v) for v in np.asarray(k, dtype=np.float64).ravel()[:2])
        if kx < 0 or (kx == 0 and ky < 0):
            kx, ky = -kx, -ky  # the stored half plane holds k or its conjugate -k
        return round(ky) + self._row0, round(kx) + self._col0

    def log_power(self, patch: F32) -> F32:
        """Log power of the windowed, mean-free patch on the half plane kx >= -MARGIN.

        Rows are ky + size/2, columns kx + MARGIN.
        """
        import cv2
        from scipy import fft

        p = patch.astype(np.float32, copy=False)
        p = (p - float(p.mean())) * self._modulated_window
        spec = fft.rfft2(p, workers=1)
        power = (spec.real * spec.real + spec.imag * spec.imag).astype(np.float32)
        # A flat patch has no spectrum at all: a floor keeps the log finite.
        np.maximum(power, float(power.mean()) * 1e-10 + 1e-20, out=power)
        mirrored = power[self._mirror_rows][:, self._mirror_cols]
        full = np.concatenate([mirrored, power], axis=1)
        return np.asarray(cv2.log(full), dtype=np.float32)

    def background(self, logp: F32) -> F32:
        """Mean log power over a ring (11x11 box minus the 5x5 core) around each bin."""
        import cv2

        outer = cv2.boxFilter(logp, -1, (11, 11), normalize=False, borderType=cv2.BORDER_REFLECT)
        inner = cv2.boxFilter(logp, -1, (5, 5), normalize=False, borderType=cv2.BORDER_REFLECT)
        return np.asarray((outer - inner) * (1.0 / (121.0 - 25.0)), dtype=np.float32)

    def peaks(self, patch: F32) -> Peaks:
        import cv2

        logp = self.log_power(patch)
        snr = logp - self.background(logp)
        local_max = logp >= cv2.dilate(logp, self._kernel)
        rows, cols = np.nonzero(local_max & self.valid & (snr > self.min_snr))
        if rows.size == 0:
            return Peaks(np.zeros((0, 2)), np.zeros(0))
        strength = snr[rows, cols]
        order = np.argsort(-strength)[: self.max_peaks]
        rows, cols, strength = rows[order], cols[order], strength[order]
        centre = logp[rows, cols].astype(np.float64)
        dx = _parabolic(logp[rows, cols - 1], centre, logp[rows, cols + 1])
        dy = _parabolic(logp[rows - 1, cols], centre, logp[rows + 1, cols])
        k = np.stack([cols + dx - self._col0, rows + dy - self._row0], axis=1)
        return Peaks(k.astype(np.float64), strength.astype(np.float64))


def _parabolic(left: npt.ArrayLike, centre: F64, right: npt.ArrayLike) -> F64:
    lv = np.asarray(left, dtype=np.float64)
    rv = np.asarray(right, dtype=np.float64)
    denom = lv - 2.0 * centre + rv
    safe = np.where(np.abs(denom) > 1e-12, denom, -1e-12)
    return np.clip(0.5 * (lv - rv) / safe, -0.5, 0.5)
