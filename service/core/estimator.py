"""The net estimator: one grey frame in, detection and pose of the net plane out.

Pipeline per frame (pure: arrays in, a NetEstimate out):

1. **Seed.** An image pyramid brings the mesh period into the range a ROI measures best (a few
   to ~20 px). Five probe ROIs pick the pyramid level; a grid of ROIs at that level gives a
   lattice per ROI (whitened spectrum -> sub-bin peaks -> robust lattice fit) and so a mesh cell
   area, mapped through the lens into normalised image units. A robust fit of the cell areas
   gives a first plane (c = r . m, linear, no mirror ambiguity; see plane.py).
2. **Rectified passes.** Each ROI is resampled through the homography of a virtual camera that
   faces that plane, scaled so the mesh period is the same known value in every ROI. The
   perspective chirp inside a ROI is gone, and on the right plane every ROI must show *the same*
   lattice. Passes repeat until one lands on the plane it was rectified with.
3. **Evidence that adds up.** No ROI needs a strong spectrum on its own: a ROI counts when its
   lattice (scale, orientation and shape) agrees with the consensus of the others - random
   texture does not produce the same two-dimensional lattice in several places. The plane is
   fitted to the agreeing ROIs only.
4. **Proof of the scale and of the net.** The whitened spectra of the agreeing ROIs are averaged
   (the net's peaks add up, noise averages down). Lattice points of any coarser mesh (the finer
   reciprocal lattices of index 2 and 3) must be empty there, or the hypothesis measured a
   harmonic of the real mesh (a distance off by sqrt 2 or sqrt 3) and is corrected or refused.
   The rectified cell must be the configured mesh (equal bars, the configured opening angle),
   and its harmonics must look like twine (thin lines crossing), not a checkerboard or bricks.
5. **Uncertainty from the data.** The plane's covariance comes from the ROIs' noise model
   pooled with their scatter (plane.py), inflated for its degrees of freedom and for
   overlapping ROIs, plus the net's deformation carried over the lever from the ROIs to the
   optical axis and half the change between the last two rectified passes. A plane the ROIs
   cannot pin down (bunched on one side of a blocked view) gives a large sigma and then no
   distance.

Everything that depends only on frame size, camera and settings (layouts, windows, ROI rays and
lens Jacobians) is computed once and cached. ROIs are measured independently of each other
(apart from the lattice hint), so they can later be batched.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from service.core.camera import CameraModel
from service.core.errors import ConfigError, EstimatorInputError
from service.core.grey import to_gray
from service.core.lattice import LatticeFinder, LatticeFit, reduce_basis
from service.core.mesh import MeshGeometry
from service.core.plane import (
    CONSENSUS_TOLERANCE,
    PlaneFit,
    RoiTriples,
    axis_leverage,
    fit_plane,
    plane_through,
    relative_sigma_c,
    tilt_leverage,
)
from service.core.plane_frame import rotation_to_z
from service.core.results import NetEstimate, RoiResult
from service.core.spectrum import Peaks, SpectrumAnalyzer

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
Image = npt.NDArray[Any]

# Refinements of index 2, 3, 4, 9 and 16 of a reciprocal lattice K: the lattices K S^-1 that
# contain K, given by S. Their extra points are where the spectrum of a mesh coarser by sqrt(2),
# sqrt(3), 2, 3 or 4 (in period) would have peaks (`_Refinements` tabulates them).
_REFINEMENT_BASES = (
    ((2, 0), (0, 1)), ((1, 0), (0, 2)), ((1, 0), (1, 2)),
    ((3, 0), (0, 1)), ((1, 0), (0, 3)), ((1, 0), (1, 3)), ((1, 0), (2, 3)),
    ((2, 0), (0, 2)), ((3, 0), (0, 3)), ((4, 0), (0, 4)),
)


# Work levels of `NetEstimator.estimate(budget=...)`: 0 is the full work.
BUDGET_LEVELS = 4
# The largest change of scale a tracked frame may have gone through unseen by its blind check:
# below sqrt(2), the smallest harmonic factor of a lattice, and below the 1.35 at which a
# rectified ROI's lattice is judged off target.
MAX_TRACKED_SCALE_STEP = 1.25
# Coarse rectified ROIs (the leanest level) only where the mesh keeps this period in them: its
# second harmonic then still lies inside the analysed band.
_COARSE_MIN_PERIOD_PX = 4.4

# How a refusal begins when the view was recognised as a grid that is not the configured net.
_NOT_A_NET = ("a brick-like grid", "a checkerboard-like grid", "the grid's cells are not",
              "mesh opening angle measured")


def refused_as_another_grid(estimate: NetEstimate) -> bool:
    """The view was recognised as a regular grid that is not the configured net (a brick wall,
    a checkerboard, cells of another shape, or a net of another opening angle): worth telling
    the pilot, unlike a view with no lattice at all."""
    return not estimate.detected and estimate.reason.startswith(_NOT_A_NET)


@dataclass(frozen=True)
class EstimatorSettings:
    """Tuning of the estimator; the defaults are what the benchmarks were run with."""

    roi_size: int = 128  # FFT size; levels whose ROI would not leave the frame room use half
    grid_cols: int = 5  # ROI budget for a 16:9 frame: cols x rows; other shapes keep the count
    grid_rows: int = 3
    levels: int = 4  # pyramid levels searched at most (fewer when the frame is small)
    preferred_period_px: float = 9.0
    min_period_px: float = 2.9
    # A mesh period below this (source pixels) is not measured: its 2nd harmonic is then within
    # a pixel or so of Nyquist, and the pixel response, JPEG's blocks and blur bias the
    # fundamental's position by percents (the integrity benchmark: 3.5-5 px gave most gross
    # errors).
    min_source_period_px: float = 5.0
    min_cycles: float = 3.0
    min_snr: float = 2.8
    # Floor on a ROI's mean peak SNR. Not a detection gate any more: a ROI's lattice counts when
    # other ROIs agree with it (the default equals min_snr, the per-peak threshold).
    min_roi_snr: float = 2.8
    min_inlier_fraction: float = 0.45
    # Peak threshold at the places a known lattice predicts (rectified passes after the first).
    guided_snr: float = 1.8
    min_rois: int = 4
    min_confidence: float = 0.25
    # Agreement of a rectified ROI's lattice with the consensus, relative to its length.
    lattice_tolerance: float = 0.06
    # Mesh shape: measured opening angle and bar-length ratio against the configured mesh.
    opening_tolerance_deg: float = 20.0
    aspect_tolerance: float = 0.25
    # No distance is reported less certain than this (1 sigma). Both limits put a gross error
    # (5 % of the range, 10 deg of the normal) at 2.5 sigma or more.
    max_sigma_range_fraction: float = 0.02
    max_sigma_normal_deg: float = 4.0
    # A tracked frame's blind scale check (a full search that proves the tracked scale is not a
    # harmonic) may be skipped while the net cannot have changed scale by a harmonic factor
    # since the prior's frame: at this closing speed (a BlueROV2's top speed is ~1.5 m/s) it
    # moves at most MAX_TRACKED_SCALE_STEP of the range between frames. Re-proved at least
    # every `scale_proof_frames` tracked frames, and whenever the range left the proved one by
    # that step.
    max_closing_speed_m_s: float = 1.5
    scale_proof_frames: int = 15

    def validate(self) -> None:
        if self.roi_size not in (64, 128, 256, 512):
            raise ConfigError("estimator.roi_size", "must be 64, 128, 256 or 512")
        for name in ("grid_cols", "grid_rows"):
            if not 2 <= getattr(self, name) <= 12:
                raise ConfigError(f"estimator.{name}", "grid must be 2..12 ROIs in each direction")
        if not 1 <= self.levels <= 5:
            raise ConfigError("estimator.levels", "must be 1..5")
        if self.min_rois < 4:
            raise ConfigError("estimator.min_rois", "must be at least 4 (3 unknowns + 1 check)")
        if self.grid_cols * self.grid_rows < self.min_rois:
            raise ConfigError("estimator.min_rois", "exceeds the number of ROIs in the grid")
        if not 0.0 <= self.min_confidence <= 1.0:
            raise ConfigError("estimator.min_confidence", "must be in 0..1")
        if not self.max_closing_speed_m_s > 0.0:
            raise ConfigError("estimator.max_closing_speed_m_s", "must be > 0")
        if not 1 <= self.scale_proof_frames <= 300:
            raise ConfigError("estimator.scale_proof_frames", "must be 1..300")
        # Periods, thresholds and tolerances: a zero or a negative one divides by zero or takes
        # a root of a negative number on every frame, instead of failing here with its name.
        for name in ("preferred_period_px", "min_period_px", "min_source_period_px",
                     "min_cycles", "min_snr", "min_roi_snr", "guided_snr", "lattice_tolerance",
                     "opening_tolerance_deg", "aspect_tolerance", "max_sigma_range_fraction",
                     "max_sigma_normal_deg"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ConfigError(f"estimator.{name}", f"must be a number > 0, got {value}")
        if not 0.0 < self.min_inlier_fraction <= 1.0:
            raise ConfigError("estimator.min_inlier_fraction", "must be in (0, 1]")


@dataclass(frozen=True)
class _Geometry:
    """Where one ROI sits and how its pixels map into normalised camera coordinates."""

    x0: int  # top-left corner in level pixels (unrectified ROIs)
    y0: int
    size: int  # FFT size (unrectified ROIs); 0 for rectified centres
    center_full: tuple[float, float]  # full-resolution distorted pixel
    ray: F64  # (x, y, 1) undistorted normalised
    jacobian: F64  # d(normalised) / d(full-resolution pixel), 2x2


@dataclass(frozen=True)
class _Layout:
    """Everything about one frame size: camera, pyramid levels with their ROI grids, and the
    grids of rectified ROIs (built on first use for each footprint, then kept)."""

    camera: CameraModel
    levels: tuple[int, ...]
    grids: dict[int, list[_Geometry]]
    probes: dict[int, list[_Geometry]]
    max_footprint: float  # half the frame's smaller side: rows and columns keep a baseline
    # By (footprint in px, FFT size, ROI budget or 0).
    rect: dict[tuple[int, int, int], list[_Geometry]] = field(default_factory=dict)
    # The frame's corners, edge midpoints and centre: where a plane's mesh period is sampled.
    corners: list[_Geometry] = field(default_factory=list)
    # Their rays (k, 3), once per frame size: every verdict compares the ROIs' spread with them.
    corner_rays: F64 = field(init=False)
    # Rectified ROI geometries by centre: a tracked frame's prior ROIs sit at these centres.
    by_centre: dict[tuple[float, float], _Geometry] = field(default_factory=dict)

    def __post_init__(self) -> None:
        rays = np.array([g.ray for g in self.corners], dtype=np.float64).reshape(-1, 3)
        object.__setattr__(self, "corner_rays", rays)  # frozen: set once, here


@dataclass
class _Roi:
    geometry: _Geometry
    level: int
    size: int
    fit: LatticeFit | None
    peaks: int
    reciprocal_px: F64 | None = None  # cycles per full-res pixel, columns k1 k2
    area_norm: float = math.nan  # mesh cell area in normalised units of the frame of `ray`
    valid: bool = False
    ray: F64 = field(default_factory=lambda: np.zeros(3))
    # Rectified ROIs only: found / intended mesh period, for a good lattice at the wrong scale.
    period_ratio: float = math.nan
    snr: F32 | None = None  # whitened spectrum (rectified ROIs)
    logp: F32 | None = None  # log power (rectified ROIs)
    footprint_px: float = 0.0
    agrees: bool = False  # its lattice is the consensus lattice (rectified ROIs)

    def __post_init__(self) -> None:
        if not self.ray.any():
            self.ray = self.geometry.ray

    @property
    def weight(self) -> float:
        """How much this ROI's lattice counts as evidence: how cleanly its peaks sit on the
        lattice and how far above the noise they stand (a speckle spectrum's maxima reach
        ~2.8 in log power over the background; 6 is unmistakable)."""
        if self.fit is None:
            return 0.0
        clear = min(max((float(self.fit.mean_snr) - 2.0) / 4.0, 0.1), 1.0)
        return float(self.fit.inlier_weight_fraction) * clear


@dataclass
class _Pass:
    """One rectified pass: its ROIs, the consensus lattice and the plane."""

    rois: list[_Roi]
    rotation: F64
    size: int
    period_out: float
    consensus: F64 | None  # 2x2 reciprocal basis in bins of the rectified ROIs
    plane: PlaneFit | None
    level: int
    note: str = ""
    # The ROIs whose lattice is the consensus, before the plane chose among them (`agrees` is
    # then the plane's choice): the ones it left out show the net too.
    on_lattice: list[_Roi] = field(default_factory=list)
    # Computed once per pass for the proofs: the agreeing ROIs' mean whitened spectrum and
    # mean log power (by `power`), and the whitened mean's noise level and spread.
    means: dict[bool, tuple[F32, int] | None] = field(default_factory=dict)
    null: tuple[float, float] | None = None


# A pass's convergence: new normal, new distance, the plane before it, and the step taken.
_Converged = tuple[F64, float, tuple[F64, float] | None, tuple[float, float]]


@dataclass(frozen=True)
class _HeldProof:
    """A tracked prior's proofs that its lattice is the net's at its true scale (the scale
    check, the twine profile), carried to the next frame. They hold there at any range the net
    cannot have reached by a harmonic factor: a sub-lattice or a checkerboard instead of the
    proved net would have to appear at the prior's period and plane within one frame (the
    tracked pass refuses any other, `_agrees` any other plane)."""

    proved_range_m: float  # the range the proofs were made at
    reach_m: float  # how far the net can have moved since the prior's frame

    def holds_at(self, range_m: float) -> bool:
        return (self.reach_m <= (1.0 - 1.0 / MAX_TRACKED_SCALE_STEP) * range_m
                and abs(math.log(range_m / self.proved_range_m))
                < math.log(MAX_TRACKED_SCALE_STEP))


@dataclass(frozen=True)
class _Budget:
    """What one work level may spend on a frame (docs/estimator.md, "Budget levels").

    Every level keeps the checks that make a distance honest (proof of scale, mesh shape, the
    tracked plane's blind scale check, the sigma limits): a leaner level measures fewer or
    coarser ROIs, so it refuses more frames or reports a larger sigma, never a surer one.
    """

    tracking_passes: int  # rectified passes while tracking (the first usually converges)
    cold_passes: int  # rectified passes from a cold seed (the seed pass is loose)
    max_rois: int | None  # ROIs per grid (cold grid and rectified passes); None: the full grid
    coarse: bool  # rectified ROIs at half size, one pyramid level coarser
    cold_levels: int  # pyramid levels whose grid a cold search measures after the probes
    blind_levels: int  # levels searched when the probes saw no lattice at all


_BUDGETS = (
    _Budget(tracking_passes=4, cold_passes=6, max_rois=None, coarse=False, cold_levels=2,
            blind_levels=5),
    _Budget(tracking_passes=1, cold_passes=4, max_rois=None, coarse=False, cold_levels=2,
            blind_levels=5),
    _Budget(tracking_passes=1, cold_passes=4, max_rois=9, coarse=False, cold_levels=1,
            blind_levels=2),
    _Budget(tracking_passes=1, cold_passes=3, max_rois=9, coarse=True, cold_levels=1,
            blind_levels=0),
)


class _Frame:
    """One frame being estimated: its pyramid (built as far as it is needed), the work level,
    and the work done so far (stage times, spectra computed)."""

    def __init__(self, gray: Image, budget: _Budget) -> None:
        self.budget = budget
        self.timings: dict[str, float] = {}
        self.ffts: dict[int, int] = {}
        self.whole: dict[bool, tuple[int, LatticeFit] | None] = {}  # by `twine`
        self._pyramid: list[Image] = [gray]

    def image(self, level: int) -> Image:
        import cv2

        while len(self._pyramid) <= level:
            self._pyramid.append(cv2.pyrDown(self._pyramid[-1]))
        return self._pyramid[level]

    def lap(self, stage: str, since: float) -> None:
        """Add the time since `since` (perf_counter) to `stage`, in ms."""
        self.timings[stage] = self.timings.get(stage, 0.0) + (time.perf_counter() - since) * 1e3

    def count_fft(self, size: int, count: int = 1) -> None:
        self.ffts[size] = self.ffts.get(size, 0) + count


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
        s = self.settings
        self._spectra = {
            n: SpectrumAnalyzer(n, min_snr=s.min_snr)
            for n in {s.roi_size, max(64, s.roi_size // 2)}
        }
        self._lattice = LatticeFinder()
        # The whole view at 64 px, down to 1.8 cycles: the "too close" check.
        self._whole = SpectrumAnalyzer(64, min_radius_bins=1.8, min_snr=s.min_snr)
        self._layouts: dict[tuple[int, int], _Layout] = {}
        self._refinements = _Refinements.build()
        self._plane_triples = RoiTriples()
        self._mesh_opening = min(mesh.opening_angle_deg, 180.0 - mesh.opening_angle_deg)

    # -- geometry, cached per frame size ------------------------------------------------------
    def _layout(self, width: int, height: int) -> _Layout:
        key = (width, height)
        if key not in self._layouts:
            self._layouts[key] = self._build_layout(width, height)
        return self._layouts[key]

    def _grid_shape(self, width: int, height: int, factor: int = 1) -> tuple[int, int]:
        """Columns and rows: the configured count of ROIs (times `factor`), shaped like the
        frame."""
        s = self.settings
        budget = s.grid_cols * s.grid_rows * factor
        aspect = width / height
        rows = max(2, round(math.sqrt(budget / aspect)))
        cols = max(2, round(budget / rows))
        return cols, rows

    def _build_layout(self, w: int, h: int) -> _Layout:
        s = self.settings
        cam = self.camera.scaled_to(w, h)
        cols, rows = self._grid_shape(w, h)
        levels: list[int] = []
        grids: dict[int, list[_Geometry]] = {}
        probes: dict[int, list[_Geometry]] = {}
        small = max(64, s.roi_size // 2)
        for level in range(s.levels):
            scale = 2**level
            lw, lh = _level_size(w, level), _level_size(h, level)
            # The full ROI size while it leaves the grid a vertical baseline; half size when only
            # that fits; no ROI at all when not even that fits.
            if s.roi_size * scale <= 0.6 * min(h, w) and s.roi_size <= min(lw, lh):
                n = s.roi_size
            elif small <= min(lw, lh) and small * scale <= min(h, w):
                n = small
            else:
                continue
            xs = np.linspace(0, lw - n, cols).round().astype(int)
            ys = np.linspace(0, lh - n, rows).round().astype(int)
            corners = sorted({(int(x), int(y)) for y in ys for x in xs}, key=lambda c: c[::-1])
            grids[level] = self._geometries(cam, corners, n, level)
            cx, cy = (lw - n) // 2, (lh - n) // 2
            qx, qy = (lw - n) // 4, (lh - n) // 4
            probe = [(cx, cy), (qx, qy), (3 * qx, qy), (qx, 3 * qy), (3 * qx, 3 * qy)]
            probes[level] = self._geometries(cam, probe, n, level)
            levels.append(level)
        foot = max(min(w, h) / 2.0, min(64.0, min(w, h)))
        samples = self._centre_geometries(cam, np.array(
            [(x, y) for x in (0.0, w / 2, w - 1.0) for y in (0.0, h / 2, h - 1.0)]))
        return _Layout(cam, tuple(levels), grids, probes, foot, corners=samples)

    def _rect_grid(
        self, layout: _Layout, footprint: float, size: int, max_rois: int | None = None
    ) -> list[_Geometry]:
        """Centres of rectified ROIs of this footprint (source pixels): spaced half a footprint
        apart (each ROI overlaps its neighbours by half) and covering the frame to its edges,
        thinned out evenly when that would exceed the ROI budget (grid_cols x grid_rows ROIs
        of roi_size; four times as many of half the size), or `max_rois` when a lower work level
        asks for fewer: the thinned grid still spans the frame, so the plane keeps its
        baseline."""
        rounded = int(round(footprint / 8.0)) * 8
        key = (rounded, size, max_rois or 0)
        if key in layout.rect:
            return layout.rect[key]
        s = self.settings
        cam = layout.camera
        w, h = cam.width, cam.height
        f = min(float(rounded), float(min(w, h)))
        budget = s.grid_cols * s.grid_rows * (s.roi_size // size) ** 2
        budget = min(budget, 4 * s.grid_cols * s.grid_rows)
        if max_rois is not None:
            budget = min(budget, max_rois)
        cols = int((w - f) // (f / 2)) + 1
        rows = int((h - f) // (f / 2)) + 1
        # A plane needs ROIs spread both ways: at least three rows and columns where they can be
        # a fifth of a footprint apart (large footprints: a coarse mesh, a near net).
        cols = max(cols, min(3, int((w - f) // (0.2 * f)) + 1))
        rows = max(rows, min(3, int((h - f) // (0.2 * f)) + 1))
        while cols * rows > budget:
            if cols / w >= rows / h and cols > 2:
                cols -= 1
            elif rows > 2:
                rows -= 1
            else:
                break
        xs = np.linspace(f / 2, w - f / 2, cols) if cols > 1 else np.array([w / 2])
        ys = np.linspace(f / 2, h - f / 2, rows) if rows > 1 else np.array([h / 2])
        centres = np.array([(x - 0.5, y - 0.5) for y in ys for x in xs])
        grid = self._centre_geometries(cam, centres)
        layout.rect[key] = grid
        layout.by_centre.update((g.center_full, g) for g in grid)
        return grid

    @staticmethod
    def _centre_geometries(cam: CameraModel, centres: F64) -> list[_Geometry]:
        eps = 2.0
        probes = np.concatenate([centres, centres + [eps, 0.0], centres + [0.0, eps]], axis=0)
        norm = cam.undistort_pixels(probes)
        k = len(centres)
        base, dx, dy = norm[:k], norm[k : 2 * k], norm[2 * k :]
        out = []
        for i in range(k):
            jac = np.stack([(dx[i] - base[i]) / eps, (dy[i] - base[i]) / eps], axis=1)
            out.append(_Geometry(0, 0, 0, (float(centres[i, 0]), float(centres[i, 1])),
                                 np.array([base[i, 0], base[i, 1], 1.0]), jac))
        return out

    def _geometries(
        self, cam: CameraModel, corners: list[tuple[int, int]], n: int, level: int
    ) -> list[_Geometry]:
        scale = 2**level
        centres = np.array(
            [((x + n / 2 - 0.5) * scale + (scale - 1) / 2, (y + n / 2 - 0.5) * scale
              + (scale - 1) / 2) for x, y in corners]
        )
        base = self._centre_geometries(cam, centres)
        return [replace(g, x0=x, y0=y, size=n) for g, (x, y) in zip(base, corners, strict=True)]

    def prepare(self, width: int, height: int) -> None:
        """Build the per-size caches (ROI layouts, rays, lens Jacobians) now, at start-up,
        so the first frame costs what every other frame costs (grids of rectified ROIs are
        built on first use of each footprint, a handful per frame size)."""
        self._layout(width, height)

    # -- per ROI -------------------------------------------------------------------------------
    def _measure(self, frame: _Frame, geom: _Geometry, level: int) -> _Roi:
        return self._measure_many(frame, [geom], level)[0]

    def _measure_many(self, frame: _Frame, geoms: list[_Geometry], level: int) -> list[_Roi]:
        """Unrectified ROIs of one pyramid level, their spectra computed together."""
        if not geoms:
            return []
        image = frame.image(level)
        out: list[_Roi] = []
        # One stack per FFT size (a level's grid has one size; a re-gridded ROI may differ).
        for n in sorted({g.size for g in geoms}):
            group = [g for g in geoms if g.size == n]
            stack = np.stack([image[g.y0 : g.y0 + n, g.x0 : g.x0 + n] for g in group])
            frame.count_fft(n, len(group))
            spectra = self._spectra[n].analyse_many(stack)
            out.extend(self._roi_from_peaks(g, level, peaks)
                       for g, (peaks, _, _) in zip(group, spectra, strict=True))
        order = {id(g): i for i, g in enumerate(geoms)}
        out.sort(key=lambda m: order[id(m.geometry)])
        return out

    def _roi_from_peaks(self, geom: _Geometry, level: int, peaks: Peaks) -> _Roi:
        n = geom.size
        fit = self._lattice.fit(peaks)
        meas = _Roi(geometry=geom, level=level, size=n, fit=fit, peaks=len(peaks),
                    footprint_px=float(n * 2**level))
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

    def _median_period(self, measurements: list[_Roi]) -> float | None:
        periods = [m.size / math.sqrt(m.fit.det) for m in measurements
                   if m.valid and m.fit is not None]
        return float(np.median(periods)) if periods else None

    # -- per frame -----------------------------------------------------------------------------
    def estimate(
        self, frame: Image, prior: NetEstimate | None = None, budget: int = 0,
        prior_age_s: float | None = None, search: bool = True,
    ) -> NetEstimate:
        """Estimate the net plane in one frame (grey, or BGR/BGRA which is converted).

        `prior` (the previous frame's estimate, while tracking) lets the estimator skip the
        scale search: the ROIs are rectified with the prior plane straight away. Without a
        detection that way it falls back to the full search.

        `prior_age_s` (the time from the prior's frame to this one, None when unknown) says
        whether the net can have changed scale by a harmonic factor since: while it cannot, and
        the scale was proved recently, the tracked frame skips the blind scale check.

        `budget` (0 .. BUDGET_LEVELS - 1) lowers the work per frame for a CPU that cannot keep
        up: 0 is the full work; each higher level measures less (see `_Budget`). A higher level
        may detect less often or less precisely, never with a sigma that no longer covers its
        error.

        `search` false: when the prior was tracked and this frame does not confirm it, the
        frame is reported without a net instead of being searched whole (a search costs three
        to ten tracked frames). The caller tries the prior again on the next frame, searching
        then if that one misses too (service/pipeline.py). A scale the blind check doubts is
        always searched.
        """
        if isinstance(budget, bool) or not isinstance(budget, int | np.integer) or not (
            0 <= budget < BUDGET_LEVELS
        ):
            raise ValueError(f"budget must be an int in 0..{BUDGET_LEVELS - 1}, got {budget!r}")
        budget = int(budget)
        t0 = time.perf_counter()
        gray = _as_gray(frame)
        h, w = gray.shape
        layout = self._layout(w, h)  # fails early on a resolution the calibration cannot serve
        current = _Frame(gray, _BUDGETS[budget])
        current.lap("grey", t0)
        if not layout.levels:
            raise EstimatorInputError(
                f"frame {w}x{h} is smaller than one {max(64, self.settings.roi_size // 2)}px ROI"
            )
        result: NetEstimate | None = None
        if prior is not None and prior.detected and prior.normal is not None and (
            prior.distance_m is not None and prior.range_m is not None
        ) and min(w, h) / self._period_at_centre(layout, prior.range_m) >= 12.0:
            # Tracking only while the mesh is well resolved: near the "too close" limit a net
            # that came closer shows harmonics at the old scale that no check can tell from it.
            tracked = self._refine(prior, current, layout, prior.level,
                                   self._prior_rois(prior, layout),
                                   passes=current.budget.tracking_passes,
                                   held=self._proof_may_hold(prior, prior_age_s))
            if tracked.detected and _agrees(tracked, prior):
                if self._scale_still_proved(tracked, prior, prior_age_s):
                    result = replace(
                        tracked, frames_since_scale_proof=prior.frames_since_scale_proof + 1,
                        scale_proved_range_m=prior.scale_proved_range_m)
                else:
                    t1 = time.perf_counter()
                    if self._blind_scale_agrees(tracked, current, layout):
                        result = _scale_proved(tracked)
                    current.lap("blind_check", t1)
            elif not search:
                result = _tracking_missed(tracked)
        if result is None:
            result = replace(_scale_proved(self._cold(current, layout)), searched=True)
        if not result.detected and not result.reason.startswith(_NOT_A_NET):
            # Not when the view was positively recognised as something else (a brick wall, a
            # checkerboard, cells of another shape): "too close" must never fire without a net.
            t1 = time.perf_counter()
            close = self._too_close(current, layout, prior)
            current.lap("too_close", t1)
            if close is not None:
                period, range_m = close
                result = replace(
                    result, too_close=True,
                    reason=(f"net too close to measure: a mesh of ~{period:.0f} px period fills "
                            f"the view (about {range_m:.2f} m away or less)"),
                )
        current.timings["total"] = (time.perf_counter() - t0) * 1e3
        return replace(result, timings_ms=current.timings, budget_level=budget,
                       fft_counts=dict(sorted(current.ffts.items())), frame_px=(w, h))

    def _too_close(
        self, frame: _Frame, layout: _Layout, prior: NetEstimate | None = None
    ) -> tuple[float, float] | None:
        """(mesh period in pixels, implied range in m) when a mesh too coarse for the ROIs fills
        the view; None otherwise.

        The whole frame's central square, shrunk to 64 px, must show one clear lattice (strong
        peaks, most of the spectral weight, a harmonic or cross term besides the two
        fundamentals) with the configured mesh's shape, of 1.8 to 9 cycles across the frame:
        fewer than the ROIs need to measure a plane (this runs only when they could not), more
        than a blur with nothing repeating.
        Nothing else in an underwater view repeats like that over the whole frame.

        While tracking (`prior`, the last detection, was already near that limit) a net that
        came closer is expected: then any clear lattice at least as coarse as the prior's will
        do (its harmonics often outshine its fundamentals when so close, so its shape is not
        required).
        """
        whole = self._whole_lattice(frame)
        if whole is None:
            return None
        side, fit = whole
        cam = layout.camera
        focal = math.sqrt(cam.fx * cam.fy)
        lengths = np.linalg.norm(fit.basis, axis=0)
        if prior is not None and prior.detected and prior.range_m is not None:
            prior_period = focal * math.sqrt(self.mesh.cell_area_m2) / prior.range_m
            # Near the limit: fewer than 12 mesh cycles across the frame's smaller side.
            if side / prior_period < 12.0 and fit.mean_snr >= 3.5 and lengths.min() >= 1.8:
                period = side / math.sqrt(fit.det)
                if period >= 0.8 * prior_period or side / lengths.min() >= 0.8 * prior_period:
                    period = max(period, prior_period)
                    return period, focal * math.sqrt(self.mesh.cell_area_m2) / period
        if fit.inliers < 3 or fit.mean_snr < 4.0 or fit.inlier_weight_fraction < 0.6:
            return None
        if lengths.min() < 1.8 or lengths.max() > 9.0:
            return None
        bars = _bar_pair(np.asarray(np.linalg.inv(fit.basis).T, dtype=np.float64))
        lu, lv = (float(np.linalg.norm(bars[:, i])) for i in range(2))
        angle = math.degrees(math.acos(float(np.clip(
            abs(bars[:, 0] @ bars[:, 1]) / (lu * lv), 0.0, 1.0))))
        opening = min(angle, 180.0 - angle)
        if max(lu, lv) / min(lu, lv) > 1.35 or abs(opening - self._mesh_opening) > 25.0:
            return None
        period = side / math.sqrt(fit.det)
        return period, focal * math.sqrt(self.mesh.cell_area_m2) / period

    def _proof_may_hold(
        self, prior: NetEstimate, prior_age_s: float | None
    ) -> _HeldProof | None:
        """The prior's proofs of scale and of a net, while the next frame may keep them: the
        proof is recent (renewed every `scale_proof_frames` frames) and the net cannot have
        moved by a harmonic factor of its range since the prior's frame. None otherwise."""
        s = self.settings
        proved = prior.scale_proved_range_m
        if prior_age_s is None or proved is None or prior.range_m is None:
            return None
        if not (math.isfinite(prior_age_s) and prior_age_s >= 0.0) or (
            prior.frames_since_scale_proof + 1 >= s.scale_proof_frames
        ):
            return None
        held = _HeldProof(proved, s.max_closing_speed_m_s * prior_age_s)
        return held if held.holds_at(prior.range_m) else None

    def _scale_still_proved(
        self, tracked: NetEstimate, prior: NetEstimate, prior_age_s: float | None
    ) -> bool:
        """May `tracked` keep the prior's proof of scale? Only if the net cannot have come
        nearer or gone further by a harmonic factor since the prior's frame: the smallest such
        factor is sqrt(2) (a diagonal sub-lattice), and a change of MAX_TRACKED_SCALE_STEP or
        more is refused by the rectified pass itself (found / intended period). A tracked frame
        also follows a net that changes scale gradually; the proof is renewed every
        `scale_proof_frames` frames and once the range has drifted that step from the proved
        one, so the blind check still runs a few times a second."""
        held = self._proof_may_hold(prior, prior_age_s)
        return held is not None and tracked.range_m is not None and held.holds_at(
            tracked.range_m)

    def _blind_scale_agrees(
        self, result: NetEstimate, frame: _Frame, layout: _Layout
    ) -> bool:
        """Do the probe ROIs, fitted blind at the pyramid level where `result` predicts the
        preferred mesh period, see that period (within 30 %)? A tracked plane was rectified with
        the previous frame's scale; if the net jumped closer by 2x, the rectified view can show
        the mesh's second harmonic exactly where the fundamental was expected."""
        assert result.normal is not None and result.distance_m is not None
        n_away = -np.asarray(result.normal, dtype=np.float64)
        centre = layout.probes[layout.levels[0]][0]
        a = self.mesh.cell_area_m2 * max(float(n_away @ centre.ray), 1e-6) ** 3 / (
            result.distance_m**2)
        period = math.sqrt(a / abs(float(np.linalg.det(centre.jacobian))))
        want = math.log2(max(period / self.settings.preferred_period_px, 1.0))
        first = min(layout.levels, key=lambda lv: abs(lv - want))
        # That level and the coarser ones: a mesh twice or four times as coarse as predicted
        # has too few cycles for the ROIs of the predicted level, but not for coarser ones.
        coarser: list[float] = []
        for level in [lv for lv in layout.levels if first <= lv <= first + 2]:
            for g, m in zip(layout.probes[level],
                            self._measure_many(frame, layout.probes[level], level), strict=True):
                if not m.valid or m.fit is None:
                    continue
                a_g = self.mesh.cell_area_m2 * max(float(n_away @ g.ray), 1e-6) ** 3 / (
                    result.distance_m**2)
                predicted = math.sqrt(a_g / abs(float(np.linalg.det(g.jacobian))))
                ratio = m.size * 2**level / math.sqrt(m.fit.det) / predicted
                if ratio > 1.5:  # coarser than predicted: the net is nearer
                    coarser.append(ratio)
        # A mesh coarser than predicted explains the predicted one (its harmonics), never the
        # other way round: two probes agreeing on a coarser mesh overrule the tracked plane.
        if len(coarser) >= 2 and max(coarser) / min(coarser) < 1.4:
            return False
        # So does a mesh so coarse that it fills the whole frame with a few cycles.
        whole = self._whole_lattice(frame)
        if whole is not None:
            side, fit = whole
            if fit.inliers >= 3 and fit.mean_snr >= 4.0 and fit.inlier_weight_fraction >= 0.5 and (
                side / math.sqrt(fit.det) > 1.5 * period
            ):
                return False
        return True

    def _whole_lattice(
        self, frame: _Frame, twine: bool = False
    ) -> tuple[int, LatticeFit] | None:
        """The lattice of the frame's central square shrunk to 64 px (side in pixels, fit);
        None when there is none (or, with `twine`, when its harmonics are not those of twine:
        a brick wall or a checkerboard filling the view is not a net too close)."""
        # Asked for by the tracked plane's blind check and again by "too close": once a frame.
        if twine not in frame.whole:
            frame.whole[twine] = self._measure_whole(frame, twine)
        return frame.whole[twine]

    def _measure_whole(self, frame: _Frame, twine: bool) -> tuple[int, LatticeFit] | None:
        import cv2

        gray = frame.image(0)
        h, w = gray.shape
        side = min(h, w)
        y0, x0 = (h - side) // 2, (w - side) // 2
        small = np.asarray(cv2.resize(
            np.asarray(gray[y0 : y0 + side, x0 : x0 + side], dtype=np.float32), (64, 64),
            interpolation=cv2.INTER_AREA), dtype=np.float32)
        frame.count_fft(self._whole.size)
        peaks, snr, logp = self._whole.analyse(small)
        fit = self._lattice.fit(peaks)
        if fit is None or (twine and _twine_profile(self._whole, snr, logp, fit.basis, 1)):
            return None
        return side, fit

    def _period_at_centre(self, layout: _Layout, range_m: float) -> float:
        """Mesh period (pixels) where the optical axis meets a net at this range, facing it."""
        cam = layout.camera
        return math.sqrt(cam.fx * cam.fy) * math.sqrt(self.mesh.cell_area_m2) / range_m

    def _prior_rois(self, prior: NetEstimate, layout: _Layout) -> list[_Roi]:
        """The previous estimate's ROI lattices, as guides for the first rectified pass."""
        used = [r for r in prior.rois if r.used_in_fit and r.reciprocal is not None]
        if not used or prior.frame_px != (layout.camera.width, layout.camera.height):
            # Another frame size (the stream changed resolution; a state from before frame
            # sizes were kept): its ROIs' pixels are not this frame's, and may lie where the
            # lens model is not even defined. Its plane still guides the rectified pass.
            return []
        # Normally cached; a prior from elsewhere (a restored state) is computed, not cached.
        missing = [r.center_px for r in used if r.center_px not in layout.by_centre]
        extra = {g.center_full: g for g in self._centre_geometries(
            layout.camera, np.array(missing))} if missing else {}
        geoms = [layout.by_centre.get(r.center_px) or extra[r.center_px] for r in used]
        out = []
        for r, g in zip(used, geoms, strict=True):
            assert r.reciprocal is not None
            m = _Roi(geometry=g, level=r.level, size=0, fit=None, peaks=r.peaks,
                     reciprocal_px=np.array(r.reciprocal, dtype=np.float64).T, valid=True)
            out.append(m)
        return out

    def _cold(self, frame: _Frame, layout: _Layout) -> NetEstimate:
        t1 = time.perf_counter()
        order, probes = self._level_order(layout, frame)
        frame.lap("scale_search", t1)
        best: NetEstimate | None = None
        tried: list[NetEstimate] = []

        def attempt(seed: NetEstimate, level: int, rois: list[_Roi]) -> NetEstimate | None:
            if any(_agrees(seed, t, 0.05, 5.0) for t in tried):
                return None
            tried.append(seed)
            return self._refine(seed, frame, layout, level, rois, frame.budget.cold_passes)

        if order:
            # The probes are spread over the frame: when they all agree on a plane, that plane
            # seeds the rectified pass and the unrectified grid pass is not needed.
            seed = self._conclude_seed(probes, order[0], frame.timings)
            if seed is not None and seed.rois_used == len(probes):
                quick = attempt(seed, order[0], probes)
                if quick is not None and quick.detected:
                    return quick
                best = quick
        # Normally the two best levels at most; when the probes saw nothing (no net, or fish
        # over every probe) the full grid at every level.
        # (Lower budgets search fewer levels.)
        searched = (order[: frame.budget.cold_levels] if order
                    else list(layout.levels)[: frame.budget.blind_levels])
        for level in searched:
            t0 = time.perf_counter()
            rois = self._measure_grid(frame, layout, level)
            frame.lap("rois", t0)
            # Seeds: the plane of the ROIs' cell areas; and, when that fails (few ROIs see the
            # net, or they are bunched), a plane facing the camera at the distance of the
            # largest group of ROIs that see the same lattice: the rectified passes find the
            # tilt from there.
            seeds = [sd for sd in (self._conclude_seed(rois, level, frame.timings),
                                   self._facing_seed(rois, level)) if sd is not None]
            if not seeds:
                result = _no_net(rois, level, self._count_reason(rois))
                if best is None or result.confidence > best.confidence:
                    best = result
                continue
            for seed in seeds:
                refined = attempt(seed, level, rois)
                if refined is None:
                    continue
                if best is None or refined.detected or refined.confidence > best.confidence:
                    best = refined
                if refined.detected:
                    return refined
        if best is None:
            best = NetEstimate(detected=False, confidence=0.0,
                               reason="no lattice at any scale in the probe ROIs")
        return best

    def _facing_seed(self, rois: list[_Roi], level: int) -> NetEstimate | None:
        """A plane facing the camera at the distance of the largest group (by evidence) of ROIs
        whose lattices agree; None unless two ROIs at least agree."""
        valid = [m for m in rois if m.valid and m.reciprocal_px is not None]
        best: tuple[float, list[_Roi]] | None = None
        if not valid:
            return None
        bases = np.array([m.reciprocal_px for m in valid if m.reciprocal_px is not None])
        agree = _agreement(bases, bases, 0.15, 1.3, floor=0.0)
        for j in range(len(valid)):
            group = [m for m, ok in zip(valid, agree[:, j].tolist(), strict=True) if ok]
            weight = sum(m.weight for m in group)
            if len(group) >= 2 and (best is None or weight > best[0]):
                best = (weight, group)
        if best is None:
            return None
        area = float(np.median([m.area_norm for m in best[1]]))
        distance = math.sqrt(self.mesh.cell_area_m2 / area)
        return NetEstimate(detected=True, confidence=0.0, normal=(0.0, 0.0, -1.0),
                           distance_m=distance, range_m=distance, level=level,
                           rois_used=len(best[1]))

    def _count_reason(self, rois: list[_Roi]) -> str:
        valid = sum(m.valid for m in rois)
        if valid < self.settings.min_rois:
            return f"{valid} of {len(rois)} ROIs show a lattice"
        return "ROI lattices do not agree on a plane"

    def _level_order(
        self, layout: _Layout, frame: _Frame
    ) -> tuple[list[int], list[_Roi]]:
        """Levels to try, best first: the finest level where the probes see a lattice whose
        period is not too coarse. Finest first because a coarser level can only lose harmonics
        and gain aliases, and a wrong lattice there can mimic a good period."""
        hi = self.settings.preferred_period_px * 1.8
        coarse: list[int] = []
        coarse_probes: list[_Roi] = []
        levels = list(layout.levels)
        for level in levels:
            probes = self._measure_many(frame, layout.probes[level], level)
            period = self._median_period(probes)
            if period is None:
                continue
            if period > hi * probes[0].size / 128 and level != levels[-1]:
                coarse.append(level)
                coarse_probes = probes
                continue
            return [level, *coarse[::-1]], probes
        return coarse[::-1], coarse_probes

    def _measure_grid(
        self, frame: _Frame, layout: _Layout, level: int
    ) -> list[_Roi]:
        """The grid at `level`; ROIs whose period sits badly there (the far side of a tilted
        net is finer, the near side coarser) are re-measured one level finer or coarser at the
        same place, keeping the better measurement."""
        s = self.settings
        grid = _thinned(layout.grids[level], frame.budget.max_rois)
        measurements = self._measure_many(frame, grid, level)
        lo, hi = s.preferred_period_px / 1.8, s.preferred_period_px * 1.8
        # Re-measure one level finer or coarser, each level's ROIs together.
        moves: dict[int, list[tuple[int, _Geometry]]] = {}
        periods: list[float | None] = []
        for i, m in enumerate(measurements):
            period = m.size / math.sqrt(m.fit.det) if m.fit is not None else None
            periods.append(period)
            if period is not None and lo <= period <= hi and m.valid:
                continue
            alt = level - 1 if period is None or period < lo else level + 1
            if alt not in layout.grids:
                continue
            moves.setdefault(alt, []).append((i, self._regrid(layout, grid[i], alt)))
        for alt, moved in moves.items():
            others = self._measure_many(frame, [g for _, g in moved], alt)
            for (i, _), other in zip(moved, others, strict=True):
                self._keep_better(measurements, i, other, periods[i])
        return measurements

    def _keep_better(
        self, measurements: list[_Roi], i: int, other: _Roi, period: float | None
    ) -> None:
        """Replace ROI `i` by its re-measurement at another level if that one is valid and its
        period nearer the preferred one."""
        s = self.settings
        m = measurements[i]
        if other.valid and other.fit is not None and (
            not m.valid or period is None
            or abs(math.log(other.size / math.sqrt(other.fit.det) / s.preferred_period_px))
            < abs(math.log(period / s.preferred_period_px))
        ):
            measurements[i] = other

    def _regrid(self, layout: _Layout, geom: _Geometry, level: int) -> _Geometry:
        """The ROI of `level` centred where `geom` is (clamped into the frame)."""
        ref = layout.grids[level][0]
        n = ref.size
        scale = 2**level
        w, h = layout.camera.width, layout.camera.height
        lw, lh = _level_size(w, level), _level_size(h, level)
        x = round((geom.center_full[0] + 0.5) / scale - n / 2)
        y = round((geom.center_full[1] + 0.5) / scale - n / 2)
        x, y = min(max(x, 0), lw - n), min(max(y, 0), lh - n)
        return self._geometries(layout.camera, [(x, y)], n, level)[0]

    def _conclude_seed(
        self, rois: list[_Roi], level: int, timings: dict[str, float]
    ) -> NetEstimate | None:
        """First plane from unrectified ROIs (biased by the perspective chirp; only a seed)."""
        t1 = time.perf_counter()
        valid = [m for m in rois if m.valid and m.fit is not None]
        plane = None
        if len(valid) >= self.settings.min_rois:
            plane = fit_plane(
                np.array([m.ray for m in valid]), np.array([m.area_norm for m in valid]),
                np.array([m.fit.relative_area_sigma for m in valid if m.fit is not None]),
                self.mesh.cell_area_m2, min_rois=self.settings.min_rois,
                triples=self._plane_triples,
            )
        timings["plane"] = timings.get("plane", 0.0) + (time.perf_counter() - t1) * 1e3
        if plane is None:
            return None
        n = -plane.normal_away
        used = {id(m) for m, u in zip(valid, plane.used, strict=True) if u}
        return NetEstimate(
            detected=True, confidence=0.0, normal=(float(n[0]), float(n[1]), float(n[2])),
            distance_m=plane.distance_m, range_m=plane.range_m,
            rois=tuple(_roi_result(m, id(m) in used) for m in rois),
            rois_used=int(plane.used.sum()), level=level,
        )

    # -- rectified passes ----------------------------------------------------------------------
    def _refine(
        self,
        seed: NetEstimate,
        frame: _Frame,
        layout: _Layout,
        level: int,
        seed_rois: list[_Roi] | None = None,
        passes: int = 6,
        held: _HeldProof | None = None,
    ) -> NetEstimate:
        """Rectified passes until one lands on the plane it was rectified with; then the checks
        that prove the scale and the net, and the verdict. `seed_rois` (the ROIs the seed came
        from) guide the first pass. `held` (a tracked prior's proofs) spares a pass those
        checks while its range is one the proofs hold at."""
        assert seed.normal is not None and seed.distance_m is not None
        normal = np.asarray(seed.normal, dtype=np.float64)
        distance = float(seed.distance_m)
        hints: F64 | None = None
        guide_rois = seed_rois
        rectified_once = False
        footprint_scale = 1.0
        previous: tuple[F64, float] | None = None
        last: _Pass | None = None
        corrected = 0
        planes: list[tuple[F64, float]] = []  # each pass's plane over this frame, in order
        planed: _Pass | None = None  # the pass that gave the last of them

        def verdict(p: _Pass, converged: _Converged | None, failure: str,
                    settled: bool = True, proofs_held: bool = False) -> NetEstimate:
            t1 = time.perf_counter()
            result = self._verdict(p, converged, layout, failure, settled, frame, proofs_held)
            frame.lap("proofs", t1)
            return result

        for _ in range(passes):
            t0 = time.perf_counter()
            # The first pass is rectified with a rough plane (the seed): its ROIs' lattices still
            # differ by the residual perspective, so agreement is judged loosely there.
            p = self._rectified_pass(frame, layout, normal, distance, hints, level,
                                     guide_rois, None if rectified_once else 2.5 *
                                     self.settings.lattice_tolerance, footprint_scale)
            guide_rois = None
            rectified_once = True
            frame.lap("rectified", t0)
            last = p
            if p.consensus is not None and p.plane is None and (
                hints is None or footprint_scale == 1.0
            ):
                # Some ROIs agree on a lattice but too few for a plane: look again with that
                # lattice as the guide (faint peaks where it predicts them), then once more
                # with smaller ROIs, which fit between what hides the net (boards, fish).
                if hints is not None:
                    footprint_scale = 0.6
                hints = p.consensus
                rectified_once = False
                continue
            if p.plane is None or p.consensus is None:
                return verdict(p, None, p.note or "ROI lattices do not agree")
            n_new = -(p.rotation.T @ p.plane.normal_away)
            n_new /= np.linalg.norm(n_new)
            d_new = p.plane.distance_m
            # Proof of scale: coarser-mesh lattice points must be empty in the averaged spectrum.
            proofs_held = held is not None and held.holds_at(d_new / float(-n_new[2]))
            t1 = time.perf_counter()
            factor = None if proofs_held else self._scale_check(p)
            frame.lap("proofs", t1)
            if factor is not None:
                if corrected >= 2:
                    return verdict(p, None,
                                   "mesh scale not proved (peaks between the lattice's)")
                corrected += 1
                # The lattice was a harmonic: the mesh is coarser, the net nearer.
                distance = d_new / math.sqrt(factor)
                normal = n_new
                hints = None
                previous = None
                continue
            hints = p.consensus
            planes.append((n_new, d_new))
            planed = p
            step = (abs(d_new / distance - 1.0), math.degrees(math.acos(
                float(np.clip(np.dot(n_new, normal), -1.0, 1.0)))))
            # Converged when the pass moved the plane by less than its own uncertainty, or by
            # less than 5 % in scale and 1.5 deg in tilt: a scale error does not distort the
            # rectified view (only the period changes), and a small tilt error only by its
            # second order, so the pass measured the plane without the chirp already.
            rel_sigma, sigma_n = _plane_sigmas(p)
            if step[0] < max(0.05, 1.5 * rel_sigma) and step[1] < max(1.5, 1.5 * sigma_n):
                return verdict(p, (n_new, d_new, previous, step), "", proofs_held=proofs_held)
            previous = (normal, distance)
            normal, distance = n_new, d_new
        assert last is not None
        failure = "the ROIs do not converge on one plane (rectified passes disagree)"
        if last is not planed or len(planes) < 2:
            # The last pass gave no plane, or one at a scale it then corrected.
            return verdict(last, None, failure)
        # The passes went round between planes, each fitted to the subset of ROIs that agreed
        # in its rectified view (a real net's cells differ more than a rendered one's, and on
        # one side of a marker board the subset decides the tilt). Each pass's own sigma does
        # not cover that: the net is seen, at a range known to about the spread of the last
        # passes, and no distance is given.
        recent = planes[-3:]
        ds = [d for _, d in recent]
        spread = ((max(ds) - min(ds)) / float(np.median(ds)),
                  max(math.degrees(math.acos(float(np.clip(np.dot(a, b), -1.0, 1.0))))
                      for (a, _), (b, _) in itertools.combinations(recent, 2)))
        n_last, d_last = planes[-1]
        return verdict(last, (n_last, d_last, planes[-2], spread), "", settled=False)

    def _rectified_pass(
        self,
        frame: _Frame,
        layout: _Layout,
        normal: F64,
        distance: float,
        hint: F64 | None,
        level: int,
        seed_rois: list[_Roi] | None = None,
        tolerance: float | None = None,
        footprint_scale: float = 1.0,
    ) -> _Pass:
        """Measure the ROIs in a virtual camera facing the plane, then fit the plane to the ROIs
        whose lattice agrees with the consensus."""
        s = self.settings
        rotation = rotation_to_z(-normal)
        n_away = -normal
        # Mesh period at each ROI centre (source pixels) predicted by the plane: the cell area
        # in normalised units, A (n . r)^3 / d^2, through the lens Jacobian.
        # The footprint: the preferred number of mesh cycles where the mesh looks coarsest,
        # but at most half the frame's smaller side (so the grid keeps a baseline both ways);
        # at least 5 cycles (a very coarse mesh: fewer, larger ROIs).
        periods = []
        for g in layout.corners:
            a = self.mesh.cell_area_m2 * max(float(n_away @ g.ray), 1e-6) ** 3 / distance**2
            periods.append(math.sqrt(a / abs(float(np.linalg.det(g.jacobian)))))
        p_max = max(periods)
        preferred_cycles = s.roi_size / s.preferred_period_px
        small = max(64, s.roi_size // 2)
        frame_side = float(min(layout.camera.width, layout.camera.height))
        footprint = min(preferred_cycles * p_max, layout.max_footprint) * footprint_scale
        # A coarse mesh: larger ROIs (fewer rows) rather than too few cycles to prove the
        # scale with.
        footprint = min(max(footprint, 6.0 * p_max), 0.9 * frame_side)
        cycles = footprint / p_max
        size = s.roi_size if cycles * s.preferred_period_px >= 0.75 * s.roi_size else small
        if frame.budget.coarse and small / cycles >= _COARSE_MIN_PERIOD_PX:
            # Half the samples over the same footprint: a quarter of the FFT work, the same
            # number of mesh cycles (so the same relative precision per peak), fewer harmonics.
            size = small
        period_out = size / cycles
        grid = self._rect_grid(layout, footprint, size, frame.budget.max_rois)
        expected = hint
        if expected is None and seed_rois:
            expected = self._guide(seed_rois, rotation, distance, size, period_out)
        rois = self._measure_rectified(frame, grid, rotation, distance, size, period_out,
                                       expected)
        tol = tolerance or s.lattice_tolerance
        consensus = _consensus(rois, tol)
        note = ""
        if consensus is None:
            # A seed at the wrong scale shows as good lattices that all miss the intended
            # period by the same factor: the true distance is the seed's divided by it. The
            # majority decides; measure once more at the corrected scale.
            ratios = [m.period_ratio for m in rois if math.isfinite(m.period_ratio)]
            if len(ratios) >= s.min_rois:
                ratio = float(np.median(ratios))
                if abs(math.log(ratio)) > math.log(1.35):
                    distance = distance / ratio
                    rois = self._measure_rectified(frame, grid, rotation, distance, size,
                                                   period_out, None)
                    consensus = _consensus(rois, tol)
            if consensus is None:
                note = f"{sum(m.valid for m in rois)} of {len(rois)} ROIs show a lattice, " \
                       "no lattice shared by enough of them"
        plane = None
        agreeing: list[_Roi] = []
        if consensus is not None:
            agreeing = [m for m in rois if m.agrees]
            if len(agreeing) >= s.min_rois:
                plane = fit_plane(
                    np.array([m.ray for m in agreeing]),
                    np.array([m.area_norm for m in agreeing]),
                    np.array([m.fit.relative_area_sigma for m in agreeing if m.fit is not None]),
                    self.mesh.cell_area_m2, min_rois=s.min_rois, triples=self._plane_triples,
                )
                if plane is not None:
                    for m, used in zip(agreeing, plane.used, strict=True):
                        m.agrees = bool(used)
                else:
                    note = "ROI lattices agree but not on one plane"
            else:
                note = f"only {len(agreeing)} ROIs share one lattice"
        return _Pass(rois, rotation, size, period_out, consensus, plane, level, note, agreeing)

    def _rect_maps(
        self, geoms: list[_Geometry], rotation: F64, distance_m: float, size: int,
        period_out: float,
    ) -> list[tuple[F64, F64, float, F64, float]]:
        """The resampling of each rectified ROI: the homography output pixel -> full-resolution
        pixel, its local Jacobian at the centre, source pixels per output pixel, the centre's
        virtual ray and the virtual normalised units per output pixel. All ROIs at once (the
        same small matrix algebra for each)."""
        k = len(geoms)
        if k == 0:
            return []
        rays = np.array([g.ray for g in geoms])
        virt = rays @ rotation.T
        virt = virt / virt[:, 2:3]
        # Normalised virtual units per output pixel so the mesh period is period_out.
        t = math.sqrt(self.mesh.cell_area_m2) / distance_m / period_out
        half = (size - 1) / 2.0
        to_virtual = np.zeros((k, 3, 3))
        to_virtual[:, 0, 0] = t
        to_virtual[:, 1, 1] = t
        to_virtual[:, 0, 2] = virt[:, 0] - t * half
        to_virtual[:, 1, 2] = virt[:, 1] - t * half
        to_virtual[:, 2, 2] = 1.0
        jinv = np.linalg.inv(np.array([g.jacobian for g in geoms]))
        centres = np.array([g.center_full for g in geoms])
        to_pixel = np.zeros((k, 3, 3))
        to_pixel[:, :2, :2] = jinv
        to_pixel[:, :2, 2] = centres - np.einsum("kij,kj->ki", jinv, rays[:, :2])
        to_pixel[:, 2, 2] = 1.0
        # Output pixel -> full-res pixel (homogeneous).
        full = to_pixel @ rotation.T @ to_virtual
        probes = np.array([[half, half, 1.0], [half + 1.0, half, 1.0], [half, half + 1.0, 1.0]])
        c = np.einsum("kij,pj->kpi", full, probes)  # (k, 3 probes, 3)
        xy = c[:, :, :2] / c[:, :, 2:3]
        jm = np.stack([xy[:, 1] - xy[:, 0], xy[:, 2] - xy[:, 0]], axis=2)
        det = jm[:, 0, 0] * jm[:, 1, 1] - jm[:, 0, 1] * jm[:, 1, 0]
        steps = np.sqrt(np.abs(det))
        return [(full[i], jm[i], float(steps[i]), virt[i], t) for i in range(k)]

    def _guide(
        self, seed_rois: list[_Roi], rotation: F64, distance_m: float, size: int,
        period_out: float,
    ) -> F64 | None:
        """The lattice the first rectified pass should find, from the seed's ROIs: each ROI's
        lattice (cycles per pixel) carried into the rectified view at its place (k . x is
        invariant: k_out = J^T k_pixel), and the one most of them agree on."""
        usable = [m for m in seed_rois if m.valid and m.reciprocal_px is not None]
        if not usable:
            return None
        maps = self._rect_maps([m.geometry for m in usable], rotation, distance_m, size,
                               period_out)
        jm_t = np.array([jm for _, jm, _, _, _ in maps]).transpose(0, 2, 1)
        carried = jm_t @ np.array([m.reciprocal_px for m in usable]) * size
        bases_kept: list[F64] = []
        weights: list[float] = []
        for m, b in zip(usable, carried, strict=True):
            basis = reduce_basis(b)
            (a, c), (b1, d) = basis.tolist()
            short, long = sorted((math.hypot(a, b1), math.hypot(c, d)))
            if short < 2.0 or long > 0.45 * size:
                continue
            bases_kept.append(basis)
            weights.append(max(m.weight, 0.2))
        if not bases_kept:
            return None
        bases = np.array(bases_kept)
        agree = _agreement(bases, bases, 0.1, 1.3)
        # Each lattice's support: the weight of the ROIs that agree with it. Rounded, so that a
        # tie goes to the first, as it did when the sums were added in ROI order.
        best = int(np.argmax(np.round(np.asarray(weights) @ agree, 9)))
        if int(agree[:, best].sum()) < 2:
            return None
        return bases[best]

    def _measure_rectified(
        self,
        frame: _Frame,
        grid: list[_Geometry],
        rotation: F64,
        distance_m: float,
        size: int,
        period_out: float,
        expected: F64 | None,
    ) -> list[_Roi]:
        """Measure ROIs in a virtual camera that faces the net squarely.

        Each patch is resampled through the homography of a camera rotated by `rotation` (so the
        net plane becomes fronto-parallel and its lattice uniform), scaled so the mesh period is
        `period_out`. Lens distortion enters through its local affine approximation at the ROI
        centre. The lattice found is then the local lattice at the ROI centre, without the
        perspective chirp across the ROI. The patches' contrast normalisation and spectra are
        computed for all ROIs together.
        """
        import cv2

        s = self.settings
        n = size
        if not grid:
            return []
        maps = self._rect_maps(grid, rotation, distance_m, size, period_out)
        levels: list[int] = []
        # Warped straight into one stack (the source's type: 8 or 16 bit, or float).
        patches = np.empty((len(maps), n, n), dtype=frame.image(0).dtype)
        for (full, _, step, _, _), patch in zip(maps, patches, strict=True):
            level = min(max(math.floor(math.log2(max(step, 1.0))), 0), s.levels - 1)
            scale = 2**level
            to_level = np.array(
                [[1 / scale, 0, -(scale - 1) / (2 * scale)],
                 [0, 1 / scale, -(scale - 1) / (2 * scale)], [0, 0, 1]]
            )
            cv2.warpPerspective(
                frame.image(level), to_level @ full, (n, n), dst=patch,
                flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REFLECT,
            )
            levels.append(level)
        spectrum = self._spectra[n]
        frame.count_fft(n, len(grid))
        normalised = _normalise_contrast_many(patches, period_out)
        spectra = spectrum.analyse_many(normalised)
        found_peaks = [peaks for peaks, _, _ in spectra]
        if expected is not None:
            # The lattice is known roughly (the consensus of the previous pass): faint peaks
            # where it predicts them count too (looked up in all ROIs at once), and it may
            # explain a smaller share of the peaks (a board or a rope in the ROI adds its own).
            found_peaks = _merge_peaks_many(found_peaks, spectrum.peaks_near_many(
                np.stack([snr for _, snr, _ in spectra]), _lattice_points(expected, order=2),
                s.guided_snr))
        fits = self._lattice.fit_many(found_peaks, expected, expected_share=0.3)
        out: list[_Roi] = []
        # Pixels -> output pixels at each ROI centre, for carrying its lattice back to pixels.
        jm_inv_t = np.linalg.inv(np.array([jm for _, jm, _, _, _ in maps])).transpose(0, 2, 1)
        for geom, (_, _, step, virt, t), level, (_, snr, logp), peaks, fit, to_pixels in zip(
            grid, maps, levels, spectra, found_peaks, fits, jm_inv_t, strict=True
        ):
            meas = _Roi(geometry=geom, level=level, size=n, fit=fit, peaks=len(peaks), snr=snr,
                        logp=logp, footprint_px=n * step)
            meas.ray = virt
            out.append(meas)
            if fit is None:
                continue
            (a, b), (c, d) = fit.basis.tolist()
            shorter, longer = sorted((math.hypot(a, c), math.hypot(b, d)))
            period_ok = shorter >= s.min_cycles and longer <= n / s.min_period_px
            if expected is not None:
                quality_ok = fit.mean_snr >= s.guided_snr and fit.inlier_weight_fraction >= 0.3
            else:
                quality_ok = fit.mean_snr >= s.min_roi_snr and fit.inlier_weight_fraction >= (
                    s.min_inlier_fraction
                )
            # The rectification was designed to show the mesh at period_out; a lattice far from
            # it means the seed plane was wrong or the ROI shows something else.
            det = abs(a * d - b * c)  # cell area in bins^2
            found = n / math.sqrt(det)
            on_target = abs(math.log(found / period_out)) < math.log(1.35)
            # Resampling cannot restore what the camera never resolved: a mesh finer than
            # ~3.5 px in the source has aliased harmonics and a peak position biased by the
            # pixel response. Both the period the ROI measured and the one the seed plane
            # predicts here must pass: a test on the measurement alone keeps, near the limit,
            # exactly the ROIs whose noise (or a billow) made the mesh look coarser, and the
            # plane fitted to them comes out nearer (a selection bias); one on the prediction
            # alone admits fine meshes whose biased peaks the seed plane underrated.
            resolved = min(found, period_out) * step >= s.min_source_period_px
            k_out = fit.basis / n  # cycles per output pixel
            meas.area_norm = t * t * n * n / det
            # For reporting: the lattice in full-resolution image pixels through the local map.
            meas.reciprocal_px = to_pixels @ k_out
            meas.valid = bool(period_ok and quality_ok and on_target and resolved)
            if period_ok and quality_ok and resolved:
                meas.period_ratio = found / period_out
        return out

    # -- proofs --------------------------------------------------------------------------------
    def _stack(self, p: _Pass, power: bool = False) -> tuple[F32, int] | None:
        """Mean whitened spectrum (or, with `power`, mean log power) of the agreeing ROIs."""
        if power not in p.means:
            maps = [m.logp if power else m.snr for m in p.rois if m.agrees]
            arrays = [a for a in maps if a is not None]
            p.means[power] = (np.mean(np.stack(arrays), axis=0, dtype=np.float32), len(arrays)
                              ) if arrays else None
        return p.means[power]

    def _pass_null(self, p: _Pass, snr: F32) -> tuple[float, float]:
        """`_null` of the pass's mean whitened spectrum `snr`, computed once."""
        if p.null is None:
            assert p.consensus is not None
            p.null = self._null(self._spectra[p.size], snr, p.consensus)
        return p.null

    def _scale_check(self, p: _Pass) -> int | None:
        """The index (2, 3, 4, 9 or 16) of a coarser mesh whose extra lattice points carry power in
        the averaged spectrum of the agreeing ROIs, or None when the scale is proved.

        A mesh's spectrum has peaks only on its own reciprocal lattice. If the lattice found is
        a sub-lattice (a harmonic pattern: every second or third point of the true one), the
        true mesh's other points - between the ones found - show in the averaged spectrum even
        when no single ROI resolved them.
        """
        assert p.consensus is not None
        stacked = self._stack(p)
        if stacked is None:
            return None
        snr, count = stacked
        spectrum = self._spectra[p.size]
        k = p.consensus
        null_level, null_spread = self._pass_null(p, snr)
        fundamentals = _lattice_points(k, order=1)
        fund = float(np.nanmean(spectrum.sample(snr, fundamentals)))
        threshold = max(null_level + 4.0 * null_spread, null_level + 0.35 * (fund - null_level))
        # The extra points of every refinement, looked up in one go.
        points, group_of = _extra_points(k, spectrum.size, self._refinements)
        if points.shape[0] == 0:
            return None
        # A real peak there is a local maximum of its own: the skirt of a strong neighbour
        # (a harmonic two bins away, smeared by what is left of the perspective) is not.
        near = spectrum.maxima_near(snr[None], points, null_level)
        if near is None:
            return None
        found, centre, keep, _, inside = near
        group_of = group_of[inside]
        # Only peaks that are not the lattice's own (the search around a point may climb onto
        # a neighbouring lattice peak).
        real = keep[0] & ~_near_lattice(found[0], k, 1.5)
        best: tuple[float, int] | None = None
        for g in np.unique(group_of).tolist():
            index = self._refinements.index[g]
            values = centre[0][real & (group_of == g)]
            # The strongest extra point: the true mesh's fundamental or a harmonic sits at one
            # of them (the others are weak cross terms, or outside the band).
            level = float(values.max()) if values.size else null_level
            if level > threshold and (best is None or level > best[0]):
                best = (level, index)
        del count
        return None if best is None else best[1]

    @staticmethod
    def _null(spectrum: SpectrumAnalyzer, snr: F32, k: F64) -> tuple[float, float]:
        """Level and spread of the averaged whitened spectrum where there is no peak: median and
        scaled MAD over the whole analysed band (peaks are a few bins among thousands). Taken
        as `sample` takes a peak's value (the largest of the 2x2 bins around a point), so the
        two compare like with like."""
        del k
        band = np.maximum(np.maximum(snr[:-1, :-1], snr[1:, :-1]),
                          np.maximum(snr[:-1, 1:], snr[1:, 1:]))[spectrum.valid[:-1, :-1]]
        if band.size < 16:
            return 0.0, 1.0
        level = float(np.median(band))
        return level, float(1.4826 * np.median(np.abs(band - level)))

    def _mesh_check(self, p: _Pass) -> tuple[float, str]:
        """Measured opening angle of the rectified mesh, and why it is not the configured net
        ("" when it is). Bars of a net are equal; its opening angle is configured."""
        assert p.consensus is not None
        # Real-space basis (columns), rectified pixels.
        edges = np.asarray(np.linalg.inv(p.consensus).T, dtype=np.float64)
        bars = _bar_pair(edges)
        u, v = bars[:, 0], bars[:, 1]
        lu, lv = float(np.linalg.norm(u)), float(np.linalg.norm(v))
        angle = math.degrees(math.acos(float(np.clip(abs(u @ v) / (lu * lv), 0.0, 1.0))))
        opening = min(angle, 180.0 - angle)
        aspect = max(lu, lv) / min(lu, lv)
        s = self.settings
        if aspect - 1.0 > s.aspect_tolerance:
            return opening, (f"the grid's cells are not a net's (sides {aspect:.2f}:1, angle "
                             f"{opening:.0f} deg)")
        bias = math.sqrt(math.sin(math.radians(opening)) / math.sin(math.radians(
            self._mesh_opening))) - 1.0
        if abs(opening - self._mesh_opening) > s.opening_tolerance_deg or abs(bias) > 0.025:
            return opening, (f"mesh opening angle measured {opening:.0f} deg, configured "
                             f"{self._mesh_opening:.0f} deg: check mesh.opening_angle_deg")
        return opening, ""

    def _profile_check(self, p: _Pass) -> str:
        """Does the averaged spectrum look like twine (thin lines crossing) rather than a
        checkerboard or a brick bond? ("" when it does, or when it cannot tell.)

        A net's image is 1 - (1 - p1(s1)) (1 - p2(s2)) for pulse trains p1, p2 of duty d1, d2
        across the two bar families (s1, s2: coordinates dual to the bars). Its Fourier
        amplitudes are |F(h, 0)| = |c1_h| (1 - d2), |F(0, l)| = |c2_l| (1 - d1) and
        |F(h, l)| = |c1_h c2_l|, with |c_1| = sin(pi d) / pi < 1 - d. Hence, whatever the twine's
        width, blur (which lowers higher frequencies more) or contrast:
        - the cross terms are weaker than the fundamentals: F(1, +-1) < F(1, 0), F(0, 1);
        - F(2, 1) <= F(1, 1), since |c_2 / c_1| = |cos(pi d)| <= 1.
        A running brick bond breaks the first (its continuous mortar lines run along a diagonal
        of the cell), a checkerboard the second (nothing at (1, +-1), the even harmonics of a
        50 % square wave, but 1/3 of the fundamental at (2, 1)). Amplitudes are compared in the
        averaged log power, only where the whitened spectrum shows a significant peak; a blurred
        grid that shows nothing but its fundamentals cannot be told from a net.
        """
        assert p.consensus is not None
        stacked = self._stack(p)
        power = self._stack(p, power=True)
        if stacked is None or power is None:
            return ""
        return _twine_profile(self._spectra[p.size], stacked[0], power[0], p.consensus,
                              stacked[1], self._pass_null(p, stacked[0]))

    # -- the verdict ---------------------------------------------------------------------------
    def _verdict(
        self,
        p: _Pass,
        converged: _Converged | None,
        layout: _Layout,
        failure: str,
        settled: bool = True,
        frame: _Frame | None = None,
        proofs_held: bool = False,
    ) -> NetEstimate:
        """The estimate from a pass. `converged` is the plane it settled on, or, when the
        passes went round without settling (`settled` false), the last plane with the spread
        of the last passes as its step: then the net is at most seen, never measured.
        `frame` (its full-resolution image) lets the verdict tell the video's own compression
        blocks from a net. `proofs_held`: the tracked prior's proof that this is twine holds
        for this pass (`_HeldProof`); the mesh's shape and the blocks are checked anyway (the
        blocks of a dark, smooth view can take over from a net that left it)."""
        s = self.settings
        rois = tuple(_roi_result(m, m.agrees) for m in p.rois)
        agreeing = [m for m in p.rois if m.agrees]
        # Confidence grows with the evidence that adds up over the agreeing ROIs (each ROI's
        # weight: the share of its peaks on the lattice and how clear they are), not with the
        # share of the frame: a net half hidden by boards is as sure a net.
        evidence = float(sum(m.weight for m in agreeing))
        confidence = 1.0 - math.exp(-evidence / 2.0)
        opening: float | None = None
        if p.consensus is not None:
            opening, shape = self._mesh_check(p)
            if not failure and shape:
                failure = shape
            if not failure and not proofs_held:
                failure = self._profile_check(p)
            if not failure and frame is not None:
                failure = _compression_grid(agreeing, frame.image(0))
        if not failure and p.size / p.period_out < 5.5:
            failure = ("mesh too coarse for the ROIs: fewer than 5.5 cycles each, its scale "
                       "cannot be proved")
        if failure or converged is None or p.plane is None:
            return NetEstimate(
                detected=False, confidence=min(confidence, 0.2), rois=rois,
                rois_used=len(agreeing), level=p.level,
                reason=failure or "no self-consistent plane",
                measured_opening_deg=opening,
            )
        n_new, d_new, previous, step = converged
        plane = p.plane
        range_m = d_new / float(-n_new[2])
        # Uncertainty from the data: the plane fit's covariance (the ROIs' noise model pooled
        # with their scatter, plane.py) inflated for its degrees of freedom and for overlapping
        # ROIs, plus half the last pass-to-pass change, the net's deformation carried to the
        # optical axis, and a 0.1 % floor for the model (resampling, interpolation).
        inflation = _inflation(p)
        # The pass-to-pass change counts only between passes over this frame: the first pass
        # of a tracked frame moved from the previous frame's plane, which is the net's motion.
        # Of the change, half is this pass's own: both passes measured the same ROIs with
        # errors of about the same size, and the last one was rectified with the better plane
        # (a scale error does not alter the rectified view, a tilt error only at second order).
        change = (_CHANGE_SHARE * step[0], _CHANGE_SHARE * step[1]) if previous is not None \
            else (0.0, 0.0)
        deformation, deformation_tilt = _deformation(
            p, agreeing, self.mesh.cell_area_m2,
            layout.corner_rays @ p.rotation.T)
        sigma_d = math.hypot(plane.sigma_distance_m * inflation, change[0] * d_new,
                             deformation * d_new, _MODEL_FLOOR * d_new)
        sigma_r = math.hypot(plane.sigma_range_m * range_m / plane.range_m * inflation,
                             change[0] * range_m, deformation * range_m, _MODEL_FLOOR * range_m)
        sigma_n = math.hypot(plane.sigma_normal_deg * inflation, change[1], deformation_tilt,
                             0.2)
        # The ROI on the optical axis measures the range there itself, whatever ROIs the plane
        # kept: a plane that disagrees with it does not describe the net at the axis.
        off_axis = _axis_disagreement(p, self.mesh.cell_area_m2, math.hypot(
            sigma_r / range_m, _MODEL_FLOOR))
        sigma_d = math.hypot(sigma_d, off_axis * d_new)
        sigma_r = math.hypot(sigma_r, off_axis * range_m)
        left_d, left_r, left_n = _left_out_pull(p, self.mesh.cell_area_m2)
        pull_r, pull_n = _CHANGE_SHARE * left_r * range_m, _CHANGE_SHARE * left_n
        sigma_d = math.hypot(sigma_d, _CHANGE_SHARE * left_d * d_new)
        sigma_r = math.hypot(sigma_r, pull_r)
        sigma_n = math.hypot(sigma_n, pull_n)
        too_uncertain = (sigma_r > s.max_sigma_range_fraction * range_m
                         or sigma_n > s.max_sigma_normal_deg)
        # The bars are what a net keeps; its opening angle is how it hangs (a diamond net at
        # 60-85 deg by its load, a square one sheared by the current). The rectified view is a
        # similarity of the net, whose angle it shows to about 0.1 deg: the cell's area is
        # L^2 sin(measured angle), and the configured angle only tells a net from other grids
        # (_mesh_check). The plane was fitted with the configured area, so every length scales
        # by the root of the areas' ratio (the normal does not change). Near 90 deg sin is
        # flat: a square net loses nothing to an angle measured a little off.
        scale = 1.0 if opening is None else math.sqrt(
            math.sin(math.radians(opening)) / math.sin(math.radians(self._mesh_opening)))
        d_new, range_m, sigma_d, sigma_r = (scale * d_new, scale * range_m, scale * sigma_d,
                                            scale * sigma_r)
        if too_uncertain or not settled:
            # Every proof passed: it is the net, at a range known only roughly. Said so (for
            # the pilot), never given as a distance.
            seen = confidence >= s.min_confidence
            pulled = pull_r**2 > 0.5 * sigma_r**2 or pull_n**2 > 0.5 * sigma_n**2
            why = ("the passes do not settle on one plane" if not settled else
                   f"the net on the optical axis is {off_axis:.0%} off the plane of the ROIs "
                   "around it" if off_axis > 0.0 else
                   f"ROIs that show the net but not this plane pull it {left_n:.0f} deg and "
                   f"{left_r:.0%} away: the net is not one plane here" if pulled else
                   "the ROIs that see the net do not span the view")
            return NetEstimate(
                detected=False, confidence=min(confidence, 0.2), rois=rois,
                rois_used=len(agreeing), level=p.level, measured_opening_deg=opening,
                reason=(f"plane too uncertain (range +- {sigma_r / range_m:.0%}, normal +- "
                        f"{sigma_n:.0f} deg): {why}"),
                approx_range_m=range_m if seen else None,
                approx_sigma_range_m=sigma_r if seen else None,
            )
        detected = confidence >= s.min_confidence
        return NetEstimate(
            detected=detected,
            confidence=confidence,
            normal=(float(n_new[0]), float(n_new[1]), float(n_new[2])) if detected else None,
            distance_m=d_new if detected else None,
            range_m=range_m if detected else None,
            sigma_distance_m=sigma_d if detected else None,
            sigma_range_m=sigma_r if detected else None,
            sigma_normal_deg=sigma_n if detected else None,
            rois=rois,
            rois_used=len(agreeing),
            level=p.level,
            reason="" if detected else f"confidence {confidence:.2f} below threshold",
            measured_opening_deg=opening,
        )


# -- helpers --------------------------------------------------------------------------------------


# Block sizes of the video codecs a camera or a stream uses (JPEG/MJPEG and MPEG-4's 8x8 DCT,
# H.264/HEVC's 8x8 transforms in 16x16 macroblocks), in source pixels.
_CODEC_BLOCKS_PX = (8.0, 16.0)
# A lattice is the blocks' when, in most of the agreeing ROIs, both bars lie along the
# pixel axes and repeat at one block size, to within what a faint ROI measures (real blocks in
# an MPEG-4 stream: 0.3 % and 0.2 deg where clear, up to 2-3 % and 2.6 deg where faint), and
# over those ROIs the median is within 1 % and 1 deg (what clear blocks give; a rendered net of
# 8.16 px under JPEG blocks in the integrity benchmark was refused at 2 %).
_CODEC_PERIOD_TOLERANCE = 0.04
_CODEC_AXIS_TOLERANCE_DEG = 3.0
_CODEC_MEDIAN_PERIOD_TOLERANCE = 0.01
_CODEC_MEDIAN_AXIS_TOLERANCE_DEG = 1.0
# ... and the image's own steps between pixels are larger on the blocks' edges (columns and
# rows 8n - 1 | 8n) than on any other column (row) of the block, by this factor, in both
# directions: a block grid has one edge per period, a net's twine two of about the same
# strength (its rising and its falling side), which no phase can merge. (Real MPEG-4 blocks
# in open water: 1.33-1.47; the other phases within 0.86-1.07 of their mean.)
_CODEC_EDGE_DOMINANCE = 1.2


def _compression_grid(rois: Sequence[_Roi], gray: Image) -> str:
    """Why the lattice the ROIs agree on is the video's compression blocks, not a net ("" when
    it is not).

    A lossy codec quantises each 8x8 (or 16x16) block on its own: where the picture is smooth
    and dark (deep water, a shadow, a low bitrate) the block edges are a square grid fixed to
    the pixel grid, 8 px apart. In a real MPEG-4 stream of open water it gave 6 ROIs agreeing on
    a 'net' 2.3 m away, tilted 1 deg. A net shows such a lattice only by coincidence: an exact
    block size in every ROI despite the lens's distortion and the plane's perspective, bars
    square to the pixel axes, and twine edges on the block edges. All three are required."""
    measured = [m for m in rois if m.reciprocal_px is not None]
    by_block: dict[float, list[tuple[_Roi, list[tuple[float, float]]]]] = {}
    for m in measured:
        found = _codec_block_of(np.asarray(m.reciprocal_px, dtype=np.float64))
        if found is not None:
            by_block.setdefault(found[0], []).append((m, found[1]))
    if not by_block:
        return ""
    block, matches = max(by_block.items(), key=lambda kv: len(kv[1]))
    if len(matches) < 3 or 2 * len(matches) <= len(measured):
        return ""
    deviations = np.array([d for _, ds in matches for d in ds])  # (period share, degrees)
    if float(np.median(np.abs(deviations[:, 0]))) > _CODEC_MEDIAN_PERIOD_TOLERANCE or float(
            np.median(deviations[:, 1])) > _CODEC_MEDIAN_AXIS_TOLERANCE_DEG:
        return ""
    blocky = [m for m, _ in matches]
    if not _block_edges(gray, [(m.geometry.center_full, m.footprint_px) for m in blocky],
                        int(block)):
        return ""
    return (f"the video's compression blocks ({block:.0f} px squares on the pixel grid), not a "
            "net: raise the stream's bitrate or quality")


def _codec_block_of(basis: F64) -> tuple[float, list[tuple[float, float]]] | None:
    """The block size whose pixel-aligned grid the lattice `basis` (columns k1 k2, cycles per
    pixel) is, with each bar's deviation from it (relative period error, degrees off its
    pixel axis); None when it is no block grid."""
    block: float | None = None
    deviations = []
    for k in basis.T:
        norm = float(np.hypot(k[0], k[1]))
        if not norm > 0.0:
            return None
        off_axis = math.degrees(math.asin(min(abs(float(k[0])), abs(float(k[1]))) / norm))
        period = 1.0 / norm
        size = min(_CODEC_BLOCKS_PX, key=lambda b: abs(math.log(period / b)))
        if off_axis > _CODEC_AXIS_TOLERANCE_DEG or abs(period / size - 1.0) > (
                _CODEC_PERIOD_TOLERANCE) or (block is not None and size != block):
            return None
        block = size
        deviations.append((period / size - 1.0, off_axis))
    return (block, deviations) if block is not None else None


def _block_edges(gray: Image, squares: Sequence[tuple[tuple[float, float], float]],
                 block: int) -> bool:
    """Whether, over the given squares (centre, side; full-resolution pixels), the image steps
    between columns (and between rows) show a block grid's edges: the mean absolute step
    across a block edge (columns block*n - 1 | block*n) exceeds that of every other phase of
    the block by _CODEC_EDGE_DOMINANCE."""
    h, w = gray.shape[:2]
    sums = np.zeros((2, block))
    counts = np.zeros((2, block))
    for (cx, cy), side in squares:
        half = max(side, float(block)) / 2.0
        x0, x1 = max(int(cx - half), 0), min(int(cx + half) + 1, w)
        y0, y1 = max(int(cy - half), 0), min(int(cy + half) + 1, h)
        if x1 - x0 < 2 * block or y1 - y0 < 2 * block:
            continue
        patch = gray[y0:y1, x0:x1].astype(np.float32)
        for axis, origin in ((1, x0), (0, y0)):
            steps = np.abs(np.diff(patch, axis=axis)).mean(axis=1 - axis)
            phase = (origin + np.arange(steps.size)) % block
            sums[axis] += np.bincount(phase, weights=steps, minlength=block)
            counts[axis] += np.bincount(phase, minlength=block)
    for axis in (1, 0):
        if counts[axis].min() == 0:
            return False
        mean = sums[axis] / counts[axis]
        others = float(np.delete(mean, block - 1).max())
        if not others > 0.0 or mean[block - 1] < _CODEC_EDGE_DOMINANCE * others:
            return False
    return True


def _twine_profile(
    spectrum: SpectrumAnalyzer, snr: F32, logp: F32, basis: F64, count: int,
    null: tuple[float, float] | None = None,
) -> str:
    """The twine-profile test of `NetEstimator._profile_check` on a (possibly averaged over
    `count` ROIs) whitened spectrum `snr` and log power `logp` with lattice `basis` (bins);
    `null`: `NetEstimator._null` of `snr` when already known."""
    null_level, null_spread = null or NetEstimator._null(spectrum, snr, basis)
    significant = null_level + max(2.0 * null_spread, 1.5)
    edges = np.asarray(np.linalg.inv(basis).T, dtype=np.float64)
    orders = [(1, 0), (0, 1), (1, 1), (1, -1), (2, 1), (1, 2), (2, -1), (1, -2)]
    # The bars: of the pairs of lattice vectors as nearly equal in length as the best, the one
    # whose own fundamentals are strongest. Usually there is one such pair; a 60 or 120 deg
    # mesh's lattice is hexagonal, its short diagonal as long as its bars, and a pair with the
    # diagonal in it would put a bar family's fundamental among the "cross terms" and call
    # the net a brick wall (half the frames of a clean 60 deg net, before).
    best: tuple[float, dict[tuple[int, int], float], dict[tuple[int, int], float]] | None = None
    for bars in _bar_pairs(edges):
        dual = np.linalg.inv(bars).T  # reciprocal basis dual to the bars (bins)
        pts = np.array([h * dual[:, 0] + j * dual[:, 1] for h, j in orders])
        sig = dict(zip(orders, spectrum.sample(snr, pts), strict=True))
        amp = dict(zip(orders, spectrum.sample(logp, pts), strict=True))
        strength = min(amp[(1, 0)], amp[(0, 1)])
        if best is None or strength > best[0]:
            best = (strength, sig, amp)
    assert best is not None
    _, sig, amp = best
    # Noise on a difference of averaged log powers; a factor 2 in power is log 2 = 0.7.
    margin = max(1.0, 2.5 * 1.28 / math.sqrt(max(count, 1)))

    def real(o: tuple[int, int]) -> bool:
        return bool(math.isfinite(sig[o]) and sig[o] > significant)

    fundamental = min(amp[(1, 0)], amp[(0, 1)])
    for cross in ((1, 1), (1, -1)):
        if real(cross) and math.isfinite(fundamental) and amp[cross] > fundamental + margin:
            return ("a brick-like grid, not twine: the cell's diagonal is stronger than its "
                    "sides (continuous lines along a diagonal)")
    diagonal = max(amp[(1, 1)], amp[(1, -1)])
    for high in ((2, 1), (1, 2), (2, -1), (1, -2)):
        if real(high) and math.isfinite(diagonal) and amp[high] > diagonal + margin:
            return ("a checkerboard-like grid (50 % squares), not twine: stronger cross "
                    "terms at (2, 1) than at (1, 1)")
    return ""


def _consensus(rois: list[_Roi], tolerance: float) -> F64 | None:
    """The lattice most of the ROIs' evidence agrees on (reduced basis, bins), refined as the
    weighted mean of the agreeing ROIs' bases; marks those ROIs. None when fewer than two agree.

    Agreement is judged on the lattice's orientation and shape (the basis over the square root
    of its cell area) within `tolerance`, and on its scale only loosely (30 %): in a pass
    rectified with a slightly wrong plane the scale still varies across the view, and that
    variation is what the plane fit measures.
    """
    cands = [m for m in rois if m.valid and m.fit is not None]
    if len(cands) < 2:
        return None
    weights = np.array([m.weight for m in cands])
    bases = np.array([m.fit.basis for m in cands if m.fit is not None])
    agree = _agreement(bases, bases, tolerance)  # [i, j]: ROI i agrees with ROI j's lattice
    # The lattice with the most evidence behind it (the first of equals).
    best = int(np.argmax(weights @ agree))
    chosen = agree[:, best]
    if int(chosen.sum()) < 2:
        return None
    members = [m for m, ok in zip(cands, chosen.tolist(), strict=True) if ok]
    # Each member's basis as the same lattice vectors as the chosen one's (a unimodular change
    # of basis), split into shape and scale; the weighted means of both are the consensus.
    w = weights[chosen]
    mapped = _aligned_many(bases[chosen], bases[best])
    scale = np.sqrt(np.abs(np.linalg.det(mapped)))
    shape = np.einsum("k,kij->ij", w / scale, mapped) / w.sum()
    consensus = reduce_basis(shape / math.sqrt(abs(float(np.linalg.det(shape))))
                             * math.exp(float(w @ np.log(scale)) / float(w.sum())))
    final = _agreement(bases[chosen], consensus[None], tolerance)[:, 0].tolist()
    agreeing = {id(m) for m, ok in zip(members, final, strict=True) if ok}
    for m in rois:
        m.agrees = id(m) in agreeing
    return consensus


def _normalise_contrast_many(patches: Image, period: float) -> F32:
    """Local contrast normalisation of a stack of ROIs (n, rows, cols): each patch minus its
    local mean, over its local standard deviation (box windows of about one and two mesh
    periods).

    Real views put high-contrast things beside a faint net: marker boards with white fiducials,
    ropes, fish. Their edges would dominate the spectrum by sheer amplitude; normalised, every
    region counts by how periodic it is, not how bright. The mesh's lattice is unchanged (a
    smooth gain does not move spectral peaks).
    """
    import cv2

    detail = np.array(patches, dtype=np.float32)  # a copy: normalised in place
    # Box filters of about one and two periods (cheaper than Gaussians, and just as smooth on
    # the scale of the ROI's spectral resolution), one patch at a time: each patch and its
    # scratch stay in the cache, and the stack needs no channel-last copy for OpenCV.
    k1 = max(3, int(round(1.6 * period)) | 1)
    k2 = max(3, int(round(3.2 * period)) | 1)
    var = np.empty_like(detail)
    work = np.empty_like(detail[0])
    for d, v in zip(detail, var, strict=True):
        cv2.blur(d, (k1, k1), dst=work, borderType=cv2.BORDER_REFLECT)
        np.subtract(d, work, out=d)
        np.multiply(d, d, out=work)
        cv2.blur(work, (k2, k2), dst=v, borderType=cv2.BORDER_REFLECT)
    # The floor is a regulariser: the median of every fourth row and column of the (box-
    # smoothed, so slowly varying) variance is as good, and a full median of every ROI's
    # pixels was the costliest step of the rectified pass.
    median = np.median(var[:, ::4, ::4].reshape(var.shape[0], -1), axis=1)
    floor = (1e-3 + 0.1 * median.astype(np.float64)).astype(np.float32)
    np.add(var, floor[:, None, None], out=var)
    np.sqrt(var, out=var)
    np.divide(detail, var, out=detail)
    return detail


def _merge_peaks_many(strong: list[Peaks], weak: list[Peaks]) -> list[Peaks]:
    """Each ROI's strong peaks plus its weak ones not already among them (within half a bin,
    either sign). All ROIs at once, each ROI's peaks padded to the most any ROI has (padding
    at infinity matches nothing), by squared distance: per ROI, numpy's overhead was most of
    the cost."""
    counts_weak = [len(p) for p in weak]
    if not any(counts_weak):
        return list(strong)
    n = len(strong)
    weak_k = _padded([p.k for p in weak], counts_weak)
    strong_k = _padded([p.k for p in strong], [len(p) for p in strong])
    wx, wy = weak_k[:, :, 0, None], weak_k[:, :, 1, None]
    sx, sy = strong_k[:, None, :, 0], strong_k[:, None, :, 1]
    with np.errstate(invalid="ignore"):  # padding against padding: never read
        d_plus = np.square(wx - sx) + np.square(wy - sy)
        d_minus = np.square(wx + sx) + np.square(wy + sy)
    nearest = np.minimum(d_plus, d_minus).min(axis=2, initial=np.inf)
    new = nearest > 0.25  # (n, most weak peaks); padded entries are never read
    out: list[Peaks] = []
    for i in range(n):
        s, w = strong[i], weak[i]
        keep = new[i, : counts_weak[i]]
        out.append(Peaks(np.concatenate([s.k, w.k[keep]]), np.concatenate([s.snr, w.snr[keep]]))
                   if keep.any() else s)
    return out


def _padded(arrays: list[F64], counts: list[int]) -> F64:
    """Stack (n, most rows, 2) of arrays of (count, 2) rows, padded with infinity."""
    out = np.full((len(arrays), max(counts, default=0), 2), np.inf)
    for i, (a, count) in enumerate(zip(arrays, counts, strict=True)):
        out[i, :count] = a
    return out


def _aligned_many(bases: F64, ref: F64) -> F64:
    """Each of `bases` (k, 2, 2) expressed as the same lattice vectors as `ref` (unimodular
    change of basis)."""
    m = np.rint(np.linalg.solve(ref, bases))
    return np.asarray(bases @ np.linalg.inv(m), dtype=np.float64)


def _lattices_agree(
    basis: F64, ref: F64, tolerance: float, max_scale: float = 1.3, floor: float = 0.5
) -> bool:
    """Do two lattices (2x2 bases) agree: after a unimodular change of basis and removing the
    scale, each basis vector within `tolerance` of its length (but not less than `floor`);
    the scales (square roots of the cell areas) within a factor `max_scale`.

    The scalar statement of the rule; `_agreement` evaluates it for all pairs at once.
    """
    a, b, c, d = float(basis[0, 0]), float(basis[0, 1]), float(basis[1, 0]), float(basis[1, 1])
    ra, rb, rc, rd = float(ref[0, 0]), float(ref[0, 1]), float(ref[1, 0]), float(ref[1, 1])
    det_b, det_r = a * d - b * c, ra * rd - rb * rc
    if det_r == 0.0 or det_b == 0.0:
        return False
    scale = math.sqrt(abs(det_b / det_r))
    if not 1.0 / max_scale <= scale <= max_scale:
        return False
    # m = round(inv(scale * ref) @ basis)
    inv = 1.0 / (scale * det_r)
    m00 = round((rd * a - rb * c) * inv)
    m01 = round((rd * b - rb * d) * inv)
    m10 = round((-rc * a + ra * c) * inv)
    m11 = round((-rc * b + ra * d) * inv)
    if abs(m00 * m11 - m01 * m10) != 1:
        return False
    # Residual of each column: basis[:, j] - scale * ref @ m[:, j]. Relative to the vector's
    # length, but never below `floor` bins: a lattice spanning few cycles with weak peaks is
    # located to a few tenths of a bin.
    for x, y, p, q in ((a, c, m00, m10), (b, d, m01, m11)):
        ex = x - scale * (ra * p + rb * q)
        ey = y - scale * (rc * p + rd * q)
        if math.hypot(ex, ey) > max(tolerance * math.hypot(x, y), floor):
            return False
    return True


def _agreement(
    bases: F64, refs: F64, tolerance: float, max_scale: float = 1.3, floor: float = 0.5
) -> npt.NDArray[np.bool_]:
    """`_lattices_agree(bases[i], refs[j], ...)` for every pair at once: (n, m) booleans for
    bases (n, 2, 2) and refs (m, 2, 2). Every ROI of a pass is compared with every other, and
    one vectorised evaluation costs what a handful of scalar ones do."""
    a, b = bases[:, 0, 0][:, None], bases[:, 0, 1][:, None]
    c, d = bases[:, 1, 0][:, None], bases[:, 1, 1][:, None]
    ra, rb = refs[:, 0, 0][None, :], refs[:, 0, 1][None, :]
    rc, rd = refs[:, 1, 0][None, :], refs[:, 1, 1][None, :]
    det_b, det_r = a * d - b * c, ra * rd - rb * rc
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        scale = np.sqrt(np.abs(det_b / det_r))
        ok = (det_b != 0.0) & (det_r != 0.0) & (scale >= 1.0 / max_scale) & (scale <= max_scale)
        inv = 1.0 / (scale * det_r)
        m00 = np.rint((rd * a - rb * c) * inv)
        m01 = np.rint((rd * b - rb * d) * inv)
        m10 = np.rint((-rc * a + ra * c) * inv)
        m11 = np.rint((-rc * b + ra * d) * inv)
        ok &= np.abs(m00 * m11 - m01 * m10) == 1.0
        for x, y, p, q in ((a, c, m00, m10), (b, d, m01, m11)):
            ex = x - scale * (ra * p + rb * q)
            ey = y - scale * (rc * p + rd * q)
            ok &= np.hypot(ex, ey) <= np.maximum(tolerance * np.hypot(x, y), floor)
    return np.asarray(ok, dtype=bool)


def _lattice_points(k: F64, order: int) -> F64:
    """Lattice points h k1 + l k2 with |h|, |l| <= order (one of each +-pair)."""
    pts = []
    for h in range(0, order + 1):
        for j in range(-order, order + 1):
            if (h, j) == (0, 0) or (h == 0 and j < 0):
                continue
            pts.append(h * k[:, 0] + j * k[:, 1])
    return np.array(pts)


def _near_lattice(points: F64, basis: F64, radius: float) -> npt.NDArray[np.bool_]:
    """Which points (m, 2) lie within `radius` bins of a point of the lattice `basis`."""
    if points.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    coords = np.linalg.solve(basis, points.T)
    nearest = basis @ np.rint(coords)
    return np.asarray(np.linalg.norm(points.T - nearest, axis=0) < radius, dtype=bool)


def _extra_points(k: F64, size: int, refinements: _Refinements
                  ) -> tuple[F64, npt.NDArray[np.int64]]:
    """The low-order points (m, 2) of each refinement of the lattice `k` that are not points
    of `k`, inside the analysed band, and the refinement each belongs to (m,): those of a
    refinement with fewer than two such points are left out.

    In `k`'s own coordinates the points of refinement S are S^-1 (h, j): which of them are not
    lattice points, and their offsets from the nearest ones, depend on S alone and are
    tabulated once (`_Refinements`); only their lengths in bins depend on `k`."""
    points = refinements.coords @ k.T
    off = refinements.offsets @ k.T  # (corners, m, 2): to the four points of `k` around each
    nearest = np.hypot(off[..., 0], off[..., 1]).min(axis=0)
    radius = np.hypot(points[:, 0], points[:, 1])
    # Too near a point of `k` to be told from its skirt, or outside the band.
    keep = (nearest >= 2.5) & (radius >= 2.6) & (radius <= 0.45 * size)
    group = refinements.group
    counts = np.bincount(group[keep], minlength=len(refinements.index))
    keep &= counts[group] >= 2
    return points[keep], group[keep]


@dataclass(frozen=True)
class _Refinements:
    """`_extra_points`' table, built once per estimator: for each refinement S (of
    `_REFINEMENT_BASES`) and each low-order (h, j), the point S^-1 (h, j)'s coordinates in the
    coarse lattice when they are not integers (`coords`), their offsets from the four integer
    points around them (`offsets`: a point halfway between two is near both), the refinement's
    number (`group`); and each refinement's index |det S| (`index`)."""

    coords: F64
    offsets: F64
    group: npt.NDArray[np.int64]
    index: tuple[int, ...]

    @classmethod
    def build(cls) -> _Refinements:
        coords: list[F64] = []
        group: list[int] = []
        index: list[int] = []
        for g, basis in enumerate(_REFINEMENT_BASES):
            s = np.array(basis, dtype=np.float64)
            inv_s = np.asarray(np.linalg.inv(s), dtype=np.float64)
            index.append(abs(round(float(np.linalg.det(s)))))
            for h in range(0, 3):
                for j in range(-2, 3):
                    if (h, j) == (0, 0) or (h == 0 and j < 0):
                        continue
                    c = inv_s @ np.array([h, j], dtype=np.float64)
                    if np.abs(c - np.rint(c)).max() < 1e-6:
                        continue
                    coords.append(c)
                    group.append(g)
        table = np.array(coords)
        corners = np.array([(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)])
        offsets = (table - np.floor(table))[None] - corners[:, None, :]
        return cls(table, offsets, np.array(group, dtype=np.int64), tuple(index))


def _bar_pair(edges: F64) -> F64:
    """The two lattice vectors that are the net's bars: the most nearly equal-length pair among
    the reduced basis (a, b) and (b, b +- a) (a rhombus with an opening under 60 deg has its
    short diagonal in the reduced basis)."""
    return _bar_pairs(edges)[0]


def _bar_pairs(edges: F64) -> list[F64]:
    """`_bar_pair`'s candidates that are as nearly equal in length as the best (within 5 %),
    the best first: more than one only for a lattice near hexagonal (a 60 or 120 deg mesh),
    where the geometry alone cannot tell the bars from the short diagonal."""
    a, b = edges[:, 0], edges[:, 1]
    candidates = [(a, b), (b, b - a), (b, b + a), (a, a - b), (a, a + b)]
    mismatch = [abs(math.log(float(np.linalg.norm(u)) / float(np.linalg.norm(v))))
                for u, v in candidates]
    order = sorted(range(len(candidates)), key=mismatch.__getitem__)
    least = mismatch[order[0]]
    return [np.stack(candidates[i], axis=1) for i in order
            if mismatch[i] <= least + _BAR_PAIR_SLACK]


# The uncertainty model (see `_verdict`, `_deformation`): the share of the last pass-to-pass
# change that is the last pass's own error, the net's deformation that the ROIs cannot see (a
# share of the distance over the ROIs' spread), and the floor for resampling and interpolation.
_CHANGE_SHARE = 0.5
# How much less equal (in log length) than the best a pair of lattice vectors may be and still
# be taken for the bars (`_bar_pairs`).
_BAR_PAIR_SLACK = 0.05
_UNSEEN_DEFORMATION = 0.005
# The same for the normal (relative to the cell areas' cube roots, over the ROIs' spread beyond
# the view's own): chosen on `netpose bench integrity` (3,000 frames, seed 7) so that the
# normal's error is within 2 sigma in 98 % and within 3 sigma in 99.4 % of valid outputs (a
# 2-D error against a total sigma: 98.2 % and 99.99 % if it were Gaussian). The range's 0.5 %
# made the normal's sigma twice too large (rms error/sigma 0.51); without it the tails of
# billowing nets stayed short (97.5 % within 3 sigma).
_UNSEEN_TILT = 0.0025
_MODEL_FLOOR = 0.001


def _inflation(p: _Pass) -> float:
    """Factor on the plane fit's sigmas: Student t for the pooled variance's degrees of freedom
    (a scatter estimated from few residuals is itself uncertain), and the square root of how
    many times over the agreeing ROIs cover their pixels: ROIs that share pixels share their
    noise, so n ROIs that cover each pixel k times carry about n / k independent measurements
    (the least-squares covariance assumed n)."""
    assert p.plane is not None
    return _t_factor(p.plane.sigma_dof) * math.sqrt(_overlap([m for m in p.rois if m.agrees]))


def _plane_sigmas(p: _Pass) -> tuple[float, float]:
    """Relative distance sigma and normal sigma (deg) of a pass's plane, for judging whether a
    pass has converged: the fit's sigmas with the overlap correction, without the Student-t
    factor. A step is compared with the scatter's estimate itself; the t factor widens the
    reported error's tails, and a weak fit (few ROIs) whose tails are wide must not be taken as
    converged after a large step for that reason (it would stop at a pass still rectified with
    a plane degrees off)."""
    assert p.plane is not None
    f = math.sqrt(_overlap([m for m in p.rois if m.agrees]))
    return (p.plane.sigma_distance_m / p.plane.distance_m * f, p.plane.sigma_normal_deg * f)


def _t_factor(dof: float) -> float:
    """How much a sigma whose variance rests on `dof` degrees of freedom must grow: the
    geometric mean of the Student-t over normal quantiles at 1 sigma (84.13 %) and at 3 sigma
    (99.865 %), so both the spread of error/sigma and its 3-sigma tail stay honest. The pooled
    variance (plane.py) has at least PRIOR_DOF = 4 degrees of freedom, so this stays finite
    (1.43 for four ROIs, 1.28 for six, 1.08 for twenty); the quantiles come from the
    Cornish-Fisher expansion, within 0.7 % of the exact ones from 4 degrees of freedom on."""
    if dof < 1.0:
        return math.inf
    ratio = 1.0
    for z in (1.0, 3.0):
        t = (z + (z**3 + z) / (4 * dof) + (5 * z**5 + 16 * z**3 + 3 * z) / (96 * dof**2)
             + (3 * z**7 + 19 * z**5 + 17 * z**3 - 15 * z) / (384 * dof**3)
             + (79 * z**9 + 776 * z**7 + 1482 * z**5 - 1920 * z**3 - 945 * z)
             / (92160 * dof**4))
        ratio *= t / z
    return math.sqrt(ratio)


def _deformation(p: _Pass, agreeing: list[_Roi], cell_area_m2: float,
                 view_rays: F64) -> tuple[float, float]:
    """Relative sigma of the range on the optical axis, and sigma of the normal (degrees), from
    a net that is not a plane.

    A billowing net's departure from its mean plane is smooth over the view, so it does not
    average out over ROIs as their noise does. Two parts:
    - what the ROIs show: the rms residual of the cell-area cube roots c beyond what their own
      noise explains. The plane absorbs the deformation's mean and tilt over the ROIs, so this
      measures the deformation rather than the error it leaves (a relative change of the local
      distance is 1.5 times that of c, since c ~ d^(-2/3), but the fitted plane sits between
      the bumps); it is taken as it is, which `netpose bench integrity` confirms (99.5 % within
      3 sigma on 2,000 frames);
    - what they cannot show: the tilt of the net between the ROIs and the optical axis. A plane
      is known best at its ROIs' centroid; the range on the axis is that plane carried across
      the lever from the centroid to the axis (`axis_leverage`, in units of the ROIs' own
      spread). The deformation seen over the ROIs' spread grows over the lever in proportion,
      and a net is never assumed flatter than `_UNSEEN_DEFORMATION` of its distance over that
      spread, even where the few ROIs of one side happen to agree perfectly.
    ROIs that surround the axis (lever ~0-1) keep the first part; a fit from one side of the
    image (a marker board over the rest, a steep view whose far side is unresolved) grows with
    the lever, which is issue 11's "use what is left without trusting a fit from one side".

    The normal is the slope of c over the ROIs: a deformation common to one side of them, not
    independent per ROI, tilts the fit by about its size over the ROIs' spread
    (`tilt_leverage`), however many ROIs there are (the fit's covariance assumed it averages
    down). The part they show counts in full; the part they cannot show only by how much less
    the ROIs span than the whole view (`_UNSEEN_TILT`): the normal reported is the net's over
    the view, and a fit over all of it leaves nothing unseen to carry. Crops of the real net
    frame disagree with it on the normal by 2-3 deg, where the fit's sigma alone claimed 0.5
    (now 1.4); crops of two SOLAQUA stills, by 9-13 deg, which this does not cover either
    (docs/estimator.md, Limits).
    """
    assert p.plane is not None
    if not agreeing:
        return 0.0, 0.0
    expected = relative_sigma_c(np.array([m.fit.relative_area_sigma for m in agreeing
                                          if m.fit is not None])) ** 2
    noise_rms2 = float(np.mean(expected)) if expected.size else 0.0
    seen = math.sqrt(max(0.0, p.plane.relative_rms**2 - noise_rms2))
    extent = _footprint(p, cell_area_m2)
    rays = np.array([m.ray for m in agreeing])
    lever = axis_leverage(rays, p.rotation @ np.array([0.0, 0.0, 1.0]), extent)
    relative = math.sqrt(seen**2 * (1.0 + lever) + _UNSEEN_DEFORMATION**2 * lever)
    pinned = tilt_leverage(rays, extent)
    # The view's own: its corners, edge midpoints and centre, a 3 x 3 grid whose variance is
    # twice that of the view filled evenly.
    whole = 2.0 * tilt_leverage(view_rays, 0.0)
    tilt = math.degrees(math.sqrt(seen**2 * pinned
                                  + _UNSEEN_TILT**2 * max(0.0, pinned - whole)))
    return relative, tilt


def _left_out_pull(p: _Pass, cell_area_m2: float) -> tuple[float, float, float]:
    """How far the ROIs that show the net's lattice but that the plane left out would pull
    it: the relative change of the distance and of the range on the optical axis, and the
    angle (deg) between the normals, from the pass's plane to the one through all of them.

    The plane's own sigma is made of the ROIs it kept, and it keeps those that agree with
    each other. On a real net that is not one plane (a fouled strip, a seam's pull, a bulge)
    the ROIs that show the net's lattice can split into two groups that each agree: which one
    the fit keeps then turns on noise, and each answer claims the small sigma of its own
    group (two noisy copies of the fouled-seam still: 14.2 +- 1.3 deg and 4.1 +- 2.6 deg).
    The ROIs left out are the net, not a fish (they show its lattice), so where they would
    move the plane is what the choice is uncertain by; half of it counts, as for the change
    between passes. A single stray ROI among many moves the plane little (rendered frames:
    3 of 1,282 valid outputs refused, `netpose bench integrity --frames 3000 --seed 7`)."""
    plane = p.plane
    on = [m for m in p.on_lattice if m.fit is not None]
    if plane is None or len(on) <= int(plane.used.sum()):
        return 0.0, 0.0, 0.0
    through = plane_through(np.array([m.ray for m in on]), np.array([m.area_norm for m in on]),
                            np.array([m.fit.relative_area_sigma for m in on
                                      if m.fit is not None]), cell_area_m2)
    if through is None:
        return 0.0, 0.0, 0.0
    normal, distance = through
    axis = p.rotation @ np.array([0.0, 0.0, 1.0])
    range_all = distance / max(float(normal @ axis), 1e-6)
    range_kept = plane.distance_m / max(float(plane.normal_away @ axis), 1e-6)
    angle = math.degrees(math.acos(min(1.0, float(normal @ plane.normal_away))))
    return (abs(distance / plane.distance_m - 1.0), abs(range_all / range_kept - 1.0), angle)


def _footprint(p: _Pass, cell_area_m2: float) -> float:
    """Side of a rectified ROI in the virtual camera's normalised units: `size` rectified
    pixels, `period_out` of them one mesh period, sqrt(cell area) / distance."""
    assert p.plane is not None
    return p.size / p.period_out * math.sqrt(cell_area_m2) / p.plane.distance_m


def _axis_disagreement(p: _Pass, cell_area_m2: float, plane_sigma: float) -> float:
    """How far, relative to the range, the plane misses the range that the ROI on the optical
    axis measures, when it clearly misses it (below); else 0.

    A ROI's cell area at ray r says c = (a / A)^(1/3) = r . m, so with the plane's normal kept
    the ROI alone puts the net at the plane's distance times (c_plane / c)^(3/2): on the axis,
    the range itself, hardly dependent on the tilt. The plane is fitted to the ROIs that agree
    with most others, and on a curved net (a real net billows, and bulges between its ropes)
    the ROIs around the view can agree on a plane that the one in the middle contradicts: the
    plane's range on the axis is then extrapolated from the sides, and its own sigma, made of
    the residuals of the ROIs it kept, does not see that. The ROI covering the axis (its
    rectified footprint holds the axis) is looked at whether the plane kept it or not; when it
    disagrees beyond the noise of both, and beyond what the plane itself counts as agreeing
    (`CONSENSUS_TOLERANCE` in c: a real net's cells differ a little from place to place), the
    reported range is uncertain by that disagreement.
    """
    plane = p.plane
    if plane is None or not p.on_lattice:
        return 0.0
    axis = p.rotation @ np.array([0.0, 0.0, 1.0])
    # Each ROI's offset from the axis where the rays cross z = 1 (its footprint is a square).
    offsets = [float(np.max(np.abs(m.ray[:2] / m.ray[2] - axis[:2] / axis[2])))
               for m in p.on_lattice]
    offset, nearest = min(zip(offsets, p.on_lattice, strict=True), key=lambda om: om[0])
    if nearest.fit is None or offset > 0.5 * _footprint(p, cell_area_m2):
        return 0.0
    c = math.cbrt(nearest.area_norm / cell_area_m2)
    predicted = plane.c_at(nearest.ray)
    if c <= 0.0 or predicted <= 0.0:
        return 0.0
    miss = abs((predicted / c) ** 1.5 - 1.0)
    own = 1.5 * float(relative_sigma_c(nearest.fit.relative_area_sigma))
    agreeing = (1.0 + CONSENSUS_TOLERANCE) ** 1.5 - 1.0
    return miss if miss > max(3.0 * math.hypot(plane_sigma, own), agreeing) else 0.0


def _overlap(rois: list[_Roi]) -> float:
    """Total footprint over the area the footprints cover (>= 1): overlapping ROIs share pixels,
    so their errors are not independent."""
    if not rois:
        return 1.0
    sq = [(m.geometry.center_full, max(m.footprint_px, 1.0)) for m in rois]
    total = sum(f * f for _, f in sq)
    xs = np.array([c[0] for c, _ in sq])
    ys = np.array([c[1] for c, _ in sq])
    fs = np.array([f for _, f in sq])
    x0, x1 = float((xs - fs / 2).min()), float((xs + fs / 2).max())
    y0, y1 = float((ys - fs / 2).min()), float((ys + fs / 2).max())
    step = max((x1 - x0), (y1 - y0)) / 64.0
    gx = np.arange(x0, x1, step) + step / 2
    gy = np.arange(y0, y1, step) + step / 2
    # Which grid columns and rows each footprint spans; a cell is covered when one footprint
    # spans both its column and its row (all footprints at once: a matrix product of the masks).
    in_x = np.abs(gx[None, :] - xs[:, None]) <= fs[:, None] / 2
    in_y = np.abs(gy[None, :] - ys[:, None]) <= fs[:, None] / 2
    covered = in_y.T.astype(np.float32) @ in_x.astype(np.float32)
    union = float(np.count_nonzero(covered)) * step * step
    return max(1.0, total / max(union, 1e-9))


def _thinned(grid: list[_Geometry], max_rois: int | None) -> list[_Geometry]:
    """Every other column of a grid that has more than `max_rois` ROIs (the outer columns
    stay, so the ROIs still span the frame)."""
    if max_rois is None or len(grid) <= max_rois:
        return grid
    xs = sorted({g.x0 for g in grid})
    keep = {x for i, x in enumerate(xs) if i % 2 == 0 or i == len(xs) - 1}
    return [g for g in grid if g.x0 in keep]


def _level_size(size: int, level: int) -> int:
    for _ in range(level):
        size = (size + 1) // 2
    return size


def _as_gray(frame: Image) -> Image:
    arr = to_gray(frame)
    if arr.dtype not in (np.uint8, np.uint16, np.float32):
        arr = arr.astype(np.float32)
    return arr


def _roi_result(m: _Roi, used: bool) -> RoiResult:
    size = round(m.footprint_px) if m.footprint_px > 0 else m.size * 2**m.level
    if m.fit is None or m.reciprocal_px is None:
        return RoiResult(center_px=m.geometry.center_full, size_px=size, level=m.level,
                         detected=False, peaks=m.peaks)
    # Columns e1, e2 of the dual basis: e_i . k_j = delta_ij, the inverse's rows (in floats:
    # this runs for every ROI of every frame, and numpy's cost per call is the most of it).
    (a, b), (c, d) = m.reciprocal_px.tolist()
    det = a * d - b * c
    e00, e01, e10, e11 = d / det, -c / det, -b / det, a / det  # edges[i, j]
    return RoiResult(
        center_px=m.geometry.center_full,
        size_px=size,
        level=m.level,
        detected=m.valid,
        reciprocal=((a, c), (b, d)),
        mesh_edges=((e00, e10), (e01, e11)),
        cell_area_px=abs(e00 * e11 - e01 * e10),
        snr_db=10.0 / math.log(10.0) * m.fit.mean_snr,
        inlier_fraction=m.fit.inlier_weight_fraction,
        peaks=m.peaks,
        used_in_fit=used,
    )


def _scale_proved(result: NetEstimate) -> NetEstimate:
    """`result` with its scale marked as proved on this frame (a detection only)."""
    if not result.detected or result.range_m is None:
        return result
    return replace(result, frames_since_scale_proof=0, scale_proved_range_m=result.range_m)


def _tracking_missed(tracked: NetEstimate) -> NetEstimate:
    """A tracked pass that did not confirm the prior, reported as it is (with no distance) when
    the caller defers the search: a net seen with too uncertain a plane stays seen."""
    if not tracked.detected:
        return tracked  # its reason as it is: callers match some reasons by their start
    # Capped as every refused estimate's confidence (`_verdict`): below any detection threshold.
    return NetEstimate(detected=False, confidence=min(tracked.confidence, 0.2),
                       rois=tracked.rois, rois_used=tracked.rois_used, level=tracked.level,
                       reason="tracking missed: the plane moved too far from the last one")


def _no_net(rois: list[_Roi], level: int, reason: str) -> NetEstimate:
    return NetEstimate(detected=False, confidence=0.0, level=level, reason=reason,
                       rois=tuple(_roi_result(m, False) for m in rois))


def _agrees(result: NetEstimate, seed: NetEstimate, rel: float = 0.08,
            degrees: float = 8.0) -> bool:
    """Does `result` land near `seed`'s plane?"""
    if not result.detected or result.normal is None or seed.normal is None:
        return False
    if result.distance_m is None or seed.distance_m is None:
        return False
    cos = float(np.dot(result.normal, seed.normal))
    return cos > math.cos(math.radians(degrees)) and abs(
        result.distance_m / seed.distance_m - 1.0
    ) < rel
