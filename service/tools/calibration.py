"""Zhang-style camera calibration from checkerboard views (pure: arrays in, CameraModel out).

Two jobs, no file or video I/O:

* `detect_board` finds the inner corners of a checkerboard in one grey image (OpenCV's
  sector-based detector where available, the classic detector plus sub-pixel refinement as a
  fallback), and `guess_board_size` says what board an image shows when the expected one is absent.
* `calibrate` solves intrinsics and plumb-bob distortion (k1, k2, p1, p2, k3) from the corner
  lists, drops views whose reprojection error is an outlier and re-solves, and judges whether the
  views cover the image well enough for the distortion to be trusted.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from service.core.camera import CameraModel
from service.core.errors import CalibrationError

FloatArray = npt.NDArray[np.float64]
GrayImage = npt.NDArray[np.uint8]

# Fewer views than this cannot separate focal length, principal point and three radial terms.
MIN_VIEWS = 3
# Below this many views the result is usable but fragile; the operator is warned.
RECOMMENDED_VIEWS = 10
# A view is an outlier when its RMS error exceeds this multiple of the median view error...
OUTLIER_FACTOR = 3.0
# ...and also this absolute error in pixels (sub-pixel scatter among good views is not an outlier).
OUTLIER_FLOOR_PX = 0.5
# At most this fraction of the views is ever rejected: beyond it the data, not a view, is bad.
MAX_REJECTED_FRACTION = 0.34
# Largest cornerSubPix half-window (px): OpenCV's customary 23x23 window.
REFINE_MAX_HALF_WINDOW = 11
# A solve worse than this is not a calibration of this camera with this board (wrong square size
# does not do it; wrong board size, a bent board or mixed cameras do): refuse to write it.
MAX_ACCEPTABLE_RMS_PX = 2.0
# Views tilted less than this against the optical axis do not constrain the focal length.
MIN_USEFUL_TILT_DEG = 15.0
# Below this largest tilt the solve is degenerate (focal length trades against the board's
# distance): with corners to 0.1 px, OpenCV's fit gave fx 411-507 for a true 520 with a sigma
# of 0.01 % at tilts under 1.6 deg, and an honest sigma (16 %, 9 %) from 2.3 deg on. Refused.
MIN_SOLVABLE_TILT_DEG = 3.0
# The image is split into COVERAGE_GRID x COVERAGE_GRID cells for the coverage check.
COVERAGE_GRID = 3


@dataclass(frozen=True)
class BoardSpec:
    """A checkerboard: inner-corner counts along its two sides and the square edge in metres."""

    columns: int
    rows: int
    square: float

    def __post_init__(self) -> None:
        if self.columns < 2 or self.rows < 2:
            raise CalibrationError(
                f"board must have at least 2x2 inner corners, got {self.columns}x{self.rows}"
            )
        if self.columns == self.rows:
            # A square board has no distinguishable orientation: corner order can rotate by 90 deg
            # between views and the solve silently mixes them up.
            raise CalibrationError(
                f"a {self.columns}x{self.rows} board is ambiguous under rotation; use a board "
                "with different inner-corner counts (e.g. 7x4)"
            )
        if not math.isfinite(self.square) or self.square <= 0:
            raise CalibrationError(f"square size must be positive metres, got {self.square}")

    @property
    def pattern_size(self) -> tuple[int, int]:
        """The (columns, rows) tuple OpenCV's detectors expect."""
        return (self.columns, self.rows)

    @property
    def corner_count(self) -> int:
        return self.columns * self.rows

    @property
    def label(self) -> str:
        return f"{self.columns}x{self.rows}"

    def object_points(self) -> npt.NDArray[np.float32]:
        """Corner positions on the board plane (z = 0, metres) in the detectors' row-major order."""
        grid = np.mgrid[0 : self.columns, 0 : self.rows].T.reshape(-1, 2)
        points = np.zeros((self.corner_count, 3), dtype=np.float32)
        points[:, :2] = grid * self.square
        return points


def parse_board_size(text: str) -> tuple[int, int]:
    """'7x4' -> (7, 4): inner corners along the two sides of the board."""
    match = re.fullmatch(r"\s*(\d+)\s*[xX*]\s*(\d+)\s*", text)
    if match is None:
        raise CalibrationError(
            f"board size '{text}' is not COLUMNSxROWS of inner corners, e.g. 7x4"
        )
    return int(match.group(1)), int(match.group(2))


