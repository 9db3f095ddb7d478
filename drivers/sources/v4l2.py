"""A V4L2 camera (USB/UVC on a plain Raspberry Pi) opened through OpenCV's V4L2 backend.

Deliberately thin: parse `v4l2:/dev/video0?width=1920&height=1080&fps=30&fourcc=MJPG`, ask the
driver for that format, read back and log what it granted (drivers round to the modes they
have), and leave the rest to LiveSource. Order matters to V4L2: the pixel format first (it
decides which sizes exist), then the size, then the frame rate (which depends on both).

On a BlueOS vehicle the camera manager already holds the camera: read its RTSP stream instead.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2

from drivers.errors import SourceError
from drivers.sources.base import SourceOptions
from drivers.sources.live import LiveSource
from drivers.sources.opencv_capture import VideoCaptureLike, fourcc_code, fourcc_text
from drivers.sources.url import SourceUrl, parse_source_url, url_error

log = logging.getLogger(__name__)

V4L2_OPTIONS = ("width", "height", "fps", "fourcc", "buffers")
V4L2_SELECT_TIMEOUT_ENV = "OPENCV_VIDEOIO_V4L_SELECT_TIMEOUT"


@dataclass(frozen=True)
class V4l2Settings:
    """What to ask the camera for; None leaves the driver's current setting alone."""

    device: str
    width: int | None = None
    height: int | None = None
    fps: float | None = None
    fourcc: str | None = None
    # Driver buffers. 1 would be "always the newest", but some drivers stall with a single
    # buffer; 2 is a safe minimum and the grabber thread keeps only the newest anyway.
    buffers: int = 2


@dataclass(frozen=True)
class GrantedFormat:
    """What the driver actually delivers after negotiation."""

    width: int
    height: int
    fps: float
    fourcc: str


def parse_v4l2_url(url: str | SourceUrl) -> V4l2Settings:
    parsed = url if isinstance(url, SourceUrl) else parse_source_url(url)
    if parsed.scheme != "v4l2":
        raise url_error(parsed.raw, "not a v4l2: URL")
    parsed.check_options(V4L2_OPTIONS)
    device = parsed.path or "/dev/video0"
    if not (device.startswith("/dev/") or device.isdigit()):
        raise url_error(parsed.raw, f"device {device!r} must be a /dev path or a camera index")
    width = parsed.integer("width", None, 16, 16384)
    height = parsed.integer("height", None, 16, 16384)
    if (width is None) != (height is None):
        raise url_error(parsed.raw, "give both width and height, or neither")
    fourcc = parsed.options.get("fourcc")
    if fourcc is not None:
        # Codes are case-sensitive in V4L2, but the common ones are all upper case.
        fourcc = fourcc.upper() if fourcc.isalnum() else fourcc
        try:
            fourcc_code(fourcc)
        except ValueError as exc:
            raise url_error(parsed.raw, f"option fourcc: {exc}") from None
    buffers = parsed.integer_or("buffers", 2, 1, 32)
    return V4l2Settings(
        device=device,
        width=width,
        height=height,
        fps=parsed.number("fps", None, 0.1, 1000.0),
        fourcc=fourcc,
        buffers=buffers,
    )


def negotiate(cap: VideoCaptureLike, settings: V4l2Settings) -> GrantedFormat:
    """Request the format in `settings` and return what the driver granted (logged)."""
    if settings.fourcc is not None:
        cap.set(cv2.CAP_PROP_FOURCC, float(fourcc_code(settings.fourcc)))
    if settings.width is not None and settings.height is not None:
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, float(settings.width))
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, float(settings.height))
    if settings.fps is not None:
        cap.set(cv2.CAP_PROP_FPS, float(settings.fps))
    cap.set(cv2.CAP_PROP_BUFFERSIZE, float(settings.buffers))
    granted = GrantedFormat(
        width=int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
        height=int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
        fps=float(cap.get(cv2.CAP_PROP_FPS)),
        fourcc=fourcc_text(cap.get(cv2.CAP_PROP_FOURCC)),
    )
    mismatches = []
    if settings.width is not None and (granted.width, granted.height) != (
        settings.width,
        settings.height,
    ):
        mismatches.append(f"size {settings.width}x{settings.height}")
    if settings.fps is not None and not math.isclose(granted.fps, settings.fps, rel_tol=0.02):
        mismatches.append(f"fps {settings.fps:g}")
    if settings.fourcc is not None and granted.fourcc != settings.fourcc:
        mismatches.append(f"fourcc {settings.fourcc}")
    level = logging.WARNING if mismatches else logging.INFO
    log.log(
        level,
        "camera %s delivers %dx%d at %.4g fps, %s%s",
        settings.device,
        granted.width,
        granted.height,
        granted.fps,
        granted.fourcc or "unknown format",
        f" (asked for {', '.join(mismatches)}: not available)" if mismatches else "",
    )
    return granted


