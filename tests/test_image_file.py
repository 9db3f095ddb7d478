"""Damaged still images are refused before anything is measured in them."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from service.core.image_file import DamagedImageError, damage_of, decode_image


def encoded(ext: str) -> bytes:
    image = np.random.default_rng(1).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    ok, data = cv2.imencode(ext, image)
    assert ok
    return data.tobytes()


@pytest.mark.parametrize("ext", [".jpg", ".png"])
def test_whole_images_decode_in_colour(ext: str) -> None:
    data = encoded(ext)
    assert damage_of(data) is None
    assert damage_of(data + b"\x00\x00\r\n") is None  # padding after the end marker is fine
    assert decode_image(data).shape == (48, 64, 3)


@pytest.mark.parametrize(("ext", "reason"), [(".jpg", "truncated JPEG"),
                                             (".png", "truncated PNG")])
@pytest.mark.parametrize("keep", [0.99, 0.5, 0.1])
def test_truncated_images_are_refused_naming_the_damage(ext: str, reason: str,
                                                        keep: float) -> None:
    data = encoded(ext)
    cut = data[: int(len(data) * keep)]
    assert damage_of(cut) == (f"{reason} (no end-of-image marker)" if ext == ".jpg"
                              else f"{reason} (no IEND chunk)")
    with pytest.raises(DamagedImageError, match=f"frame.jpg: {reason}"):
        decode_image(cut, "frame.jpg")


def test_empty_and_foreign_bytes() -> None:
    with pytest.raises(DamagedImageError, match="empty"):
        decode_image(b"", "x")
    with pytest.raises(DamagedImageError, match="not an image OpenCV can decode"):
        decode_image(b"GIF89a this is not much of a gif", "y")
