"""The thin layer over cv2.VideoCapture shared by the camera, stream and file sources.

OpenCV is imported inside the functions, so importing drivers.sources stays cheap. Everything
here works on OpenCV 4.6 (Debian bookworm) as well as 5.x; properties that an older build lacks
are simply not requested.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, Protocol

import cv2

from drivers.errors import SourceError
from service.core.redact import redact_text


class VideoCaptureLike(Protocol):
    """The part of cv2.VideoCapture the sources use: the edge that tests replace with a fake."""

    def isOpened(self) -> bool: ...  # noqa: N802 - OpenCV's name
    def read(self) -> tuple[bool, Any]: ...
    def grab(self) -> bool: ...
    def retrieve(self) -> tuple[bool, Any]: ...
    def get(self, prop_id: int) -> float: ...
    def set(self, prop_id: int, value: float) -> bool: ...
    def release(self) -> None: ...


CaptureFactory = Callable[[], VideoCaptureLike]

# OpenCV's FFmpeg backend reads its demuxer/protocol options from this environment variable
# (key;value pairs joined by '|') each time a capture is opened; there is no per-capture API
# in OpenCV 4.6. The environment is process-wide, so the variable is set only for the duration
# of one open, under this lock, and restored afterwards. Caveat: another thread opening a
# capture without going through this module at the same instant would see our options.
FFMPEG_OPTIONS_ENV = "OPENCV_FFMPEG_CAPTURE_OPTIONS"
_FFMPEG_ENV_LOCK = threading.Lock()


@contextmanager
def ffmpeg_capture_options(options: str | None) -> Iterator[None]:
    """Set OPENCV_FFMPEG_CAPTURE_OPTIONS to `options` (None: leave as is) for one open."""
    if options is None:
        yield
        return
    with _FFMPEG_ENV_LOCK:
        previous = os.environ.get(FFMPEG_OPTIONS_ENV)
        os.environ[FFMPEG_OPTIONS_ENV] = options
        try:
            yield
        finally:
            if previous is None:
                os.environ.pop(FFMPEG_OPTIONS_ENV, None)
            else:
                os.environ[FFMPEG_OPTIONS_ENV] = previous


def timeout_params(open_timeout_s: float, read_timeout_s: float) -> list[int]:
    """VideoCapture open parameters for the FFmpeg backend's open and read time limits.

    Both properties exist since OpenCV 4.5.2; a build without them gets no parameters (an unknown
    parameter would make the open fail).
    """
    params: list[int] = []
    for name, seconds in (
        ("CAP_PROP_OPEN_TIMEOUT_MSEC", open_timeout_s),
        ("CAP_PROP_READ_TIMEOUT_MSEC", read_timeout_s),
    ):
        prop = getattr(cv2, name, None)
        if prop is not None:
            params += [int(prop), max(1, round(seconds * 1000.0))]
    return params


def open_ffmpeg_capture(
    url: str,
    target: str,
    *,
    options: str | None,
    open_timeout_s: float,
    read_timeout_s: float,
    failure: str | None = None,
) -> VideoCaptureLike:
    """A cv2.VideoCapture on `target` through the FFmpeg backend; SourceError naming `url`
    (with `failure` as the reason when given)."""
    params = timeout_params(open_timeout_s, read_timeout_s)
    with ffmpeg_capture_options(options):
        try:
            cap = cv2.VideoCapture(target, cv2.CAP_FFMPEG, params)
        except cv2.error as exc:
            raise SourceError(redact_text(url), f"OpenCV refused to open it: {exc}") from None
    if not cap.isOpened():
        cap.release()
        raise SourceError(
            redact_text(url),
            failure
            or f"OpenCV's FFmpeg backend could not open it within {open_timeout_s:g} s "
            "(nothing there, no stream yet, or a format FFmpeg does not know)",
        )
    return cap


# Codecs whose FFmpeg decoder uses frame threads (what cameras and BlueOS stream).
FRAME_THREADED_CODECS = frozenset({"h264", "avc1", "hevc", "hev1", "hvc1"})


def decoder_frames_held(cap: VideoCaptureLike) -> int:
    """How many frames FFmpeg's decoder holds back: one per frame thread past the first (it
    returns frame n once frame n + threads - 1 has come in; measured on loopback, docs/
    sources.md), for a codec it decodes with frame threads; 0 for any other or an unknown one.

    The thread count: what OpenCV reports (CAP_PROP_N_THREADS, newer than OpenCV 4.6); an
    OpenCV without that property gives its decoder one thread per online CPU
    (sysconf(_SC_NPROCESSORS_ONLN) in its FFmpeg backend, whatever the process's affinity:
    measured unchanged under `taskset`)."""
    prop = getattr(cv2, "CAP_PROP_N_THREADS", None)
    try:
        codec = fourcc_text(cap.get(cv2.CAP_PROP_FOURCC)).lower()
        threads = int(cap.get(int(prop))) if prop is not None else os.sysconf("SC_NPROCESSORS_ONLN")
    except (cv2.error, ValueError, OverflowError, OSError):
        return 0
    return max(0, threads - 1) if codec in FRAME_THREADED_CODECS else 0


def fourcc_text(code: float) -> str:
    """'MJPG' from the float OpenCV returns for CAP_PROP_FOURCC ('' when unknown)."""
    value = int(code)
    if value <= 0:
        return ""
    text = "".join(chr((value >> (8 * i)) & 0xFF) for i in range(4))
    return text if text.isprintable() else f"0x{value:08x}"


def fourcc_code(text: str) -> int:
    """The CAP_PROP_FOURCC value for a four-character code such as 'MJPG' or 'YUYV'."""
    if len(text) != 4 or not text.isascii():
        raise ValueError(f"a FOURCC has exactly 4 ASCII characters, got {text!r}")
    return sum(ord(c) << (8 * i) for i, c in enumerate(text))
