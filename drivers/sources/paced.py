"""Sources that produce frames on demand (files, image folders, the renderer), optionally paced.

Without pacing, read() returns the next frame at once: a recording is replayed as fast as the
consumer goes and no frame is lost (tests, benchmarks, offline replay). With `realtime`, frames
become due at their media time after open(), as from a camera: read() waits for the next due
frame and skips (counts as drops) the frames that came due while the consumer was busy, so a
slow consumer sees the newest frame, as from a live source. Skipped frames are not rendered or
converted (a video file still has to decode them). No thread is involved: decoding happens in
the caller.

Timestamps are media time on the clocks of open(): t_monotonic = (monotonic at open) + media
time, so a replay keeps the recording's frame spacing whatever the processing speed.
"""

from __future__ import annotations

import logging
import math
import time
from abc import abstractmethod
from dataclasses import dataclass

from drivers.errors import SourceError
from drivers.sources.base import (
    Frame,
    FrameSource,
    RateMeter,
    SourceOptions,
    SourceState,
    SourceStats,
    split_gray_color,
    wall_time_of,
)
from service.core.backoff import Backoff
from service.core.redact import redact_text

log = logging.getLogger(__name__)


class EndOfMediaError(Exception):
    """Raised by _next_media() after the last frame."""


class MediaGoneError(Exception):
    """Raised by _next_media() when the medium vanished under it (a folder deleted or
    unmounted): an outage, not a corrupt frame."""


@dataclass(frozen=True, eq=False)
class MediaFrame:
    """One frame as the medium holds it. `image` None: this frame cannot be decoded."""

    image: object | None
    number: int  # position in the medium, 0-based
    media_time_s: float
    truth: object | None = None
    budget: int | None = None  # a recording's budget level for this frame
    measured: bool = True  # False: the recording's vehicle did not measure this frame
    inspected: bool | None = None  # a recording's: the vehicle searched it for holes
    skipped_before: int = 0  # unreadable frames passed over just before this one
    # Frames the medium's timestamps show were never recorded, just before this one (a
    # constant-rate camera that stalled): counted as dropped.
    missing_before: int = 0
    wall_s: float | None = None  # a recording's own capture time (time.time) for this frame


