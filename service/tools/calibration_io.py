"""Reading calibration input: image files, folders of images and videos, as named grey frames.

Videos are sampled: the video is cut into as many equal segments as frames are wanted, and each
segment contributes its sharpest frame showing the board unless that frame is blurred (well below
the median sharpness of the board frames) or nearly identical to a frame already taken (the board
held still). Whether a frame shows the board is asked first, on a small copy; sharpness is then
measured on the board alone, so a net or any fine texture behind it cannot outrank it. A video in
which the board is never seen is sampled by whole-frame sharpness, for the full-size detector and
the board-size hint to look at.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from service.core.errors import NetposeError
from service.core.grey import IMAGE_SUFFIXES, frame_order, is_image_name

GrayImage = npt.NDArray[np.uint8]

VIDEO_SUFFIXES = frozenset(
    {".mp4", ".mkv", ".avi", ".mov", ".webm", ".m4v", ".mpg", ".mpeg", ".ts", ".h264", ".h265"}
)
# A pick is "blurred" when its sharpness is below this fraction of the median over the frames
# scored (those showing the board, when any does).
BLUR_FRACTION = 0.5
# Mean absolute grey-level difference (0-255) of 64-px thumbnails below which frames are duplicates.
DUPLICATE_DIFFERENCE = 2.0
THUMBNAIL_WIDTH = 64
# Frames scored per segment of a long video (a segment is 1/max_frames of the video).
CANDIDATES_PER_SEGMENT = 8
# Frames are asked whether they show the board at this size (longer side, pixels). The
# sector-based detector found there every board the full-size detector found in the rendered
# test sets (up to 40 deg tilt, blurred, through a fisheye, 640x480 to 1920x1080): a board
# narrower than ~1/8 of the frame is missed, too small to calibrate with anyway. Its time grows
# with the size where a net fills the frame: 16 ms at 320, 43 ms at 400, 63 ms at 480 (a net of
# 14 px meshes in 640x480; the classic detector's FAST_CHECK took 29 ms on a net).
BOARD_CHECK_SIZE = 320
# Neighbouring squares of a board seen on the small copy must differ by at least this much
# (grey levels) in the checkerboard's sense: the meshes of a net, which the detector takes for a
# board now and then, are all alike (differences of 0-18 levels either way; a board: 210).
MIN_SQUARE_CONTRAST = 8.0

Progress = Callable[[int, int], None]


class CalibrationInputError(NetposeError):
    """An input named for calibration does not exist or cannot be decoded."""


@dataclass(frozen=True)
class Frame:
    name: str
    gray: GrayImage


@dataclass(frozen=True)
class InputPlan:
    """What will be read: still images and videos, in the order given."""

    images: tuple[Path, ...]
    videos: tuple[Path, ...]

    @property
    def count(self) -> int:
        return len(self.images) + len(self.videos)


def plan_inputs(inputs: Sequence[str | Path]) -> InputPlan:
    """Expand folders to the images inside them; refuse names that do not exist."""
    images: list[Path] = []
    videos: list[Path] = []
    for raw in inputs:
        path = Path(raw)
        if path.is_dir():
            found = sorted((p for p in path.iterdir() if is_image_name(p)), key=frame_order)
            if not found:
                raise CalibrationInputError(
                    f"{path}: folder contains no images ({', '.join(sorted(IMAGE_SUFFIXES))})"
                )
            images.extend(found)
        elif not path.exists():
            raise CalibrationInputError(f"{path}: no such file or folder")
        elif path.suffix.lower() in VIDEO_SUFFIXES:
            videos.append(path)
        else:
            images.append(path)
    if not images and not videos:
        raise CalibrationInputError("no input images or videos given")
    return InputPlan(images=tuple(images), videos=tuple(videos))


def read_image(path: Path) -> GrayImage:
    """One still image as 8-bit grey; a clear error if it is not an image OpenCV can decode."""
    try:
        data = np.fromfile(str(path), dtype=np.uint8)
    except OSError as exc:
        raise CalibrationInputError(f"{path}: cannot read ({exc.strerror})") from None
    # Sensor pixels, as the calibration must describe them (not turned by EXIF orientation).
    flags = cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION
    gray = cv2.imdecode(data, flags) if data.size else None
    if gray is None:
        raise CalibrationInputError(f"{path}: not an image OpenCV can decode")
    return np.asarray(gray, dtype=np.uint8)


def sharpness(gray: GrayImage) -> float:
    """Variance of the Laplacian on a half-size copy: high for crisp edges, low for blur."""
    small = cv2.resize(gray, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    return float(cv2.Laplacian(small, cv2.CV_32F).var())


def _thumbnail(gray: GrayImage) -> npt.NDArray[np.float32]:
    h, w = gray.shape[:2]
    size = (THUMBNAIL_WIDTH, max(1, round(THUMBNAIL_WIDTH * h / w)))
    return cv2.resize(gray, size, interpolation=cv2.INTER_AREA).astype(np.float32)


@dataclass(frozen=True)
class BoardRegion:
    """Where a board is in a frame: a box (full-size pixels) and its square size in pixels."""

    x0: int
    y0: int
    x1: int
    y1: int
    square: float


def board_region(gray: GrayImage, pattern: tuple[int, int]) -> BoardRegion | None:
    """The box around a `pattern` (inner corners) board, one square of margin on every side,
    asked of a small copy of `gray`; None when no such board is seen there."""
    height, width = gray.shape[:2]
    scale = min(1.0, BOARD_CHECK_SIZE / max(height, width))
    small = gray if scale == 1.0 else np.asarray(
        cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA), dtype=np.uint8
    )
    if hasattr(cv2, "findChessboardCornersSB"):
        found, corners = cv2.findChessboardCornersSB(
            small, pattern, flags=cv2.CALIB_CB_NORMALIZE_IMAGE
        )
    else:  # OpenCV < 4.3
        found, corners = cv2.findChessboardCorners(small, pattern, flags=cv2.CALIB_CB_FAST_CHECK)
    if not found or not _squares_alternate(small, np.asarray(corners, np.float32), pattern):
        return None
    points = np.asarray(corners, dtype=np.float64).reshape(-1, 2) / scale
    # Neighbours in detector order are one square apart, but for the jumps between rows.
    square = float(np.median(np.linalg.norm(np.diff(points, axis=0), axis=1)))
    (x0, y0), (x1, y1) = points.min(axis=0) - square, points.max(axis=0) + square
    return BoardRegion(max(0, int(x0)), max(0, int(y0)), min(width, int(np.ceil(x1))),
                       min(height, int(np.ceil(y1))), square)


def _squares_alternate(
    gray: GrayImage, corners: npt.NDArray[np.float32], pattern: tuple[int, int]
) -> bool:
    """Whether the squares between `corners` alternate dark and light, every neighbour pair of
    them: a checkerboard does, the look-alike grid the detector sometimes finds in a net not."""
    columns, rows = pattern
    grid = corners.reshape(rows, columns, 2)
    centres = (grid[:-1, :-1] + grid[1:, 1:] + grid[:-1, 1:] + grid[1:, :-1]) / 4.0
    smooth = cv2.blur(gray, (3, 3))  # one pixel of noise must not decide
    values = cv2.remap(smooth, centres[..., 0], centres[..., 1], cv2.INTER_LINEAR)
    signed = values.astype(np.float64) * np.where(np.indices(values.shape).sum(axis=0) % 2, -1, 1)
    # signed[a] + signed[b] = +-(value[a] - value[b]) for neighbours a, b: one sign on a board.
    steps = np.concatenate([(signed[:, :-1] + signed[:, 1:]).ravel(),
                            (signed[:-1] + signed[1:]).ravel()])
    return bool(np.all(steps >= MIN_SQUARE_CONTRAST) or np.all(steps <= -MIN_SQUARE_CONTRAST))


def board_sharpness(gray: GrayImage, region: BoardRegion) -> float:
    """Sharpness of the board alone, comparable between near and far, bright and dim boards.

    The Laplacian's variance grows with the contrast squared and with the edge length per area
    (one over the square size) as well as with sharpness: both are divided out, so the blur cut
    compares boards by their blur, not by how close or well lit they were."""
    crop = gray[region.y0 : region.y1, region.x0 : region.x1]
    contrast = float(np.var(crop)) if crop.size else 0.0
    if contrast < 1.0 or min(crop.shape[:2]) < 8:
        return 0.0
    return sharpness(crop) * region.square / contrast


@dataclass
class _Candidate:
    index: int
    sharpness: float
    gray: GrayImage


@dataclass(frozen=True)
class VideoSample:
    """What `sample_video` took from a video."""

    frames: list[Frame]
    decoded: int  # frames read
    skipped: int  # segment picks left out as blurred or duplicate
    board_seen: int  # frames scored that showed the board (0: sampled by whole-frame sharpness)


class _Picker:
    """The best frame of every segment: among frames that show the board, by the board's own
    sharpness; while no frame has shown it, by whole-frame sharpness (for the full-size detector
    and the board-size hint, when the board is of another size or never sharp enough)."""

    def __init__(self, pattern: tuple[int, int]) -> None:
        self.pattern = pattern
        self.board: dict[int, _Candidate] = {}
        self.board_scores: list[float] = []
        self.plain: dict[int, _Candidate] = {}
        self.plain_scores: list[float] = []

    def offer(self, segment: int, index: int, gray: GrayImage) -> None:
        region = board_region(gray, self.pattern)
        if region is not None:
            # The board is in this video: frames without it are of no use (and not kept).
            self.plain.clear()
            self.plain_scores.clear()
            self._keep(self.board, self.board_scores, segment,
                       _Candidate(index, board_sharpness(gray, region), gray))
        elif not self.board:
            self._keep(self.plain, self.plain_scores, segment,
                       _Candidate(index, sharpness(gray), gray))

    @staticmethod
    def _keep(
        best: dict[int, _Candidate], scores: list[float], segment: int, cand: _Candidate
    ) -> None:
        scores.append(cand.sharpness)
        current = best.get(segment)
        if current is None or cand.sharpness > current.sharpness:
            best[segment] = cand

    def picks(self) -> tuple[dict[int, _Candidate], list[float]]:
        if self.board:
            return self.board, self.board_scores
        return self.plain, self.plain_scores


def sample_video(
    path: Path, max_frames: int, pattern: tuple[int, int], progress: Progress | None = None
) -> VideoSample:
    """Up to `max_frames` sharp, distinct frames showing a `pattern` board, spread over the video.

    One decoding pass; memory holds one candidate frame per segment.
    """
    capture = cv2.VideoCapture(str(path))
    picker = _Picker(pattern)
    try:
        if not capture.isOpened():
            raise CalibrationInputError(f"{path}: cannot be opened as a video")
        total = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        if total <= 0:
            total = _count_frames(path)
        segments = max(1, min(max_frames, total))
        decoded = 0
        # Judge at most CANDIDATES_PER_SEGMENT frames per segment; the others are only grabbed
        # (demuxed and decoded, not converted or scored), which keeps long videos cheap.
        stride = max(1, total // (segments * CANDIDATES_PER_SEGMENT))
        while True:
            if decoded % stride:
                if not capture.grab():
                    break
                decoded += 1
                continue
            ok, frame = capture.read()
            if not ok:
                break
            gray = np.asarray(
                cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY) if frame.ndim == 3 else frame,
                dtype=np.uint8,
            )
            picker.offer(min(segments - 1, decoded * segments // max(total, 1)), decoded, gray)
            decoded += 1
            if progress is not None:
                progress(decoded, max(total, decoded))
        if progress is not None:
            progress(decoded, decoded)
    finally:
        capture.release()
    if decoded == 0:
        raise CalibrationInputError(f"{path}: no frame could be decoded")
    frames, skipped = _sharp_and_distinct(path, *picker.picks())
    return VideoSample(frames, decoded, skipped, len(picker.board_scores))


def _sharp_and_distinct(
    path: Path, best: dict[int, _Candidate], scores: list[float]
) -> tuple[list[Frame], int]:
    """The segments' picks less the blurred and the repeated ones, and how many were left out."""
    median = float(np.median(scores))
    frames: list[Frame] = []
    thumbs: list[npt.NDArray[np.float32]] = []
    skipped = 0
    for segment in sorted(best):
        cand = best[segment]
        if cand.sharpness < BLUR_FRACTION * median:
            skipped += 1
            continue
        thumb = _thumbnail(cand.gray)
        if any(float(np.mean(np.abs(thumb - t))) < DUPLICATE_DIFFERENCE for t in thumbs):
            skipped += 1
            continue
        thumbs.append(thumb)
        frames.append(Frame(name=f"{path.name}#{cand.index}", gray=cand.gray))
    return frames, skipped


def _count_frames(path: Path) -> int:
    """Frame count for containers that do not store one (raw H.264, some MJPEG streams)."""
    capture = cv2.VideoCapture(str(path))
    count = 0
    try:
        while capture.grab():
            count += 1
    finally:
        capture.release()
    return count


def iter_images(
    paths: Sequence[Path], progress: Progress | None = None
) -> Iterator[Frame]:
    """Decode still images one at a time (a folder of 4K photos need not fit in memory)."""
    for done, path in enumerate(paths, start=1):
        yield Frame(name=path.name, gray=read_image(path))
        if progress is not None:
            progress(done, len(paths))