@dataclass(frozen=True)
class BoardView:
    """The detected inner corners (N x 2 pixels, detector order) of one image, named for reports."""

    name: str
    corners: FloatArray

    def __post_init__(self) -> None:
        if self.corners.ndim != 2 or self.corners.shape[1] != 2:
            raise CalibrationError(f"{self.name}: corners must be an N x 2 array")


@dataclass(frozen=True)
class ViewError:
    """Reprojection error of one view after the final solve (pixels)."""

    name: str
    rms: float
    tilt_deg: float


@dataclass(frozen=True)
class RejectedView:
    name: str
    rms: float
    reason: str


@dataclass(frozen=True)
class CalibrationResult:
    """What a calibration produced and how far it can be trusted."""

    camera: CameraModel
    board: BoardSpec
    rms: float
    views: tuple[ViewError, ...]
    rejected: tuple[RejectedView, ...]
    # One-sigma uncertainties from the final solve, keyed fx, fy, cx, cy, k1, k2, p1, p2, k3.
    std_devs: dict[str, float] = field(default_factory=dict)
    coverage: float = 0.0
    warnings: tuple[str, ...] = ()

    def summary(self) -> dict[str, Any]:
        """A JSON-ready description (what `netpose calibrate --json` prints)."""
        cam = self.camera
        return {
            "image_width": cam.width,
            "image_height": cam.height,
            "camera_matrix": [[float(v) for v in row] for row in cam.matrix],
            "fx": cam.fx,
            "fy": cam.fy,
            "cx": cam.cx,
            "cy": cam.cy,
            "distortion_model": "plumb_bob",
            "distortion": dict(zip(("k1", "k2", "p1", "p2", "k3"), cam.distortion, strict=True)),
            "std_devs": self.std_devs,
            "rms_px": self.rms,
            "board": {"columns": self.board.columns, "rows": self.board.rows,
                      "square_m": self.board.square},
            "views_used": [
                {"name": v.name, "rms_px": v.rms, "tilt_deg": v.tilt_deg} for v in self.views
            ],
            "views_rejected": [
                {"name": r.name, "rms_px": r.rms, "reason": r.reason} for r in self.rejected
            ],
            "coverage": self.coverage,
            "warnings": list(self.warnings),
        }


# ---------------------------------------------------------------------------------------------
# Detection


def _to_gray(image: npt.NDArray[Any]) -> GrayImage:
    if image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    elif image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    elif image.ndim != 2:
        raise CalibrationError(f"expected a grey or BGR image, got shape {image.shape}")
    if image.dtype != np.uint8:
        lo, hi = float(np.min(image)), float(np.max(image))
        image = ((image - lo) * (255.0 / max(hi - lo, 1e-12))).astype(np.uint8)
    return np.ascontiguousarray(image)


def _corner_spacing(corners: FloatArray, board: BoardSpec) -> float:
    """Smallest distance between neighbouring corners along the board's rows and columns."""
    grid = corners.reshape(board.rows, board.columns, 2)
    return min(
        float(np.min(np.linalg.norm(np.diff(grid, axis=1), axis=2))),
        float(np.min(np.linalg.norm(np.diff(grid, axis=0), axis=2))),
    )


