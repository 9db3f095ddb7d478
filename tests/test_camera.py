"""Camera model: calibration files (ROS camera_info YAML), lens model and resolution scaling."""

from __future__ import annotations

import importlib.util
import math
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from service.core.camera import (
    CameraModel,
    camera_from_ros_dict,
    load_camera,
    save_camera,
)
from service.core.errors import CalibrationError
from tests.shared_data import REAL_NET_DIR

REAL_DIR = REAL_NET_DIR
REAL_CALIBRATION = REAL_DIR / "camera_solaqua_1280x720.yaml"
REAL_FRAME = REAL_DIR / "net_1280x720.jpg"
needs_real_data = pytest.mark.skipif(
    not REAL_CALIBRATION.exists(), reason="real-net-frame data set not present"
)


def _valid_doc() -> dict[str, object]:
    return {
        "image_width": 640,
        "image_height": 480,
        "camera_name": "unit",
        "camera_matrix": {
            "rows": 3, "cols": 3, "data": [500.0, 0, 319.5, 0, 502.0, 239.5, 0, 0, 1]
        },
        "distortion_model": "plumb_bob",
        "distortion_coefficients": {"rows": 1, "cols": 5, "data": [-0.1, 0.02, 0.001, -0.002, 0]},
    }


def _write(tmp_path: Path, doc: object, name: str = "cam.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    return path


# -- files ----------------------------------------------------------------------------------------


def test_save_then_load_gives_the_same_camera(tmp_path: Path) -> None:
    camera = CameraModel(
        width=1920, height=1080, fx=1012.25, fy=1010.5, cx=955.125, cy=541.75,
        distortion=(-0.21, 0.083, 0.0012, -0.0007, -0.013), name="front", skew=0.25,
    )
    path = tmp_path / "front.yaml"
    save_camera(camera, path)
    assert load_camera(path) == camera
    # The file is plain ROS camera_info: a ROS tool reads these keys.
    doc = yaml.safe_load(path.read_text())
    assert doc["distortion_model"] == "plumb_bob"
    assert doc["camera_matrix"]["data"][0] == pytest.approx(1012.25)
    assert len(doc["projection_matrix"]["data"]) == 12


def test_rational_polynomial_round_trip(tmp_path: Path) -> None:
    camera = CameraModel(
        width=800, height=600, fx=600.0, fy=600.0, cx=400.0, cy=300.0,
        distortion=(0.1, -0.05, 0.0, 0.0, 0.01, 0.02, -0.01, 0.003),
    )
    path = tmp_path / "rational.yaml"
    save_camera(camera, path)
    assert yaml.safe_load(path.read_text())["distortion_model"] == "rational_polynomial"
    assert load_camera(path) == camera


@needs_real_data
def test_real_calibration_file_loads() -> None:
    camera = load_camera(REAL_CALIBRATION)
    assert (camera.width, camera.height) == (1280, 720)
    assert (camera.fx, camera.fy, camera.cx, camera.cy) == (882.0, 821.0, 680.0, 360.0)
    assert camera.distortion == pytest.approx((0.2037, 0.85736, 0.013247, -0.004259, -0.940367))
    assert camera.has_distortion


def test_camera_from_ros_dict_defaults_to_no_distortion() -> None:
    doc = _valid_doc()
    del doc["distortion_coefficients"]
    del doc["distortion_model"]
    camera = camera_from_ros_dict(doc)
    assert not camera.has_distortion
    assert camera.fy == 502.0


# -- lens model -----------------------------------------------------------------------------------


@needs_real_data
def test_undistort_and_project_are_inverse_over_the_whole_frame() -> None:
    camera = load_camera(REAL_CALIBRATION)
    u, v = np.meshgrid(np.linspace(0, 1279, 33), np.linspace(0, 719, 19))
    pixels = np.stack([u, v], axis=-1)
    normalized = camera.undistort_pixels(pixels)
    assert normalized.shape == pixels.shape
    # The lens is strong: the corners move by tens of pixels, so the inverse test means something.
    pinhole = normalized * [camera.fx, camera.fy] + [camera.cx, camera.cy]
    assert np.abs(pinhole - pixels).max() > 20.0
    # Measured 1e-12 px with the iterative undistortion; 1e-6 px is the required accuracy.
    assert np.abs(camera.project_normalized(normalized) - pixels).max() < 1e-6


def test_pinhole_undistort_is_the_matrix_inverse() -> None:
    camera = CameraModel(width=640, height=480, fx=500.0, fy=400.0, cx=320.0, cy=240.0)
    out = camera.undistort_pixels([[820.0, 40.0], [320.0, 240.0]])
    np.testing.assert_allclose(out, [[1.0, -0.5], [0.0, 0.0]], atol=1e-15)
    np.testing.assert_allclose(camera.project_normalized(out), [[820.0, 40.0], [320.0, 240.0]])


def test_scaled_to_half_resolution_uses_pixel_centres() -> None:
    camera = CameraModel(width=1280, height=720, fx=882.0, fy=821.0, cx=680.0, cy=360.0)
    half = camera.scaled_to(640, 360)
    assert (half.fx, half.fy) == (441.0, 410.5)
    # Pixel i's centre is at i, so full-res pixels 0 and 1 average into half-res pixel 0 whose
    # centre is full-res 0.5: x_half = (x_full + 0.5) / 2 - 0.5.
    assert half.cx == pytest.approx((680.0 + 0.5) / 2 - 0.5)
    assert half.cy == pytest.approx((360.0 + 0.5) / 2 - 0.5)
    # Same ray through corresponding points of both images.
    full_px = np.array([[100.5, 50.5], [1200.5, 700.5]])
    half_px = (full_px + 0.5) / 2 - 0.5
    np.testing.assert_allclose(
        half.undistort_pixels(half_px), camera.undistort_pixels(full_px), atol=1e-12
    )
    assert camera.scaled_to(1280, 720) is camera


def test_scaled_to_another_aspect_ratio_is_refused() -> None:
    camera = CameraModel(width=1280, height=720, fx=882.0, fy=821.0, cx=680.0, cy=360.0)
    with pytest.raises(CalibrationError, match="aspect ratio"):
        camera.scaled_to(640, 480)


@pytest.mark.parametrize(("size", "scales"), [
    ((960, 540), True), ((478, 267), True),  # resized: each side rounded to whole pixels
    ((1920, 1088), False), ((1920, 1072), False),  # a decoder's padding, a crop: 8 rows
    ((1904, 1080), False),  # 16 columns cropped
])
def test_only_a_resized_frame_takes_the_calibration_scaled(
    size: tuple[int, int], scales: bool
) -> None:
    """Stretching fx and fy apart for 8 rows of padding would bias every distance by about
    0.5 % (fy by 8/1080) at a sigma that does not know it: a frame more than the rounding of a
    resize from the calibrated size is refused, saying why."""
    camera = CameraModel(width=1920, height=1080, fx=1300.0, fy=1300.0, cx=960.0, cy=540.0)
    if scales:
        scaled = camera.scaled_to(*size)
        assert scaled.fx / scaled.fy == pytest.approx(1.0, abs=0.01)
    else:
        with pytest.raises(CalibrationError, match="cropped or padded"):
            camera.scaled_to(*size)


def test_a_strong_lens_is_inverted_exactly_on_every_opencv() -> None:
    """A 100 deg pincushion (k1 0.1, k2 0.3): OpenCV 4.6 (bookworm's, a Pi's) stops its
    iteration with corners 46 px off where OpenCV 5 gets within 0.003 px. Every pixel's ray
    must project back onto it, whichever OpenCV runs."""
    f = 0.5 * 1280 / math.tan(math.radians(50.0))
    camera = CameraModel(1280, 720, f, f, 639.5, 359.5, (0.1, 0.3, 0.0, 0.0, 0.0))
    v, u = np.mgrid[0:720:3, 0:1280:3].astype(np.float64)
    pixels = np.stack([u, v], axis=-1)
    back = camera.project_normalized(camera.undistort_pixels(pixels))
    assert float(np.abs(back - pixels).max()) < 1e-5


def test_a_lens_model_that_folds_within_the_frame_is_refused() -> None:
    """A tangential term of 0.1 at 100 deg: no ray reaches the frame's corners (the model
    folds first). Its rays there would be wrong (OpenCV 5's 279 px off, 4.6's NaN): the
    calibration is refused, saying where."""
    f = 0.5 * 1280 / math.tan(math.radians(50.0))
    camera = CameraModel(1280, 720, f, f, 639.5, 359.5, (0.0, 0.0, 0.0, 0.1, 0.0))
    corners = np.array([[0.0, 0.0], [1279.0, 0.0], [0.0, 719.0], [1279.0, 719.0]])
    with pytest.raises(CalibrationError, match="cannot be inverted at pixel"):
        camera.undistort_pixels(corners)


def test_a_skewed_camera_matrix_is_refused_and_a_tiny_skew_ignored() -> None:
    """OpenCV's model (projectPoints, undistortPoints) has no skew: a NaN or a real skew would
    be used by one path and not the other; rounding-size skew is kept in the file only."""
    for skew in (float("nan"), 50.0):
        with pytest.raises(CalibrationError, match="skew"):
            CameraModel(1280, 720, 900.0, 900.0, 640.0, 360.0, skew=skew)
    camera = CameraModel(1280, 720, 900.0, 900.0, 640.0, 360.0, skew=0.25)
    pixels = np.array([[10.0, 700.0], [1270.0, 20.0]])
    back = camera.project_normalized(camera.undistort_pixels(pixels))
    np.testing.assert_allclose(back, pixels, atol=1e-9)


def test_a_filestorage_matrix_of_the_wrong_size_names_the_file(tmp_path: Path) -> None:
    path = tmp_path / "one_row.yml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 1280)
    fs.write("image_height", 720)
    fs.write("camera_matrix", np.array([[900.0, 0.0, 640.0, 0.0, 900.0, 360.0]]))
    fs.release()
    with pytest.raises(CalibrationError, match=r"one_row\.yml: camera_matrix must have 9 values"):
        load_camera(path)


# -- bad files: a clear CalibrationError naming the problem ---------------------------------------


@pytest.mark.parametrize("text", [
    '<?xml version="1.0"?>\n<opencv_storage>\n<image_width>640\n',
    "%YAML:1.0\n---\nimage_width: 640\ncamera_matrix: !!opencv-matrix\n   rows: 3\n",
    '<?xml version="1.0"?>\n<opencv_storage>\n<image_width>abc</image_width>\n'
    "<image_height>480</image_height>\n<camera_matrix type_id=\"opencv-matrix\"><rows>3</rows>"
    "<cols>3</cols><dt>d</dt><data>500. 0. 319.5 0. 502. 239.5 0. 0. 1.</data></camera_matrix>"
    "\n</opencv_storage>\n",
], ids=["truncated-xml", "truncated-yml", "width-not-a-number"])
def test_a_broken_filestorage_file_is_a_calibration_error(tmp_path: Path, text: str) -> None:
    """OpenCV's parser raised SystemError on a truncated file (a traceback, exit 1 instead of
    78, and a SIGHUP to such a file ended the running daemon); a width it read as 1.8e308
    passed the check and failed at the first frame."""
    path = tmp_path / ("cam.xml" if text.startswith("<") else "cam.yml")
    path.write_text(text, encoding="utf-8")
    with pytest.raises(CalibrationError) as err:
        load_camera(path)
    assert str(path) in str(err.value)


def test_an_opencv_fisheye_calibration_is_refused_not_read_as_plumb_bob(tmp_path: Path) -> None:
    """OpenCV's calibration sample writes a fisheye lens as `fisheye_model: 1` with four
    coefficients, k1-k4 of the equidistant model. They were read as plumb-bob k1 k2 p1 p2: rays
    3.9 deg off at x = 1000 px, 19 deg in the corner, and `run --check` said OK."""
    path = tmp_path / "fisheye.yml"
    path.write_text(
        "%YAML 1.2\n---\nimage_width: 1280\nimage_height: 720\nfisheye_model: 1\n"
        "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
        "   data: [ 560., 0., 640., 0., 560., 360., 0., 0., 1. ]\n"
        "distortion_coefficients: !!opencv-matrix\n   rows: 4\n   cols: 1\n   dt: d\n"
        "   data: [ 0.05, -0.01, 0.003, -0.001 ]\n", encoding="utf-8")
    with pytest.raises(CalibrationError, match="fisheye") as err:
        load_camera(path)
    assert str(path) in str(err.value)
    path.write_text(path.read_text().replace("fisheye_model: 1", "fisheye_model: 0"))
    assert load_camera(path).distortion[:4] == (0.05, -0.01, 0.003, -0.001)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="not found") as err:
        load_camera(tmp_path / "nope.yaml")
    assert "nope.yaml" in str(err.value)


