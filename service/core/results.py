"""What the estimator returns: plain, immutable values that every output can serialise."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]
Mat2 = tuple[Vec2, Vec2]


@dataclass(frozen=True)
class RoiResult:
    """One square region of the frame and the lattice found in its spectrum.

    Vectors are in full-resolution, distorted pixel units of the input frame. `reciprocal`
    holds the reduced reciprocal basis k1, k2 in cycles per pixel; `mesh_edges` the dual (real
    space) basis e1, e2 in pixels, with e_i . k_j = delta_ij.
    """

    center_px: Vec2
    size_px: int
    level: int
    detected: bool
    reciprocal: Mat2 | None = None
    mesh_edges: Mat2 | None = None
    cell_area_px: float = math.nan
    snr_db: float = 0.0
    inlier_fraction: float = 0.0
    peaks: int = 0
    used_in_fit: bool = False

    @property
    def period_px(self) -> float:
        """Geometric-mean mesh period (sqrt of the cell area) in pixels."""
        return math.sqrt(self.cell_area_px) if self.cell_area_px > 0 else math.nan


@dataclass(frozen=True)
class NetEstimate:
    """Detection and pose of the net plane in the camera frame (x right, y down, z forward).

    `normal` is the unit normal of the net plane pointing from the net towards the camera;
    `distance_m` the perpendicular distance from the camera centre to the plane; `range_m` the
    distance along the optical axis to the plane. Sigmas are one standard deviation.
    """

    detected: bool
    confidence: float
    normal: Vec3 | None = None
    distance_m: float | None = None
    range_m: float | None = None
    sigma_distance_m: float | None = None
    sigma_range_m: float | None = None
    sigma_normal_deg: float | None = None
    rois: tuple[RoiResult, ...] = ()
    rois_used: int = 0
    level: int = 0
    reason: str = ""
    timings_ms: dict[str, float] = field(default_factory=dict)
    # The net is in view but too close to measure (a blur of mesh filling the view, or a mesh
    # period beyond the largest ROI): `detected` stays False and there is no distance; a consumer
    # treats it as an out-of-range-low reading, not as "no net".
    too_close: bool = False
    # Opening angle (degrees) of the mesh as measured on the rectified lattice, whenever a lattice
    # was measured; a mismatch with the configured mesh refuses the distance (see `reason`).
    measured_opening_deg: float | None = None
    # The work level this frame was measured at (0 = full work; higher levels measure fewer
    # ROIs, fewer rectified passes, coarser spectra: see docs/estimator.md, "Budget levels").
    budget_level: int = 0
    # ROI spectra computed for this frame, by FFT size: the work done, whatever the clock says.
    fft_counts: dict[int, int] = field(default_factory=dict)
    # When the mesh scale was last proved without a prior (a cold search, or a tracked frame's
    # blind check): this many frames ago, at this range. A tracked frame skips the blind check
    # only while the proof is recent and the net cannot have moved a harmonic factor since.
    frames_since_scale_proof: int = 0
    scale_proved_range_m: float | None = None
    # The net was recognised (the configured mesh, its scale proved, a plane that the ROIs
    # converge on) but that plane is not precise enough for a distance (`reason` says by how
    # much): `detected` stays False and nothing goes to the autopilot, but the pilot can be
    # told that a net is in view and roughly how far. For such a frame only: the range along
    # the optical axis and its one-sigma uncertainty that were refused (None whenever
    # `detected`: then `range_m` holds the distance). See `net_seen`.
    approx_range_m: float | None = None
    approx_sigma_range_m: float | None = None
    # The full scale search ran on this frame: there was no prior, or the prior plane did not
    # hold (and the caller did not defer the search: `NetEstimator.estimate(search=False)`).
    # Such a frame costs several times a tracked one (the daemon's budget is judged on
    # tracked frames only: service/core/budget.py).
    searched: bool = False
    # (width, height) of the frame measured: `rois` are in its pixels. A prior from a frame of
    # another size (a stream that changed resolution) guides with its plane, not its ROIs.
    frame_px: tuple[int, int] | None = None

    @property
    def net_seen(self) -> bool:
        """A net is in view: measured (`detected`), or recognised with a range too uncertain
        to give (`approx_range_m`)."""
        return self.detected or self.approx_range_m is not None

    def seen_text(self) -> str | None:
        """'net seen, ~0.83 +- 0.03 m: no distance (why)' for a net seen without a distance
        (None otherwise): the one wording of captions and command lines."""
        if self.approx_range_m is None or self.approx_sigma_range_m is None:
            return None
        return (f"net seen, ~{self.approx_range_m:.2f} +- {self.approx_sigma_range_m:.2f} m: "
                f"no distance ({self.reason.split(':')[0]})")

    @property
    def tilt_deg(self) -> float | None:
        """Angle between the optical axis and the net normal (0 = facing the net squarely)."""
        if self.normal is None:
            return None
        return math.degrees(math.acos(min(1.0, abs(self.normal[2]))))

    def to_json_dict(self) -> dict[str, Any]:
        """Plain JSON-ready dict (no ROI detail); None where not detected."""

        def rounded(value: float | None, digits: int) -> float | None:
            return None if value is None else round(float(value), digits)

        return {
            "detected": self.detected,
            "confidence": round(self.confidence, 4),
            "range_m": rounded(self.range_m, 5),
            "distance_m": rounded(self.distance_m, 5),
            "normal": None if self.normal is None else [round(v, 6) for v in self.normal],
            "tilt_deg": rounded(self.tilt_deg, 3),
            "sigma_range_m": rounded(self.sigma_range_m, 5),
            "sigma_distance_m": rounded(self.sigma_distance_m, 5),
            "sigma_normal_deg": rounded(self.sigma_normal_deg, 3),
            "rois_used": self.rois_used,
            "rois": len(self.rois),
            "reason": self.reason,
            "net_seen": self.net_seen,
            "approx_range_m": rounded(self.approx_range_m, 4),
            "approx_sigma_range_m": rounded(self.approx_sigma_range_m, 4),
            "too_close": self.too_close,
            "level": self.level,
            "measured_opening_deg": rounded(self.measured_opening_deg, 2),
            "budget_level": self.budget_level,
            # Sorted: the same frame gives the same keys in the same order (the values are
            # times, which vary from run to run).
            "timings_ms": {k: round(v, 3) for k, v in sorted(self.timings_ms.items())},
        }
