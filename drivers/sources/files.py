"""Recorded frames: a video file (`file:`) or a folder of images (`images:`).

    file:dive.mp4?loop=1&realtime=1     replay a recording, endlessly, at its own frame rate
    images:frames/?fps=10               every image in frames/, in name order, as 10 fps
    images:frames/*.png                 a glob pattern instead of a whole folder

Options: `loop` (start again after the last frame), `realtime` (pace to the frame rate and drop
what the consumer misses; default: as fast as the consumer reads, nothing lost), `fps` (the
rate of an image folder, default 10; for a video, only used when the file does not say).
A frame that cannot be decoded is counted as corrupt and skipped; a file that cannot be opened
at all, or has no decodable frame, is an error naming the URL.
"""

from __future__ import annotations

import glob
import itertools
import logging
import statistics
from pathlib import Path
from typing import Any

import cv2

from drivers.errors import SourceError
from drivers.sources.base import SourceOptions
from drivers.sources.opencv_capture import VideoCaptureLike, open_ffmpeg_capture
from drivers.sources.paced import EndOfMediaError, MediaFrame, MediaGoneError, PacedSource
from drivers.sources.url import SourceUrl, parse_source_url, url_error
from service.core.grey import (
    IMAGE_SUFFIXES,
    DamagedImageError,
    decode_gray,
    frame_order,
    is_image_name,
)

log = logging.getLogger(__name__)

FILE_OPTIONS = ("loop", "realtime", "fps")
DEFAULT_IMAGE_FPS = 10.0
# Failed reads in a row that mean "end of file" rather than "a damaged frame". OpenCV's FFmpeg
# backend returns False both for a frame the decoder rejects (and goes on with the next one) and
# at the end, so failures only count as corrupt frames once a good frame follows them.
END_AFTER_FAILED_READS = 8
# A gap in a video's timestamps longer than this is a discontinuity (files joined, an encoder
# restarted: hours, or a wrap), not a stretch the camera missed: those are kept as they were,
# and longer than the tracker's coasting, so a replay shows the outage it was.
MAX_TIMESTAMP_GAP_S = 60.0
# A step between two frames shorter than this share of the stated period cannot happen at that
# rate: the rate varies (a phone's or a browser's recording, such as Cockpit's).
VARIABLE_SHORT_STEP = 0.75
# ... and a typical (median) step this many stated periods long or more says that the stated
# rate is not the frames' (a container stating its time base, or a maximum rate).
VARIABLE_TYPICAL_STEP = 1.25
# Frames whose timestamps are read at open, to tell a varying rate from the start: up to this
# many, or this much of the video (a phone recording steady for its first half second was
# numbered two ways).
TIMELINE_PROBE_FRAMES = 90
TIMELINE_PROBE_S = 3.0
# A container may state its average rate (frames over duration) rather than its frames' own:
# a 10 fps recording that lost a second in 25 s states 9.6 fps. When the steps between the
# first frames are steady (all but a few within STEADY_STEP_SPREAD of their mean, the rest
# gaps) and that mean says a rate more than STATED_RATE_TOLERANCE from the stated one, the
# frames' own rate numbers and times them.
STEADY_STEP_SPREAD = 0.05
STEADY_STEP_SPREAD_S = 0.002  # ... or the 1 ms ticks of a millisecond time base, and a margin
STEADY_MIN_STEPS = 8
STATED_RATE_TOLERANCE = 0.01
# ... up to this far from it: a camera that lost a tenth of its frames is a bad recording, one
# that differs by more changed its rate after the first seconds (a UVC camera halves it in low
# light: 30 then 15 fps states 21 fps), which numbered at the first rate gave every later frame
# a number 15 too high and counted 15 frames lost that never were (diff review). Such a file
# keeps the stated rate, and its varying steps are found as they come (`rate_varies`).
MAX_LOST_SHARE = 0.10


def _parse(url: str, scheme: str) -> SourceUrl:
    parsed = parse_source_url(url)
    if parsed.scheme != scheme:
        raise url_error(url, f"not a {scheme}: URL")
    parsed.check_options(FILE_OPTIONS)
    if not parsed.path:
        raise url_error(url, f"{scheme}: needs a path")
    return parsed


def rate_varies(steps_s: list[float], period_s: float) -> bool:
    """Whether steps between consecutive frames (their timestamps' differences, discontinuities
    left out) show a rate other than the stated constant one."""
    if any(step < VARIABLE_SHORT_STEP * period_s for step in steps_s):
        return True
    return len(steps_s) >= 3 and statistics.median(steps_s) >= VARIABLE_TYPICAL_STEP * period_s


