"""The frame-source interface: what the daemon, the tools and the tests read frames through.

A source hands out the newest frame it has, converted once to 8-bit grey (what the estimator
wants), with the time it was captured on both clocks and its frame number from the source, so a
consumer can see gaps. Live sources keep running while the consumer is busy and drop what it
misses; file-like sources can instead be read frame by frame without losing any.
"""

from __future__ import annotations

import time
from abc import abstractmethod
from dataclasses import dataclass
from enum import Enum
from typing import TYPE_CHECKING, Any, Self

import numpy as np
import numpy.typing as npt

from drivers.lifecycle import Closeable
from service.core.grey import to_gray
from service.core.redact import redact_text

if TYPE_CHECKING:
    from service.core.camera import CameraModel

GrayImage = npt.NDArray[np.uint8]
ColorImage = npt.NDArray[np.uint8]


@dataclass(frozen=True, eq=False)
class Frame:
    """One captured frame.

    `index` counts frames as the source produced them (a file's frame number, a camera's
    capture count): a jump of more than one means frames were dropped or unreadable.
    `t_monotonic` (time.monotonic) and `t_wall` (time.time) are the same capture instant,
    except for a netpose recording played back: its `t_wall` is the vehicle's own capture
    time, days ago perhaps, while `t_monotonic` follows the playback.
    `truth` is the ground truth of a synthetic frame (drivers.synthetic_net.GroundTruth).
    """

    image: GrayImage
    index: int
    t_monotonic: float
    t_wall: float
    color: ColorImage | None = None
    truth: object | None = None
    # The estimator's work level this frame got on the vehicle, when a recording says so
    # (service.core.budget): a replay gives it the same work. None: not recorded.
    budget: int | None = None
    # False when a recording says the vehicle read this frame without measuring it (a paced
    # search in open water, service/daemon/search_pace.py): a replay does not measure it either.
    measured: bool = True
    # Whether the vehicle searched this frame for holes, when a recording says so (its CPU
    # time chose): a replay searches the same frames. None: not recorded, the replay chooses.
    inspected: bool | None = None


class SourceState(Enum):
    OPENING = "opening"  # not opened yet, or the first open is under way
    UP = "up"  # frames are flowing
    DOWN = "down"  # lost (camera gone, stream stalled): being re-opened with backoff
    ENDED = "ended"  # a finite source (file without loop) has delivered its last frame
    CLOSED = "closed"  # close() was called


@dataclass(frozen=True)
class SourceStats:
    """Counters since open(). `drops` are frames the consumer never saw because a newer one
    replaced them; `corrupt` frames could not be decoded and were skipped."""

    state: SourceState
    frames: int  # handed to the consumer
    captured: int  # produced by the camera / stream / file
    drops: int
    corrupt: int
    reconnects: int
    fps: float  # recent capture rate, frames per second
    error: str = ""  # why the source is not delivering (empty while it is)


class FrameSource(Closeable):
    """Base of every frame source. Use as a context manager, or open() ... close()."""

    def __init__(self, url: str) -> None:
        self._url = url

    @property
    def url(self) -> str:
        return self._url

    @property
    def camera(self) -> CameraModel | None:
        """The camera this source describes itself (synthetic only); None for real cameras."""
        return None

    @property
    def stated_size(self) -> tuple[int, int] | None:
        """(width, height) of the frames this source's URL asks for, known before open();
        None when only the frames will tell (a stream, a file, a camera left to its driver)."""
        return None

    @property
    def rendered(self) -> bool:
        """True for sources that render a scene instead of filming one (synthetic:, sim:): their
        distances are not facts about the water and never reach an autopilot unless the
        configuration says so (mavlink.allow_simulated)."""
        return False

    @property
    def recorded(self) -> bool:
        """True for sources that play frames filmed earlier (a video file, an image folder, a
        netpose recording): not what the vehicle's camera sees now, so, like a rendered source,
        their distances reach an autopilot only with mavlink.allow_simulated."""
        return False

    @abstractmethod
    def open(self) -> None:
        """Start delivering frames; raises drivers.errors.SourceError if that is impossible."""

    @abstractmethod
    def read(self, timeout_s: float) -> Frame | None:
        """The newest frame not yet returned, waiting at most `timeout_s`; None if none came."""

    @property
    @abstractmethod
    def state(self) -> SourceState: ...

    @abstractmethod
    def stats(self) -> SourceStats: ...

    @abstractmethod
    def close(self) -> None:
        """Stop and release everything (idempotent)."""

    def __enter__(self) -> Self:
        self.open()
        return self


    def __repr__(self) -> str:
        return f"{type(self).__name__}({redact_text(self._url)!r})"