def _open_v4l2_capture(device: str) -> VideoCaptureLike:
    return cv2.VideoCapture(int(device) if device.isdigit() else device, cv2.CAP_V4L2)


# Where the kernel describes each video node (its `index` among its device's nodes).
SYSFS_VIDEO = Path("/sys/class/video4linux")


def _node_hint(device: str, sysfs: Path) -> str:
    """Why a node that exists gives no frames, when the kernel says: a UVC camera's second
    node (index 1) carries its frames' metadata, not frames."""
    if device.isdigit():
        device = f"/dev/video{device}"
    try:
        name = Path(device).resolve(strict=True).name  # /dev/v4l/by-id/... -> videoN
    except OSError:
        name = Path(device).name
    try:
        index = int((sysfs / name / "index").read_text().strip())
    except (OSError, ValueError):
        return ""
    if index == 0:
        return ""
    return (f"; {device} is node {index} of its device, which carries no frames (a UVC "
            "camera's metadata): use its node 0, /dev/v4l/by-id/...-video-index0, which also "
            "keeps its name when the camera is plugged in again")


class V4l2Source(LiveSource):
    """A V4L2 camera device; a camera that disappears is re-opened with backoff."""

    def __init__(
        self,
        url: str,
        options: SourceOptions | None = None,
        *,
        capture_factory: Callable[[str], VideoCaptureLike] = _open_v4l2_capture,
        sysfs: Path = SYSFS_VIDEO,
    ) -> None:
        super().__init__(url, options)
        self.settings = parse_v4l2_url(url)
        self._capture_factory = capture_factory
        self._sysfs = sysfs
        self.granted: GrantedFormat | None = None
        self._use_driver_timestamps = True

    @property
    def stated_size(self) -> tuple[int, int] | None:
        if self.settings.width is None or self.settings.height is None:
            return None
        return self.settings.width, self.settings.height

    def _connect(self) -> VideoCaptureLike:
        device = self.settings.device
        # OpenCV's V4L2 backend has no read time limit property: a camera that stops sending
        # blocks each read for OPENCV_VIDEOIO_V4L_SELECT_TIMEOUT seconds (default 10), read once
        # per process at the first frame. Bound it by the stall timeout unless the user set it.
        os.environ.setdefault(
            V4L2_SELECT_TIMEOUT_ENV, str(max(1, math.ceil(self._options.stall_timeout_s)))
        )
        try:
            cap = self._capture_factory(device)
        except Exception as exc:
            raise SourceError(self.url, f"OpenCV's V4L2 backend raised {exc}") from None
        if not cap.isOpened():
            cap.release()
            raise SourceError(
                self.url,
                f"cannot open {device} (missing, unplugged, no permission: is the user in "
                "group 'video'? or held by another program such as the BlueOS camera "
                f"manager){_node_hint(device, self._sysfs)}",
            )
        self.granted = negotiate(cap, self.settings)
        return cap

    def _capture_time(self, cap: VideoCaptureLike, received_mono: float,
                      read_s: float) -> float:
        """The driver's buffer timestamp when it is usable, else when read() returned.

        OpenCV's V4L2 backend reports the kernel's buffer timestamp as CAP_PROP_POS_MSEC; UVC
        and most CSI drivers stamp buffers with CLOCK_MONOTONIC at capture, which is what
        time.monotonic() reads on Linux. A value that is not within the last second is some
        other clock, and the driver's timestamps are ignored from then on.
        """
        if not self._use_driver_timestamps:
            return received_mono
        stamp = cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
        if received_mono - 1.0 <= stamp <= received_mono + 1e-3:
            return min(stamp, received_mono)
        if stamp > 0.0:
            self._use_driver_timestamps = False
            log.info(
                "camera %s: buffer timestamps are not on the monotonic clock; using read time",
                self.settings.device,
            )
        return received_mono