def _refine_corners(gray: GrayImage, corners: FloatArray, board: BoardSpec) -> FloatArray:
    """cornerSubPix with the largest safe window, retried smaller where a corner wandered off.

    The half-window is half the corner spacing (at most 11 px, OpenCV's customary 23x23 window):
    larger windows average more edge pixels. On a steeply tilted view the window can reach the next
    grid line and drag a corner onto it (seen: 7.6 px on OpenCV's left02.jpg), so a corner that
    moved by more than max(1 px, 10 % of the spacing) from the detector's estimate is refined
    again with half the window.
    """
    spacing = _corner_spacing(corners, board)
    start = corners.astype(np.float32).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 40, 0.001)
    half = int(max(2, min(REFINE_MAX_HALF_WINDOW, 0.5 * spacing)))
    refined = cv2.cornerSubPix(gray, start.copy(), (half, half), (-1, -1), criteria)
    limit = max(1.0, 0.1 * spacing)
    wandered = np.linalg.norm((refined - start).reshape(-1, 2), axis=1) > limit
    while wandered.any() and half > 2:
        half = max(2, half // 2)
        refined[wandered] = cv2.cornerSubPix(
            gray, start[wandered].copy(), (half, half), (-1, -1), criteria
        )
        wandered = np.linalg.norm((refined - start).reshape(-1, 2), axis=1) > limit
    refined[wandered] = start[wandered]  # no window agreed: keep the detector's own estimate
    return np.asarray(refined, dtype=np.float64).reshape(-1, 2)


def detect_board(image: npt.NDArray[Any], board: BoardSpec) -> FloatArray | None:
    """Inner corners (N x 2, pixels) of `board` in `image`, or None when it is not (fully) seen."""
    gray = _to_gray(image)
    pattern = board.pattern_size
    if hasattr(cv2, "findChessboardCornersSBWithMeta"):
        # Sector-based detector: robust to blur and uneven light (underwater). EXHAUSTIVE is left
        # out on purpose: with it the detector "finds" boards in fish-nets. LARGER makes it report
        # the whole board it sees, so a 7x4 patch of a 9x6 board is refused instead of poisoning
        # the solve (plain SB and the classic detector both return such patches).
        flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_LARGER
        found, corners, _meta = cv2.findChessboardCornersSBWithMeta(gray, pattern, flags=flags)
        if found and np.asarray(corners).reshape(-1, 2).shape[0] != board.corner_count:
            return None
    else:  # OpenCV < 4.3
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        found, corners = cv2.findChessboardCorners(gray, pattern, flags=flags)
    if not found:
        return None
    # Refine with the gradient-orthogonality criterion even after the SB detector: on rendered
    # boards its own corners are ~0.07 px scattered with a bias that moves the focal length by
    # ~0.4 %; cornerSubPix brings that below 0.1 %.
    return _refine_corners(gray, np.asarray(corners, dtype=np.float64).reshape(-1, 2), board)


def guess_board_size(image: npt.NDArray[Any]) -> tuple[int, int] | None:
    """The inner-corner size of whatever checkerboard `image` shows, or None.

    Asks the sector-based detector for any board at least 3x3 and reads the real size from its
    meta data; used only to explain "no 9x6 board found" when the board is e.g. 7x4. The size is
    (columns, rows) as --board writes it, the larger count first (7x4, 9x6).
    """
    if not hasattr(cv2, "findChessboardCornersSBWithMeta"):
        return None
    gray = _to_gray(image)
    flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_LARGER
    found, _corners, meta = cv2.findChessboardCornersSBWithMeta(gray, (3, 3), flags=flags)
    if not found or meta is None:
        return None
    rows, cols = meta.shape[:2]
    if rows == cols or rows * cols < 12:
        # Tiny or square "boards" are what the detector sees in nets and tiled walls.
        return None
    # The detector lays the grid out either way round, from view to view (a landscape 7x4 board
    # came out 4x7 in most views), and --board finds a board in either orientation: so the size
    # is given in --board's order, which is also what lets the views' guesses agree.
    return (int(max(rows, cols)), int(min(rows, cols)))


# ---------------------------------------------------------------------------------------------
# Calibration


def _tilt_deg(rvec: FloatArray) -> float:
    """Angle between the board normal and the optical axis."""
    rot, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))
    return float(np.degrees(np.arccos(min(1.0, abs(float(rot[2, 2]))))))


@dataclass(frozen=True)
class _Solve:
    rms: float
    matrix: FloatArray
    dist: FloatArray
    view_rms: FloatArray
    tilts: FloatArray
    std_devs: FloatArray


