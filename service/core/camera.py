"""Camera model: intrinsics and plumb-bob distortion, read from and written to calibration files.

The on-disk format is the ROS camera_info YAML layout (what `camera_calibration` and most robotics
users already have). OpenCV FileStorage files (`cv2.FileStorage`, keys `camera_matrix` and
`distortion_coefficients`) are read too.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import yaml

from service.core.errors import CalibrationError
from service.core.files import read_small, write_atomically

FloatArray = npt.NDArray[np.float64]
# How far a frame may be from the calibrated size scaled and still count as that size
# resized (`CameraModel.scaled_to`): the rounding of each side, with room for one more pixel.
_RESIZE_SLACK_PX = 2.0
# OpenCV's projectPoints and undistortPoints leave a camera matrix's skew out; so does this
# model. Up to this share of fx (about a pixel) that changes a ray by under a pixel at the frame's
# edge; a larger skew is refused rather than ignored.
_SKEW_LIMIT = 1e-3
# Undistortion, checked (`CameraModel._inverted`): points projected back per call, how far they
# may land from where they came from, and how near the points that missed are then brought
# (the estimator differentiates rays 2 px apart: their errors must be far below that).
_INVERSION_SAMPLE = 4096
# Sanity of a calibration file: the largest image side (a 32K sensor), and the focal length as
# a multiple of the image side (0.05: a 169 deg field of view; 100: 0.6 deg).
_MAX_SIDE_PX = 32768
_FOCAL_RANGE = (0.05, 100.0)
# Where a file's lens model is checked to invert (a grid over the frame, edges included).
_CHECK_GRID = (17, 9)
# A calibration is a few kilobytes (an OpenCV file with comments, tens): a larger "file" is
# something else named by mistake, or a device.
_MAX_CALIBRATION_BYTES = 1 << 20
_INVERSION_TOLERANCE_PX = 1e-3
_INVERSION_TARGET_PX = 1e-6


@dataclass(frozen=True)
class CameraModel:
    """A pinhole camera with OpenCV plumb-bob distortion (k1, k2, p1, p2, k3)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    name: str = "camera"
    skew: float = field(default=0.0)

    def __post_init__(self) -> None:
        if not (0 < self.width <= _MAX_SIDE_PX and 0 < self.height <= _MAX_SIDE_PX):
            raise CalibrationError(f"image size must be positive and at most {_MAX_SIDE_PX} px "
                                   f"a side, got {self.width}x{self.height}")
        for label, value, side in (("fx", self.fx, self.width), ("fy", self.fy, self.height)):
            if not math.isfinite(value) or value <= 0:
                raise CalibrationError(f"camera_matrix {label} must be positive, got {value}")
            if not _FOCAL_RANGE[0] * side <= value <= _FOCAL_RANGE[1] * side:
                raise CalibrationError(
                    f"camera_matrix {label} = {value:g} px for a {side} px side is a field of "
                    "view no lens has: is the file for this camera, in pixels?")
        for label, value in (("cx", self.cx), ("cy", self.cy)):
            if not math.isfinite(value):
                raise CalibrationError(f"camera_matrix {label} is not finite")
        if not (0.0 <= self.cx <= self.width and 0.0 <= self.cy <= self.height):
            raise CalibrationError(
                f"principal point ({self.cx:.1f}, {self.cy:.1f}) lies outside the "
                f"{self.width}x{self.height} image: is the file for this resolution?")
        # OpenCV's lens model has no skew (calibrateCamera fixes it at zero; projectPoints and
        # undistortPoints leave it out): kept for the file's sake, used nowhere.
        if not (math.isfinite(self.skew) and abs(self.skew) <= _SKEW_LIMIT * self.fx):
            raise CalibrationError(
                f"camera_matrix skew (row 1, column 2) must be about 0, got {self.skew}: "
                "OpenCV's lens model has none (recalibrate with OpenCV or ROS "
                "camera_calibration)")
        if len(self.distortion) not in (4, 5, 8, 12, 14):
            raise CalibrationError(
                f"distortion_coefficients must have 4, 5, 8, 12 or 14 values, "
                f"got {len(self.distortion)}"
            )
        if not all(math.isfinite(d) for d in self.distortion):
            raise CalibrationError("distortion_coefficients contain a non-finite value")

    @property
    def matrix(self) -> FloatArray:
        return np.array(
            [[self.fx, self.skew, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]],
            dtype=np.float64,
        )

    @property
    def dist_coeffs(self) -> FloatArray:
        return np.asarray(self.distortion, dtype=np.float64)

    @property
    def has_distortion(self) -> bool:
        return any(abs(d) > 0.0 for d in self.distortion)

    def scaled_to(self, width: int, height: int) -> CameraModel:
        """The same lens at another resolution of the same sensor (same aspect ratio)."""
        if (width, height) == (self.width, self.height):
            return self
        sx, sy = width / self.width, height / self.height
        # A resize rounds each side to whole pixels: a frame that is the calibrated one scaled
        # matches it to a pixel or two. More is a crop or padding (a decoder's 1088 rows for
        # 1080), where stretching fx and fy apart would bias every distance (0.5 % for 8 rows
        # of 1080) at a sigma that does not know it.
        if min(abs(height - self.height * sx), abs(width - self.width * sy)) > _RESIZE_SLACK_PX:
            raise CalibrationError(
                f"calibration is for {self.width}x{self.height}; frames are {width}x{height}, "
                "not that size scaled (a different aspect ratio, or cropped or padded): "
                "recalibrate at this resolution"
            )
        # Pixel centres: OpenCV's convention puts pixel i's centre at i, so scale about -0.5.
        return CameraModel(
            width=width,
            height=height,
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5,
            cy=(self.cy + 0.5) * sy - 0.5,
            distortion=self.distortion,
            name=self.name,
            skew=self.skew * sx,
        )

    def undistort_pixels(self, pixels: npt.ArrayLike) -> FloatArray:
        """Distorted pixel coordinates (..., 2) -> undistorted normalised coordinates (..., 2)."""
        pts = np.asarray(pixels, dtype=np.float64)
        shape = pts.shape
        flat = pts.reshape(-1, 1, 2)
        if not self.has_distortion:
            out = np.empty_like(flat)
            out[..., 1] = (flat[..., 1] - self.cy) / self.fy
            out[..., 0] = (flat[..., 0] - self.cx) / self.fx  # no skew, as OpenCV's model
            return out.reshape(shape)
        # The default 5 iterations are not enough for strong underwater-housing distortion.
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x
            und = cv2.undistortPointsIter(flat, self.matrix, self.dist_coeffs, None, None, criteria)
        else:  # OpenCV 5 folded the iterative variant into undistortPoints
            und = cv2.undistortPoints(
                flat, self.matrix, self.dist_coeffs, R=None, P=None, criteria=criteria
            )
        inverted = self._inverted(pts.reshape(-1, 2), np.asarray(und, np.float64).reshape(-1, 2))
        return inverted.reshape(shape)

    def _inverted(self, pixels: FloatArray, guess: FloatArray) -> FloatArray:
        """`guess` (OpenCV's inversion of the lens at `pixels`) made exact where it is not.

        OpenCV 4.6 (Debian bookworm's, what a Pi runs) stops its fixed-point iteration without
        converging for a strong lens (a wide pincushion, large tangential terms: corners off by
        tens to thousands of pixels), or returns NaN, where OpenCV 5 inverts it to 1e-12 px;
        nothing downstream could tell, and a NaN corner ray stopped every frame. A sample of the
        points (and every non-finite one) is projected back; only when that shows a miss are
        all of them checked and the ones that miss refined by Newton steps on the forward model
        itself. A point still not inverted means the model folds over within the frame: no
        calibration for it."""
        n = len(pixels)
        bad = np.asarray(~np.isfinite(guess).all(axis=1), dtype=bool)
        sample = np.arange(0, n, max(1, n // _INVERSION_SAMPLE))
        miss = np.linalg.norm(self.project_normalized(np.nan_to_num(guess[sample]))
                              - pixels[sample], axis=1)
        if not bad.any() and not (miss > _INVERSION_TOLERANCE_PX).any():
            return guess
        linear = np.stack([(pixels[:, 0] - self.cx) / self.fx,
                           (pixels[:, 1] - self.cy) / self.fy], axis=1)
        out = np.where(bad[:, None], linear, guess)
        residual = self.project_normalized(out) - pixels
        todo = np.flatnonzero(~(np.linalg.norm(residual, axis=1) <= _INVERSION_TARGET_PX))
        h = 1e-7
        for _ in range(50):
            if todo.size == 0:
                break
            x = out[todo]
            f0 = residual[todo]
            jx = (self.project_normalized(x + [h, 0.0]) - pixels[todo] - f0) / h
            jy = (self.project_normalized(x + [0.0, h]) - pixels[todo] - f0) / h
            det = jx[:, 0] * jy[:, 1] - jy[:, 0] * jx[:, 1]
            safe = np.where(np.abs(det) > 1e-12, det, np.nan)
            step = np.stack([(jy[:, 1] * f0[:, 0] - jy[:, 0] * f0[:, 1]) / safe,
                             (jx[:, 0] * f0[:, 1] - jx[:, 1] * f0[:, 0]) / safe], axis=1)
            out[todo] = x - np.clip(np.nan_to_num(step), -0.2, 0.2)
            residual[todo] = self.project_normalized(out[todo]) - pixels[todo]
            todo = todo[~(np.linalg.norm(residual[todo], axis=1) <= _INVERSION_TARGET_PX)]
        todo = todo[~(np.linalg.norm(residual[todo], axis=1) <= _INVERSION_TOLERANCE_PX)]
        if todo.size:
            u, v = pixels[todo[0]]
            raise CalibrationError(
                f"the lens model cannot be inverted at pixel ({u:.0f}, {v:.0f}) of "
                f"{self.width}x{self.height} (its distortion folds the image over there): "
                "check the calibration's distortion coefficients, or recalibrate")
        return out

    def project_normalized(self, normalized: npt.ArrayLike) -> FloatArray:
        """Undistorted normalised coordinates (..., 2) -> distorted pixel coordinates (..., 2)."""
        pts = np.asarray(normalized, dtype=np.float64)
        shape = pts.shape
        obj = np.concatenate([pts.reshape(-1, 2), np.ones((pts.size // 2, 1))], axis=1)
        img, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), self.matrix, self.dist_coeffs)
        return np.asarray(img, dtype=np.float64).reshape(shape)

    def to_ros_dict(self) -> dict[str, Any]:
        k = self.matrix
        p = np.zeros((3, 4))
        p[:, :3] = k
        return {
            "image_width": int(self.width),
            "image_height": int(self.height),
            "camera_name": self.name,
            "camera_matrix": {"rows": 3, "cols": 3, "data": [float(v) for v in k.ravel()]},
            "distortion_model": "plumb_bob" if len(self.distortion) <= 5 else "rational_polynomial",
            "distortion_coefficients": {
                "rows": 1,
                "cols": len(self.distortion),
                "data": [float(v) for v in self.distortion],
            },
            "rectification_matrix": {
                "rows": 3,
                "cols": 3,
                "data": [float(v) for v in np.eye(3).ravel()],
            },
            "projection_matrix": {"rows": 3, "cols": 4, "data": [float(v) for v in p.ravel()]},
        }


def _matrix(doc: Mapping[str, Any], key: str, rows: int, cols: int | None) -> FloatArray:
    node = doc.get(key)
    if node is None:
        raise CalibrationError(f"missing key '{key}'")
    data = node.get("data") if isinstance(node, Mapping) else node
    try:
        arr = np.asarray(data, dtype=np.float64).ravel()
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"'{key}' data is not a list of numbers") from exc
    if cols is not None and arr.size != rows * cols:
        raise CalibrationError(f"'{key}' must have {rows * cols} values, got {arr.size}")
    return arr


def camera_from_ros_dict(doc: Mapping[str, Any], source: str = "calibration") -> CameraModel:
    """Build a camera from a parsed ROS camera_info YAML document."""
    if not isinstance(doc, Mapping):
        raise CalibrationError(f"{source}: not a YAML mapping")
    for key in ("image_width", "image_height"):
        if key not in doc:
            raise CalibrationError(f"{source}: missing key '{key}'")
    try:
        width, height = int(doc["image_width"]), int(doc["image_height"])
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"{source}: image_width/image_height must be integers") from exc
    try:
        k = _matrix(doc, "camera_matrix", 3, 3).reshape(3, 3)
        model = str(doc.get("distortion_model", "plumb_bob"))
        if model not in ("plumb_bob", "rational_polynomial"):
            raise CalibrationError(
                f"distortion_model '{model}' is not supported (use plumb_bob or "
                "rational_polynomial)"
            )
        dist = _matrix(doc, "distortion_coefficients", 1, None) if (
            "distortion_coefficients" in doc
        ) else np.zeros(5)
        if dist.size == 0:
            dist = np.zeros(5)
        return _from_matrix(k, dist, width, height, str(doc.get("camera_name", "camera")))
    except CalibrationError as exc:
        raise CalibrationError(f"{source}: {exc}") from None


def _load_opencv_storage(path: Path) -> CameraModel:
    unreadable = CalibrationError(f"{path}: cannot be parsed as YAML or OpenCV FileStorage")
    try:
        # A truncated file makes OpenCV's parser raise cv2.error, or SystemError from the
        # binding, rather than report a file it could not open.
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError):
        raise unreadable from None
    try:
        if not fs.isOpened():
            raise unreadable
        try:
            k = fs.getNode("camera_matrix").mat()
            d = fs.getNode("distortion_coefficients").mat()
            w_node, h_node = fs.getNode("image_width"), fs.getNode("image_height")
            missing = w_node.empty() or h_node.empty()
            size = (w_node.real(), h_node.real()) if not missing else (0.0, 0.0)
            fisheye = fs.getNode("fisheye_model")
            is_fisheye = not fisheye.empty() and fisheye.real() != 0.0
        except (cv2.error, SystemError):
            raise unreadable from None
        if is_fisheye:
            # OpenCV's calibration sample marks the equidistant model so: its four
            # coefficients are k1-k4 of another lens model, not plumb-bob's k1 k2 p1 p2.
            raise CalibrationError(
                f"{path}: fisheye_model is set: fisheye (equidistant) calibrations are not "
                "supported; calibrate with `netpose calibrate` (plumb_bob or rational_polynomial)")
        if k is None:
            raise CalibrationError(f"{path}: missing key 'camera_matrix'")
        if missing:
            raise CalibrationError(f"{path}: missing key 'image_width'/'image_height'")
        # A value that is not a number reads as 1.8e308 (its "real" value), not as an error.
        if not all(math.isfinite(v) and v == int(v) for v in size):
            raise CalibrationError(f"{path}: image_width/image_height must be integers")
        dist = np.zeros(5) if d is None else np.asarray(d, dtype=np.float64).ravel()
        try:
            return _from_matrix(k, dist, int(size[0]), int(size[1]), path.stem)
        except CalibrationError as exc:
            raise CalibrationError(f"{path}: {exc}") from None
    finally:
        fs.release()


def _from_matrix(k: npt.NDArray[Any], dist: npt.NDArray[Any], width: int,
                 height: int, name: str) -> CameraModel:
    """The model of a camera matrix K and its distortion coefficients, as both file formats
    store them."""
    k = np.asarray(k, dtype=np.float64)
    if k.size != 9:
        raise CalibrationError(f"camera_matrix must have 9 values (3x3), got {k.size}")
    k = k.reshape(3, 3)
    if not (k[1, 0] == 0.0 and k[2, 0] == 0.0 and k[2, 1] == 0.0 and k[2, 2] == 1.0):
        raise CalibrationError(
            "camera_matrix must be [fx, 0, cx, 0, fy, cy, 0, 0, 1] row by row, got "
            f"{[round(float(v), 3) for v in k.ravel()]} (stored column by column?)")
    return CameraModel(
        width=width,
        height=height,
        fx=float(k[0, 0]),
        fy=float(k[1, 1]),
        cx=float(k[0, 2]),
        cy=float(k[1, 2]),
        skew=float(k[0, 1]),
        distortion=tuple(float(v) for v in dist),
        name=name,
    )


class _CalibrationYamlLoader(yaml.SafeLoader):
    """YAML's safe loader without aliases. A calibration file has no use for them, and a
    574-byte file of aliases of aliases expands into 400 million numbers: a calibration
    uploaded on the web page held the interpreter for 25 s and 3.3 GB while the frame loop
    waited (the GIL)."""

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            raise yaml.composer.ComposerError(
                None, None, "aliases (*name) are not allowed in a calibration file",
                self.peek_event().start_mark)
        return super().compose_node(parent, index)


def load_camera(path: str | Path) -> CameraModel:
    """Read a calibration file (ROS camera_info YAML, or OpenCV FileStorage YAML/XML)."""
    p = Path(path)
    try:
        text = read_small(p, _MAX_CALIBRATION_BYTES).decode("utf-8")
    except FileNotFoundError:
        raise CalibrationError(f"{p}: calibration file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"{p}: cannot read calibration file ({exc})") from None
    if text.lstrip().startswith("%YAML") or p.suffix.lower() == ".xml" or "!!opencv-matrix" in text:
        camera = _load_opencv_storage(p)
    else:
        try:
            doc = yaml.load(text, Loader=_CalibrationYamlLoader)  # a SafeLoader
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            where = f" at line {mark.line + 1}" if mark is not None else ""
            problem = getattr(exc, "problem", None)
            raise CalibrationError(f"{p}: invalid YAML{where}"
                                   + (f" ({problem})" if problem else "")) from None
        except RecursionError:  # the parser recurses per nested list or mapping
            raise CalibrationError(f"{p}: invalid YAML (nested too deeply)") from None
        camera = camera_from_ros_dict(doc, source=str(p))
    check_invertible(camera, p)
    return camera


def check_invertible(camera: CameraModel, path: Path) -> None:
    """A lens model that folds over within the frame (k1 = 50: no ray reaches its edges) is
    refused when its file is read, not at the first frame whose ROIs reach there (and by
    `netpose calibrate` before it writes one); `path` names the file in the error."""
    cols, rows = _CHECK_GRID
    xs = np.linspace(0.0, camera.width - 1.0, cols)
    ys = np.linspace(0.0, camera.height - 1.0, rows)
    grid = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    try:
        camera.undistort_pixels(grid)
    except CalibrationError as exc:
        raise CalibrationError(f"{path}: {exc}") from None


def save_camera(camera: CameraModel, path: str | Path, *, durable: bool = True) -> None:
    """Write a calibration in the ROS camera_info YAML layout (`durable`: on the card when
    this returns; a recording's copy need not be)."""
    write_atomically(path, yaml.safe_dump(camera.to_ros_dict(), sort_keys=False,
                                          default_flow_style=None).encode("utf-8"),
                     durable=durable)