class PacedSource(FrameSource):
    """Base of the file, image-folder and synthetic sources."""

    def __init__(
        self,
        url: str,
        options: SourceOptions | None = None,
        *,
        loop: bool = False,
        realtime: bool = False,
    ) -> None:
        super().__init__(url)
        self._options = options or SourceOptions()
        self.loop = loop
        self.realtime = realtime
        self._state = SourceState.OPENING
        self._t0_mono = 0.0
        self._loop_time_s = 0.0  # media time added per completed loop
        self._loop_index = 0  # frame numbers added per completed loop
        self._highest_number = -1  # of the current pass, decodable or not
        self._pass_end_s = 0.0  # the latest media time of a frame of the current pass
        self._good_since_rewind = 0
        self._pending: tuple[MediaFrame, Frame] | None = None
        self._frames = 0
        self._drops = 0
        self._corrupt = 0
        self._rate = RateMeter()
        self._error = ""
        self._damage = ""
        self._backoff = Backoff(self._options.reconnect_min_s, self._options.reconnect_max_s)
        self._retry_at = 0.0

    # -- what a subclass provides -----------------------------------------------------------
    @abstractmethod
    def _start(self) -> None:
        """Open the medium; raise SourceError naming the URL if that is impossible."""

    @abstractmethod
    def _next_media(self) -> MediaFrame:
        """The next frame of the medium; raise EndOfMediaError after the last."""

    @abstractmethod
    def _skip_to(self, number: int) -> int:
        """Pass over frames so that the next one is `number` (or the end); return how many
        frames were passed over. Never goes backwards."""

    def _skip_due(self, media_time_s: float) -> int:
        """Pass over the frames that another frame has followed by `media_time_s` (this pass's
        media time now); return how many were passed over. By frame number at a constant rate;
        a medium whose frames come at their own times overrides it."""
        return self._skip_to(math.floor(media_time_s / self.frame_period_s))

    @abstractmethod
    def _rewind(self) -> None:
        """Go back to the first frame (for `loop`)."""

    @abstractmethod
    def _stop(self) -> None:
        """Release the medium."""

    @property
    @abstractmethod
    def frame_period_s(self) -> float:
        """Nominal time between frames (1 / fps)."""

    # -- FrameSource ------------------------------------------------------------------------
    def open(self) -> None:
        if self._state not in (SourceState.OPENING, SourceState.DOWN):
            return
        try:
            self._start()
        except SourceError as exc:
            if not self._options.wait_at_start:
                raise
            # Not there yet (a file still being copied, a folder not mounted): retried by
            # read() with backoff, like a camera that is not plugged in.
            self._go_down(exc.reason)
            return
        if self._state is SourceState.DOWN:
            # Back after an outage: a new clock origin, frame numbers carry on after the last.
            self._loop_index += self._highest_number + 1
            self._loop_time_s = 0.0
            self._highest_number = -1
            self._pass_end_s = 0.0
            self._good_since_rewind = 0
            self._pending = None
        self._backoff.reset()
        self._error = ""
        self._t0_mono = time.monotonic()
        self._state = SourceState.UP
        log.info(
            "frame source %s up: %.4g fps%s%s",
            redact_text(self.url),
            1.0 / self.frame_period_s,
            ", looping" if self.loop else "",
            ", paced in real time" if self.realtime else "",
        )

    def _go_down(self, reason: str) -> None:
        """An outage: said once per reason, re-opened by read() with backoff."""
        if self._state is not SourceState.DOWN or reason != self._error:
            log.warning("frame source %s down: %s; retrying with backoff",
                        redact_text(self.url), reason)
        self._state, self._error = SourceState.DOWN, reason
        self._retry_at = time.monotonic() + self._backoff.next_delay(time.monotonic())

    def read(self, timeout_s: float) -> Frame | None:
        if self._state is SourceState.DOWN:
            wait = self._retry_at - time.monotonic()
            if wait > timeout_s:
                time.sleep(max(0.0, timeout_s))
                return None
            time.sleep(max(0.0, wait))
            self.open()
            return None
        if self._state is not SourceState.UP:
            if self._state is SourceState.ENDED:
                # Nothing will come: wait like a quiet camera, so a polling loop does not spin.
                time.sleep(max(0.0, timeout_s))
            return None
        if not self.realtime:
            item = self._next_frame()
            return None if item is None else self._deliver(item[1])
        deadline = time.monotonic() + max(0.0, timeout_s)
        if self._pending is None:
            pass_before = self._loop_index
            item = self._frame_due_now()
            if (item is not None and self._loop_index != pass_before
                    and item[1].t_monotonic + self.frame_period_s <= time.monotonic()):
                # The skip ran past a looping medium's end into the next pass, whose first
                # frame came due as long ago as the consumer was late past the end: once more,
                # to the frame due now. (Not for a frame that is only late by the time it took
                # to make: that one would be thrown away and another made, every frame.)
                self._drops += 1
                item = self._frame_due_now()
            if item is None:
                return None
            self._pending = item
        frame = self._pending[1]
        now = time.monotonic()
        if frame.t_monotonic > now:
            if frame.t_monotonic > deadline:
                time.sleep(max(0.0, deadline - now))
                return None
            time.sleep(frame.t_monotonic - now)
        self._pending = None
        return self._deliver(frame)

    @property
    def state(self) -> SourceState:
        return self._state

    def stats(self) -> SourceStats:
        return SourceStats(
            state=self._state,
            frames=self._frames,
            captured=self._frames + self._drops,
            drops=self._drops,
            corrupt=self._corrupt,
            reconnects=0,
            fps=self._rate.rate(time.monotonic()),
            error=self._error,
        )

    def close(self) -> None:
        if self._state is SourceState.CLOSED:
            return
        if self._state is not SourceState.OPENING:
            self._stop()
        self._state = SourceState.CLOSED
        self._pending = None

    # -- internals --------------------------------------------------------------------------
    def _frame_due_now(self) -> tuple[MediaFrame, Frame] | None:
        """Jump straight to the frame due now: frames the consumer missed are never decoded or
        rendered (a renderer slower than the frame rate would otherwise never catch up)."""
        skipped = self._skip_due(time.monotonic() - self._t0_mono - self._loop_time_s)
        self._drops += skipped
        # Frames passed over are part of this pass: its length (the next pass's numbers and
        # clock) counts them, and a pass that was only passed over still had frames.
        self._highest_number += skipped
        self._good_since_rewind += skipped
        return self._next_frame()

    def _deliver(self, frame: Frame) -> Frame:
        self._frames += 1
        self._rate.tick(time.monotonic())
        return frame

    def _note_damage(self, reason: str) -> None:
        """Why the frame about to be counted as corrupt could not be used (for the log)."""
        self._damage = reason

    def _count_corrupt(self, count: int) -> None:
        if count <= 0:
            return
        if self._corrupt == 0:
            log.warning(
                "frame source %s: skipped an undecodable frame%s (further ones are only "
                "counted)", redact_text(self.url), f": {self._damage}" if self._damage else "",
            )
        self._corrupt += count

    def _next_frame(self) -> tuple[MediaFrame, Frame] | None:
        """The next decodable frame (looping if asked), or None at the end (state ENDED)."""
        while True:
            try:
                media = self._next_media()
            except MediaGoneError as exc:
                if not self._options.wait_at_start:
                    raise SourceError(self.url, str(exc)) from None
                # Down at once, with the reason (not a string of "corrupt" frames until the
                # stall timeout), and re-opened with backoff like a camera unplugged.
                self._stop()
                self._go_down(str(exc))
                return None
            except EndOfMediaError:
                if self.loop and self._good_since_rewind > 0:
                    # The next pass continues the numbering and the clock after this one.
                    length = self._highest_number + 1
                    # After the pass's last frame by its own time too (a varying rate's frames
                    # are not a period apart): the next pass's times never go back.
                    self._loop_time_s += max(length * self.frame_period_s,
                                             self._pass_end_s + self.frame_period_s)
                    self._loop_index += length
                    self._good_since_rewind = 0
                    self._highest_number = -1
                    self._pass_end_s = 0.0
                    self._rewind()
                    continue
                if self.loop and self._options.wait_at_start:
                    # Nothing decodable in a whole pass (a folder emptied, a file replaced):
                    # for a service that is an outage, retried, not the end.
                    self._stop()
                    self._go_down("no decodable frame in a whole pass")
                    return None
                if self.loop:
                    log.warning("frame source %s: no decodable frame to loop",
                                redact_text(self.url))
                self._state = SourceState.ENDED
                log.info("frame source %s ended after %d frames", redact_text(self.url),
                         self._frames)
                return None
            self._count_corrupt(media.skipped_before)
            self._drops += media.missing_before
            self._highest_number = max(self._highest_number, media.number)
            self._pass_end_s = max(self._pass_end_s, media.media_time_s)
            converted = (
                None if media.image is None
                else split_gray_color(media.image, self._options.keep_color)
            )
            if converted is None:
                self._count_corrupt(1)
                continue
            self._good_since_rewind += 1
            offset = self._loop_time_s + media.media_time_s
            frame = Frame(
                image=converted[0],
                index=self._loop_index + media.number,
                t_monotonic=self._t0_mono + offset,
                # The wall clock of now, as live sources say it: one read at open() kept a
                # Pi's 1970 clock for the whole run after NTP had set it (field review).
                t_wall=media.wall_s if media.wall_s is not None else wall_time_of(
                    self._t0_mono + offset),
                color=converted[1],
                truth=media.truth,
                budget=media.budget,
                measured=media.measured,
                inspected=media.inspected,
            )
            return media, frame