def split_gray_color(image: Any, keep_color: bool) -> tuple[GrayImage, ColorImage | None] | None:
    """Grey (and optionally the colour original) of a decoded image; None if it is unusable.

    OpenCV hands out BGR, BGRA or single-channel 8-bit images depending on backend and format.
    """
    import cv2

    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.size == 0:
        return None
    if image.ndim == 3 and image.shape[2] == 4:
        image = _u8(cv2.cvtColor(image, cv2.COLOR_BGRA2BGR))
    if image.ndim == 3 and image.shape[2] == 3:
        return _u8(to_gray(image)), (image if keep_color else None)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim != 2:
        return None
    gray = np.ascontiguousarray(image)
    return gray, (_u8(cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)) if keep_color else None)


def _u8(image: Any) -> npt.NDArray[np.uint8]:
    return np.asarray(image, dtype=np.uint8)  # no copy: OpenCV already returns uint8


def wall_time_of(t_monotonic: float) -> float:
    """time.time() at the instant `t_monotonic` (a recent time.monotonic() value)."""
    return time.time() - (time.monotonic() - t_monotonic)


class RateMeter:
    """Event rate over a sliding time constant (exponentially weighted), events per second."""

    def __init__(self, time_constant_s: float = 2.0) -> None:
        self._tau = time_constant_s
        self._rate = 0.0
        self._last: float | None = None

    def tick(self, now: float) -> None:
        if self._last is not None:
            dt = max(now - self._last, 1e-6)
            if self._rate == 0.0:
                self._rate = 1.0 / dt  # the first interval is the best guess there is
            else:
                weight = min(dt / self._tau, 1.0)
                self._rate += weight * (1.0 / dt - self._rate)
        self._last = now

    def rate(self, now: float) -> float:
        if self._last is None:
            return 0.0
        # Silence pulls the rate down: no event for a while means the rate is at most 1/gap.
        gap = now - self._last
        return min(self._rate, 1.0 / gap) if gap > 0 else self._rate


@dataclass(frozen=True)
class SourceOptions:
    """How a source behaves, beyond what its URL says (the daemon fills this from its config).

    keep_color: also hand out the BGR image (preview); grey is always there.
    stall_timeout_s: a live source with no frame for this long is re-opened (also the read
        time limit handed to FFmpeg).
    wait_at_start: a source that cannot be opened at start (camera not plugged in, stream not
        served yet, file not there) is retried with backoff like one lost later, instead of
        open() raising: what a service wants (the camera manager may start after it); tools
        that read one recording want the error at once (the default).
    open_timeout_s: longest single attempt to open a network stream.
    reconnect_min_s / reconnect_max_s: the backoff between re-open attempts while the source
        stays down (service/core/backoff.py): its first wait (a live source probes every
        0.25 s while the outage is young instead) and its longest; the waits grow with the
        outage's age.
    ffmpeg_options: replaces the stream source's low-latency FFmpeg options
        ("key;value|key;value", see docs/sources.md); None keeps the defaults.
    realtime_default: file-like sources (file:, images:, recording:) are paced to their frame
        rate unless their URL says `realtime`: what a service wants (it serves the present:
        read faster than that, media time runs ahead of its clock); tools that read a
        recording want every frame at once (the default).
    """

    keep_color: bool = False
    stall_timeout_s: float = 3.0
    open_timeout_s: float = 5.0
    reconnect_min_s: float = 0.5
    reconnect_max_s: float = 10.0
    ffmpeg_options: str | None = None
    wait_at_start: bool = False
    realtime_default: bool = False

    def __post_init__(self) -> None:
        from service.core.errors import ConfigError

        for name in ("stall_timeout_s", "open_timeout_s", "reconnect_min_s", "reconnect_max_s"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and 0.01 <= value <= 3600.0):
                raise ConfigError(f"source.{name}", f"must be 0.01..3600 s, got {value!r}")
        if self.reconnect_max_s < self.reconnect_min_s:
            raise ConfigError("source.reconnect_max_s", "must not be below reconnect_min_s")