def steady_rate(steps_s: list[float]) -> float | None:
    """The frame rate that steady steps between frames show (gaps, such as frames a camera
    missed, left out); None when there are too few steps or they vary (a phone's recording)."""
    if len(steps_s) < STEADY_MIN_STEPS:
        return None
    typical = statistics.median(steps_s)
    regular = [step for step in steps_s if 0.5 * typical <= step <= 1.5 * typical]
    if len(regular) < 0.8 * len(steps_s):
        return None
    mean = statistics.fmean(regular)
    if any(abs(step - mean) > max(STEADY_STEP_SPREAD * mean, STEADY_STEP_SPREAD_S)
           for step in regular):
        return None
    return 1.0 / mean


class _Timeline:
    """Numbers and media times of a video's frames, from their presentation timestamps.

    At a constant rate a frame's number is its time over the period: frames the camera or the
    encoder missed leave gaps in the numbers (a replay shows the outage, and the source counts
    them as dropped), and its time is its number's. Where the rate varies, or the stated rate is
    not the frames' (`rate_varies`), frames are numbered as they come (what a frame-numbered
    truth file counts) and timed by their own timestamps (what the filter's steps need):
    numbered by the average rate, a 30-frame, 4.45 s phone recording had frames numbered up to
    35 and a duration of 5.3 s. A jump of the timestamps backwards, or forwards beyond any
    outage (files joined, an encoder restarted), is played on without the gap, and said.
    """

    def __init__(self, path: Path, fps: float, steps_s: list[float]) -> None:
        """`steps_s`: steps between frames already seen (the probe's at open)."""
        self._path = path
        self._fps = fps
        self._steps = steps_s[-32:]
        self.variable = rate_varies(self._steps, 1.0 / fps)
        self._origin_ms: float | None = None
        self._last_s: float | None = None  # the last frame's time by its timestamp
        self._given_s: float | None = None  # ... and the time given for it
        self._shift = 0.0  # added to the timestamps' times since the rate was found to vary

    @property
    def steps(self) -> list[float]:
        return list(self._steps)

    @property
    def period_s(self) -> float:
        """The time between frames: the stated one at a constant rate, else the typical step."""
        if self.variable and self._steps:
            return statistics.median(self._steps)
        return 1.0 / self._fps

    def place(self, number: int, media_ms: float) -> tuple[int, float]:
        """(number, media time) of the frame read after `number` frames (decoded or failed)
        came before it in this pass, presented at `media_ms`. The times given never go back."""
        period = 1.0 / self._fps
        if self._origin_ms is None:
            # Containers such as MPEG-TS start at a non-zero time; the first frame is frame 0.
            self._origin_ms = media_ms - 1000.0 * number * period
        t = (media_ms - self._origin_ms) / 1000.0
        last = self._last_s
        if last is not None:
            step = t - last
            if not -0.5 * period <= step <= max(MAX_TIMESTAMP_GAP_S, 10.0 * period):
                log.warning("%s: the timestamps jump by %.1f s after %.2f s (files joined, an "
                            "encoder restarted?): played on without the gap", self._path,
                            step, last)
                self._origin_ms = media_ms - 1000.0 * (last + period)
                t = last + period
            elif step > 0.0:  # (not a repeated timestamp, nor one the container rounded back)
                self._steps = [*self._steps[-31:], step]
                if not self.variable and rate_varies(self._steps, period):
                    self.variable = True
                    log.info("%s: its frame rate varies (or is not the stated %.4g fps): "
                             "frames numbered as they come, timed by their timestamps",
                             self._path, self._fps)
                    # Numbered by the stated rate, the times given may have run ahead of the
                    # timestamps (a frame sooner than a period still took the next number):
                    # from here on they go on from the last one given, never back (a step back
                    # restarts the filter's track).
                    if self._given_s is not None:
                        self._shift = max(0.0, self._given_s + step - t)
            t = max(t, last)
        self._last_s = t
        if self.variable:
            given = t + self._shift
        else:
            number = max(number, round(t * self._fps))
            given = number * period
        if self._given_s is not None:
            given = max(given, self._given_s)
        self._given_s = given
        return number, given


