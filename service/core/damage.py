"""Net damage from the lattice: where the mesh that fits everywhere else does not hold.

Pure: one grey frame and the estimator's `NetEstimate` of it in, candidate holes out.

Method (docs/inspection.md):

1. **The lattice on the plane.** The estimate gives the plane (normal, distance) and, per ROI,
   the mesh lattice in pixels. Each ROI's reciprocal lattice is carried onto the plane through
   the lens and the plane's homography (k_plane = J^T k_pixel), and the ROIs' consensus gives
   the mesh's orientation in the plane; the configured mesh (bar length, opening angle) says
   which lattice vectors are the bars.
2. **A lattice image.** The frame is resampled on the net's own coordinates: S samples per
   bar along each bar family, so every cell of the net is an S x S block whose first row and
   column are its bars. The resampling goes through the lens model and reads a pyramid level
   at which the net is not undersampled; parts of the view where the mesh is finer than a few
   pixels, or seen too obliquely, are not inspected.
3. **Phase.** The plane and the lattice are known to a few per cent, which over tens of cells
   is a fraction of a cell: the knots' exact place is measured locally. Each cell's samples are
   demodulated at the lattice's fundamental of each bar family (a smooth complex amplitude,
   averaged over ~1.5 cells around), whose phase says where the twine is; the twine's polarity
   (dark or light) comes from the sign of the knots' cross term. The frame is resampled once
   more with the knots where the phase puts them.
4. **Bars.** For every bar: its twine contrast (middle half of the bar against the openings on
   both sides), in units of the contrast of its neighbours (the median of the bars of its
   family within 3 cells) and of their spread. An intact bar has a ratio near 1; a missing bar
   shows the background of the openings beside it, a ratio near 0. Fouling lowers the contrast
   of the neighbours too (the ratio stays), so does turbidity; a seam raises it.
5. **Holes.** Missing bars merge the openings they separated (union-find); each merged group
   is a candidate. It is a hole only when:
   - the lattice around it is there: the bars on its boundary are intact (a fish, a board or a
     rope hides the bars around what it hides as well);
   - it is small (at most `max_cells` cells, not longer than `max_extent_cells`): a rope or a
     seam lying across bars is long, a board or a fish is large;
   - its openings look like the openings around it (a hole shows what is behind the net, like
     any opening; a fish behind or in front changes their brightness);
   - every cell of it and of its ring was inspected (none beyond the frame's edge or the
     inspected region).
6. **Metric size.** The hole's cells span a known number of bars: its extent knot to knot is
   measured on the plane with the configured bar length along the plane's horizontal and
   vertical (the camera's right and down laid onto the plane), with the orientation measured.

Confirmation over several frames (the hole must stay put on the net while the ROV moves) is
`damage_track.py`'s job; this module judges one frame.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from service.core.camera import CameraModel
from service.core.damage_plan import InspectionPlanner, Window
from service.core.errors import ConfigError
from service.core.grey import to_gray
from service.core.mesh import MeshGeometry
from service.core.plane_frame import plane_axes, rotation_to_z
from service.core.results import NetEstimate

F64 = npt.NDArray[np.float64]
F32 = npt.NDArray[np.float32]
Image = npt.NDArray[Any]
Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]
Cell = tuple[int, int]  # (i, j): the opening with corner knots (i, j) .. (i + 1, j + 1)
Bar = tuple[int, int, int]  # (family, i, j): left (1) or top (2) bar of cell (i, j)

# Window lengths whose DCT matrices a detector keeps (the oldest goes first).
_DCT_CACHE_SIZES = 8


@dataclass(frozen=True)
class DamageSettings:
    """`[damage]`: net inspection (hole detection). The defaults are what the benchmark ran."""

    enabled: bool = True
    # Samples per bar in the lattice image (even; the bar's twine is its first sample).
    samples_per_cell: int = 8
    # Not inspected: where a cell is smaller than this in the frame (pixels, square root of its
    # area), or seen more obliquely than this (angle between the ray and the net's normal).
    min_cell_px: float = 4.5
    max_view_angle_deg: float = 65.0
    # Cells inspected in one frame at most: a larger view is inspected a window at a time,
    # candidates' places first, then what was inspected longest ago (damage_plan.py).
    max_cells_inspected: int = 1000
    # A bar is missing when its contrast is below this share of its neighbours' ...
    missing_ratio: float = 0.3
    # ... and below them by this many times their spread (noise and texture), while the
    # neighbours stand out of the openings by at least `min_lattice_snr` times that spread.
    missing_sigmas: float = 3.0
    min_lattice_snr: float = 3.5
    # A hole's missing bars together: their shortfalls in spreads, summed and divided by the
    # square root of their number (one cut bar must fall this far short on its own; four
    # missing around a knot may each fall half as far).
    hole_sigmas: float = 5.0
    # The bars around a hole: at least this share of them intact (ratio >= 0.6).
    min_ring_intact: float = 0.85
    # ... and at full strength together: their median contrast at least this share of their
    # neighbours'. A cut leaves the bars beside it whole; a patch of fouling fades out over
    # cells, so the bars around its dimmest part are dimmed too (median 0.5-0.8 on the
    # benchmark's patches, 0.83-1.3 around its holes).
    min_ring_ratio: float = 0.8
    # A hole merges at most this many cells and is at most this long (cells, either way).
    max_cells: int = 16
    max_extent_cells: int = 7
    # The openings of a hole differ from the openings around it by at most this share of the
    # twine contrast.
    max_opening_difference: float = 0.6
    # Evidence crop: this many times the hole's size in the image, at most this many pixels.
    crop_scale: float = 3.0
    crop_max_px: int = 160
    # Average share of the estimator's frame time the daemon lets inspection take (frames are
    # skipped to stay within it), or every n-th tracked frame when `every_n_frames` > 0.
    max_cost_fraction: float = 0.3
    every_n_frames: int = 0
    # Confirmation (damage_track.py), counted in *looks*: inspections whose judged region held
    # the candidate's place on the net. A hole is reported (once) when it was found in
    # `confirm_hits` of the last `confirm_looks` looks; a candidate is dropped when the looks
    # since its last sighting leave it no way to reach that. Three sightings, not two: before a
    # track's velocity is known its gate must allow for the net moving up to 0.6 m/s, wide
    # enough for two unrelated candidates on a patchily fouled net to meet in it; the third
    # must also agree with the velocity the first two give.
    confirm_hits: int = 3
    confirm_looks: int = 5
    # A candidate belongs to a track when within this distance on the net (plus the track's own
    # motion); a track not seen for this long ends.
    gate_m: float = 0.06
    track_timeout_s: float = 2.0
    # MAVLink STATUSTEXT to the pilot: at most one per this many seconds.
    notify_interval_s: float = 5.0

    def __post_init__(self) -> None:
        def bad(key: str, problem: str) -> ConfigError:
            return ConfigError(f"damage.{key}", problem)

        if self.samples_per_cell not in (6, 8, 10, 12):
            raise bad("samples_per_cell", "must be 6, 8, 10 or 12")
        if not 3.0 <= self.min_cell_px <= 20.0:
            raise bad("min_cell_px", "must be 3..20 px")
        if not 20.0 <= self.max_view_angle_deg <= 80.0:
            raise bad("max_view_angle_deg", "must be 20..80 deg")
        if not 0.0 < self.missing_ratio < 0.6:
            raise bad("missing_ratio", "must be between 0 and 0.6")
        if not 0.0 <= self.min_ring_ratio < 1.0:
            raise bad("min_ring_ratio", "must be in [0, 1)")
        if not 0.0 < self.max_cost_fraction <= 1.0:
            raise bad("max_cost_fraction", "must be in (0, 1]")
        if self.every_n_frames < 0:
            raise bad("every_n_frames", "must be >= 0 (0: by max_cost_fraction)")
        if not 2 <= self.max_cells <= 64:
            raise bad("max_cells", "must be 2..64")
        if not 1 <= self.confirm_hits <= 20:
            raise bad("confirm_hits", "must be 1..20")
        if not self.confirm_hits <= self.confirm_looks <= 50:
            raise bad("confirm_looks", f"must be confirm_hits ({self.confirm_hits})..50")
        for key in ("gate_m", "track_timeout_s", "notify_interval_s", "crop_scale"):
            if not getattr(self, key) > 0:
                raise bad(key, "must be > 0")


@dataclass(frozen=True, eq=False)
class HoleCandidate:
    """One place in one frame where bars are missing and the lattice around holds."""

    centre_px: Vec2  # in the frame
    box_px: tuple[float, float, float, float]  # x0, y0, x1, y1 of its knots in the frame
    cells: int  # mesh openings merged into the hole
    missing_bars: int
    width_m: float  # knot to knot on the net plane, along its horizontal
    height_m: float  # along its vertical
    plane_xy_m: Vec2  # centre on the net plane: right and down of the camera's foot point
    point_m: Vec3  # centre in the camera frame (x right, y down, z forward)
    range_m: float  # camera to the hole's centre
    significance: float  # how far its bars fall short of their neighbours together (spreads)
    ring_intact: float  # share of the bars around it that are intact
    crop: npt.NDArray[np.uint8] | None = field(default=None, repr=False)  # evidence
    # The hole's knots' box in the crop's pixels (to mark it on the evidence).
    crop_box_px: tuple[float, float, float, float] | None = None
    stats: Any = field(default=None, repr=False)

    @property
    def confidence(self) -> float:
        """0..1 from one frame: how clearly the bars are missing and the ring is intact."""
        clear = 1.0 - math.exp(-max(self.significance - 3.0, 0.0) / 3.0)
        return float(clear * min(1.0, max(0.0, (self.ring_intact - 0.7) / 0.3)))


@dataclass(frozen=True, eq=False)
class DamageScan:
    """What inspection saw in one frame."""

    candidates: tuple[HoleCandidate, ...] = ()
    inspected_cells: int = 0  # cells whose bars were judged
    # Bars sampled, and those clear enough against their neighbours to show a missing one.
    bars_sampled: int = 0
    bars_judgeable: int = 0
    levels: tuple[int, ...] = ()  # pyramid levels read (each cell from the one that suits it)
    reason: str = ""  # why nothing was inspected ("" when something was)
    timings_ms: dict[str, float] = field(default_factory=dict)
    # Groups of missing bars judged not to be holes: (centre pixel, cells, why), for the
    # benchmark's account of what it missed.
    rejected: tuple[tuple[Vec2, int, str], ...] = ()
    # For drawing and for confirmation: the inspected region of the frame as a polygon of
    # pixels (its outline), and the net geometry of this frame.
    outline_px: tuple[Vec2, ...] = ()
    geometry: NetFrame | None = None
    # Where a hole could be judged: cells with three inspected cells around them every way
    # (the ring a hole is judged by), as a polygon of pixels. A place outside it was not looked
    # at in this frame, whatever the outline says.
    judged_px: tuple[Vec2, ...] = ()
    # A view of more than `max_cells_inspected` cells is inspected a window at a time
    # (damage_plan.py): about how many windows the view needs (1: all of it at once), and how
    # many open candidates' places this frame's window was chosen to hold.
    windows: int = 1
    revisits: int = 0


@dataclass(frozen=True, eq=False)
class NetFrame:
    """The net plane of one frame in the camera frame: where a pixel's ray meets it, and the
    plane's horizontal/vertical axes (sizes and positions are given along them)."""

    normal: F64  # unit, towards the camera
    distance_m: float
    horizontal: F64
    vertical: F64

    def point_of_ray(self, ray: F64) -> F64 | None:
        """Camera-frame point where the undistorted ray (x, y, 1) meets the plane."""
        away = -self.normal
        denom = float(away @ ray)
        if denom <= 1e-6:
            return None
        return ray * (self.distance_m / denom)

    def plane_xy(self, point: F64) -> Vec2:
        """Coordinates on the plane (right, down) of a camera-frame point, from the foot of
        the perpendicular from the camera."""
        foot = -self.normal * self.distance_m
        rel = point - foot
        return float(rel @ self.horizontal), float(rel @ self.vertical)


