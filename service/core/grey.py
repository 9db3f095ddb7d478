"""One grey conversion for every way a frame arrives: files, video, live sources and tests.

Why one: the estimator's verdict on a borderline frame can hinge on a single grey level, and the
usual conversions disagree by that much. `cv2.imread(path, IMREAD_GRAYSCALE)` lets libjpeg hand
out its own luma (Y of YCbCr, rounded its way), while a video decoder gives BGR that
`cv2.cvtColor(..., COLOR_BGR2GRAY)` turns into grey with OpenCV's fixed-point weights
(0.299 R + 0.587 G + 0.114 B). Every path therefore decodes to BGR and converts here, so the same
frame gives the same grey, and the same answer, however it arrived.

Decoding also checks the encoded bytes first (`encoded_damage`): OpenCV decodes a truncated JPEG
without an error (the missing rows come out flat grey, and libjpeg's warning only reaches
stderr), which would let a damaged frame produce a plausible but wrong distance.

Pure functions: bytes and arrays in, arrays out; reading files is the caller's business.
"""

from __future__ import annotations

import re
import struct
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from service.core.errors import EstimatorInputError

GrayImage = npt.NDArray[Any]  # 2-D; uint8 for decoded and camera frames
ColorImage = npt.NDArray[np.uint8]  # H x W x 3, BGR

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# What a folder of frames is read for (an `images:` source, `netpose estimate` and `netpose
# calibrate` given a folder): still formats OpenCV decodes.
IMAGE_SUFFIXES = frozenset(
    {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm", ".pnm"}
)


def is_image_name(path: Path) -> bool:
    """A frame's file by its name: an image suffix, and not hidden (macOS leaves an
    AppleDouble "._000.png" beside every file copied to exFAT or SMB: not an image, and sorted
    first it took the first frame numbers)."""
    return not path.name.startswith(".") and path.suffix.lower() in IMAGE_SUFFIXES


def frame_order(path: Path) -> tuple[tuple[str | int, ...], str]:
    """Sort key of a folder's frames: by name, its numbers by value, so that `frame_2.png`
    comes before `frame_10.png` (exporters often leave numbers unpadded; read as text, row
    "frame 2" was frame_10.png and every pairing with a truth table after it was wrong).
    Zero-padded names keep their order; equal numbers fall back to the name."""
    parts = re.split(r"(\d+)", path.name)
    return tuple(int(t) if i % 2 else t for i, t in enumerate(parts)), path.name


class DamagedImageError(EstimatorInputError):
    """Encoded image bytes that are truncated or corrupt: no estimate may come from them."""


def to_gray(image: npt.ArrayLike) -> GrayImage:
    """The grey image of a decoded frame: 2-D grey, H x W x 1, BGR or BGRA, any OpenCV depth.

    Colour goes through `cv2.cvtColor` (BGR2GRAY / BGRA2GRAY), the conversion a video decoder's
    BGR output gets. Grey input is returned as it is (no copy). Depths OpenCV cannot convert
    (e.g. float64, int32) become float32 first. Raises EstimatorInputError for any other shape.
    """
    import cv2

    arr = np.asarray(image)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.ndim == 2:
        return arr
    if arr.ndim != 3 or arr.shape[2] not in (3, 4):
        raise EstimatorInputError(
            f"expected a grey, BGR or BGRA image, got an array of shape {arr.shape}"
        )
    if arr.dtype not in (np.uint8, np.uint16, np.float32):
        arr = arr.astype(np.float32)
    code = cv2.COLOR_BGR2GRAY if arr.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
    return np.asarray(cv2.cvtColor(arr, code))


def encoded_damage(data: bytes) -> str | None:
    """Why these encoded image bytes are damaged, or None when they look intact.

    JPEG: the marker structure is walked from SOI to EOI, through every entropy-coded scan; a
    file that ends before EOI is truncated, and a marker that cannot occur (or a segment longer
    than the file) means corruption. PNG: every chunk's CRC is checked and IEND must be there.
    Other formats are only checked by decoding. A JPEG scan whose bits were flipped without
    creating an impossible marker decodes to a damaged picture that no structural check sees;
    that is the limit of this test.
    """
    if data[:2] == b"\xff\xd8":
        return _jpeg_damage(data)
    if data[:8] == _PNG_SIGNATURE:
        return _png_damage(data)
    return None


def decode_gray(data: bytes) -> tuple[GrayImage, ColorImage]:
    """Grey and BGR images of encoded bytes (JPEG, PNG, BMP, TIFF...). Raises DamagedImageError
    when the bytes are damaged or not an image."""
    import cv2

    if not data:
        raise DamagedImageError("empty file")
    damage = encoded_damage(data)
    if damage is not None:
        raise DamagedImageError(damage)
    # The pixels as the sensor gave them: a JPEG's EXIF orientation would turn the frame, and
    # the calibration describes the sensor's pixels, not the turned ones.
    encoded = np.frombuffer(data, np.uint8)
    flags = cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION
    color = cv2.imdecode(encoded, flags | cv2.IMREAD_ANYDEPTH)
    if color is not None and color.dtype == np.uint16:
        color = _eight_bits_of(color)
    elif color is not None and color.dtype != np.uint8:
        color = cv2.imdecode(encoded, flags)  # float TIFFs and the like: OpenCV's own scaling
    if color is None:
        raise DamagedImageError("cannot decode: not an image, or an unsupported format")
    bgr: ColorImage = np.asarray(color, dtype=np.uint8)
    return to_gray(bgr), bgr


def _eight_bits_of(wide: npt.NDArray[Any]) -> npt.NDArray[np.uint8]:
    """The top eight of the bits a 16-bit image's pixels use. Machine-vision cameras store 10-
    or 12-bit pixels in 16-bit PNGs: OpenCV's own cut (the container's top byte) would leave a
    12-bit frame 16 grey levels, and the net's faint contrast with them. The bits are read from
    the frame's brightest pixel (PNG's sBIT chunk is optional and OpenCV does not expose it):
    a dim frame gets more gain, which the estimator's contrast normalisation does not see."""
    shift = max(0, int(wide.max()).bit_length() - 8)
    return np.asarray(wide >> shift, dtype=np.uint8)


def _jpeg_damage(data: bytes) -> str | None:
    n = len(data)
    pos = 2
    while True:
        # Fill bytes (0xFF) may pad between segments.
        while pos < n and data[pos] == 0xFF and pos + 1 < n and data[pos + 1] == 0xFF:
            pos += 1
        if pos + 1 >= n:
            return "truncated JPEG (no end-of-image marker)"
        if data[pos] != 0xFF:
            return f"corrupt JPEG: marker expected at byte {pos}"
        marker = data[pos + 1]
        pos += 2
        if marker == 0xD9:  # EOI
            return None
        if 0xD0 <= marker <= 0xD7 or marker in (0x01, 0xD8):
            if marker == 0xD8:
                return f"corrupt JPEG: second start-of-image marker at byte {pos - 2}"
            continue  # stand-alone markers
        if marker < 0xC0:
            return f"corrupt JPEG: invalid marker 0xFF{marker:02X} at byte {pos - 2}"
        if pos + 2 > n:
            return "truncated JPEG (inside a segment header)"
        length = struct.unpack(">H", data[pos : pos + 2])[0]
        if length < 2:
            return f"corrupt JPEG: segment length {length} at byte {pos}"
        if pos + length > n:
            return "truncated JPEG (a segment runs past the end of the file)"
        pos += length
        if marker != 0xDA:  # not a start of scan
            continue
        # Entropy-coded data: 0xFF is followed by a stuffed 0x00, a restart marker or fill; any
        # other marker ends the scan (the next table or scan in a progressive file, or EOI).
        while True:
            pos = data.find(b"\xff", pos)
            if pos < 0 or pos + 1 >= n:
                return "truncated JPEG (image data ends before the end-of-image marker)"
            nxt = data[pos + 1]
            if nxt == 0x00 or 0xD0 <= nxt <= 0xD7 or nxt == 0xFF:
                pos += 1 if nxt == 0xFF else 2
                continue
            if nxt < 0xC0 or nxt == 0xD8:
                return f"corrupt JPEG: invalid marker 0xFF{nxt:02X} in the image data"
            break


def _png_damage(data: bytes) -> str | None:
    n = len(data)
    pos = len(_PNG_SIGNATURE)
    while True:
        if pos + 8 > n:
            return "truncated PNG (no IEND chunk)"
        length, kind = struct.unpack(">I4s", data[pos : pos + 8])
        end = pos + 8 + length + 4
        if end > n:
            return "truncated PNG (a chunk runs past the end of the file)"
        crc = struct.unpack(">I", data[end - 4 : end])[0]
        if zlib.crc32(data[pos + 4 : end - 4]) & 0xFFFFFFFF != crc:
            return f"corrupt PNG: CRC mismatch in a {kind.decode('latin-1')!r} chunk"
        if kind == b"IEND":
            return None
        pos = end