def test_invalid_yaml_names_the_line(tmp_path: Path) -> None:
    path = tmp_path / "broken.yaml"
    path.write_text("image_width: 640\nimage_height: 480\ncamera_matrix: [1, 2\n  : ]\n")
    with pytest.raises(CalibrationError, match=r"invalid YAML at line \d+") as err:
        load_camera(path)
    line = int(str(err.value).split("line ")[1].split()[0])
    assert 3 <= line <= 4  # the unclosed flow sequence starts on line 3


@pytest.mark.parametrize(
    ("edit", "expected"),
    [
        (lambda d: d.pop("camera_matrix"), "missing key 'camera_matrix'"),
        (lambda d: d.pop("image_width"), "missing key 'image_width'"),
        (
            lambda d: d["camera_matrix"].update(data=[500.0, 0, 319.5, 0, 502.0, 239.5, 0, 0]),
            "'camera_matrix' must have 9 values, got 8",
        ),
        (
            lambda d: d["camera_matrix"].update(data=[-500.0, 0, 319.5, 0, 502.0, 239.5, 0, 0, 1]),
            "fx must be positive",
        ),
        (lambda d: d.update(distortion_model="fisheye"), "distortion_model 'fisheye'"),
        (
            lambda d: d["distortion_coefficients"].update(data=[0.1, 0.2, 0.3]),
            "4, 5, 8, 12 or 14 values, got 3",
        ),
        (lambda d: d["camera_matrix"].update(data="wide"), "not a list of numbers"),
        (lambda d: d.update(image_width="big"), "must be integers"),
        # Stored column by column: the principal point read as (0, 0), the distances off by
        # 8 % on a rendered net, "acquired" at a tilt it did not have.
        (
            lambda d: d["camera_matrix"].update(data=[500.0, 0, 0, 0, 502.0, 0, 319.5, 239.5, 1]),
            "camera_matrix must be [fx, 0, cx, 0, fy, cy, 0, 0, 1]",
        ),
        (
            lambda d: d["camera_matrix"].update(data=[500.0, 0, 5000, 0, 502.0, -4000, 0, 0, 1]),
            "principal point (5000.0, -4000.0) lies outside the 640x480 image",
        ),
        (
            lambda d: d["camera_matrix"].update(data=[1e-6, 0, 319.5, 0, 1e-6, 239.5, 0, 0, 1]),
            "a field of view no lens has",
        ),
        (lambda d: d.update(image_width=10**9), "image size"),
        # The lens model folds over within the frame (no ray reaches the corners): refused
        # when the file is read, not at the first frame whose ROIs reach there.
        (
            lambda d: d["distortion_coefficients"].update(data=[-5.0, 0, 0, 0, 0]),
            "cannot be inverted at pixel",
        ),
    ],
    ids=[
        "no-camera-matrix", "no-width", "eight-values", "negative-fx", "fisheye",
        "three-distortion-values", "matrix-not-numbers", "width-not-integer",
        "matrix-transposed", "principal-point-outside", "focal-length-absurd", "width-absurd",
        "folding-lens",
    ],
)
def test_bad_content_is_a_clear_calibration_error(
    tmp_path: Path, edit: object, expected: str
) -> None:
    doc = _valid_doc()
    edit(doc)  # type: ignore[operator]
    path = _write(tmp_path, doc)
    with pytest.raises(CalibrationError) as err:
        load_camera(path)
    message = str(err.value)
    assert expected in message
    assert str(path) in message  # which file, for a user with several calibrations


