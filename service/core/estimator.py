"""The net estimator: one grayscale frame in, detection and pose of the net plane out.

Pipeline per frame (pure: arrays in, a NetEstimate out):
1. scale search - the ROI size is fixed; an image pyramid brings the mesh period into the range
   the ROI measures best (a few to ~20 px). A handful of probe ROIs pick the level, unless the
   caller passes the previous estimate's level as a hint;
2. a grid of ROIs over the frame at that level: whitened spectrum -> sub-bin peaks -> robust
   lattice fit -> mesh cell area, mapped through the lens (undistortion Jacobian at the ROI
   centre) into normalised image units;
3. a robust multi-ROI plane fit gives the unit normal, the distance and the range, without the
   mirror ambiguity of single-square PnP, and with uncertainties.

Everything that depends only on frame size, camera and settings (windows, ROI rays and
Jacobians) is computed once and cached.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from service.core.camera import CameraModel
from service.core.errors import ConfigError, EstimatorInputError
from service.core.grey import to_gray
from service.core.lattice import LatticeFinder, LatticeFit
from service.core.mesh import MeshGeometry
from service.core.plane import fit_plane
from service.core.results import Mat2, NetEstimate, RoiResult
from service.core.spectrum import SpectrumAnalyzer

F64 = npt.NDArray[np.float64]
Image = npt.NDArray[Any]


@dataclass(frozen=True)
class EstimatorSettings:
    """Tuning of the estimator; the defaults are what the benchmark was run with."""

    roi_size: int = 128
    grid_cols: int = 5
    grid_rows: int = 3
    levels: int = 3
    preferred_period_px: float = 9.0
    min_period_px: float = 2.9
    min_source_period_px: float = 3.5
    min_cycles: float = 3.0
    min_snr: float = 2.8
    min_roi_snr: float = 4.0
    min_inlier_fraction: float = 0.45
    min_rois: int = 4
    min_confidence: float = 0.25

    def validate(self) -> None:
        if self.roi_size not in (64, 128, 256, 512):
            raise ConfigError("estimator.roi_size", "must be 64, 128, 256 or 512")
        if not 2 <= self.grid_cols <= 12 or not 2 <= self.grid_rows <= 12:
            raise ConfigError("estimator.grid_cols", "grid must be 2..12 ROIs in each direction")
        if not 1 <= self.levels <= 5:
            raise ConfigError("estimator.levels", "must be 1..5")
        if self.min_rois < 4:
            raise ConfigError("estimator.min_rois", "must be at least 4 (3 unknowns + 1 check)")
        if self.grid_cols * self.grid_rows < self.min_rois:
            raise ConfigError("estimator.min_rois", "exceeds the number of ROIs in the grid")
        if not 0.0 <= self.min_confidence <= 1.0:
            raise ConfigError("estimator.min_confidence", "must be in 0..1")


@dataclass(frozen=True)
class _RoiGeometry:
    """Where one ROI sits and how its pixels map into normalised camera coordinates."""

    x0: int  # top-left corner in level pixels
    y0: int
    center_full: tuple[float, float]  # full-resolution distorted pixel
    ray: F64  # (x, y, 1) undistorted normalised
    jacobian: F64  # d(normalised) / d(full-resolution pixel), 2x2


@dataclass
class _RoiMeasurement:
    geometry: _RoiGeometry
    level: int
    fit: LatticeFit | None
    peaks: int
    reciprocal_px: F64 | None = None  # cycles per full-res pixel, columns k1 k2
    area_norm: float = math.nan  # mesh cell area in normalised units of the frame of `ray`
    valid: bool = False
    ray: F64 = field(default_factory=lambda: np.zeros(3))
    # Rectified ROIs only: found / intended mesh period, for a good lattice at the wrong scale.
    period_ratio: float = math.nan

    def __post_init__(self) -> None:
        if not self.ray.any():
            self.ray = self.geometry.ray


class NetEstimator:
    """Multi-ROI FFT net estimator for one camera and one mesh geometry."""

    def __init__(
        self,
        camera: CameraModel,
        mesh: MeshGeometry,
        settings: EstimatorSettings | None = None,
    ) -> None:
        self.settings = settings or EstimatorSettings()
        self.settings.validate()
        self.camera = camera
        self.mesh = mesh
        self._spectrum = SpectrumAnalyzer(self.settings.roi_size, min_snr=self.settings.min_snr)
        self._lattice = LatticeFinder()
        self._grids: dict[tuple[int, int, int, str], list[_RoiGeometry]] = {}
        self._cameras: dict[tuple[int, int], CameraModel] = {}

    # -- geometry, cached per frame size and level ---------------------------------------------
    def _camera_for(self, width: int, height: int) -> CameraModel:
        key = (width, height)
        if key not in self._cameras:
            self._cameras[key] = self.camera.scaled_to(width, height)
        return self._cameras[key]

    def _layout(self, width: int, height: int, level: int, kind: str) -> list[_RoiGeometry]:
        key = (width, height, level, kind)
        if key in self._grids:
            return self._grids[key]
        n = self.settings.roi_size
        scale = 2**level
        lw, lh = _level_size(width, level), _level_size(height, level)
        grid: list[_RoiGeometry] = []
        if lw >= n and lh >= n:
            if kind == "probe":
                # Centre and four quadrant points: a school of fish rarely covers all five.
                cx, cy = (lw - n) // 2, (lh - n) // 2
                qx, qy = (lw - n) // 4, (lh - n) // 4
                corners = [(cx, cy), (qx, qy), (3 * qx, qy), (qx, 3 * qy), (3 * qx, 3 * qy)]
            elif kind == "grid":
                cols, rows = self.settings.grid_cols, self.settings.grid_rows
                xs = np.linspace(0, lw - n, cols).round().astype(int)
                ys = np.linspace(0, lh - n, rows).round().astype(int)
                corners = sorted({(int(x), int(y)) for y in ys for x in xs}, key=lambda c: c[::-1])
            else:  # "grid@L": level L's grid, re-centred at this level, ROI for ROI
                source = self._layout(width, height, int(kind.split("@")[1]), "grid")
                corners = []
                for g in source:
                    x = round((g.center_full[0] + 0.5) / scale - n / 2)
                    y = round((g.center_full[1] + 0.5) / scale - n / 2)
                    corners.append((min(max(x, 0), lw - n), min(max(y, 0), lh - n)))
            cam = self._camera_for(width, height)
            centres = np.array(
                [((x + n / 2 - 0.5) * scale + (scale - 1) / 2, (y + n / 2 - 0.5) * scale
                  + (scale - 1) / 2) for x, y in corners]
            )
            eps = 2.0
            probes = np.concatenate(
                [centres, centres + [eps, 0.0], centres + [0.0, eps]], axis=0
            )
            norm = cam.undistort_pixels(probes)
            k = len(corners)
            base, dx, dy = norm[:k], norm[k : 2 * k], norm[2 * k :]
            for i, (x, y) in enumerate(corners):
                jac = np.stack([(dx[i] - base[i]) / eps, (dy[i] - base[i]) / eps], axis=1)
                grid.append(
                    _RoiGeometry(
                        x0=x,
                        y0=y,
                        center_full=(float(centres[i, 0]), float(centres[i, 1])),
                        ray=np.array([base[i, 0], base[i, 1], 1.0]),
                        jacobian=jac,
                    )
                )
        self._grids[key] = grid
        return grid

    # -- per ROI ---------------------------------------------------------------------------------
    def _measure(self, image: Image, geom: _RoiGeometry, level: int) -> _RoiMeasurement:
        n = self.settings.roi_size
        patch = image[geom.y0 : geom.y0 + n, geom.x0 : geom.x0 + n]
        peaks = self._spectrum.peaks(np.asarray(patch, dtype=np.float32))
        fit = self._lattice.fit(peaks)
        meas = _RoiMeasurement(geometry=geom, level=level, fit=fit, peaks=len(peaks))
        if fit is None:
            return meas
        s = self.settings
        lengths = np.linalg.norm(fit.basis, axis=0)
        period_ok = lengths.min() >= s.min_cycles and lengths.max() <= n / s.min_period_px
        quality_ok = fit.mean_snr >= s.min_roi_snr and fit.inlier_weight_fraction >= (
            s.min_inlier_fraction
        )
        reciprocal = fit.basis / (n * 2**level)
        meas.reciprocal_px = reciprocal
        det_k = abs(float(np.linalg.det(reciprocal)))
        meas.area_norm = abs(float(np.linalg.det(geom.jacobian))) / det_k
        meas.valid = bool(period_ok and quality_ok)
        return meas

    def _median_period(self, measurements: list[_RoiMeasurement]) -> float | None:
        periods = [
            self.settings.roi_size / math.sqrt(m.fit.det)
            for m in measurements
            if m.valid and m.fit is not None
        ]
        return float(np.median(periods)) if periods else None

    def prepare(self, width: int, height: int) -> None:
        """Build every per-size cache (ROI layouts, rays, lens Jacobians) now, at start-up,
        so the first frame costs what every other frame costs."""
        self._camera_for(width, height)
        for level in range(self.settings.levels):
            grid = self._layout(width, height, level, "grid")
            self._layout(width, height, level, "probe")
            if grid:
                for other in range(self.settings.levels):
                    if other != level and self._layout(width, height, other, "grid"):
                        self._layout(width, height, other, f"grid@{level}")

    # -- per frame -------------------------------------------------------------------------------
    def estimate(self, frame: Image, prior: NetEstimate | None = None) -> NetEstimate:
        """Estimate the net plane in one frame (grayscale, or BGR which is converted).

        `prior` (the previous frame's estimate, while tracking) lets the estimator skip the
        scale search and the unrectified pass: the ROIs are rectified with the prior plane
        straight away. Without a detection that way it falls back to the full search.
        """
        import cv2

        t0 = time.perf_counter()
        gray = _as_gray(frame)
        h, w = gray.shape
        self._camera_for(w, h)  # fail early on a resolution the calibration cannot serve
        timings: dict[str, float] = {}
        pyramid: list[Image] = [gray]

        def level_image(level: int) -> Image:
            while len(pyramid) <= level:
                pyramid.append(cv2.pyrDown(pyramid[-1]))
            return pyramid[level]

        levels = [lv for lv in range(self.settings.levels) if self._layout(w, h, lv, "grid")]
        if not levels:
            raise EstimatorInputError(
                f"frame {w}x{h} is smaller than one {self.settings.roi_size}px ROI"
            )
        if prior is not None and prior.detected and prior.normal is not None and (
            prior.distance_m is not None and prior.level in levels
        ):
            tracked = self._rectified_pass(level_image, prior.level, prior, w, h, timings)
            if _agrees(tracked, prior):
                timings["total"] = (time.perf_counter() - t0) * 1e3
                return replace(tracked, timings_ms=timings)
        t1 = time.perf_counter()
        order, probes = self._level_order(levels, level_image, w, h)
        t2 = time.perf_counter()
        timings["scale_search"] = (t2 - t1) * 1e3
        if order:
            # The probes are spread over the frame: when they agree on a plane, that plane
            # seeds the rectified pass and the unrectified grid pass is not needed.
            seed = self._conclude(probes, order[0], np.eye(3), timings)
            # Only a unanimous seed: with 5 probes, 4 leave a single redundant check, and a fish
            # in one probe can then tilt the seed enough to mislead the rectification.
            if seed.normal is not None and seed.distance_m is not None and (
                seed.rois_used == len(probes)
            ):
                quick = self._rectified_pass(level_image, order[0], seed, w, h, timings)
                if _agrees(quick, seed):
                    timings["total"] = (time.perf_counter() - t0) * 1e3
                    return replace(quick, timings_ms=timings)
        # Normally the two best levels at most; when the probes saw nothing (no net, or fish
        # over every probe) the full grid at every level.
        searched = order[:2] if order else levels
        best: NetEstimate | None = None
        for level in searched:
            result = self._estimate_at(level_image, level, w, h, timings)
            if best is None or result.confidence > best.confidence:
                best = result
            if result.detected:
                break
        if best is None:
            best = NetEstimate(
                detected=False, confidence=0.0, reason="no lattice at any scale in the probe ROIs"
            )
        timings["total"] = (time.perf_counter() - t0) * 1e3
        return replace(best, timings_ms=timings)

    def _level_order(
        self, levels: list[int], level_image: Callable[[int], Image], w: int, h: int
    ) -> tuple[list[int], list[_RoiMeasurement]]:
        """Levels to try, best first: the finest level where the probes see a lattice whose
        period is not too coarse. Finest first because a coarser level can only lose harmonics
        and gain aliases, and a wrong lattice there can mimic a good period."""
        hi = self.settings.preferred_period_px * 1.8
        coarse: list[int] = []
        coarse_probes: list[_RoiMeasurement] = []
        for level in levels:
            probes = [
                self._measure(level_image(level), g, level)
                for g in self._layout(w, h, level, "probe")
            ]
            period = self._median_period(probes)
            if period is None:
                continue
            if period > hi and level != levels[-1]:
                coarse.append(level)
                coarse_probes = probes
                continue
            return [level, *coarse[::-1]], probes
        return coarse[::-1], coarse_probes

    def _measure_grid(
        self, level_image: Callable[[int], Image], level: int, w: int, h: int
    ) -> list[_RoiMeasurement]:
        """Measure the grid at `level`; ROIs whose period sits badly there (the far side of a
        tilted net is finer, the near side coarser) are re-measured one level finer or coarser,
        keeping the better measurement."""
        s = self.settings
        n = s.roi_size
        grid = self._layout(w, h, level, "grid")
        measurements = [self._measure(level_image(level), g, level) for g in grid]
        top = s.levels - 1
        lo, hi = s.preferred_period_px / 1.8, s.preferred_period_px * 1.8
        for i, m in enumerate(measurements):
            period = n / math.sqrt(m.fit.det) if m.fit is not None else None
            if period is not None and lo <= period <= hi and m.valid:
                continue
            alt = level - 1 if period is None or period < lo else level + 1
            if not 0 <= alt <= top or not self._layout(w, h, alt, "grid"):
                continue
            geom = self._layout(w, h, alt, f"grid@{level}")[i]
            other = self._measure(level_image(alt), geom, alt)
            if other.valid and other.fit is not None and (
                not m.valid or abs(math.log(n / math.sqrt(other.fit.det) / s.preferred_period_px))
                < abs(math.log(period / s.preferred_period_px))  # type: ignore[operator]
            ):
                measurements[i] = other
        return measurements

    def _estimate_at(
        self,
        level_image: Callable[[int], Image],
        level: int,
        w: int,
        h: int,
        timings: dict[str, float],
    ) -> NetEstimate:
        t0 = time.perf_counter()
        measurements = self._measure_grid(level_image, level, w, h)
        timings["rois"] = timings.get("rois", 0.0) + (time.perf_counter() - t0) * 1e3
        first = self._conclude(measurements, level, np.eye(3), timings)
        return self._refine_rectified(first, level_image, level, w, h, timings)

    def _refine_rectified(
        self,
        seed: NetEstimate,
        level_image: Callable[[int], Image],
        level: int,
        w: int,
        h: int,
        timings: dict[str, float],
        iterations: int = 3,
    ) -> NetEstimate:
        """Rectified passes until one lands on the plane it was rectified with.

        The unrectified pass is biased by the perspective chirp and can be wrong outright on
        extreme views; only a self-consistent rectified result is reported as a detection.
        """
        current = seed
        for _ in range(iterations):
            if not current.detected or current.normal is None or current.distance_m is None:
                break
            result = self._rectified_pass(level_image, level, current, w, h, timings)
            if _agrees(result, current):
                return result
            current = result
        return _undetected(
            seed if not current.detected else current,
            "the ROIs do not converge on one plane (rectified passes disagree)",
        )

    def _rectified_pass(
        self,
        level_image: Callable[[int], Image],
        level: int,
        seed: NetEstimate,
        w: int,
        h: int,
        timings: dict[str, float],
    ) -> NetEstimate:
        """Measure the grid in a virtual camera facing the seed's plane, and fit the plane."""
        assert seed.normal is not None and seed.distance_m is not None
        t0 = time.perf_counter()
        rotation = _rotation_to_z(-np.asarray(seed.normal))
        grid = self._layout(w, h, level, "grid")
        # The seed's own lattice at each ROI (when it measured the same grid) spares the
        # lattice search its hypotheses: the rectified lattice is that one, resampled.
        hints: list[Mat2 | None] = [None] * len(grid)
        if len(seed.rois) == len(grid):
            hints = [r.reciprocal if r.detected else None for r in seed.rois]
        # In the rectified view the lattice is the same in every ROI (the net faces the virtual
        # camera), so the last good ROI's lattice is the expected one for the next.
        rect: list[_RoiMeasurement] = []
        shared: F64 | None = None
        for g, hint in zip(grid, hints, strict=True):
            m = self._measure_rectified(level_image, g, rotation, seed.distance_m, hint, shared)
            if m.valid and m.fit is not None:
                shared = m.fit.basis
            rect.append(m)
        # A seed at the wrong scale (a wrong lattice density in the first pass, fish) shows as
        # good lattices that all miss the intended period by the same factor: the true distance
        # is the seed's divided by that factor. Measure once more at the corrected scale.
        # The majority decides: a few ROIs can agree on a wrong density while most see the
        # true lattice at the "wrong" period.
        valid = sum(m.valid for m in rect)
        ratios = [m.period_ratio for m in rect if not m.valid and math.isfinite(m.period_ratio)]
        if len(ratios) > valid and len(ratios) >= self.settings.min_rois:
            ratio = float(np.median(ratios))
            if abs(math.log(ratio)) > math.log(1.35):
                distance = seed.distance_m / ratio
                rect = [
                    self._measure_rectified(level_image, g, rotation, distance, None)
                    for g in grid
                ]
        timings["rectified"] = timings.get("rectified", 0.0) + (time.perf_counter() - t0) * 1e3
        return self._conclude(rect, level, rotation, timings)

    def _conclude(
        self,
        measurements: list[_RoiMeasurement],
        level: int,
        rotation: F64,
        timings: dict[str, float],
    ) -> NetEstimate:
        """Plane fit over the valid ROIs and the verdict. `rotation` maps camera rays to the
        frame the measurements' rays and areas are expressed in."""
        t1 = time.perf_counter()
        valid = [m for m in measurements if m.valid and m.fit is not None]
        plane = None
        if len(valid) >= self.settings.min_rois:
            rays = np.array([m.ray for m in valid])
            areas = np.array([m.area_norm for m in valid])
            sigmas = np.array([m.fit.relative_area_sigma for m in valid if m.fit is not None])
            plane = fit_plane(
                rays, areas, sigmas, self.mesh.cell_area_m2, min_rois=self.settings.min_rois
            )
        timings["plane"] = timings.get("plane", 0.0) + (time.perf_counter() - t1) * 1e3
        used_ids = set()
        if plane is not None:
            used_ids = {id(m) for m, u in zip(valid, plane.used, strict=True) if u}
        rois = tuple(
            _roi_result(m, self.settings.roi_size, id(m) in used_ids) for m in measurements
        )
        # Confidence: the share of the grid that shows one consistent net, weighted by how
        # cleanly each ROI's peaks sit on its lattice and how well the ROIs agree on a plane.
        scores = [
            (m.fit.inlier_weight_fraction * min(1.0, m.fit.mean_snr / 8.0))
            if id(m) in used_ids and m.fit is not None
            else 0.0
            for m in measurements
        ]
        coverage = float(np.mean(scores)) if scores else 0.0
        if plane is None:
            reason = (
                f"{len(valid)} of {len(measurements)} ROIs show a lattice"
                if len(valid) < self.settings.min_rois
                else "ROI lattices do not agree on a plane"
            )
            return NetEstimate(
                detected=False, confidence=min(coverage, 0.2), rois=rois, level=level,
                reason=reason,
            )
        consistency = math.exp(-plane.relative_rms / 0.03)
        confidence = float(np.clip(math.sqrt(coverage) * consistency, 0.0, 1.0))
        detected = confidence >= self.settings.min_confidence
        n_away = rotation.T @ plane.normal_away
        n = -n_away / np.linalg.norm(n_away)
        range_m = plane.distance_m / float(n_away[2])
        # The range's sigma follows the same first-order propagation as in the fitted frame,
        # rescaled by the change of the normal's z component.
        sigma_range = plane.sigma_range_m * range_m / plane.range_m
        return NetEstimate(
            detected=detected,
            confidence=confidence,
            normal=(float(n[0]), float(n[1]), float(n[2])) if detected else None,
            distance_m=plane.distance_m if detected else None,
            range_m=range_m if detected else None,
            sigma_distance_m=plane.sigma_distance_m if detected else None,
            sigma_range_m=sigma_range if detected else None,
            sigma_normal_deg=plane.sigma_normal_deg if detected else None,
            rois=rois,
            rois_used=int(plane.used.sum()),
            level=level,
            reason="" if detected else f"confidence {confidence:.2f} below threshold",
        )

    def _measure_rectified(
        self,
        level_image: Callable[[int], Image],
        geom: _RoiGeometry,
        rotation: F64,
        distance_m: float,
        hint: Mat2 | None = None,
        expected_out: F64 | None = None,
    ) -> _RoiMeasurement:
        """Measure one ROI in a virtual camera that faces the net squarely.

        The patch is resampled through the homography of a camera rotated by `rotation` (so the
        net plane becomes fronto-parallel and its lattice uniform), scaled so the mesh period is
        the preferred one. Lens distortion enters through its local affine approximation at the
        ROI centre. The lattice found is then the local lattice at the ROI centre, without the
        perspective chirp across the ROI.
        """
        import cv2

        s = self.settings
        n = s.roi_size
        virt = rotation @ geom.ray
        virt = virt / virt[2]
        # Normalised virtual units per output pixel so the mesh period is preferred_period_px.
        period_norm = math.sqrt(self.mesh.cell_area_m2) / distance_m
        t = period_norm / s.preferred_period_px
        half = (n - 1) / 2.0
        to_virtual = np.array(
            [[t, 0.0, virt[0] - t * half], [0.0, t, virt[1] - t * half], [0.0, 0.0, 1.0]]
        )
        jinv = np.linalg.inv(geom.jacobian)
        centre = np.asarray(geom.center_full)
        to_pixel = np.eye(3)
        to_pixel[:2, :2] = jinv
        to_pixel[:2, 2] = centre - jinv @ geom.ray[:2]
        full = to_pixel @ rotation.T @ to_virtual  # output pixel -> full-res pixel (homogeneous)
        # Source pixels per output pixel at the centre decide the pyramid level to sample from.
        c0 = full @ np.array([half, half, 1.0])
        c1 = full @ np.array([half + 1.0, half, 1.0])
        c2 = full @ np.array([half, half + 1.0, 1.0])
        jm = np.stack([c1[:2] / c1[2] - c0[:2] / c0[2], c2[:2] / c2[2] - c0[:2] / c0[2]], axis=1)
        step = math.sqrt(abs(float(np.linalg.det(jm))))
        level = int(np.clip(math.floor(math.log2(max(step, 1.0))), 0, s.levels - 1))
        scale = 2**level
        to_level = np.array(
            [[1 / scale, 0, -(scale - 1) / (2 * scale)], [0, 1 / scale, -(scale - 1) / (2 * scale)],
             [0, 0, 1]]
        )
        patch = cv2.warpPerspective(
            level_image(level), to_level @ full, (n, n),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REFLECT,
        )
        peaks = self._spectrum.peaks(np.asarray(patch, dtype=np.float32))
        expected = expected_out
        if hint is not None:
            # k . x is invariant: with x_full = jm x_out, k_out = jm^T k_full (per pixel), x n.
            expected = (jm.T @ np.asarray(hint, dtype=np.float64).T) * n
        fit = self._lattice.fit(peaks, expected)
        rect_geom = _RoiGeometry(
            x0=geom.x0, y0=geom.y0, center_full=geom.center_full, ray=geom.ray,
            jacobian=geom.jacobian,
        )
        meas = _RoiMeasurement(geometry=rect_geom, level=level, fit=fit, peaks=len(peaks))
        meas.ray = virt
        if fit is None:
            return meas
        lengths = np.linalg.norm(fit.basis, axis=0)
        period_ok = lengths.min() >= s.min_cycles and lengths.max() <= n / s.min_period_px
        quality_ok = fit.mean_snr >= s.min_roi_snr and fit.inlier_weight_fraction >= (
            s.min_inlier_fraction
        )
        # The rectification was designed to show the mesh at the preferred period; a lattice far
        # from it means the seed plane was wrong or the ROI shows something else.
        period_out = n / math.sqrt(fit.det)
        on_target = abs(math.log(period_out / s.preferred_period_px)) < math.log(1.35)
        # Resampling cannot restore what the camera never resolved: a mesh finer than ~3.5 px in
        # the source has aliased harmonics and a peak position biased by the pixel response.
        resolved = period_out * step >= s.min_source_period_px
        k_out = fit.basis / n  # cycles per output pixel
        meas.area_norm = t * t / abs(float(np.linalg.det(k_out)))
        # For reporting: the lattice in full-resolution image pixels through the local map.
        meas.reciprocal_px = np.linalg.inv(jm).T @ k_out
        meas.valid = bool(period_ok and quality_ok and on_target and resolved)
        if period_ok and quality_ok:
            meas.period_ratio = period_out / s.preferred_period_px
        return meas


def _level_size(size: int, level: int) -> int:
    for _ in range(level):
        size = (size + 1) // 2
    return size


def _as_gray(frame: Image) -> Image:
    arr = to_gray(frame)
    if arr.dtype not in (np.uint8, np.uint16, np.float32):
        arr = arr.astype(np.float32)
    return arr


def _mat2(m: F64) -> Mat2:
    return ((float(m[0, 0]), float(m[0, 1])), (float(m[1, 0]), float(m[1, 1])))


def _roi_result(m: _RoiMeasurement, size: int, used: bool) -> RoiResult:
    scale = 2**m.level
    if m.fit is None or m.reciprocal_px is None:
        return RoiResult(
            center_px=m.geometry.center_full, size_px=size * scale, level=m.level,
            detected=False, peaks=m.peaks,
        )
    # Columns e1, e2 of the dual basis: e_i . k_j = delta_ij.
    edges = np.asarray(np.linalg.inv(m.reciprocal_px), dtype=np.float64).T
    return RoiResult(
        center_px=m.geometry.center_full,
        size_px=size * scale,
        level=m.level,
        detected=m.valid,
        reciprocal=_mat2(m.reciprocal_px.T),
        mesh_edges=_mat2(edges.T),
        cell_area_px=1.0 / abs(float(np.linalg.det(m.reciprocal_px))),
        snr_db=10.0 / math.log(10.0) * m.fit.mean_snr,
        inlier_fraction=m.fit.inlier_weight_fraction,
        peaks=m.peaks,
        used_in_fit=used,
    )


def _rotation_to_z(direction: F64) -> F64:
    """The smallest rotation taking the unit vector `direction` onto +z."""
    v = direction / np.linalg.norm(direction)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(v, z)
    sin = float(np.linalg.norm(axis))
    cos = float(v @ z)
    if sin < 1e-12:
        return np.eye(3) if cos > 0 else np.diag([1.0, -1.0, -1.0])
    k = axis / sin
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.asarray(np.eye(3) + sin * kx + (1 - cos) * (kx @ kx), dtype=np.float64)


def _undetected(result: NetEstimate, reason: str) -> NetEstimate:
    return replace(
        result,
        detected=False,
        confidence=min(result.confidence, 0.2),
        normal=None,
        distance_m=None,
        range_m=None,
        sigma_distance_m=None,
        sigma_range_m=None,
        sigma_normal_deg=None,
        reason=result.reason or reason,
    )


def _agrees(result: NetEstimate, seed: NetEstimate) -> bool:
    """A rectified pass is trusted only when it lands near the plane it was rectified with.

    Rectifying with a badly wrong plane stretches the ROIs anisotropically (aliasing in one
    direction) and can produce a self-consistent but wrong plane; the seed check catches that.
    """
    if not result.detected or result.normal is None or seed.normal is None:
        return False
    if result.distance_m is None or seed.distance_m is None:
        return False
    cos = float(np.dot(result.normal, seed.normal))
    return cos > math.cos(math.radians(8.0)) and abs(
        result.distance_m / seed.distance_m - 1.0
    ) < 0.08
