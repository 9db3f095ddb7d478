"""Still images from bytes, refusing damaged ones.

A truncated JPEG decodes "successfully": libjpeg pads the missing rows with grey and only warns
on stderr. The estimator then measures a mesh in two thirds of a frame and a flat band in the
rest, and reports a distance a few percent off with full confidence. So a container that is not
complete (a JPEG without its end-of-image marker, a PNG without its IEND chunk) is refused here,
before anything is measured, with a reason a person can act on.
"""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt

from service.core.errors import NetposeError

JPEG_SOI = b"\xff\xd8"
JPEG_EOI = b"\xff\xd9"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_IEND = b"IEND\xaeB`\x82"
# Bytes some writers leave after the end marker (padding to a block size).
_TRAILING_PADDING = b"\x00\r\n \t"


class DamagedImageError(NetposeError):
    """An image file is truncated or cannot be decoded."""


def damage_of(data: bytes) -> str | None:
    """Why `data` is not a complete image file, or None when its container is whole."""
    if not data:
        return "the file is empty"
    if data.startswith(JPEG_SOI):
        if not data.rstrip(_TRAILING_PADDING).endswith(JPEG_EOI):
            return "truncated JPEG (no end-of-image marker)"
    elif data.startswith(PNG_SIGNATURE) and not data.rstrip(_TRAILING_PADDING).endswith(PNG_IEND):
        return "truncated PNG (no IEND chunk)"
    return None


def decode_image(data: bytes, name: str = "image") -> npt.NDArray[np.uint8]:
    """The image in `data` as OpenCV decodes it in colour (BGR), or DamagedImageError."""
    reason = damage_of(data)
    if reason is not None:
        raise DamagedImageError(f"{name}: {reason}")
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_COLOR)
    if image is None or image.size == 0:
        raise DamagedImageError(f"{name}: not an image OpenCV can decode")
    return np.asarray(image, dtype=np.uint8)
