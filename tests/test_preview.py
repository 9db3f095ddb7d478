"""Preview drawing and JPEG encoding (service/preview.py), on a black canvas where every drawn
pixel can be accounted for, and on the real net frame."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from service.core.errors import NetposeError
from service.core.results import NetEstimate, RoiResult
from service.tools.preview import (
    NOT_DETECTED,
    REJECTED,
    USED,
    encode_jpeg,
    estimate_caption,
    render_preview,
)
from tests.shared_data import REAL_NET_FRAME, needs_real_net_frame

REAL_FRAME = REAL_NET_FRAME


def colour_mask(image: np.ndarray, colour: tuple[int, int, int]) -> np.ndarray:
    """Pixels whose colour points the way of `colour` (anti-aliasing against black only scales
    a colour down, so the direction, not the brightness, identifies it)."""
    pixels = image.astype(float)
    target = np.array(colour, dtype=float)
    norms = np.linalg.norm(pixels, axis=2) * np.linalg.norm(target)
    cosine = (pixels @ target) / np.maximum(norms, 1e-9)
    return (cosine > 0.99) & (norms > 0)


def square_roi(detected: bool = True, used: bool = True) -> RoiResult:
    # Full-resolution 1280x720 frame, previewed at 320 px: scale 1/4. The ROI (256 px square at
    # the centre) becomes x 128..192, y 58..122; the mesh edges (40 px) become 10 px cells.
    return RoiResult(center_px=(640.0, 360.0), size_px=256, level=0, detected=detected,
                     mesh_edges=((40.0, 0.0), (0.0, 40.0)) if detected else None,
                     cell_area_px=1600.0, used_in_fit=used)


def test_roi_and_mesh_are_drawn_where_they_are_and_nowhere_else() -> None:
    frame = np.zeros((720, 1280), np.uint8)
    original = frame.copy()
    image = render_preview(frame, [square_roi()], width=320)
    assert image.shape == (180, 320, 3) and image.dtype == np.uint8
    np.testing.assert_array_equal(frame, original)  # the frame is not drawn on

    drawn = image.max(axis=2) > 0
    ys, xs = np.nonzero(drawn)
    # Everything inside the scaled ROI square (1 px of anti-aliasing allowed).
    assert xs.min() >= 127 and xs.max() <= 193 and ys.min() >= 57 and ys.max() <= 123
    green = colour_mask(image, USED)
    assert green[drawn].mean() > 0.9  # a used ROI is green
    # Mesh lines of a 10 px lattice through the centre (160, 90): on the lines, not between.
    for x in (140, 150, 160, 170, 180):
        assert (green & (image[..., 1] > 150))[70:110, x].mean() > 0.9, x
    for y in (70, 80, 90, 100, 110):
        assert (green & (image[..., 1] > 150))[y, 140:180].mean() > 0.9, y
    assert not drawn[85, 155] and not drawn[95, 165]  # centres of cells stay untouched


@pytest.mark.parametrize(("roi", "colour"), [
    (square_roi(detected=True, used=False), REJECTED),
    (square_roi(detected=False), NOT_DETECTED),
])
def test_roi_colour_says_what_it_contributed(roi: RoiResult, colour: tuple[int, int, int]) -> None:
    image = render_preview(np.zeros((720, 1280, 3), np.uint8), [roi], width=320)
    drawn = image.max(axis=2) > 0
    assert colour_mask(image, colour)[drawn].mean() > 0.9
    if not roi.detected:  # no lattice: only the outline, the inside stays black
        assert not drawn[62:118, 132:188].any()


@needs_real_net_frame
def test_real_frame_with_caption_and_float_input() -> None:
    frame = cv2.imread(str(REAL_FRAME), cv2.IMREAD_GRAYSCALE)
    assert frame is not None
    estimate = NetEstimate(detected=True, confidence=0.49, normal=(0.0, 0.3, -0.954),
                           distance_m=0.84, sigma_distance_m=0.01, rois=(square_roi(),))
    caption = estimate_caption(estimate)
    assert caption == ["d 0.84 m +/- 0.010", "tilt 17 deg  conf 0.49"]  # acos(0.954) = 17.4
    # With the scale's share (the daemon's 2.24 %): hypot(10 mm, 18.8 mm) = 21.3 mm.
    assert estimate_caption(estimate, 0.02236)[0] == "d 0.84 m +/- 0.021"
    image = render_preview(frame, estimate.rois, caption, width=320)
    plain = render_preview(frame, [], width=320)
    # The downscale itself is faithful: compare with OpenCV's area resampling.
    reference = cv2.resize(frame, (320, 180), interpolation=cv2.INTER_AREA)
    np.testing.assert_array_equal(plain[..., 0], reference)
    changed = (image != plain).any(axis=2)
    assert changed[:45, :200].mean() > 0.05  # the caption, top left
    assert changed[58:123, 127:194].any() and not changed[130:, :].any()
    # A float frame in [0, 1] previews like the uint8 frame (to rounding).
    as_float = render_preview(frame.astype(np.float32) / 255.0, [], width=320)
    assert np.abs(as_float.astype(int) - plain.astype(int)).max() <= 1


def test_no_net_caption_and_no_upscaling() -> None:
    caption = estimate_caption(NetEstimate(detected=False, confidence=0.1, reason="no lattice"))
    assert caption == ["no net (no lattice)"]
    small = np.full((100, 200), 128, np.uint8)
    assert render_preview(small, [], width=320).shape == (100, 200, 3)


@needs_real_net_frame
def test_jpeg_round_trip_and_errors() -> None:
    frame = cv2.imread(str(REAL_FRAME), cv2.IMREAD_COLOR)
    assert frame is not None
    image = render_preview(frame, [square_roi()], ["x"], width=320)
    jpeg = encode_jpeg(image, quality=90)
    assert jpeg[:3] == b"\xff\xd8\xff"
    decoded = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert decoded is not None and decoded.shape == image.shape
    # Measured 4.2 levels mean error at quality 90 (busy net, thin coloured lines that JPEG's
    # chroma subsampling smears); a broken encoder or a channel swap would be far above 6.
    assert np.abs(decoded.astype(int) - image.astype(int)).mean() < 6.0
    assert len(encode_jpeg(image, quality=30)) < len(jpeg)
    with pytest.raises(NetposeError):
        encode_jpeg(image.astype(np.float32))
    with pytest.raises(NetposeError):
        render_preview(np.zeros((0, 5), np.uint8), [])