def _solve(
    image_points: Sequence[npt.NDArray[np.float32]],
    object_points: npt.NDArray[np.float32],
    image_size: tuple[int, int],
    fix_k3: bool,
) -> _Solve:
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    objects = [object_points] * len(image_points)
    try:
        (rms, matrix, dist, rvecs, _tvecs, std_intr, _std_ext, per_view) = (
            cv2.calibrateCameraExtended(  # type: ignore[call-overload]
                objects, list(image_points), image_size, None, None, flags=flags,
                criteria=criteria,
            )
        )
    except cv2.error as exc:
        raise CalibrationError(f"the calibration solve failed: {exc.err}") from None
    dist = np.asarray(dist, dtype=np.float64).ravel()[:5]
    return _Solve(
        rms=float(rms),
        matrix=np.asarray(matrix, dtype=np.float64),
        dist=np.pad(dist, (0, 5 - dist.size)),
        view_rms=np.asarray(per_view, dtype=np.float64).ravel(),
        tilts=np.array([_tilt_deg(r) for r in rvecs]),
        std_devs=np.asarray(std_intr, dtype=np.float64).ravel(),
    )


def _outlier_threshold(view_rms: FloatArray, factor: float, floor_px: float) -> float:
    return max(factor * float(np.median(view_rms)), floor_px)


def _coverage(views: Sequence[FloatArray], image_size: tuple[int, int]) -> tuple[float, list[str]]:
    """Fraction of the image inside some board outline, and the grid cells nobody visited."""
    width, height = image_size
    scale = min(1.0, 256.0 / max(width, height))  # a coarse mask is enough and cheap
    mask = np.zeros((max(1, round(height * scale)), max(1, round(width * scale))), np.uint8)
    for corners in views:
        hull = cv2.convexHull((corners * scale).astype(np.float32)).astype(np.int32)
        cv2.fillConvexPoly(mask, hull, 1)
    covered = float(mask.mean())
    cell_names = (
        ("top-left corner", "top edge", "top-right corner"),
        ("left edge", "centre", "right edge"),
        ("bottom-left corner", "bottom edge", "bottom-right corner"),
    )
    all_corners = np.concatenate(list(views), axis=0)
    cell_x = np.clip((all_corners[:, 0] / width * COVERAGE_GRID).astype(int), 0, COVERAGE_GRID - 1)
    cell_y = np.clip((all_corners[:, 1] / height * COVERAGE_GRID).astype(int), 0, COVERAGE_GRID - 1)
    visited = set(zip(cell_y.tolist(), cell_x.tolist(), strict=True))
    empty = [
        cell_names[gy][gx]
        for gy in range(COVERAGE_GRID)
        for gx in range(COVERAGE_GRID)
        if (gy, gx) not in visited
    ]
    return covered, empty


