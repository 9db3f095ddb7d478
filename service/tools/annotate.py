"""The replay's annotated frame, in the manner of the paper's Figure 6.

On top of the preview drawing (service/preview.py: ROI squares coloured by what they contributed,
mesh cells inside each ROI) this adds what the paper shows: the mesh parallelogram found in each
ROI used for the plane fit, the net's coordinate system back-projected into the image (two axes
along the mesh bars in the net plane, and the normal), and the distance and orientation as text.

Pure: returns a new BGR image, never draws on the frame it is given.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np
import numpy.typing as npt

from service.core.camera import CameraModel
from service.core.damage_track import DamageReport
from service.core.readings import RangeReading, RangeStatus
from service.core.results import NetEstimate, RoiResult
from service.core.tracking import TrackOutput, TrackState
from service.tools.damage_report import draw_damage
from service.tools.preview import TEXT, render_preview
from service.tools.replay import Truth

F64 = npt.NDArray[np.float64]
BGR = npt.NDArray[np.uint8]

MESH = (255, 0, 255)  # magenta: the detected mesh cell of a used ROI
AXIS_COLOURS = ((0, 0, 255), (0, 200, 0), (255, 80, 0))  # first bar, second bar, normal (BGR)
AXIS_LABELS = ("e1", "e2", "n")
# Axis length as a fraction of the range: the drawn system keeps about the same size on screen
# (a quarter of the focal length) at any distance.
AXIS_LENGTH_OF_RANGE = 0.25


def caption_lines(
    estimate: NetEstimate | None,
    track: TrackOutput | None = None,
    truth: Truth | None = None,
    refused: str = "",
    sent: RangeReading | None = None,
) -> list[str]:
    """What the autopilot was handed first when `sent` is given ('autopilot 1.00 m along the
    axis': what the page's header and a ground station show), then the estimate's 'perp 0.82 m
    axis 1.00 m  tilt 35 deg  conf 0.91', the filter's and the truth's lines if given. Each
    distance is named: the overlay led with a perpendicular "d=0.82" while the header and the
    autopilot had the range along the axis, 1.00 m (pilot review)."""
    lines: list[str] = []
    if sent is not None:
        lines.append(sent_caption(sent))
    if estimate is None:
        lines.append(f"no estimate ({refused})" if refused else "no estimate")
    elif estimate.detected and estimate.distance_m is not None:
        tilt = estimate.tilt_deg
        text = f"perp {estimate.distance_m:.2f} m"
        if estimate.range_m is not None:
            text += f"  axis {estimate.range_m:.2f} m"
        if tilt is not None:
            text += f"  tilt {tilt:.0f} deg"
        lines.append(f"{text}  conf {estimate.confidence:.2f}")
    elif (seen := estimate.seen_text()) is not None:
        lines.append(seen)
    elif estimate.too_close:
        lines.append(f"too close: {estimate.reason}")
    else:
        reason = estimate.reason or "no net"
        lines.append(f"no net ({reason})  conf {estimate.confidence:.2f}")
    if track is not None:
        if track.valid and track.distance_m is not None:
            lines.append(f"filter {track.state.value}  perp {track.distance_m:.2f} m")
        elif track.state is TrackState.LOST:
            lines.append("filter lost")
        else:
            lines.append(f"filter {track.state.value} (not reported)")
    if truth is not None:
        if not truth.net_present:
            lines.append("truth: no net")
        elif truth.distance_m is not None:
            text = f"truth perp {truth.distance_m:.2f} m"
            tilt_true = truth.tilt()
            if tilt_true is not None:
                text += f"  tilt {tilt_true:.0f} deg"
            if estimate is not None and estimate.detected and estimate.distance_m is not None:
                text += f"  err {100.0 * (estimate.distance_m - truth.distance_m):+.1f} cm"
            lines.append(text)
    return lines


def sent_caption(sent: RangeReading) -> str:
    """'autopilot 1.00 m along the axis': what the autopilot was handed for this frame."""
    if sent.status is RangeStatus.TOO_CLOSE:
        return "autopilot: too close (below its minimum)"
    if sent.status is RangeStatus.NONE:
        return "autopilot: nothing sent"
    along = {"optical_axis": " along the axis", "perpendicular": " perpendicular"}
    return f"autopilot {sent.distance_m:.2f} m{along.get(sent.along or '', '')}"


def _plane_point(camera: CameraModel, normal: F64, distance: float, pixel: F64) -> F64 | None:
    """Where the ray through a (distorted) pixel meets the plane n.X = -distance."""
    ray = np.append(camera.undistort_pixels(pixel), 1.0)
    denominator = float(normal @ ray)
    if abs(denominator) < 1e-9:
        return None
    t = -distance / denominator
    return t * ray if t > 0 else None


def net_axes(
    camera: CameraModel, estimate: NetEstimate, roi: RoiResult | None = None
) -> tuple[F64, F64, F64] | None:
    """Unit 3-D directions (camera frame) of the two mesh bars in the net plane and the normal.

    The bar directions are the mesh edges `roi` measured, back-projected onto the estimated
    plane; without a usable ROI, the image x axis and its perpendicular within the plane.
    The more horizontal bar comes first, pointing right in the image; the other points up.
    """
    if estimate.normal is None or estimate.distance_m is None:
        return None
    n = np.asarray(estimate.normal, dtype=float)
    n = n / np.linalg.norm(n)
    bars: list[F64] = []
    if roi is not None and roi.mesh_edges is not None:
        centre = np.asarray(roi.center_px, dtype=float)
        origin = _plane_point(camera, n, estimate.distance_m, centre)
        for edge in roi.mesh_edges:
            tip = _plane_point(camera, n, estimate.distance_m, centre + np.asarray(edge))
            if origin is None or tip is None:
                bars = []
                break
            bars.append(tip - origin)
    if len(bars) != 2 or min(float(np.linalg.norm(b)) for b in bars) == 0.0:
        x_axis = np.array([1.0, 0.0, 0.0])
        first = x_axis - (x_axis @ n) * n
        if float(np.linalg.norm(first)) < 1e-6:
            return None
        bars = [first, np.cross(n, first)]
    a1, a2 = (b / np.linalg.norm(b) for b in bars)
    # The more horizontal bar first, pointing right (+x); the other pointing up (-y).
    if abs(a2[0]) > abs(a1[0]):
        a1, a2 = a2, a1
    if a1[0] < 0:
        a1 = -a1
    if a2[1] > 0:
        a2 = -a2
    return a1, a2, n


def _central_used_roi(estimate: NetEstimate, width: int, height: int) -> RoiResult | None:
    used = [r for r in estimate.rois if r.used_in_fit and r.mesh_edges is not None]
    if not used:
        return None
    centre = np.array([width / 2.0, height / 2.0])
    return min(used, key=lambda r: float(np.linalg.norm(np.asarray(r.center_px) - centre)))


def mesh_parallelogram(roi: RoiResult) -> F64 | None:
    """Corners (4, 2) of the mesh cell centred on the ROI: centre +- e1/2 +- e2/2."""
    if roi.mesh_edges is None:
        return None
    c = np.asarray(roi.center_px, dtype=float)
    e1, e2 = (np.asarray(e, dtype=float) / 2.0 for e in roi.mesh_edges)
    corners = np.array([c - e1 - e2, c + e1 - e2, c + e1 + e2, c - e1 + e2])
    return corners if np.all(np.isfinite(corners)) else None


class FrameAnnotator:
    """Draws estimates on frames of one camera; the camera is rescaled once per frame size.

    `width` (optional) downscales the output to at most that many pixels wide.
    """

    def __init__(self, camera: CameraModel, width: int | None = None) -> None:
        self._camera = camera
        self._width = width
        self._cameras: dict[tuple[int, int], CameraModel] = {}

    def _camera_for(self, width: int, height: int) -> CameraModel:
        key = (width, height)
        if key not in self._cameras:
            self._cameras[key] = self._camera.scaled_to(width, height)
        return self._cameras[key]

    def annotate(
        self,
        frame: npt.NDArray[np.generic],
        estimate: NetEstimate | None,
        *,
        track: TrackOutput | None = None,
        truth: Truth | None = None,
        label: str = "",
        refused: str = "",
        damage: DamageReport | None = None,
        sent: RangeReading | None = None,
    ) -> BGR:
        h, w = frame.shape[:2]
        out_width = w if self._width is None else min(w, self._width)
        rois: Sequence[RoiResult] = estimate.rois if estimate is not None else ()
        image = render_preview(frame, rois, lines=(), width=out_width)
        scale = image.shape[1] / w
        font = max(0.45, 0.8 * image.shape[1] / 1280.0)
        thick = max(1, round(2 * font))

        if estimate is not None:
            for roi in rois:
                if roi.used_in_fit:
                    corners = mesh_parallelogram(roi)
                    if corners is not None:
                        pts = np.round(corners * scale).astype(np.int32).reshape(-1, 1, 2)
                        cv2.polylines(image, [pts], True, MESH, thick, cv2.LINE_AA)
            if estimate.detected:
                self._draw_axes(image, estimate, w, h, scale, font, thick)
        draw_damage(image, damage, scale, font, thick)

        lines = caption_lines(estimate, track, truth, refused, sent)
        step = round(30 * font) + 4
        for row, text in enumerate(lines):
            _put_text(image, text, (8, step * (row + 1)), font, thick)
        if label:
            _put_text(image, label, (8, image.shape[0] - 10), font * 0.8, max(1, thick - 1))
        return image

    def _draw_axes(
        self, image: BGR, estimate: NetEstimate, w: int, h: int, scale: float, font: float,
        thick: int,
    ) -> None:
        if estimate.range_m is None or not math.isfinite(estimate.range_m) or estimate.range_m <= 0:
            return
        camera = self._camera_for(w, h)
        axes = net_axes(camera, estimate, _central_used_roi(estimate, w, h))
        if axes is None:
            return
        # The net point on the optical axis, where the range is measured, and the axis tips.
        origin = np.array([0.0, 0.0, estimate.range_m])
        length = AXIS_LENGTH_OF_RANGE * estimate.range_m
        points = np.array([origin, *(origin + length * a for a in axes)])
        if np.any(points[:, 2] <= 0.05 * estimate.range_m):
            return  # a tip at or behind the camera has no meaningful projection
        pixels, _ = cv2.projectPoints(
            points, np.zeros(3), np.zeros(3), camera.matrix, camera.dist_coeffs
        )
        px = np.asarray(pixels, dtype=float).reshape(-1, 2) * scale
        if not np.all(np.isfinite(px)):
            return
        o = (round(px[0, 0]), round(px[0, 1]))
        for tip, colour, label in zip(px[1:], AXIS_COLOURS, AXIS_LABELS, strict=True):
            end = (round(tip[0]), round(tip[1]))
            cv2.arrowedLine(image, o, end, colour, thick + 1, cv2.LINE_AA, tipLength=0.12)
            # The label just beyond the arrow head, centred on the axis' continuation.
            direction = tip - px[0]
            norm = float(np.linalg.norm(direction))
            if norm < 1.0:
                continue
            (tw, th), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, font * 0.8, thick)
            centre = tip + direction / norm * (0.6 * max(tw, th) + 4)
            text_at = (round(centre[0] - tw / 2), round(centre[1] + th / 2))
            cv2.putText(image, label, text_at, cv2.FONT_HERSHEY_SIMPLEX, font * 0.8, colour,
                        thick, cv2.LINE_AA)
        cv2.circle(image, o, thick + 2, TEXT, -1, cv2.LINE_AA)


def _put_text(image: BGR, text: str, origin: tuple[int, int], font: float, thick: int) -> None:
    """White text on a half-dark box, readable on bright and dark water alike. (A thicker dark
    outline does not work at larger sizes: Hershey glyphs advance with the thickness.)"""
    (tw, th), baseline = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, font, thick)
    x, y = origin
    pad = max(2, thick + 1)
    x0, y0 = max(0, x - pad), max(0, y - th - pad)
    x1, y1 = min(image.shape[1], x + tw + pad), min(image.shape[0], y + baseline + pad)
    if x1 > x0 and y1 > y0:
        box = image[y0:y1, x0:x1]
        box[:] = (box.astype(np.uint16) * 2 // 5).astype(np.uint8)
    cv2.putText(image, text, origin, cv2.FONT_HERSHEY_SIMPLEX, font, TEXT, thick, cv2.LINE_AA)
