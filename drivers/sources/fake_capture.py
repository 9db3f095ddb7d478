"""PC stand-ins for what cannot exist here: a V4L2 camera, and a numbered test pattern.

`FakeCamera` behaves like a UVC camera seen through OpenCV's V4L2 backend: it offers a list of
modes (pixel format, size, frame rate), snaps requests to the nearest mode it has the way
drivers do, stamps buffers with CLOCK_MONOTONIC, paces read() to its frame rate, and can be
unplugged and plugged back in. Pass `camera.open` as the V4l2Source capture factory.

`numbered_pattern` / `read_pattern_number` draw and read back a frame number as big black and
white blocks that survive lossy video coding, so tests can tell which frame came through.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from drivers.sources.opencv_capture import fourcc_code, fourcc_text

PATTERN_BITS = 16


def numbered_pattern(number: int, width: int = 320, height: int = 240) -> npt.NDArray[np.uint8]:
    """A grey frame showing `number` as PATTERN_BITS blocks (white = 1) in a 4x4 grid, framed
    by mid-grey so block edges are far from the image border."""
    image = np.full((height, width), 128, np.uint8)
    bw, bh = width // 5, height // 5
    for bit in range(PATTERN_BITS):
        row, col = divmod(bit, 4)
        y0, x0 = bh // 2 + row * bh, bw // 2 + col * bw
        image[y0 : y0 + bh, x0 : x0 + bw] = 255 if (number >> bit) & 1 else 0
    return image


def read_pattern_number(image: npt.NDArray[np.uint8]) -> int:
    """The number drawn by numbered_pattern, read from block centres (any size, grey)."""
    height, width = image.shape[:2]
    bw, bh = width // 5, height // 5
    number = 0
    for bit in range(PATTERN_BITS):
        row, col = divmod(bit, 4)
        yc, xc = bh // 2 + row * bh + bh // 2, bw // 2 + col * bw + bw // 2
        patch = image[yc - bh // 4 : yc + bh // 4, xc - bw // 4 : xc + bw // 4]
        if float(patch.mean()) > 128.0:
            number |= 1 << bit
    return number


@dataclass(frozen=True)
class CameraMode:
    fourcc: str
    width: int
    height: int
    fps: float


class FakeCamera:
    """A camera device with modes, a frame clock and a plug. Thread-safe."""

    def __init__(self, modes: Sequence[CameraMode], *, device: str = "/dev/video0") -> None:
        if not modes:
            raise ValueError("a camera has at least one mode")
        self.modes = tuple(modes)
        self.device = device
        self._lock = threading.Lock()
        self._plugged = True
        self._corrupt_next = 0
        self._fail_next = 0
        self.frames_made = 0
        self.opens = 0

    def unplug(self) -> None:
        with self._lock:
            self._plugged = False

    def plug(self) -> None:
        with self._lock:
            self._plugged = True

    @property
    def plugged(self) -> bool:
        with self._lock:
            return self._plugged

    def corrupt_next(self, count: int) -> None:
        """The next `count` frames come out as the truncated buffers a failing USB link gives."""
        with self._lock:
            self._corrupt_next += count

    def fail_next(self, count: int) -> None:
        """The next `count` reads fail at once, as OpenCV's decoder returns a frame it cannot
        decode (a stream joined between key frames): each takes a frame number."""
        with self._lock:
            self._fail_next += count

    def stop_failing(self) -> None:
        """Reads decode again (the stream's key frame came)."""
        with self._lock:
            self._fail_next = 0

    def _failing(self) -> bool:
        with self._lock:
            if self._fail_next <= 0 or not self._plugged:
                return False
            self._fail_next -= 1
            self.frames_made += 1
            return True

    def open(self, device: str) -> FakeCapture:
        """The capture factory: what cv2.VideoCapture(device, cv2.CAP_V4L2) would return."""
        with self._lock:
            self.opens += 1
            ok = self._plugged and device == self.device
        return FakeCapture(self, opened=ok)

    def _next_frame(self, mode: CameraMode) -> tuple[bool, npt.NDArray[np.uint8] | None]:
        with self._lock:
            if not self._plugged:
                return False, None
            number = self.frames_made
            self.frames_made += 1
            if self._corrupt_next > 0:
                self._corrupt_next -= 1
                return True, np.zeros((0,), np.uint8)
        gray = numbered_pattern(number, mode.width, mode.height)
        return True, np.repeat(gray[:, :, None], 3, axis=2)  # OpenCV converts to BGR


class FakeCapture:
    """cv2.VideoCapture(device, CAP_V4L2) on a FakeCamera, with the V4L2 backend's semantics."""

    def __init__(self, camera: FakeCamera, *, opened: bool) -> None:
        self._cv2 = cv2
        self._camera = camera
        self._opened = opened
        self._mode = camera.modes[0]
        self._requested_size: tuple[int | None, int | None] = (None, None)
        self._buffers = 4
        self._next_due = time.monotonic()
        self._stamp = 0.0
        self._grabbed: npt.NDArray[np.uint8] | None = None
        self.set_calls: list[tuple[int, float]] = []

    def isOpened(self) -> bool:  # noqa: N802 - OpenCV's name
        return self._opened

    def release(self) -> None:
        self._opened = False

    def read(self) -> tuple[bool, npt.NDArray[np.uint8] | None]:
        if not self._opened or self._camera._failing():
            return False, None
        now = time.monotonic()
        if self._next_due > now:
            time.sleep(self._next_due - now)
        self._next_due = max(self._next_due, now) + 1.0 / self._mode.fps
        ok, image = self._camera._next_frame(self._mode)
        if not ok:
            return False, None
        self._stamp = time.monotonic() - 0.002  # exposure ended a moment before the dequeue
        return True, image

    def grab(self) -> bool:
        ok, self._grabbed = self.read()
        return ok

    def retrieve(self) -> tuple[bool, npt.NDArray[np.uint8] | None]:
        image, self._grabbed = self._grabbed, None
        return image is not None, image

    def get(self, prop_id: int) -> float:
        cv2 = self._cv2
        values = {
            cv2.CAP_PROP_FRAME_WIDTH: float(self._mode.width),
            cv2.CAP_PROP_FRAME_HEIGHT: float(self._mode.height),
            cv2.CAP_PROP_FPS: float(self._mode.fps),
            cv2.CAP_PROP_FOURCC: float(fourcc_code(self._mode.fourcc)),
            cv2.CAP_PROP_BUFFERSIZE: float(self._buffers),
            cv2.CAP_PROP_POS_MSEC: self._stamp * 1000.0,
        }
        return values.get(prop_id, -1.0)

    def set(self, prop_id: int, value: float) -> bool:
        cv2 = self._cv2
        self.set_calls.append((prop_id, value))
        if not self._opened:
            return False
        if prop_id == cv2.CAP_PROP_FOURCC:
            wanted = fourcc_text(value)
            same = [m for m in self._camera.modes if m.fourcc == wanted]
            if not same:
                return False  # VIDIOC_S_FMT keeps the current format
            self._mode = self._nearest(same, self._mode.width, self._mode.height, self._mode.fps)
            return True
        if prop_id in (cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT):
            # Like OpenCV's V4L2 backend: the size changes once both width and height are set.
            w, h = self._requested_size
            if prop_id == cv2.CAP_PROP_FRAME_WIDTH:
                w = int(value)
            else:
                h = int(value)
            if w is None or h is None:
                self._requested_size = (w, h)
                return True
            self._requested_size = (None, None)
            same = [m for m in self._camera.modes if m.fourcc == self._mode.fourcc]
            self._mode = self._nearest(same, w, h, self._mode.fps)
            return True
        if prop_id == cv2.CAP_PROP_FPS:
            same = [
                m
                for m in self._camera.modes
                if (m.fourcc, m.width, m.height)
                == (self._mode.fourcc, self._mode.width, self._mode.height)
            ]
            self._mode = min(same, key=lambda m: abs(m.fps - value))
            return True
        if prop_id == cv2.CAP_PROP_BUFFERSIZE:
            self._buffers = max(1, int(value))
            return True
        return False

    @staticmethod
    def _nearest(modes: list[CameraMode], width: int, height: int, fps: float) -> CameraMode:
        # Drivers pick the closest size, then the closest rate that size offers.
        return min(
            modes,
            key=lambda m: (abs(m.width - width) + abs(m.height - height), abs(m.fps - fps)),
        )