def calibrate(
    views: Sequence[BoardView],
    board: BoardSpec,
    image_size: tuple[int, int],
    *,
    fix_k3: bool = False,
    outlier_factor: float = OUTLIER_FACTOR,
    outlier_floor_px: float = OUTLIER_FLOOR_PX,
    name: str = "camera",
) -> CalibrationResult:
    """Solve the camera from board views of one camera at `image_size` = (width, height).

    Views whose RMS reprojection error exceeds max(outlier_factor x median, outlier_floor_px) are
    dropped one at a time (worst first) and the camera re-solved, up to MAX_REJECTED_FRACTION of
    the views.
    """
    width, height = image_size
    if width <= 0 or height <= 0:
        raise CalibrationError(f"image size must be positive, got {width}x{height}")
    for view in views:
        if view.corners.shape[0] != board.corner_count:
            raise CalibrationError(
                f"{view.name}: {view.corners.shape[0]} corners, a {board.label} board has "
                f"{board.corner_count}"
            )
    if len(views) < MIN_VIEWS:
        raise CalibrationError(
            f"only {len(views)} view(s) with a {board.label} board; at least {MIN_VIEWS} are "
            f"needed and {RECOMMENDED_VIEWS}+ recommended"
        )
    object_points = board.object_points()
    active = list(views)
    rejected: list[RejectedView] = []
    max_rejected = int(len(views) * MAX_REJECTED_FRACTION)
    while True:
        solve = _solve(
            [v.corners.astype(np.float32).reshape(-1, 1, 2) for v in active],
            object_points, image_size, fix_k3,
        )
        threshold = _outlier_threshold(solve.view_rms, outlier_factor, outlier_floor_px)
        worst = int(np.argmax(solve.view_rms))
        if (
            solve.view_rms[worst] <= threshold
            or len(rejected) >= max_rejected
            or len(active) - 1 < MIN_VIEWS
        ):
            break
        rejected.append(
            RejectedView(
                name=active[worst].name,
                rms=float(solve.view_rms[worst]),
                reason=f"reprojection error {solve.view_rms[worst]:.2f} px > {threshold:.2f} px",
            )
        )
        del active[worst]

    if solve.rms > MAX_ACCEPTABLE_RMS_PX:
        raise CalibrationError(
            f"reprojection error {solve.rms:.2f} px over {len(active)} views is too high to "
            f"trust (limit {MAX_ACCEPTABLE_RMS_PX} px): check the board size, that the board is "
            "flat, and that all inputs come from the same camera and zoom"
        )
    max_tilt = float(np.max(solve.tilts)) if solve.tilts.size else 0.0
    if max_tilt < MIN_SOLVABLE_TILT_DEG:
        raise CalibrationError(
            f"all {len(active)} views are face-on (largest tilt {max_tilt:.1f} deg): the focal "
            "length cannot be told from the board's distance, so no distance could be "
            "trusted; add views with the board tilted 20-45 deg"
        )
    k = solve.matrix
    camera = CameraModel(
        width=width, height=height, fx=float(k[0, 0]), fy=float(k[1, 1]),
        cx=float(k[0, 2]), cy=float(k[1, 2]),
        distortion=tuple(float(v) for v in solve.dist), name=name,
    )
    std_names = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    std_devs = {
        n: float(s) for n, s in zip(std_names, solve.std_devs[: len(std_names)], strict=False)
    }
    coverage, empty_cells = _coverage([v.corners for v in active], image_size)
    warnings = _judge(
        len(active), solve, coverage, empty_cells, camera, std_devs, len(views),
        [r.name for r in rejected],
    )
    return CalibrationResult(
        camera=camera,
        board=board,
        rms=solve.rms,
        views=tuple(
            ViewError(name=v.name, rms=float(e), tilt_deg=float(t))
            for v, e, t in zip(active, solve.view_rms, solve.tilts, strict=True)
        ),
        rejected=tuple(rejected),
        std_devs=std_devs,
        coverage=coverage,
        warnings=tuple(warnings),
    )


def _judge(
    used: int,
    solve: _Solve,
    coverage: float,
    empty_cells: Sequence[str],
    camera: CameraModel,
    std_devs: dict[str, float],
    offered: int,
    rejected_names: Sequence[str],
) -> list[str]:
    """Plain-language warnings about what the views do not pin down."""
    warnings: list[str] = []
    if used < RECOMMENDED_VIEWS:
        warnings.append(
            f"only {used} usable views; {RECOMMENDED_VIEWS} or more, at varied tilts and "
            "positions, give a trustworthy calibration"
        )
    if empty_cells:
        warnings.append(
            "no board corners in the " + ", ".join(empty_cells) + " of the image: distortion "
            "there is extrapolated; add views with the board in those areas"
        )
    elif coverage < 0.5:
        warnings.append(
            f"the boards cover only {coverage:.0%} of the image; move the board closer to the "
            "edges and corners"
        )
    max_tilt = float(np.max(solve.tilts)) if solve.tilts.size else 0.0
    if max_tilt < MIN_USEFUL_TILT_DEG:
        warnings.append(
            f"all views are nearly face-on (largest tilt {max_tilt:.0f} deg): the focal length is "
            "poorly constrained; add views with the board tilted 20-45 deg"
        )
    fx_std = std_devs.get("fx", 0.0)
    if math.isfinite(fx_std) and fx_std > 0.005 * camera.fx:
        warnings.append(
            f"focal length uncertain by {100 * fx_std / camera.fx:.1f}% (one sigma); distance "
            "errors scale 1:1 with it"
        )
    if rejected_names and len(rejected_names) >= int(offered * MAX_REJECTED_FRACTION):
        warnings.append(
            f"{len(rejected_names)} of {offered} views were rejected as outliers; check that the "
            "board is flat and the square size is right"
        )
    if solve.rms > 1.0:
        warnings.append(
            f"overall RMS reprojection error {solve.rms:.2f} px is high (expect < 0.5 px for a "
            "sharp, flat board)"
        )
    return warnings