class VideoFileSource(PacedSource):
    """A video file decoded by OpenCV's FFmpeg backend."""

    def __init__(self, url: str, options: SourceOptions | None = None) -> None:
        parsed = _parse(url, "file")
        super().__init__(
            url, options, loop=parsed.flag("loop", False), realtime=parsed.flag(
                "realtime", (options or SourceOptions()).realtime_default)
        )
        self.path = Path(parsed.path).expanduser()
        # The file's own frame rate wins; this is for files that do not state one.
        self._fps = parsed.number_or("fps", 25.0, 0.1, 1000.0)
        self._cap: VideoCaptureLike | None = None
        self._first: MediaFrame | None = None
        self._decoded = 0
        self._timeline = _Timeline(self.path, self._fps, [])

    @property
    def recorded(self) -> bool:
        return True

    @property
    def frame_period_s(self) -> float:
        return self._timeline.period_s

    def _open_capture(self) -> VideoCaptureLike:
        if not self.path.is_file():
            raise SourceError(self.url, f"no such file: {self.path.resolve()}")
        return open_ffmpeg_capture(
            self.url,
            str(self.path),
            options=None,
            open_timeout_s=self._options.open_timeout_s,
            read_timeout_s=max(self._options.stall_timeout_s, 5.0),
            failure="OpenCV's FFmpeg backend cannot read it (damaged, truncated, or not a video "
            "format it knows)",
        )

    def _start(self) -> None:
        self._cap = self._open_capture()
        file_fps = self._cap.get(cv2.CAP_PROP_FPS)
        steps = self._probe_steps()
        own = steady_rate(steps)
        if 0.1 <= file_fps <= 1000.0:
            self._fps = file_fps
            if (own is not None
                    and STATED_RATE_TOLERANCE < abs(own / file_fps - 1.0) <= MAX_LOST_SHARE):
                log.warning("%s states %.4g fps (its average: frames missing?) but its frames "
                            "are %.4g fps apart: numbered and timed at %.4g fps", self.path,
                            file_fps, own, own)
                self._fps = own
        elif own is not None and 0.1 <= own <= 1000.0:
            log.warning("%s does not state its frame rate; its frames are %.4g fps apart",
                        self.path, own)
            self._fps = own
        else:
            log.warning("%s does not state its frame rate; assuming %g fps", self.path, self._fps)
        self._timeline = _Timeline(self.path, self._fps, steps)
        try:
            self._first = self._next_media()
        except EndOfMediaError:
            self._stop()
            raise SourceError(self.url, "the file opens but holds no decodable frame") from None

    def _next_media(self) -> MediaFrame:
        if self._first is not None:
            first, self._first = self._first, None
            return first
        cap = self._cap
        if cap is None:
            raise EndOfMediaError
        failed = 0
        while True:
            ok, image = cap.read()
            if ok and image is not None:
                break
            failed += 1
            if failed >= END_AFTER_FAILED_READS:
                raise EndOfMediaError
        number, media_time_s = self._timeline.place(self._decoded + failed,
                                                    cap.get(cv2.CAP_PROP_POS_MSEC))
        missing = number - (self._decoded + failed)
        self._decoded = number + 1
        return MediaFrame(
            image=image,
            number=number,
            media_time_s=media_time_s,
            skipped_before=failed,
            missing_before=max(0, missing),
        )

    def _probe_steps(self) -> list[float]:
        """Steps between the first frames' timestamps, read with a capture of their own: a
        varying rate is then known from the first frame, and all are numbered one way."""
        try:
            probe = self._open_capture()
        except SourceError:
            return []  # the main capture says why
        times: list[float] = []
        try:
            while (len(times) < TIMELINE_PROBE_FRAMES
                   and (len(times) < 2 or times[-1] - times[0] < TIMELINE_PROBE_S)
                   and probe.grab()):
                times.append(probe.get(cv2.CAP_PROP_POS_MSEC) / 1000.0)
        finally:
            probe.release()
        return [b - a for a, b in itertools.pairwise(times) if 0.0 < b - a <= MAX_TIMESTAMP_GAP_S]

    def _skip_to(self, number: int) -> int:
        # grab() decodes without converting: the cheapest way past frames in any codec.
        skipped = 0
        if self._first is not None and number > self._first.number:
            self._first = None  # the frame peeked at open() is not wanted any more
            skipped += 1
        while self._first is None and self._cap is not None and self._decoded < number:
            if not self._cap.grab():
                break  # the end, or a damaged frame: read() sorts out which
            # Placed like a frame read: the timeline learns the rate from consecutive frames.
            passed, _ = self._timeline.place(self._decoded, self._cap.get(cv2.CAP_PROP_POS_MSEC))
            self._decoded = passed + 1
            skipped += 1
        return skipped

    def _skip_due(self, media_time_s: float) -> int:
        """At a varying rate, by the frames' own times: a frame is passed over when the next
        one is due too (by a typical step after it), found by decoding without converting
        (grab), and the first one that is not is converted (retrieve) and kept for the read."""
        if not self._timeline.variable:
            return super()._skip_due(media_time_s)
        step = self._timeline.period_s
        skipped = 0
        while True:
            if self._first is not None:
                if self._first.media_time_s + step > media_time_s:
                    return skipped
                self._first = None
                skipped += 1
            cap = self._cap
            if cap is None or not cap.grab():
                return skipped  # the end, or a damaged frame: read() sorts out which
            number, t = self._timeline.place(self._decoded, cap.get(cv2.CAP_PROP_POS_MSEC))
            self._decoded = number + 1
            if t + step <= media_time_s:
                skipped += 1
                continue
            ok, image = cap.retrieve()
            self._first = MediaFrame(image=image if ok else None, number=number,
                                     media_time_s=t)
            return skipped

    def _rewind(self) -> None:
        # Re-opening is the one rewind every container and codec supports.
        self._stop()
        self._decoded = 0
        # The next pass keeps what this one learnt of the rate.
        self._timeline = _Timeline(self.path, self._fps, self._timeline.steps)
        try:
            self._cap = self._open_capture()
        except SourceError as exc:
            # The file went away (or was replaced by something unreadable) between passes: a
            # pass without a frame, which a service's source retries as an outage.
            self._note_damage(exc.reason)

    def _stop(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


class ImageFolderSource(PacedSource):
    """Every image of a folder (or glob pattern), in name order, at a nominal frame rate."""

    def __init__(self, url: str, options: SourceOptions | None = None) -> None:
        parsed = _parse(url, "images")
        super().__init__(
            url, options, loop=parsed.flag("loop", False), realtime=parsed.flag(
                "realtime", (options or SourceOptions()).realtime_default)
        )
        self.pattern = parsed.path
        self._fps = parsed.number_or("fps", DEFAULT_IMAGE_FPS, 0.01, 1000.0)
        self._files: list[Path] = []
        self._position = 0

    @property
    def recorded(self) -> bool:
        return True

    @property
    def frame_period_s(self) -> float:
        return 1.0 / self._fps

    @property
    def files(self) -> list[Path]:
        return list(self._files)

    def _start(self) -> None:
        path = Path(self.pattern).expanduser()
        if glob.has_magic(self.pattern):
            candidates = [Path(p) for p in glob.glob(str(path))]
        elif path.is_dir():
            candidates = list(path.iterdir())
        else:
            raise SourceError(self.url, f"no such folder: {path.resolve()}")
        self._files = sorted(
            (p for p in candidates if p.is_file() and is_image_name(p)), key=frame_order
        )
        if not self._files:
            raise SourceError(
                self.url, f"no images ({', '.join(sorted(IMAGE_SUFFIXES))}) in {self.pattern}"
            )

    def _next_media(self) -> MediaFrame:
        if self._position >= len(self._files):
            raise EndOfMediaError
        number = self._position
        self._position += 1
        path = self._files[number]
        image: Any = None
        try:
            # Decoded in colour and converted like every other frame (one grey conversion), and
            # refused when truncated: a half-written JPEG would otherwise decode with a grey band.
            image = decode_gray(path.read_bytes())[1]
        except FileNotFoundError:
            raise MediaGoneError(f"{path} is gone (the folder changed under the source)") from None
        except OSError as exc:
            self._note_damage(f"{path.name}: {exc.strerror or exc}")
        except DamagedImageError as exc:
            self._note_damage(f"{path.name}: {exc}")
        return MediaFrame(image=image, number=number, media_time_s=number / self._fps)

    def _skip_to(self, number: int) -> int:
        skipped = max(0, min(number, len(self._files)) - self._position)
        self._position += skipped
        return skipped

    def _rewind(self) -> None:
        # The folder is read again on every pass: images added or removed meanwhile count.
        self._position = 0
        try:
            self._start()
        except SourceError as exc:
            self._files = []
            self._note_damage(exc.reason)

    def _stop(self) -> None:
        self._files = []
        self._position = 0
