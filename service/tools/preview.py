"""Preview picture: a downscaled frame with the ROIs and the detected mesh drawn on it.

Drawing (`render_preview`) and encoding (`encode_jpeg`) are separate so the replay tool can draw
on frames it writes to a video. Both are pure: they return new arrays / bytes and never modify
the frame they are given.

Colours say what each ROI contributed: green = lattice found and used in the plane fit,
yellow = lattice found but rejected by the fit, grey = no lattice.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from service.core.errors import NetposeError
from service.core.results import NetEstimate, RoiResult
from service.core.scale import total_sigma

USED = (60, 220, 60)  # BGR
REJECTED = (0, 210, 230)
NOT_DETECTED = (150, 150, 150)
TEXT = (255, 255, 255)
# Mesh cells drawn either side of an ROI centre: enough to show the lattice's orientation and
# shear without hiding the picture.
CELLS_EACH_SIDE = 2


def estimate_caption(estimate: NetEstimate | None, scale: float = 0.0) -> list[str]:
    """Short text lines for a preview: distance and sigma (with the scale's share `scale`,
    service.core.scale), tilt and confidence, or why not."""
    if estimate is None:
        return []
    if not estimate.detected:
        return [f"no net ({estimate.reason or 'no net'})"]
    lines = []
    if estimate.distance_m is not None:
        text = f"d {estimate.distance_m:.2f} m"
        total = total_sigma(estimate.distance_m, estimate.sigma_distance_m, scale)
        if total is not None:
            # Millimetres: a precision of 3 mm read "+/- 0.00" to two decimals.
            text += f" +/- {total:.3f}"
        lines.append(text)
    details = []
    if estimate.tilt_deg is not None:
        details.append(f"tilt {estimate.tilt_deg:.0f} deg")
    details.append(f"conf {estimate.confidence:.2f}")
    lines.append("  ".join(details))
    return lines


def _scale_for(frame: np.ndarray, width: int) -> float:
    if frame.ndim not in (2, 3) or frame.shape[0] < 1 or frame.shape[1] < 1:
        raise NetposeError(f"preview needs an image, got an array of shape {frame.shape}")
    return min(1.0, width / frame.shape[1])


def render_preview(
    frame: np.ndarray,
    rois: Sequence[RoiResult],
    lines: Sequence[str] = (),
    width: int = 320,
) -> np.ndarray:
    """A BGR uint8 image at most `width` pixels wide with ROIs, mesh cells and text drawn.

    `frame` is grey (H, W) or BGR (H, W, 3), uint8 or float in [0, 1] / [0, 255]; ROI
    coordinates are in its full-resolution pixels (as the estimator reports them).
    """
    scale = _scale_for(frame, width)
    image = frame
    if image.dtype != np.uint8:
        peak = float(np.nanmax(image)) if image.size else 0.0
        factor = 255.0 if peak <= 1.0 else 1.0
        image = np.clip(np.nan_to_num(image) * factor, 0, 255).astype(np.uint8)
    if scale < 1.0:
        size = (max(1, round(frame.shape[1] * scale)), max(1, round(frame.shape[0] * scale)))
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()

    for roi in rois:
        _draw_roi(image, roi, scale)
    for row, text in enumerate(lines):
        origin = (6, 18 + 18 * row)
        # Dark outline first so the text reads on bright and dark water alike.
        cv2.putText(image, text, origin, cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(image, text, origin, cv2.FONT_HERSHEY_SIMPLEX, 0.5, TEXT, 1, cv2.LINE_AA)
    return image


def _draw_roi(image: np.ndarray, roi: RoiResult, scale: float) -> None:
    cx, cy = roi.center_px[0] * scale, roi.center_px[1] * scale
    half = roi.size_px * scale / 2.0
    x0, y0 = round(cx - half), round(cy - half)
    x1, y1 = round(cx + half), round(cy + half)
    colour = (USED if roi.used_in_fit else REJECTED) if roi.detected else NOT_DETECTED
    cv2.rectangle(image, (x0, y0), (x1, y1), colour, 1, cv2.LINE_AA)
    if not roi.detected or roi.mesh_edges is None:
        return
    e1 = np.asarray(roi.mesh_edges[0], dtype=float) * scale
    e2 = np.asarray(roi.mesh_edges[1], dtype=float) * scale
    if not (np.all(np.isfinite(e1)) and np.all(np.isfinite(e2))):
        return
    if min(math.hypot(*e1), math.hypot(*e2)) < 2.0:
        return  # cells smaller than 2 preview pixels would only paint the ROI solid
    rect = (x0, y0, max(1, x1 - x0), max(1, y1 - y0))
    centre = np.array([cx, cy])
    n = CELLS_EACH_SIDE
    # Lines along e1 at offsets j*e2 and along e2 at offsets j*e1, clipped to the ROI square.
    for along, across in ((e1, e2), (e2, e1)):
        for j in range(-n, n + 1):
            start = centre + j * across - n * along
            end = centre + j * across + n * along
            inside, p, q = cv2.clipLine(
                rect,
                (round(start[0]), round(start[1])),
                (round(end[0]), round(end[1])),
            )
            if inside:
                cv2.line(image, p, q, colour, 1, cv2.LINE_AA)


def encode_jpeg(image: np.ndarray, quality: int = 70) -> bytes:
    """JPEG bytes of a BGR or grey uint8 image."""
    if image.dtype != np.uint8:
        raise NetposeError(f"JPEG encoding needs uint8 pixels, got {image.dtype}")
    ok, buffer = cv2.imencode(".jpg", image, [int(cv2.IMWRITE_JPEG_QUALITY), int(quality)])
    if not ok:
        raise NetposeError("OpenCV could not encode the preview as JPEG")
    return bytes(buffer.tobytes())