def test_a_yaml_list_is_not_a_calibration(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="not a YAML mapping"):
        load_camera(_write(tmp_path, [1, 2, 3]))


# -- netpose command line: a bad calibration is one line on stderr, exit 78 ----------------------


def _netpose(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "service.cli", *args],
        capture_output=True, text=True, timeout=60, check=False,
    )


def _assert_one_line_calibration_error(result: subprocess.CompletedProcess[str], what: str) -> None:
    assert result.returncode == 78, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr  # no traceback
    assert lines[0].startswith("netpose: calibration error:")
    assert what in lines[0]


@pytest.mark.skipif(
    importlib.util.find_spec("service.commands.estimate") is None,
    reason="netpose estimate is not part of this build yet",
)
@needs_real_data
def test_estimate_cli_reports_a_bad_calibration_in_one_line(tmp_path: Path) -> None:
    doc = _valid_doc()
    doc["camera_matrix"] = {"rows": 3, "cols": 3, "data": [1.0, 2.0]}
    bad = _write(tmp_path, doc)
    result = _netpose(
        "estimate", str(REAL_FRAME), "--calibration", str(bad), "--mesh-size", "0.02"
    )
    _assert_one_line_calibration_error(result, "must have 9 values")


@needs_real_data
def test_undistort_cli_reports_a_bad_calibration_in_one_line(tmp_path: Path) -> None:
    doc = _valid_doc()
    doc["distortion_model"] = "equidistant"
    bad = _write(tmp_path, doc)
    out = tmp_path / "out.png"
    result = _netpose("undistort", str(REAL_FRAME), "--camera", str(bad), "-o", str(out))
    _assert_one_line_calibration_error(result, "distortion_model 'equidistant'")
    assert not out.exists()


