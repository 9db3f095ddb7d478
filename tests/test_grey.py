"""One grey conversion (service.core.grey) for files, video, live sources and the estimator, and
damaged encoded frames refused before they can give a distance."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

from drivers.sources.base import split_gray_color
from service.core.errors import EstimatorInputError
from service.core.grey import DamagedImageError, decode_gray, encoded_damage, to_gray

U8 = npt.NDArray[np.uint8]


def _colour_scene(seed: int = 0, shape: tuple[int, int] = (96, 128)) -> U8:
    """A colourful BGR picture with edges and gradients: JPEG's chroma handling shows on it."""
    rng = np.random.default_rng(seed)
    h, w = shape
    y, x = np.mgrid[0:h, 0:w]
    b = 128 + 100 * np.sin(x / 5.0)
    g = 128 + 100 * np.cos(y / 7.0)
    r = rng.integers(0, 256, (h // 8, w // 8)).repeat(8, 0).repeat(8, 1)
    return np.clip(np.stack([b, g, r], axis=2), 0, 255).astype(np.uint8)


def _jpeg(image: U8, quality: int = 85) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert ok
    return bytes(buf)


def _png(image: U8) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", image)
    assert ok
    return bytes(buf)


def test_every_path_gives_the_same_grey() -> None:
    import cv2

    data = _jpeg(_colour_scene())
    decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    assert decoded is not None
    reference = cv2.cvtColor(decoded, cv2.COLOR_BGR2GRAY)
    gray, colour = decode_gray(data)  # files (netpose estimate)
    assert np.array_equal(gray, reference) and np.array_equal(colour, decoded)
    assert np.array_equal(to_gray(decoded), reference)  # the estimator's own input path
    live = split_gray_color(decoded, keep_color=False)  # video and live sources
    assert live is not None and np.array_equal(live[0], reference)
    bgra = cv2.cvtColor(decoded, cv2.COLOR_BGR2BGRA)
    assert np.array_equal(to_gray(bgra), reference)
    via_bgra = split_gray_color(bgra, keep_color=True)
    assert via_bgra is not None and np.array_equal(via_bgra[0], reference)
    # Why it matters: libjpeg's own grey decoding is another conversion (it differs on this
    # picture), which is exactly what the one conversion replaces.
    libjpeg_grey = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
    assert libjpeg_grey is not None
    assert int(np.abs(libjpeg_grey.astype(int) - reference.astype(int)).max()) >= 1


def _with_exif_orientation(jpeg: bytes, orientation: int) -> bytes:
    """`jpeg` with an EXIF segment saying how a viewer should turn it (as phones write)."""
    import struct

    ifd = struct.pack("<HHHIHHI", 1, 0x0112, 3, 1, orientation, 0, 0)  # one entry, SHORT
    tiff = b"II*\x00" + struct.pack("<I", 8) + ifd
    body = b"Exif\x00\x00" + tiff
    app1 = b"\xff\xe1" + struct.pack(">H", len(body) + 2) + body
    return jpeg[:2] + app1 + jpeg[2:]


def test_exif_orientation_does_not_turn_the_frame() -> None:
    """The calibration describes the sensor's pixels: a still whose EXIF says "turned 180"
    must be read as the sensor gave it (a real SOLAQUA frame so tagged read 1.136 m for
    1.106 m, 5 sigma off, when OpenCV turned it)."""
    image = _colour_scene(shape=(96, 128))
    plain = decode_gray(_jpeg(image))[0]
    tagged = decode_gray(_with_exif_orientation(_jpeg(image), 3))[0]
    assert np.array_equal(tagged, plain)


@pytest.mark.parametrize(("bits", "channels"), [(12, 1), (10, 3), (16, 1), (16, 3)])
def test_a_16_bit_image_keeps_its_grey_levels_whatever_bits_it_uses(
    bits: int, channels: int
) -> None:
    """Machine-vision cameras store 10- or 12-bit pixels in 16-bit PNGs. Cut to 8 bits by the
    container's depth (OpenCV's default: the top byte) a 12-bit frame keeps 16 grey levels of
    its 4096 and the net's contrast with them; cut by the bits the pixels use, it keeps 256,
    exactly the 8-bit frame those pixels were made from here."""
    import cv2

    colour = _colour_scene(shape=(96, 128))
    eight = colour if channels == 3 else cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY)
    wide = eight.astype(np.uint16) << (bits - 8)
    if bits == 16:
        wide |= eight.astype(np.uint16)  # full range: 255 -> 65535
    ok, png = cv2.imencode(".png", wide)
    assert ok
    grey, bgr = decode_gray(png.tobytes())
    expected_bgr = eight if channels == 3 else cv2.cvtColor(eight, cv2.COLOR_GRAY2BGR)
    assert bgr.dtype == np.uint8 and np.array_equal(bgr, expected_bgr)
    assert np.array_equal(grey, to_gray(expected_bgr))


def test_grey_input_passes_through_and_bad_shapes_are_refused() -> None:
    grey = np.arange(64, dtype=np.uint8).reshape(8, 8)
    assert to_gray(grey) is grey
    assert np.array_equal(to_gray(grey[:, :, None]), grey)
    with pytest.raises(EstimatorInputError, match="shape"):
        to_gray(np.zeros((8, 8, 2), np.uint8))
    with pytest.raises(EstimatorInputError, match="shape"):
        to_gray(np.zeros(64, np.uint8))


def test_intact_files_are_accepted() -> None:
    image = _colour_scene(1)
    for data in (_jpeg(image), _png(image)):
        assert encoded_damage(data) is None
        gray, _ = decode_gray(data)
        assert gray.shape == image.shape[:2]


@pytest.mark.parametrize("keep", [0.3, 0.6, 0.95, 0.999])
def test_truncated_jpeg_is_refused(keep: float) -> None:
    data = _jpeg(_colour_scene(2))
    with pytest.raises(DamagedImageError, match="truncated"):
        decode_gray(data[: int(len(data) * keep)])


def test_corrupt_jpeg_is_refused() -> None:
    data = bytearray(_jpeg(_colour_scene(3)))
    # An impossible marker in the middle of the scan data, as a flipped bit after 0xFF makes.
    pos = (data.index(b"\xff\xda") + len(data)) // 2
    data[pos : pos + 2] = b"\xff\x42"
    with pytest.raises(DamagedImageError, match="corrupt"):
        decode_gray(bytes(data))


def test_damaged_png_is_refused() -> None:
    data = bytearray(_png(_colour_scene(4)))
    with pytest.raises(DamagedImageError, match="truncated"):
        decode_gray(bytes(data[: len(data) - 30]))
    data[len(data) // 2] ^= 0x10
    with pytest.raises(DamagedImageError, match="CRC"):
        decode_gray(bytes(data))


def test_not_an_image_is_refused() -> None:
    with pytest.raises(DamagedImageError):
        decode_gray(b"not an image at all")
    with pytest.raises(DamagedImageError, match="empty"):
        decode_gray(b"")


def test_estimate_cli_refuses_a_truncated_jpeg(tmp_path: Path) -> None:
    import cv2

    from drivers.synthetic_net import NetPose, NetRenderer
    from service.benchmarks.scenes import PAPER_MESH, bench_camera
    from service.core.camera import save_camera

    camera = bench_camera(640, 360)
    frame, _ = NetRenderer(camera, PAPER_MESH, seed=1).render(
        NetPose(0.8, tilt_deg=10.0), rng=np.random.default_rng(1)
    )
    data = _jpeg(np.asarray(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR), np.uint8), 90)
    good = tmp_path / "good.jpg"
    bad = tmp_path / "bad.jpg"
    good.write_bytes(data)
    bad.write_bytes(data[: len(data) * 2 // 3])
    calibration = tmp_path / "camera.yaml"
    save_camera(camera, calibration)
    result = subprocess.run(
        [sys.executable, "-m", "service.cli", "estimate", str(good), str(bad),
         "--calibration", str(calibration), "--mesh-size", str(PAPER_MESH.bar_length_m)],
        capture_output=True, text=True, timeout=120, check=False,
    )
    assert result.returncode == 1, result.stderr
    lines = result.stdout.strip().splitlines()
    assert len(lines) == 2
    assert lines[0].startswith(f"{good}: net detected"), lines[0]
    # The damaged file: an error line, no distance, and a warning naming it.
    assert lines[1].startswith(f"{bad}: error: truncated JPEG"), lines[1]
    assert "range" not in lines[1] and "distance" not in lines[1]
    assert f"warning: {bad}" in result.stderr and "no estimate" in result.stderr
