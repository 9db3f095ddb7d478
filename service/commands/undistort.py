"""`netpose undistort`: write an undistorted copy of an image or video frame with a calibration.

The point is a visual check of a calibration: straight edges (the board, a rope, a hull seam) must
come out straight. The side-by-side layout shows the original on the left.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from service.core.camera import CameraModel, load_camera
from service.core.errors import ConfigError, NetposeError
from service.tools.calibration_io import VIDEO_SUFFIXES, CalibrationInputError, read_image

Image = npt.NDArray[np.uint8]


def add_parser(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "undistort",
        help="write an undistorted preview of an image or video frame",
        description="Remove lens distortion from one image (or one video frame) with a "
        "calibration file, to check that straight lines come out straight.",
    )
    p.add_argument("input", type=Path, help="image or video file")
    p.add_argument(
        "--camera", "-c", type=Path, required=True,
        help="calibration file (ROS camera_info YAML or OpenCV FileStorage)",
    )
    p.add_argument("--output", "-o", type=Path, required=True,
                   help="image file to write (never the input)")
    p.add_argument("--force", action="store_true", help="overwrite OUTPUT if it exists")
    p.add_argument(
        "--alpha", type=float, default=0.0,
        help="0 = crop to valid pixels only, 1 = keep every source pixel (default 0)",
    )
    p.add_argument(
        "--frame", type=int, default=0, help="frame index when INPUT is a video (default 0)"
    )
    p.add_argument(
        "--side-by-side", action="store_true", help="original on the left, undistorted right"
    )
    p.set_defaults(handler=run)


def undistort_image(camera: CameraModel, image: Image, alpha: float = 0.0) -> Image:
    """`image` with the lens distortion of `camera` removed, same size, new pinhole intrinsics."""
    h, w = image.shape[:2]
    cam = camera.scaled_to(w, h)
    new_matrix, _roi = cv2.getOptimalNewCameraMatrix(
        cam.matrix, cam.dist_coeffs, (w, h), alpha, (w, h)
    )
    map_x, map_y = cv2.initUndistortRectifyMap(
        cam.matrix, cam.dist_coeffs, None, new_matrix, (w, h), cv2.CV_32FC1
    )
    return np.asarray(cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR), dtype=np.uint8)


def side_by_side(camera: CameraModel, image: Image, alpha: float = 0.0) -> Image:
    """Original | undistorted, with a thin separator, for eyeballing a calibration."""
    undistorted = undistort_image(camera, image, alpha)
    separator_shape = (image.shape[0], 4, *image.shape[2:])
    separator = np.full(separator_shape, 255, dtype=np.uint8)
    return np.concatenate([image, separator, undistorted], axis=1)


def _read_input(path: Path, frame_index: int) -> Image:
    if not path.exists():
        raise CalibrationInputError(f"{path}: no such file")
    if not path.is_file():
        raise CalibrationInputError(f"{path}: not a file (an image or a video)")
    if path.suffix.lower() not in VIDEO_SUFFIXES:
        image = cv2.imdecode(np.fromfile(str(path), dtype=np.uint8),
                             cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
        return read_image(path) if image is None else np.asarray(image, dtype=np.uint8)
    capture = cv2.VideoCapture(str(path))
    try:
        if not capture.isOpened():
            raise CalibrationInputError(f"{path}: cannot be opened as a video")
        ok, frame = False, None
        for _ in range(frame_index + 1):  # grab sequentially: seeking is inexact for many codecs
            ok, frame = capture.read()
            if not ok:
                break
    finally:
        capture.release()
    if not ok or frame is None:
        raise CalibrationInputError(f"{path}: has no frame {frame_index}")
    return np.asarray(frame, dtype=np.uint8)


def run(args: argparse.Namespace) -> int:
    if not 0.0 <= args.alpha <= 1.0:
        raise ConfigError("--alpha", f"must be between 0 and 1, got {args.alpha}")
    if args.frame < 0:
        raise ConfigError("--frame", f"must be >= 0, got {args.frame}")
    if args.output.exists():
        # Checked before any work, and --force never makes the input its own output: the
        # original is what the calibration is being checked against.
        if args.input.exists() and args.output.resolve() == args.input.resolve():
            raise ConfigError("--output", f"{args.output} would overwrite the input")
        if not args.force:
            raise ConfigError("--output", f"{args.output} exists (--force to overwrite it)")
    camera = load_camera(args.camera)
    image = _read_input(args.input, args.frame)
    out = side_by_side(camera, image, args.alpha) if args.side_by_side else (
        undistort_image(camera, image, args.alpha)
    )
    try:
        written = cv2.imwrite(str(args.output), out)
    except cv2.error:  # OpenCV 5 raises where 4.x returns False
        written = False
    if not written:
        raise NetposeError(f"{args.output}: cannot write (unknown image extension or folder?)")
    print(f"wrote {args.output}")
    return 0
