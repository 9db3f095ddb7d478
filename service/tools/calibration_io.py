"""Reading calibration input: image files, folders of images and videos, as named grey frames.

Videos are sampled: the video is cut into as many equal segments as frames are wanted, and each
segment contributes its sharpest frame unless that frame is blurred (well below the video's median
sharpness) or nearly identical to a frame already taken (the board held still).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from service.core.errors import NetposeError
from service.core.grey import IMAGE_SUFFIXES, is_image_name

GrayImage = npt.NDArray[np.uint8]

VIDEO_SUFFIXES = frozenset(
    {".mp4", ".mkv", ".avi", ".mov", ".webm", ".m4v", ".mpg", ".mpeg", ".ts", ".h264", ".h265"}
)
# A frame is "blurred" when its sharpness is below this fraction of the video's median.
BLUR_FRACTION = 0.5
# Mean absolute grey-level difference (0-255) of 64-px thumbnails below which frames are duplicates.
DUPLICATE_DIFFERENCE = 2.0
THUMBNAIL_WIDTH = 64
# Frames scored per segment of a long video (a segment is 1/max_frames of the video).
CANDIDATES_PER_SEGMENT = 8

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
            found = sorted(p for p in path.iterdir() if is_image_name(p))
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


@dataclass
class _Candidate:
    index: int
    sharpness: float
    gray: GrayImage


def sample_video(
    path: Path, max_frames: int, progress: Progress | None = None
) -> tuple[list[Frame], int, int]:
    """Up to `max_frames` sharp, distinct frames spread over the video.

    Returns (frames, frames read, segment picks skipped as blurred or duplicate). One decoding
    pass; memory holds one candidate frame per segment.
    """
    capture = cv2.VideoCapture(str(path))
    try:
        if not capture.isOpened():
            raise CalibrationInputError(f"{path}: cannot be opened as a video")
        total = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        if total <= 0:
            total = _count_frames(path)
        segments = max(1, min(max_frames, total))
        best: dict[int, _Candidate] = {}
        scores: list[float] = []
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
            score = sharpness(gray)
            scores.append(score)
            segment = min(segments - 1, decoded * segments // max(total, 1))
            current = best.get(segment)
            if current is None or score > current.sharpness:
                best[segment] = _Candidate(decoded, score, np.ascontiguousarray(gray))
            decoded += 1
            if progress is not None:
                progress(decoded, max(total, decoded))
        if progress is not None:
            progress(decoded, decoded)
    finally:
        capture.release()
    if decoded == 0:
        raise CalibrationInputError(f"{path}: no frame could be decoded")
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
    return frames, decoded, skipped


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