def test_a_file_of_aliases_is_refused_before_it_expands(tmp_path: Path) -> None:
    """Aliases of aliases: a 574-byte file whose camera_matrix expands to 400 million numbers
    held the web page's upload (and the frame loop, through the GIL) for 25 s and 3.3 GB. A
    calibration has no use for aliases: refused as they are met (here 10^6 numbers)."""
    lines = ["a0: &a0 [1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0]"]
    for depth in range(1, 6):
        lines.append(f"a{depth}: &a{depth} [" + ", ".join([f"*a{depth - 1}"] * 10) + "]")
    lines += ["image_width: 640", "image_height: 360",
              "camera_matrix: {rows: 3, cols: 3, data: *a5}",
              "distortion_coefficients: {rows: 1, cols: 5, data: [0, 0, 0, 0, 0]}"]
    path = tmp_path / "bomb.yaml"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(CalibrationError, match=r"aliases \(\*name\) are not allowed"):
        load_camera(path)


def test_yaml_nested_beyond_the_parsers_depth_is_a_calibration_error(tmp_path: Path) -> None:
    path = tmp_path / "deep.yaml"
    path.write_text("image_width: " + "[" * 20000 + "]" * 20000 + "\n")
    with pytest.raises(CalibrationError, match="invalid YAML"):
        load_camera(path)