def net_frame_of(estimate: NetEstimate) -> NetFrame | None:
    """The net plane of a frame's estimate (None without a detection)."""
    if not estimate.detected or estimate.normal is None or estimate.distance_m is None:
        return None
    normal = np.asarray(estimate.normal, dtype=np.float64)
    horizontal, vertical = plane_axes(normal)
    return NetFrame(normal, float(estimate.distance_m), horizontal, vertical)


@dataclass(frozen=True)
class _Lattice:
    """The net's lattice on the plane, in the virtual camera that faces it."""

    rotation: F64  # camera -> virtual (virtual z along the normal, away from the camera)
    distance: float
    bars: F64  # 2x2, columns b1, b2: bar vectors on the plane (metres, virtual x/y)
    origin: F64  # plane point (virtual x/y, metres) of lattice coordinates (0, 0)


class DamageDetector:
    """Finds holes in the net of one frame, given the estimator's plane and lattices."""

    def __init__(self, camera: CameraModel, mesh: MeshGeometry,
                 settings: DamageSettings | None = None) -> None:
        self.camera = camera
        self.mesh = mesh
        self.settings = settings or DamageSettings()
        self._cameras: dict[tuple[int, int], CameraModel] = {}
        self._rays: dict[tuple[int, int], tuple[F64, F64, F64]] = {}
        self._dcts: dict[int, F64] = {}  # DCT matrices by length: windows repeat their sizes
        self._carriers: dict[int, npt.NDArray[np.complex64]] = {}  # by samples per cell
        # Which part of a large view to inspect, and what was inspected (places on the net).
        self.planner = InspectionPlanner(mesh.bar_length_m)

    def _dct(self, n: int) -> F64:
        if n not in self._dcts:
            # Bounded: a daemon that sees every window size from a few cells to a few hundred
            # over hours would otherwise keep tens of megabytes of matrices it rarely reuses.
            if len(self._dcts) >= _DCT_CACHE_SIZES:
                del self._dcts[next(iter(self._dcts))]
            self._dcts[n] = _dct_matrix(n)
        return self._dcts[n]

    def _carrier(self, s: int) -> npt.NDArray[np.complex64]:
        """exp(-2 pi i q / s) for q < s: a cell's first harmonic over its s samples (built
        once per sample count, not per inspection; a handful of counts occur). Read-only."""
        carrier = self._carriers.get(s)
        if carrier is None:
            carrier = np.exp(-2j * np.pi * np.arange(s) / s).astype(np.complex64)
            carrier.flags.writeable = False
            self._carriers[s] = carrier
        return carrier

    def _camera(self, w: int, h: int) -> CameraModel:
        key = (w, h)
        if key not in self._cameras:
            self._cameras[key] = self.camera.scaled_to(w, h)
        return self._cameras[key]

    # -- per frame ---------------------------------------------------------------------------
    def inspect(self, frame: Image, estimate: NetEstimate,
                revisit: Sequence[Vec2] = ()) -> DamageScan:
        """Candidate holes in `frame`, whose net plane `estimate` measured (a detection).

        A view of more than `max_cells_inspected` cells is inspected a window at a time
        (`damage_plan.py`): one that holds the places on the net plane in `revisit` (open
        candidates, where they are predicted now) if it can, else the one whose cells were
        judged longest ago, so that the whole view is covered in few frames."""
        t0 = time.perf_counter()
        if not estimate.detected or estimate.normal is None or estimate.distance_m is None:
            return DamageScan(reason="no net plane in this frame")
        gray = to_gray(frame)
        h, w = gray.shape[:2]
        cam = self._camera(w, h)
        timings: dict[str, float] = {}
        lattice = self._lattice(cam, estimate)
        if lattice is None:
            return DamageScan(reason="the ROIs' lattices do not give the mesh's orientation")
        found_region = self._region(cam, lattice)
        if found_region is None:
            return DamageScan(reason="no part of the view shows the mesh resolved")
        region, seen = found_region
        net = net_frame_of(estimate)
        assert net is not None  # detected, with a normal and a distance (above)
        window = self._window(lattice, net, region, seen, revisit)
        i0, j0 = region[0] + window.i0, region[1] + window.j0
        n1, n2 = window.n1, window.n2
        timings["geometry"] = (time.perf_counter() - t0) * 1e3
        t1 = time.perf_counter()
        s = self.settings.samples_per_cell
        pyramid = _Pyramid(gray)
        coarse = self._coarse_pixels(cam, lattice, i0, j0, n1, n2, None, s // 2)
        levels = _cell_levels(coarse, s)
        # Where the knots are: a first look at half the samples, one level coarser (the twine
        # blurred wide enough for them), is enough for the phase of the fundamentals.
        lat, valid = _sample(pyramid, coarse, s // 2, levels + 1)
        polarity, shift = self._phase(lat, valid, n1, n2, s // 2)
        used = tuple(int(v) for v in np.unique(levels))
        timings["phase"] = (time.perf_counter() - t1) * 1e3
        if polarity == 0:
            return DamageScan(reason="no twine contrast in the inspected region", levels=used,
                              timings_ms=timings, windows=window.windows,
                              revisits=window.revisits)
        t1 = time.perf_counter()
        coarse = self._coarse_pixels(cam, lattice, i0, j0, n1, n2, shift, s)
        lat, valid = _sample(pyramid, coarse, s, levels)
        timings["sample"] = (time.perf_counter() - t1) * 1e3
        t1 = time.perf_counter()
        bars = _bar_statistics(lat, valid, n1, n2, s, polarity, self.settings.min_lattice_snr)
        found, rejected = self._holes(bars, n1, n2)
        timings["bars"] = (time.perf_counter() - t1) * 1e3
        t1 = time.perf_counter()
        candidates = tuple(
            self._candidate(gray, cam, lattice, net, cells, hole, i0, j0, shift)
            for cells, hole in found)
        timings["measure"] = (time.perf_counter() - t1) * 1e3
        timings["total"] = (time.perf_counter() - t0) * 1e3
        why = tuple(
            (_cell_pixel(coarse, cells), len(cells), reason) for cells, reason in rejected
            if len(cells) <= 4 * self.settings.max_cells)
        return DamageScan(candidates=candidates, inspected_cells=int(bars.inspected),
                          bars_sampled=bars.bars_sampled, bars_judgeable=bars.bars_judgeable,
                          levels=used, timings_ms=timings, outline_px=_outline(coarse, w, h),
                          geometry=net, rejected=why, windows=window.windows,
                          revisits=window.revisits,
                          judged_px=_outline(coarse, w, h, _judgeable(bars.cell_ok)))

    def _window(self, lat: _Lattice, net: NetFrame, region: tuple[int, int, int, int],
                seen: F64, revisit: Sequence[Vec2]) -> Window:
        """The window of the region inspected this time (damage_plan.py), in region cells."""
        i0, j0, n1, n2 = region
        # Cells in view: the hull of the resolved grid points, in region cells.
        view = np.zeros((n2, n1), dtype=np.uint8)
        hull = _hull(seen - np.array([i0, j0], dtype=np.float64))
        if hull is not None:
            import cv2

            cv2.fillConvexPoly(view, hull, 1)
        # Cell centres on the plane: the map from lattice to plane coordinates is affine.
        c0, c1, c2 = self._lattice_to_plane(lat, net, np.array(
            [[i0 + 0.5, j0 + 0.5], [i0 + 1.5, j0 + 0.5], [i0 + 0.5, j0 + 1.5]]))
        cells_xy = (c0 + np.arange(n1)[None, :, None] * (c1 - c0)
                    + np.arange(n2)[:, None, None] * (c2 - c0))
        places = self._plane_to_lattice(lat, net, np.array(revisit, dtype=np.float64)
                                        .reshape(-1, 2)) - np.array([i0, j0])
        return self.planner.choose(view.astype(bool), cells_xy,
                                   self.settings.max_cells_inspected, places)

    @staticmethod
    def _lattice_to_plane(lat: _Lattice, net: NetFrame, s: F64) -> F64:
        """Net-plane coordinates (NetFrame.plane_xy) of lattice coordinates s, shape (k, 2)."""
        q = lat.origin + s @ lat.bars.T
        pts = np.concatenate([q, np.full((len(q), 1), lat.distance)], axis=1) @ lat.rotation
        rel = pts + net.normal * net.distance_m
        return np.stack([rel @ net.horizontal, rel @ net.vertical], axis=-1)

    @staticmethod
    def _plane_to_lattice(lat: _Lattice, net: NetFrame, xy: F64) -> F64:
        """Lattice coordinates of net-plane coordinates (the inverse of _lattice_to_plane)."""
        if len(xy) == 0:
            return np.zeros((0, 2))
        pts = (-net.normal * net.distance_m + xy[:, :1] * net.horizontal
               + xy[:, 1:] * net.vertical)
        q = (pts @ lat.rotation.T)[:, :2] - lat.origin
        return np.asarray(np.linalg.solve(lat.bars, q.T).T, dtype=np.float64)

    # -- geometry ----------------------------------------------------------------------------
    def _lattice(self, cam: CameraModel, est: NetEstimate) -> _Lattice | None:
        """The mesh's bars on the plane from the ROIs' lattices (consensus), and the virtual
        camera facing the plane."""
        assert est.normal is not None and est.distance_m is not None
        away = -np.asarray(est.normal, dtype=np.float64)
        rotation = rotation_to_z(away)
        d = float(est.distance_m)
        rois = [r for r in est.rois if r.used_in_fit and r.reciprocal is not None]
        if not rois:
            rois = [r for r in est.rois if r.detected and r.reciprocal is not None]
        if not rois:
            return None
        centres = np.array([r.center_px for r in rois], dtype=np.float64)
        rays = np.concatenate([cam.undistort_pixels(centres), np.ones((len(rois), 1))], axis=1)
        virt = rays @ rotation.T
        ok = virt[:, 2] > 1e-6
        q = virt[:, :2] / np.where(ok, virt[:, 2], 1.0)[:, None] * d
        eps = 1e-3 * d
        probes = np.concatenate([q, q + [eps, 0.0], q + [0.0, eps]], axis=0)
        px = self._project_plane(cam, rotation, d, probes)
        k = len(rois)
        jac = np.stack([(px[k:2 * k] - px[:k]) / eps, (px[2 * k:] - px[:k]) / eps], axis=2)
        bases = []
        weights = []
        for m, roi in enumerate(rois):
            if not ok[m]:
                continue
            assert roi.reciprocal is not None
            k_px = np.array(roi.reciprocal, dtype=np.float64).T  # columns k1, k2 (cycles/px)
            bases.append(_reduce(jac[m].T @ k_px))  # cycles per metre on the plane
            weights.append(roi.snr_db * roi.inlier_fraction)
        if not bases:
            return None
        recip = _consensus(bases, weights)
        if recip is None:
            return None
        edges = np.asarray(np.linalg.inv(recip).T, dtype=np.float64)  # real-space basis, m
        bars = self._bar_pair(edges)
        if bars is None:
            return None
        return _Lattice(rotation, d, bars, np.zeros(2))

    def _bar_pair(self, edges: F64) -> F64 | None:
        """The two lattice vectors that are the bars (columns, metres on the plane): the pair
        among the reduced basis and its sums closest to the configured mesh (bar length,
        opening angle). The measured vectors are kept (the twine is where the image has it:
        real nets are stretched and sheared a little), so long as they are the configured
        mesh within the estimator's own tolerances (bars within 25 % of each other and of the
        configured length, the opening angle within 25 degrees)."""
        a, b = edges[:, 0], edges[:, 1]
        length = self.mesh.bar_length_m
        alpha = min(self.mesh.opening_angle_deg, 180.0 - self.mesh.opening_angle_deg)
        best: tuple[float, F64, F64, float, float] | None = None
        for u, v in ((a, b), (b, b - a), (b, b + a), (a, a - b), (a, a + b)):
            lu, lv = float(np.linalg.norm(u)), float(np.linalg.norm(v))
            angle = math.degrees(math.acos(float(np.clip(abs(u @ v) / (lu * lv), 0.0, 1.0))))
            aspect = abs(math.log(lu / lv))
            scale = abs(math.log(math.sqrt(lu * lv) / length))
            err = abs(angle - alpha)
            score = aspect + scale + err / 20.0
            if best is None or score < best[0]:
                best = (score, u, v, aspect + scale, err)
        assert best is not None
        _, u, v, size_err, angle_err = best
        if size_err > math.log(1.25) or angle_err > 25.0:
            return None
        if float(u @ v) < 0:
            v = -v
        return np.stack([u, v], axis=1)

    def _project_plane(self, cam: CameraModel, rotation: F64, d: float, q: F64) -> F64:
        """Frame pixels of plane points q (virtual x/y, metres)."""
        pts_v = np.concatenate([q, np.full((len(q), 1), d)], axis=1)
        pts_c = pts_v @ rotation  # virtual -> camera (rotation is orthonormal)
        z = np.maximum(pts_c[:, 2:3], 1e-9)
        return cam.project_normalized(pts_c[:, :2] / z)

    def _grid_rays(self, cam: CameraModel) -> tuple[F64, F64, F64]:
        """A grid of pixels over the frame (about 24 rows) and their rays, once per size."""
        key = (cam.width, cam.height)
        if key not in self._rays:
            w, h = cam.width, cam.height
            step = max(8, min(w, h) // 24)
            xs = np.arange(step / 2, w, step)
            ys = np.arange(step / 2, h, step)
            grid = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
            rays = np.concatenate([cam.undistort_pixels(grid), np.ones((len(grid), 1))], axis=1)
            self._rays[key] = (xs, ys, rays)
        return self._rays[key]

    def _region(self, cam: CameraModel, lat: _Lattice
                ) -> tuple[tuple[int, int, int, int], F64] | None:
        """Cells to inspect (first cell, counts): where the cells are at least `min_cell_px`
        and seen within `max_view_angle_deg`; and the lattice coordinates of the grid points
        there (the view's shape in cells)."""
        st = self.settings
        xs, ys, rays = self._grid_rays(cam)
        step = float(xs[1] - xs[0]) if len(xs) > 1 else 1.0
        virt = rays @ lat.rotation.T
        cos_view = virt[:, 2] / np.linalg.norm(virt, axis=1)
        ok = cos_view > math.cos(math.radians(st.max_view_angle_deg))
        q = virt[:, :2] / np.where(virt[:, 2] > 1e-6, virt[:, 2], 1.0)[:, None] * lat.distance
        s = (q - lat.origin) @ np.linalg.inv(lat.bars).T
        # Cell size in pixels at each grid point: the pixel step over the lattice step.
        sg = s.reshape(len(ys), len(xs), 2)
        dsx = np.asarray(np.gradient(sg, axis=1), dtype=np.float64) / step
        dsy = np.asarray(np.gradient(sg, axis=0), dtype=np.float64) / step
        det = np.abs(dsx[..., 0] * dsy[..., 1] - dsx[..., 1] * dsy[..., 0]).reshape(-1)
        cell_px = 1.0 / np.sqrt(np.maximum(det, 1e-12))
        ok &= cell_px >= st.min_cell_px
        if ok.sum() < 4:
            return None
        lo = np.floor(s[ok].min(axis=0)).astype(int)
        hi = np.ceil(s[ok].max(axis=0)).astype(int)
        return (int(lo[0]), int(lo[1]), int(hi[0] - lo[0]), int(hi[1] - lo[1])), s[ok]

    def _coarse_pixels(self, cam: CameraModel, lat: _Lattice, i0: int, j0: int, n1: int,
                       n2: int, shift: F64 | None, samples: int) -> F64:
        """Frame pixels of the lattice points at the sample positions S k + (S - 1) / 2 of
        cells k = -1 .. n (one cell of margin each side), shifted by `shift` (cells, per cell:
        where the knots really are), shape (n2 + 2, n1 + 2, 2)."""
        off = (samples - 1) / (2.0 * samples)
        k1 = np.arange(-1, n1 + 1) + i0 + off
        k2 = np.arange(-1, n2 + 1) + j0 + off
        g1, g2 = np.meshgrid(k1, k2)
        if shift is not None:
            pad = np.pad(shift, ((1, 1), (1, 1), (0, 0)), mode="edge")
            g1 = g1 + pad[..., 0]
            g2 = g2 + pad[..., 1]
        sv = np.stack([g1, g2], axis=-1).reshape(-1, 2)
        q = lat.origin + sv @ lat.bars.T
        px = self._project_plane(cam, lat.rotation, lat.distance, q)
        return px.reshape(n2 + 2, n1 + 2, 2)

    # -- phase -------------------------------------------------------------------------------
    def _phase(self, lat: F32, valid: npt.NDArray[np.bool_], n1: int, n2: int, s: int
               ) -> tuple[int, F64]:
        """Twine polarity (+1 light, -1 dark, 0 none) and, per cell, where the knots are
        relative to the nominal lattice (cells, each family), unwrapped over the region."""
        carrier = self._carrier(s)
        block = lat.reshape(n2, s, n1, s)
        ok = _cells_valid(valid, n1, n2, s)
        across = block @ carrier  # (n2, s, n1): each row of a cell at family 1's carrier
        z1 = across.mean(axis=1)  # (n2, n1)
        z2 = np.einsum("jqi,q->ji", block.mean(axis=3), carrier)
        cross = np.einsum("jqi,q->ji", across, carrier) / s
        # The knots' cross term has the opposite sign of the twine's (1 - (1 - p1)(1 - p2) has
        # -p1 p2 in it), whatever the twine's width: that gives its polarity.
        prod = cross * np.conj(z1) * np.conj(z2)
        total = complex(prod[ok].sum()) if ok.any() else 0j
        if total.real == 0.0:
            return 0, np.zeros((n2, n1, 2))
        polarity = -1 if total.real > 0 else 1
        weight = ok.astype(np.float64)
        out = np.zeros((n2, n1, 2))
        for f, z in enumerate((z1, z2)):
            zs = _smooth_complex(polarity * z * weight, 1.5)
            out[..., f] = -_unwrap(zs, self._dct(n2), self._dct(n1)) / (2 * np.pi)
        return polarity, out

    # -- holes -------------------------------------------------------------------------------
    def _holes(self, bars: _Bars, n1: int, n2: int
               ) -> tuple[list[tuple[frozenset[Cell], _HoleStats]],
                          list[tuple[frozenset[Cell], str]]]:
        """Groups of openings merged by missing bars: those judged holes, and the others with
        why not."""
        st = self.settings
        missing1 = bars.missing(1, st)
        missing2 = bars.missing(2, st)
        if not missing1.any() and not missing2.any():
            return [], []
        parent: dict[Cell, Cell] = {}

        def find(c: Cell) -> Cell:
            while parent.setdefault(c, c) != c:
                parent[c] = parent[parent[c]]
                c = parent[c]
            return c

        def union(a: Cell, b: Cell) -> None:
            ra, rb = find(a), find(b)
            if ra != rb:
                parent[ra] = rb

        # Bar (1, i, j) separates cells (i - 1, j) and (i, j); (2, i, j): (i, j - 1), (i, j).
        for j, i in zip(*np.nonzero(missing1), strict=True):
            union((int(i) - 1, int(j)), (int(i), int(j)))
        for j, i in zip(*np.nonzero(missing2), strict=True):
            union((int(i), int(j) - 1), (int(i), int(j)))
        groups: dict[Cell, set[Cell]] = {}
        for c in list(parent):
            groups.setdefault(find(c), set()).add(c)
        holes = []
        rejected = []
        for members in groups.values():
            cells = frozenset(members)
            verdict = self._judge(bars, cells, (missing1, missing2), n1, n2)
            if isinstance(verdict, str):
                rejected.append((cells, verdict))
            else:
                holes.append((cells, verdict))
        return holes, rejected

    def _judge(self, bars: _Bars, cells: frozenset[Cell],
               missing: tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_]],
               n1: int, n2: int) -> _HoleStats | str:
        """A hole's statistics, or why these merged openings are not a hole."""
        st = self.settings
        ii = [i for i, _ in cells]
        jj = [j for _, j in cells]
        if len(cells) > st.max_cells:
            return f"too large ({len(cells)} cells)"
        extent = max(max(ii) - min(ii), max(jj) - min(jj)) + 1
        if extent > st.max_extent_cells:
            return f"too long ({extent} cells)"
        # Every cell and the cells around it inside the inspected region.
        if min(ii) < 3 or min(jj) < 3 or max(ii) > n1 - 4 or max(jj) > n2 - 4:
            return "at the edge of the inspected region"
        for i, j in cells:
            if not bars.cell_ok[j - 3 : j + 4, i - 3 : i + 4].all():
                return "at the edge of the inspected region"
        inner: set[Bar] = set()
        ring: set[Bar] = set()
        for i, j in cells:
            # The four bars of cell (i, j): (1, i, j) left, (1, i + 1, j) right, (2, i, j) top,
            # (2, i, j + 1) bottom; each to the neighbour across it.
            for bar, other in (((1, i, j), (i - 1, j)), ((1, i + 1, j), (i + 1, j)),
                               ((2, i, j), (i, j - 1)), ((2, i, j + 1), (i, j + 1))):
                (inner if other in cells else ring).add(bar)
        broken = [b for b in sorted(ring) if bars.broken(*b, 0.6)]
        intact = 1.0 - len(broken) / max(len(ring), 1)
        if intact < st.min_ring_intact:
            return f"the bars around it are not intact ({intact:.0%})"
        ring_ratio = float(np.median([bars.ratio(*b) for b in sorted(ring)]))
        if ring_ratio < st.min_ring_ratio:
            return f"the bars around it are dimmed ({ring_ratio:.2f} of their neighbours'): " \
                "fouling fading out, not a cut"
        # One cell further out: no bar missing there either (a streak of light or a rope
        # crossing parallel bars leaves a row of them; a hole is alone).
        near = {(i + di, j + dj) for i, j in cells for di in (-1, 0, 1) for dj in (-1, 0, 1)}
        outer: set[Bar] = set()
        for i, j in near - set(cells):
            outer.update({(1, i, j), (1, i + 1, j), (2, i, j), (2, i, j + 1)})
        outer -= ring
        weak = [b for b in sorted(outer) if bars.broken(*b, 0.6)]
        if any(bars.missing_at(*b, 0.35) for b in weak) or len(weak) > (
                1.0 - st.min_ring_intact) * len(outer):
            return "bars missing or weak one cell further out"
        # And no more faint bars there than noise explains (a rope or a seam lying on the net
        # hides the bars along it, each only a little where it is thin or blurred).
        wide = {(i + di, j + dj) for i, j in cells for di in range(-2, 3) for dj in range(-2, 3)}
        around: set[Bar] = set()
        for i, j in wide - set(cells):
            around.update({(1, i, j), (1, i + 1, j), (2, i, j), (2, i, j + 1)})
        ratios = np.array([bars.ratio(*b) for b in sorted(around - inner)])
        if float(np.mean(ratios < 0.5)) > 0.08 or float(np.mean(ratios < 0.3)) > 0.03:
            return "faint bars around it (a rope, a seam or an edge)"
        gone = [b for b in sorted(inner) if missing[b[0] - 1][b[2], b[1]]]
        if not gone:
            return "no bar missing inside"
        sig = float(sum(bars.significance(*b) for b in gone) / math.sqrt(len(gone)))
        if sig < st.hole_sigmas:
            return f"too faint ({sig:.1f} spreads together)"
        # The openings of the hole against the openings around it, in twine contrasts.
        inside = np.array([bars.cell[j, i] for i, j in cells])
        outside = np.array([bars.cell[j, i] for i, j in sorted(near - set(cells))])
        scale = float(np.median([abs(bars.reference(*b)) for b in sorted(ring)]))
        diff = abs(float(np.median(inside)) - float(np.median(outside))) / max(scale, 1e-6)
        if diff > st.max_opening_difference:
            return f"its openings differ from those around ({diff:.1f} twine contrasts)"
        around_ratio = float(np.median([bars.ratio(*b) for b in sorted(ring | outer)]))
        worst = float(min(bars.ratio(*b) for b in sorted(ring | outer)))
        gone_ratio = float(max(bars.ratio(*b) for b in gone))
        return _HoleStats(missing_bars=len(gone), significance=sig, ring_intact=intact,
                          ring_ratio=ring_ratio, opening_difference=diff,
                          around_ratio=around_ratio,
                          worst_around=worst, gone_ratio=gone_ratio)

    def _candidate(self, gray: Image, cam: CameraModel, lat: _Lattice, net: NetFrame,
                   cells: frozenset[tuple[int, int]], hole: _HoleStats, i0: int, j0: int,
                   shift: F64) -> HoleCandidate:
        """Size, place and evidence of a hole whose cells are given in region indices."""
        knots = sorted({(i + di, j + dj) for i, j in cells for di in (0, 1) for dj in (0, 1)})
        k = np.array(knots, dtype=np.float64)
        # Knots where the phase puts them (the shift of the cell each knot belongs to).
        sh = np.array([shift[min(max(j, 0), shift.shape[0] - 1),
                             min(max(i, 0), shift.shape[1] - 1)] for i, j in knots])
        sv = k + np.array([i0, j0]) + sh
        q = lat.origin + sv @ lat.bars.T
        pts_v = np.concatenate([q, np.full((len(q), 1), lat.distance)], axis=1)
        pts = pts_v @ lat.rotation  # camera frame
        px = cam.project_normalized(pts[:, :2] / pts[:, 2:3])
        width = float(np.ptp(pts @ net.horizontal))
        height = float(np.ptp(pts @ net.vertical))
        centre = pts.mean(axis=0)
        c_px = cam.project_normalized(centre[:2] / centre[2])
        box = (float(px[:, 0].min()), float(px[:, 1].min()), float(px[:, 0].max()),
               float(px[:, 1].max()))
        crop, crop_box = _crop(gray, box, self.settings)
        return HoleCandidate(
            centre_px=(float(c_px[0]), float(c_px[1])), box_px=box, cells=len(cells),
            missing_bars=hole.missing_bars, width_m=width, height_m=height,
            plane_xy_m=net.plane_xy(centre),
            point_m=(float(centre[0]), float(centre[1]), float(centre[2])),
            range_m=float(np.linalg.norm(centre)), significance=hole.significance,
            ring_intact=hole.ring_intact, crop=crop, stats=hole, crop_box_px=crop_box,
        )


@dataclass(frozen=True)
class _HoleStats:
    missing_bars: int
    significance: float
    ring_intact: float
    ring_ratio: float = 1.0
    opening_difference: float = 0.0
    around_ratio: float = 1.0
    worst_around: float = 1.0
    gone_ratio: float = 0.0


@dataclass(frozen=True)
class _Bars:
    """Per-bar statistics of a lattice image. Arrays are indexed [j, i]: bar (1, i, j) is the
    family-1 bar on the left of cell (i, j), bar (2, i, j) the family-2 bar on its top.

    `contrast`: the twine's contrast (polarity applied: positive for twine) of the bar's middle
    half against the straight line between the openings on its two sides; `ref`: the same of
    its neighbours (robust local mean); `sigma`: how uncertain a bar's contrast is - the local
    spread of neighbouring bars' contrasts, and the background's step between the openings on
    its two sides (the step's place between them is unknown: a fish's edge behind the net)."""

    contrast: tuple[F64, F64]
    ref: tuple[F64, F64]
    sigma: tuple[F64, F64]
    usable: tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_]]
    # The same over the middle third of each bar only (`gap`): whether a bar is missing is
    # judged there, where a cut leaves no twine whatever its stubs.
    gap: tuple[F64, F64]
    gap_ref: tuple[F64, F64]
    gap_sigma: tuple[F64, F64]
    gap_usable: tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_]]
    cell: F64
    cell_ok: npt.NDArray[np.bool_]
    inspected: int
    # Bars sampled (both families), and those among them whose neighbours stand out clearly
    # enough (min_lattice_snr) for a missing middle third to show: on fouled twine far fewer.
    bars_sampled: int = 0
    bars_judgeable: int = 0

    def reference(self, fam: int, i: int, j: int) -> float:
        """The contrast of the bar's neighbours (its family, within 3 cells)."""
        return float(self.ref[fam - 1][j, i])

    def ratio(self, fam: int, i: int, j: int) -> float:
        f = fam - 1
        if not self.usable[f][j, i]:
            return 0.0
        return float(self.contrast[f][j, i] / self.ref[f][j, i])

    def significance(self, fam: int, i: int, j: int) -> float:
        """How many sigmas the bar's middle third falls short of its neighbours'. A bar that
        is gone shows the openings beside it (contrast 0): reading lighter than them is light
        on the bar (a streak, a speck), not more of the bar gone, so it counts as 0."""
        f = fam - 1
        gap = max(float(self.gap[f][j, i]), 0.0)
        return float((self.gap_ref[f][j, i] - gap) / self.gap_sigma[f][j, i])

    def broken(self, fam: int, i: int, j: int, ratio: float) -> bool:
        """The bar is clearly weaker than `ratio` of its neighbours (or cannot be judged)."""
        f = fam - 1
        if not self.usable[f][j, i]:
            return True
        c, r, sg = self.contrast[f][j, i], self.ref[f][j, i], self.sigma[f][j, i]
        return bool(c < ratio * r and r - c > 3.0 * sg)

    def missing_at(self, fam: int, i: int, j: int, ratio: float) -> bool:
        """The bar can be judged and is clearly weaker than `ratio` of its neighbours."""
        return self.usable[fam - 1][j, i] and self.broken(fam, i, j, ratio)

    def missing(self, fam: int, st: DamageSettings) -> npt.NDArray[np.bool_]:
        """Bars cut: their middle third is gone (whatever stubs the cut left on the knots),
        and the bar as a whole falls short of its neighbours as well (a dip in the middle of
        an otherwise intact bar, a speck or a thin place of the twine, is not a cut)."""
        f = fam - 1
        c, r, sg = self.gap[f], self.gap_ref[f], self.gap_sigma[f]
        whole, whole_ref, whole_sigma = self.contrast[f], self.ref[f], self.sigma[f]
        # Gone, not inverted: where a bar is missing its place looks like the openings beside
        # it; a streak of light along a bar makes it lighter than them.
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.asarray(self.gap_usable[f] & (c < st.missing_ratio * r)
                              & (r - c > st.missing_sigmas * sg)
                              & (c > -st.missing_ratio * r - 2.0 * sg)
                              & self.usable[f]
                              & (whole_ref - whole > st.missing_sigmas * whole_sigma),
                              dtype=bool)


