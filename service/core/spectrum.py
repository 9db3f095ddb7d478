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


def half_plane_power(patches: F32) -> F32:
    """|F(ky, kx)|^2 of each real square patch of a stack (n, N, N), for kx = 0 .. N/2: what
    a real 2D FFT gives (numpy's `rfft2` layout), computed by OpenCV's real DFT.

    Why OpenCV and not scipy.fft: it is as fast for these sizes, and the process already holds
    it; scipy.fft brings scipy.special with it, about 24 MB of resident memory and a fifth of
    a second of start-up on a Pi (issue 13), for nothing else the frame loop needs.

    OpenCV returns a real input's spectrum packed (CCS): columns 1 .. N-2 hold Re and Im of
    kx = 1 .. N/2 - 1 side by side, for every row; columns 0 and N-1 hold kx = 0 and kx = N/2,
    whose spectra are Hermitian along ky, packed down the column: Re F(0), then Re and Im of
    ky = 1 .. N/2 - 1, then Re F(N/2); rows ky > N/2 are the mirror images of N - ky.
    """
    import cv2

    n, size, _ = patches.shape
    half = size // 2
    packed = np.empty((n, size, size), dtype=np.float32)
    for i in range(n):
        cv2.dft(patches[i], packed[i])
    power = np.empty((n, size, half + 1), dtype=np.float32)
    # Squared in one contiguous pass, then Re^2 + Im^2 from the interleaved squares: half the
    # time of squaring the two strided halves apart.
    squares = np.square(packed[:, :, 1 : size - 1])
    np.add(squares[:, :, 0::2], squares[:, :, 1::2], out=power[:, :, 1:half])
    for column, kx in ((0, 0), (size - 1, half)):
        col = packed[:, :, column]
        inner = col[:, 1 : size - 1 : 2] ** 2 + col[:, 2 : size - 1 : 2] ** 2  # ky 1 .. N/2-1
        power[:, 0, kx] = col[:, 0] ** 2
        power[:, 1:half, kx] = inner
        power[:, half, kx] = col[:, size - 1] ** 2
        power[:, half + 1 :, kx] = inner[:, ::-1]
    return power


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
        """(row, column) of the bin nearest wave vector k (bins) in a spectrum of `analyse`."""
        kx, ky = (float(v) for v in np.asarray(k, dtype=np.float64).ravel()[:2])
        if kx < 0 or (kx == 0 and ky < 0):
            kx, ky = -kx, -ky  # the stored half plane holds k or its conjugate -k
        return round(ky) + self._row0, round(kx) + self._col0

    def _log_power_many(self, patches: F32) -> F32:
        """Log power of each windowed, mean-free patch of a stack (n, size, size) on the half
        plane kx >= -MARGIN, one stacked real FFT: rows ky + size/2, columns kx + MARGIN."""
        import cv2

        p = patches.astype(np.float32, copy=False)
        p = p - p.mean(axis=(1, 2), keepdims=True)
        p *= self._modulated_window
        power = half_plane_power(p)
        # A flat patch has no spectrum at all: a floor keeps the log finite.
        floor = power.mean(axis=(1, 2), keepdims=True) * np.float32(1e-10) + np.float32(1e-20)
        np.maximum(power, floor, out=power)
        n, rows, cols = power.shape
        m = self.MARGIN
        full = np.empty((n, rows, cols + m), dtype=np.float32)
        full[:, :, m:] = power
        full[:, :, :m] = power[:, :, self._mirror_cols][:, self._mirror_rows]
        flat = full.reshape(n * rows, cols + m)
        cv2.log(flat, flat)
        return full

    def peaks(self, patch: F32) -> Peaks:
        return self.analyse(patch)[0]

    def analyse(self, patch: F32) -> tuple[Peaks, F32, F32]:
        """The peaks, the whitened spectrum they were found in (log power over the local
        background, natural log) and the log power itself; rows ky + size/2, columns
        kx + MARGIN.

        The whitened spectrum of ROIs that show the same lattice (the rectified ROIs of one
        frame) can be averaged: the net's peaks add up while the noise (std ~1.28 per bin for
        a speckle spectrum) averages down, which is how weak evidence from many ROIs is judged.
        """
        return self.analyse_many(np.asarray(patch)[None])[0]

    def analyse_many(self, patches: npt.NDArray[np.generic]) -> list[tuple[Peaks, F32, F32]]:
        """`analyse` of every patch of a stack (n, size, size) at once.

        One stacked FFT and one call of each local filter for all ROIs: numpy's and OpenCV's
        cost per call, not the arithmetic, is what a ROI of 128 px costs one at a time.
        """
        out: list[tuple[Peaks, F32, F32]] = []
        # OpenCV filters at most 512 channels per image.
        for start in range(0, patches.shape[0], 256):
            out.extend(self._analyse_chunk(patches[start : start + 256]))
        return out

    def _analyse_chunk(self, patches: npt.NDArray[np.generic]) -> list[tuple[Peaks, F32, F32]]:
        import cv2

        n = patches.shape[0]
        logp = self._log_power_many(np.asarray(patches, dtype=np.float32))
        # The ROIs as channels of one image: OpenCV filters them all in one call.
        channels = np.ascontiguousarray(logp.transpose(1, 2, 0))
        snr_cl = channels - _ring_mean(channels)
        local_max = channels >= cv2.dilate(channels, self._kernel).reshape(channels.shape)
        snr = np.ascontiguousarray(snr_cl.transpose(2, 0, 1))
        # Found in the channels' own layout (a transposed mask costs nonzero() a strided walk),
        # then ordered by ROI below.
        mask = local_max & (snr_cl > self.min_snr) & self.valid[:, :, None]
        # Flat indices split by hand: a 3-D nonzero() is ten times slower on a mask this sparse.
        rows, rest = np.divmod(np.flatnonzero(mask), mask.shape[1] * mask.shape[2])
        cols, roi = np.divmod(rest, mask.shape[2])
        strength = snr[roi, rows, cols]
        # Strongest first within each ROI, at most max_peaks each.
        order = np.lexsort((-strength, roi))
        roi, rows, cols, strength = roi[order], rows[order], cols[order], strength[order]
        starts = np.searchsorted(roi, np.arange(n + 1))
        rank = np.arange(roi.size) - starts[roi]
        keep = rank < self.max_peaks
        roi, rows, cols, strength = roi[keep], rows[keep], cols[keep], strength[keep]
        centre = logp[roi, rows, cols].astype(np.float64)
        dx = _parabolic(logp[roi, rows, cols - 1], centre, logp[roi, rows, cols + 1])
        dy = _parabolic(logp[roi, rows - 1, cols], centre, logp[roi, rows + 1, cols])
        k = np.stack([cols + dx - self._col0, rows + dy - self._row0], axis=1)
        strength64 = strength.astype(np.float64)
        bounds = np.searchsorted(roi, np.arange(n + 1))
        return [
            (Peaks(k[bounds[i] : bounds[i + 1]], strength64[bounds[i] : bounds[i + 1]]),
             snr[i], logp[i])
            for i in range(n)
        ]

    def peaks_near(self, snr: F32, k: npt.ArrayLike, min_snr: float) -> Peaks:
        """Peaks of the whitened spectrum `snr` where a lattice is expected: for each wave vector
        k (bins), the largest bin within one bin of it, kept when it is a local maximum of at
        least `min_snr`, refined to sub-bin by log-parabolic interpolation.

        A threshold this low would let noise through in a blind search over every bin; at a
        handful of predicted places it does not (a speckle bin exceeds 1.8 with probability
        ~3 %), so a faint mesh that the prediction points at is still seen.
        """
        return self.peaks_near_many(snr[None], k, min_snr)[0]

    def peaks_near_many(self, snrs: F32, k: npt.ArrayLike, min_snr: float) -> list[Peaks]:
        """`peaks_near` at the same wave vectors in each whitened spectrum of a stack
        (n, rows, cols): the ROIs of one rectified pass all expect the same lattice."""
        near = self.maxima_near(snrs, k, min_snr)
        if near is None:
            return [Peaks(np.zeros((0, 2)), np.zeros(0)) for _ in range(snrs.shape[0])]
        found, centre, keep, flat, _ = near
        n, _, cols_n = snrs.shape
        # Two points may land on the same bin: keep each peak once, ordered by bin within its
        # ROI (one np.unique over every ROI's (ROI, bin) key instead of one per ROI).
        roi, point = np.nonzero(keep)
        key = roi * (snrs.shape[1] * cols_n) + flat[roi, point]
        _, first = np.unique(key, return_index=True)
        roi, point = roi[first], point[first]
        k_found = found[roi, point].astype(np.float64)
        snr_found = centre[roi, point]
        bounds = np.searchsorted(roi, np.arange(n + 1))
        return [Peaks(k_found[bounds[i] : bounds[i + 1]], snr_found[bounds[i] : bounds[i + 1]])
                for i in range(n)]

    def maxima_near(
        self, snrs: F32, k: npt.ArrayLike, min_snr: float
    ) -> tuple[F64, F64, npt.NDArray[np.bool_], npt.NDArray[np.int64],
               npt.NDArray[np.bool_]] | None:
        """For each spectrum of a stack (n, rows, cols) and each wave vector k (m, 2) inside
        the array: the largest bin within one bin of k, refined to sub-bin (n, m', 2), its value
        (n, m'), whether it is a local maximum of at least `min_snr` inside the analysed band
        (n, m'), its flat bin index (n, m'), and which of the m wave vectors these are (m,):
        those too near the array's edge are left out (m' <= m, in their order). None when none
        is left."""
        kk = np.asarray(k, dtype=np.float64).reshape(-1, 2).copy()
        flip = (kk[:, 0] < 0) | ((kk[:, 0] == 0) & (kk[:, 1] < 0))
        kk[flip] *= -1.0
        n, rows_n, cols_n = snrs.shape
        r0 = np.rint(kk[:, 1]).astype(np.int64) + self._row0
        c0 = np.rint(kk[:, 0]).astype(np.int64) + self._col0
        ok = (r0 >= 2) & (r0 < rows_n - 2) & (c0 >= 2) & (c0 < cols_n - 2)
        r0, c0 = r0[ok], c0[ok]
        if r0.size == 0:
            return None
        # The largest of the 3x3 bins around each point, then whether it is a local maximum.
        dr, dc = _OFFSETS[:, 0], _OFFSETS[:, 1]
        roi = np.arange(n)[:, None]
        around = snrs[roi[:, :, None], (r0[:, None] + dr)[None], (c0[:, None] + dc)[None]]
        best = np.argmax(around, axis=2)
        r = r0[None, :] + dr[best]
        c = c0[None, :] + dc[best]
        centre = snrs[roi, r, c].astype(np.float64)
        neighbours = snrs[roi[:, :, None], r[:, :, None] + dr, c[:, :, None] + dc]
        # Inside the analysed band (the mirrored columns kx < 0 hold the conjugate half, so a
        # point near kx = 0 is found on either side).
        radius = np.hypot(c - self._col0, r - self._row0)
        band = (radius >= 2.0) & (radius <= 0.47 * self.size)
        keep = band & (centre >= min_snr) & (centre >= neighbours.max(axis=2))
        ddx = _parabolic(snrs[roi, r, c - 1], centre, snrs[roi, r, c + 1])
        ddy = _parabolic(snrs[roi, r - 1, c], centre, snrs[roi, r + 1, c])
        found = np.stack([c + ddx - self._col0, r + ddy - self._row0], axis=2)
        return found, centre, keep, r * cols_n + c, ok

    def sample(self, snr: F32, k: npt.ArrayLike) -> F64:
        """The whitened spectrum at wave vectors k (m, 2) in bins: the largest value among the
        bins touching each k (a peak between bins shows in one of them), NaN where k lies
        outside the analysed band."""
        kk = np.asarray(k, dtype=np.float64).reshape(-1, 2).copy()
        flip = (kk[:, 0] < 0) | ((kk[:, 0] == 0) & (kk[:, 1] < 0))
        kk[flip] *= -1.0  # the stored half plane holds k or its conjugate -k
        radius = np.hypot(kk[:, 0], kk[:, 1])
        inside = (radius >= 2.0) & (radius <= 0.47 * self.size)
        out = np.full(kk.shape[0], np.nan)
        c0 = np.floor(kk[:, 0]).astype(np.int64) + self._col0
        r0 = np.floor(kk[:, 1]).astype(np.int64) + self._row0
        rows_n, cols_n = snr.shape
        ok = inside & (r0 >= 0) & (r0 + 1 < rows_n) & (c0 >= 0) & (c0 + 1 < cols_n)
        if ok.any():
            r, c = r0[ok], c0[ok]
            out[ok] = np.maximum(np.maximum(snr[r, c], snr[r, c + 1]),
                                 np.maximum(snr[r + 1, c], snr[r + 1, c + 1]))
        return out


# The 3x3 neighbourhood of a bin, (row, column) offsets.
_OFFSETS = np.array([(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1)])


def _parabolic(left: npt.ArrayLike, centre: F64, right: npt.ArrayLike) -> F64:
    lv = np.asarray(left, dtype=np.float64)
    rv = np.asarray(right, dtype=np.float64)
    denom = lv - 2.0 * centre + rv
    safe = np.where(np.abs(denom) > 1e-12, denom, -1e-12)
    return np.clip(0.5 * (lv - rv) / safe, -0.5, 0.5)


def _ring_mean(channels: F32) -> F32:
    """Mean over a ring (11x11 box minus the 5x5 core) around each bin of an image of stacked
    spectra (rows, cols, n), every channel alike: the local background a peak stands out of."""
    import cv2

    outer = cv2.boxFilter(channels, -1, (11, 11), normalize=False,
                          borderType=cv2.BORDER_REFLECT)
    inner = cv2.boxFilter(channels, -1, (5, 5), normalize=False,
                          borderType=cv2.BORDER_REFLECT)
    ring = (outer - inner) * np.float32(1.0 / (121.0 - 25.0))
    return np.asarray(ring.reshape(channels.shape), dtype=np.float32)