def _across_bars(lat: F32, n1: int, n2: int, s: int) -> tuple[F32, F32]:
    """Profiles across every bar, row by row: for the family-1 bar on the left of cell
    (i, j) and the family-2 bar on its top, the lattice image at offsets -S/2 .. S/2 samples
    from the bar's line (index S/2 is the line), for each sample along the middle half of the
    bar. Shape (n2, n1, rows, S + 1) each; the first column and row wrap around (those bars
    are not used)."""
    block = lat.reshape(n2, s, n1, s)
    mid = slice(s // 4, s - s // 4 + 1)
    half = s // 2
    m1 = block[:, mid, :, :].transpose(0, 2, 1, 3)  # (n2, n1, rows, s)
    m2 = block[:, :, :, mid].transpose(0, 2, 3, 1)  # (n2, n1, rows, s)
    a1 = np.concatenate([np.roll(m1, 1, axis=1)[..., half:], m1[..., : half + 1]], axis=3)
    a2 = np.concatenate([np.roll(m2, 1, axis=0)[..., half:], m2[..., : half + 1]], axis=3)
    return np.asarray(a1, dtype=np.float32), np.asarray(a2, dtype=np.float32)


def _cells_valid(valid: npt.NDArray[np.bool_], n1: int, n2: int, s: int
                 ) -> npt.NDArray[np.bool_]:
    """(n2, n1): the cells of a lattice image (S x S samples each) whose samples are all valid.
    Down each cell's rows first (a reduction numpy runs over whole rows), then across its
    columns element-wise: one reduction over both axes at once took five times as long."""
    rows_ok = valid.reshape(n2, s, n1 * s).all(axis=1).reshape(n2, n1, s)
    return np.asarray(functools.reduce(np.logical_and, np.moveaxis(rows_ok, 2, 0)), dtype=bool)


def _bar_statistics(lat: F32, valid: npt.NDArray[np.bool_], n1: int, n2: int, s: int,
                    polarity: int, min_snr: float) -> _Bars:
    """Twine contrast of every bar against the background beside it, and its neighbours'.

    The local intact net is the mean profile across the bars of the cells around (7 x 7): its
    sign is the twine's polarity there (dark twine is lighter than a dark fish behind the
    net), and it says where the background is on either side of a bar (the nearest place
    within a quarter of the profile's contrast of the opening's level; the middle of the
    opening when the twine is fouled and thick). A bar's contrast: along the middle half of
    the bar, the twine's value (the strongest within one sample of the line: real bars are not
    straight) against the mean of the background on its two sides."""
    import cv2

    okc = _cells_valid(valid, n1, n2, s)
    core = slice(s // 2 - 1, s // 2 + 2)
    cell = lat.reshape(n2, s, n1, s)[:, core, :, core].mean(axis=(1, 3)).astype(np.float64)
    ok1 = okc & np.roll(okc, 1, axis=1)
    ok1[:, 0] = False
    ok2 = okc & np.roll(okc, 1, axis=0)
    ok2[0, :] = False
    half = s // 2
    # The middle third of the bar, as rows of the middle half: a torn bar keeps stubs of up
    # to a third of a bar on its knots, so its twine is surely gone only there.
    third = slice(-(-s // 3) - s // 4, 2 * s // 3 - s // 4 + 1)
    contrasts, gaps, steps = [], [], []
    del polarity  # the local profile decides, bar by bar
    for rows, ok in zip(_across_bars(lat, n1, n2, s), (ok1, ok2), strict=True):
        prof = rows.mean(axis=2)  # (n2, n1, s + 1)
        w = ok.astype(np.float32)
        num = cv2.boxFilter(prof * w[..., None], -1, (7, 7), normalize=False,
                            borderType=cv2.BORDER_CONSTANT)
        den = cv2.boxFilter(w, -1, (7, 7), normalize=False, borderType=cv2.BORDER_CONSTANT)
        local = np.asarray(num, dtype=np.float32).reshape(prof.shape) / np.maximum(
            np.asarray(den, dtype=np.float32), 1.0)[..., None]
        sign = np.where(local[..., half] >= 0.5 * (local[..., 0] + local[..., -1]), 1.0,
                        -1.0).astype(np.float32)
        local = local * sign[..., None]
        # Element-wise over the profile's few samples: numpy's reduction over a short last
        # axis costs several times more than these calls (the same values).
        lo = functools.reduce(np.minimum, np.moveaxis(local, 2, 0))
        hi = functools.reduce(np.maximum, np.moveaxis(local, 2, 0))
        level = (local - lo[..., None]) / np.maximum(hi - lo, 1e-6)[..., None]
        on = level >= 0.5
        on[..., half] = True
        sides = 0.5 * (level[..., half + 1 :] + level[..., half - 1 :: -1][..., : half])
        beyond = np.arange(1, half + 1)[None, None, :] > np.argmax(~on[..., half:], axis=2)[
            ..., None] - 1
        flat = (sides <= 0.25) & beyond
        k = np.where(flat.any(axis=2), np.argmax(flat, axis=2) + 1, half)
        line = rows[..., half - 1 : half + 2] * sign[..., None, None]
        strongest = np.maximum(np.maximum(line[..., 0], line[..., 1]),
                               line[..., 2])  # (n2, n1, rows)
        # The profile across the bar, along its middle half, with the twine's sign: the mean
        # of the signed rows is the signed mean (a sign change is exact).
        across = prof * sign[..., None]
        left = np.take_along_axis(across, (half - k)[..., None], axis=2)[..., 0]
        right = np.take_along_axis(across, (half + k)[..., None], axis=2)[..., 0]
        background = 0.5 * (left + right)
        contrasts.append(np.asarray(strongest.mean(axis=2) - background, dtype=np.float64))
        gaps.append(np.asarray(strongest[..., third].mean(axis=2) - background,
                               dtype=np.float64))
        steps.append(np.abs(np.asarray(right - left, dtype=np.float64)))
    # Both families' bars, whole and middle thirds, judged as four channels of one stack: the
    # arrays are a few hundred cells, so each filter call's overhead was most of the cost.
    ref, sigma, usable = _judged_against_neighbours(
        np.stack(contrasts + gaps, axis=-1), np.stack((ok1, ok2, ok1, ok2), axis=-1),
        np.stack(steps + steps, axis=-1), min_snr)
    whole = [(ref[..., i], sigma[..., i], usable[..., i]) for i in (0, 1)]
    middle = [(ref[..., i], sigma[..., i], usable[..., i]) for i in (2, 3)]
    return _Bars(contrast=(contrasts[0], contrasts[1]), ref=(whole[0][0], whole[1][0]),
                 sigma=(whole[0][1], whole[1][1]), usable=(whole[0][2], whole[1][2]),
                 gap=(gaps[0], gaps[1]), gap_ref=(middle[0][0], middle[1][0]),
                 gap_sigma=(middle[0][1], middle[1][1]), gap_usable=(middle[0][2], middle[1][2]),
                 cell=cell, cell_ok=okc, inspected=int(okc.sum()),
                 bars_sampled=int(ok1.sum() + ok2.sum()),
                 bars_judgeable=int(usable[..., 2:4].sum()))


def _judged_against_neighbours(c: F64, ok: npt.NDArray[np.bool_], step: F64, min_snr: float
                               ) -> tuple[F64, F64, npt.NDArray[np.bool_]]:
    """Bar contrasts `c` in units of their neighbours': the local reference (robust mean of
    the family within 3 cells), the uncertainty of a bar's contrast against it, and where the
    neighbours stand out of the openings by `min_snr` times their spread. Arrays of cells
    (rows, columns), or stacks of them as channels (rows, columns, n) judged each on its own."""
    ref, spread = _local_level(c, ok, 7)
    # The background's step across the bar: where it lies between the two sides is unknown
    # (a fish's edge behind the net), so it blurs what the bar's contrast means.
    sigma = np.sqrt(spread**2 + (0.15 * step) ** 2)
    with np.errstate(invalid="ignore"):
        usable = np.asarray(ok & (ref > min_snr * spread), dtype=bool)
    return ref, sigma, usable


def _smooth_complex(z: npt.NDArray[np.complexfloating[Any, Any]], sigma: float
                    ) -> npt.NDArray[np.complex128]:
    import cv2

    parts = [np.asarray(cv2.GaussianBlur(np.ascontiguousarray(p, dtype=np.float32), (0, 0),
                                         sigma), dtype=np.float64) for p in (z.real, z.imag)]
    return parts[0] + 1j * parts[1]


def _unwrap(z: npt.NDArray[np.complex128], c2: F64, c1: F64) -> F64:
    """Phase of a smooth complex field, unwrapped: least-squares integration of its wrapped
    gradients (Ghiglia and Romero's DCT solution of the Poisson equation), with the constant
    that best matches the wrapped phase. Gradients where the field is weak (a hole, a board)
    are left out. `c2`, `c1`: `_dct_matrix` of the field's rows and columns."""
    n2, n1 = z.shape
    mag = np.abs(z)
    strong = mag > 0.2 * float(np.median(mag[mag > 0])) if (mag > 0).any() else mag > 0
    gx = np.zeros((n2, n1))
    gy = np.zeros((n2, n1))
    gx[:, :-1] = np.angle(z[:, 1:] * np.conj(z[:, :-1])) * (strong[:, 1:] & strong[:, :-1])
    gy[:-1, :] = np.angle(z[1:, :] * np.conj(z[:-1, :])) * (strong[1:, :] & strong[:-1, :])
    rho = gx.copy()
    rho[:, 1:] -= gx[:, :-1]
    rho += gy
    rho[1:, :] -= gy[:-1, :]
    # The orthonormal 2D DCT-II as two matrix products: these grids are at most a few hundred
    # cells a side, where that is as fast as an FFT and keeps scipy out of the frame loop.
    d = c2 @ rho @ c1.T
    ii = np.arange(n1)
    jj = np.arange(n2)[:, None]
    denom = 2.0 * np.cos(np.pi * ii / n1) + 2.0 * np.cos(np.pi * jj / n2) - 4.0
    denom[0, 0] = 1.0
    d = d / denom
    d[0, 0] = 0.0
    phi = np.asarray(c2.T @ d @ c1, dtype=np.float64)
    offset = float(np.angle(np.sum(z * np.exp(-1j * phi))))
    return phi + offset


def _dct_matrix(n: int) -> F64:
    """The orthonormal DCT-II of length n as a matrix (scipy's `dct(type=2, norm="ortho")`):
    row k is sqrt(2 / n) cos(pi (2 i + 1) k / 2n), row 0 divided by sqrt(2)."""
    k = np.arange(n)[:, None]
    i = np.arange(n)[None, :]
    c = np.sqrt(2.0 / n) * np.cos(np.pi * (2 * i + 1) * k / (2 * n))
    c[0] /= np.sqrt(2.0)
    return np.asarray(c, dtype=np.float64)


def _cell_pixel(coarse: F64, cells: frozenset[Cell]) -> Vec2:
    """Frame pixel at the middle of a group of cells (from the sampling map)."""
    c = np.array([coarse[j + 1, i + 1] for i, j in cells]).mean(axis=0)
    return float(c[0]), float(c[1])


def _box_sum(a: F64, size: int) -> F64:
    import cv2

    return np.asarray(cv2.boxFilter(a, -1, (size, size), normalize=False,
                                    borderType=cv2.BORDER_CONSTANT), dtype=np.float64)


def _local_level(c: F64, ok: npt.NDArray[np.bool_], size: int) -> tuple[F64, F64]:
    """Robust local mean and spread (1 sigma) of `c` over size x size windows of valid values
    (each channel of a stack (rows, columns, n) on its own: every step is per element or a box
    filter, which OpenCV applies to each channel alike).

    Mean: a plain mean, then one without the values beyond 2.5 mean deviations (missing bars,
    a seam). Spread: from the differences between neighbouring bars (|a - b| / sqrt 2, trimmed
    the same way), so a smooth change across the window (fouling, a fish behind) does not
    count as noise."""
    w = ok.astype(np.float64)
    v = np.where(ok, c, 0.0)
    n = np.maximum(_box_sum(w, size), 1.0)
    m0 = _box_sum(v, size) / n
    ad0 = _box_sum(np.abs(v - m0) * w, size) / n
    inl = ok & (np.abs(c - m0) < 2.5 * ad0 + 1e-9)
    wi = inl.astype(np.float64)
    ni = np.maximum(_box_sum(wi, size), 1.0)
    m1 = _box_sum(np.where(inl, c, 0.0), size) / ni
    diffs = []
    for axis in (0, 1):
        d = np.abs(c - np.roll(c, 1, axis=axis))
        both = ok & np.roll(ok, 1, axis=axis)
        if axis == 0:
            both[0, :] = False
        else:
            both[:, 0] = False
        diffs.append((np.where(both, d, 0.0), both))
    dsum = sum(_box_sum(d, size) for d, _ in diffs)
    dn = np.maximum(sum(_box_sum(b.astype(np.float64), size) for _, b in diffs), 1.0)
    md = dsum / dn
    tsum = sum(_box_sum(np.where(b & (d < 2.5 * md), d, 0.0), size) for d, b in diffs)
    tn = np.maximum(sum(_box_sum((b & (d < 2.5 * md)).astype(np.float64), size)
                        for d, b in diffs), 1.0)
    spread = 1.25 * (tsum / tn) / math.sqrt(2.0)
    enough = ni >= 0.4 * size * size
    return np.where(enough, m1, np.nan), np.where(enough, np.maximum(spread, 1e-6), np.inf)


class _Pyramid:
    """The frame's image pyramid, levels built when first asked for."""

    def __init__(self, gray: Image) -> None:
        self._levels: list[F32] = [np.asarray(gray, dtype=np.float32)]

    def __getitem__(self, level: int) -> F32:
        import cv2

        while len(self._levels) <= level:
            self._levels.append(np.asarray(cv2.pyrDown(self._levels[-1]), dtype=np.float32))
        return self._levels[level]


def _cell_levels(coarse: F64, s: int) -> npt.NDArray[np.int64]:
    """Pyramid level to read each cell from: the finest at which it spans at most 2 S pixels
    (fewer would lose nothing but time; more would be undersampled), shape (n2, n1)."""
    di = 0.5 * (coarse[1:-1, 2:] - coarse[1:-1, :-2])
    dj = 0.5 * (coarse[2:, 1:-1] - coarse[:-2, 1:-1])
    area = np.abs(di[..., 0] * dj[..., 1] - di[..., 1] * dj[..., 0])
    size = np.sqrt(np.maximum(area, 1e-9))
    return np.asarray(np.clip(np.ceil(np.log2(size / (2.0 * s))), 0, 3), dtype=np.int64)


def _sample(pyramid: _Pyramid, coarse: F64, s: int, levels: npt.NDArray[np.int64]
            ) -> tuple[F32, npt.NDArray[np.bool_]]:
    """The lattice image: `coarse` (frame pixels of one point per cell, one cell of margin)
    interpolated to S samples per cell, each cell read (bilinear) from its pyramid level."""
    import cv2

    n2p, n1p = coarse.shape[:2]
    big = cv2.resize(coarse.astype(np.float32), (n1p * s, n2p * s),
                     interpolation=cv2.INTER_LINEAR)[s:-s, s:-s]
    lat = np.zeros(big.shape[:2], dtype=np.float32)
    valid = np.zeros(big.shape[:2], dtype=bool)
    for level in np.unique(levels):
        # Only the cells read from this level (their bounding box of samples).
        rows, cols = np.nonzero(levels == level)
        r0, r1 = int(rows.min()) * s, (int(rows.max()) + 1) * s
        c0, c1 = int(cols.min()) * s, (int(cols.max()) + 1) * s
        image = pyramid[int(level)]
        scale = float(2**level)
        box = big[r0:r1, c0:c1]
        mx = np.ascontiguousarray((box[..., 0] + 0.5) / scale - 0.5)
        my = np.ascontiguousarray((box[..., 1] + 0.5) / scale - 0.5)
        h, w = image.shape[:2]
        here = np.repeat(np.repeat(levels[r0 // s : r1 // s, c0 // s : c1 // s] == level, s,
                                   axis=0), s, axis=1)
        read = cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        inside = (mx >= 0) & (mx <= w - 1) & (my >= 0) & (my <= h - 1)
        lat[r0:r1, c0:c1][here] = read[here]
        valid[r0:r1, c0:c1][here] = inside[here]
    return lat, valid


def _hull(points: F64) -> npt.NDArray[np.int32] | None:
    """Convex hull of 2-D points as the int32 polygon cv2's fill functions take."""
    import cv2

    if len(points) < 3:
        return None
    pts = np.round(points).astype(np.int32).reshape(-1, 1, 2)
    return np.asarray(cv2.convexHull(pts), dtype=np.int32)


def _judgeable(cell_ok: npt.NDArray[np.bool_]) -> npt.NDArray[np.bool_]:
    """Cells with inspected cells three deep around them every way (a hole there and its ring
    are wholly judged)."""
    import cv2

    ok = cv2.erode(cell_ok.astype(np.uint8), np.ones((7, 7), np.uint8),
                   borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return np.asarray(ok > 0, dtype=bool)


def _outline(coarse: F64, w: int, h: int, cells: npt.NDArray[np.bool_] | None = None
             ) -> tuple[Vec2, ...]:
    """Outline (convex hull, frame pixels) of the inspected cells (or of `cells`, shape
    (n2, n1)) inside the frame."""
    import cv2

    pts = coarse[1:-1, 1:-1]
    pts = (pts[cells] if cells is not None else pts).reshape(-1, 2)
    pts = pts[(pts[:, 0] >= 0) & (pts[:, 0] <= w - 1) & (pts[:, 1] >= 0) & (pts[:, 1] <= h - 1)]
    if len(pts) < 3:
        return ()
    hull = cv2.convexHull(pts.astype(np.float32).reshape(-1, 1, 2)).reshape(-1, 2)
    return tuple((float(x), float(y)) for x, y in hull)


def _crop(gray: Image, box: tuple[float, float, float, float], st: DamageSettings
          ) -> tuple[npt.NDArray[np.uint8], tuple[float, float, float, float]]:
    """The frame around the hole: `crop_scale` times its size (at least 48 px), at most
    `crop_max_px` on a side (shrunk to that); and the hole's box in the crop's pixels."""
    import cv2

    h, w = gray.shape[:2]
    cx, cy = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
    side = max(48.0, st.crop_scale * max(box[2] - box[0], box[3] - box[1]))
    x0 = int(max(0, math.floor(cx - side / 2)))
    y0 = int(max(0, math.floor(cy - side / 2)))
    x1 = int(min(w, math.ceil(cx + side / 2)))
    y1 = int(min(h, math.ceil(cy + side / 2)))
    crop = np.asarray(gray[y0:y1, x0:x1])
    if crop.dtype != np.uint8:
        crop = np.clip(crop, 0, 255).astype(np.uint8)
    big = max(crop.shape[:2])
    f = 1.0
    if big > st.crop_max_px:
        f = st.crop_max_px / big
        crop = cv2.resize(crop, (max(1, round(crop.shape[1] * f)), max(1, round(
            crop.shape[0] * f))), interpolation=cv2.INTER_AREA)
    inside = ((box[0] - x0) * f, (box[1] - y0) * f, (box[2] - x0) * f, (box[3] - y0) * f)
    return np.ascontiguousarray(crop), inside


def _reduce(basis: F64) -> F64:
    """Lagrange-Gauss reduced basis (columns)."""
    a, b = basis[:, 0].copy(), basis[:, 1].copy()
    if a @ a > b @ b:
        a, b = b, a
    for _ in range(32):
        mu = round(float(a @ b) / float(a @ a))
        if mu == 0:
            break
        b = b - mu * a
        if b @ b < a @ a:
            a, b = b, a
        else:
            break
    return np.stack([a, b], axis=1)


# Two ROIs see the same lattice when each vector is within this share of the reference's.
ALIGN_TOLERANCE = 0.12


def _consensus(bases: list[F64], weights: list[float]) -> F64 | None:
    """The lattice most ROIs agree on: each basis expressed in the frame of the reference (of
    the five clearest ROIs, the one most others agree with; the first of equals), as the
    vectors closest to its columns among +-a, +-b, +-(a +- b), then the median of those that
    are the same lattice within `ALIGN_TOLERANCE`."""
    stack = np.stack(bases)
    order = sorted(range(len(bases)), key=lambda k: -weights[k])[:5]
    # Every reference at once: one evaluation of the stacks costs what one reference at a time
    # did, and the chosen reference's distances are then at hand for the alignment.
    refs = stack[order]  # (r, 2, 2)
    cands = _candidate_vectors(stack)  # (k, 8, 2)
    dist = _distances_to_columns(cands, refs)  # (r, k, 8, 2)
    same = (dist.min(axis=2) <= ALIGN_TOLERANCE * np.linalg.norm(refs, axis=1)[:, None, :])
    agrees = same.all(axis=2)  # (r, k)
    best = int(np.argmax(agrees.sum(axis=1)))
    ok = agrees[best]
    if not ok.any():
        return None
    pick = np.argmin(dist[best], axis=1)  # (k, 2)
    rows = np.arange(len(bases))[:, None]
    aligned = np.transpose(cands[rows, pick], (0, 2, 1))  # columns: the picked vectors
    return np.asarray(np.median(aligned[ok], axis=0), dtype=np.float64)


def _candidate_vectors(bases: F64) -> F64:
    """For bases (k, 2, 2; columns a, b): the vectors +-a, +-b, +-(a +- b), (k, 8, 2)."""
    a, b = bases[:, :, 0], bases[:, :, 1]
    return np.stack([a, -a, b, -b, a + b, -a - b, a - b, b - a], axis=1)


def _distances_to_columns(cands: F64, refs: F64) -> F64:
    """(r, k, 8, 2): how far each candidate vector (k, 8, 2) lies from each column of each
    reference basis (r, 2, 2)."""
    return np.asarray(np.linalg.norm(
        cands[None, :, :, None, :] - refs.transpose(0, 2, 1)[:, None, None], axis=4),
        dtype=np.float64)
