"""Live sources (camera, network stream): a grabber thread that keeps only the newest frame.

A camera or stream produces frames whether or not anybody is ready for them. Reading them only
when the estimator asks would leave it working on frames that queued up in OpenCV's or FFmpeg's
buffers, seconds old. So one thread, owned by the source and joined by close(), reads
continuously and keeps just the latest frame; a frame replaced before the consumer took it is
counted as a drop.

The same thread watches the source: reads that keep failing, or no frame for
`stall_timeout_s`, close the capture and re-open it with exponential backoff. Meanwhile the
state is DOWN and read() returns None. State changes are logged once each, never per attempt.
"""

from __future__ import annotations

import logging
import threading
import time
from abc import abstractmethod

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
from drivers.sources.opencv_capture import VideoCaptureLike
from service.core.backoff import Backoff
from service.core.redact import redact_text

log = logging.getLogger(__name__)

# Consecutive failed reads after which the capture is considered lost. One failed read on its
# own is a frame the decoder rejected (counted as corrupt once a good frame follows).
MAX_FAILED_READS = 5
# Reads that fail at once (a stream joined mid-GOP on OpenCV 4.6, a server that answers and
# closes) are retried after a pause once this many came in a row: back to back, 3 million
# reads in 2 s took a whole core until the stall time, on a Pi whose cores the estimator
# needs. The first ones go at full speed: each may be a packet FFmpeg buffered while opening
# (at most a few seconds of a stream), which a pause would only delay the key frame behind.
INSTANT_FAILURE_S = 0.002
INSTANT_FAILURES_BEFORE_PAUSE = 200
FAILED_READ_PAUSE_S = 0.005
# How long close() waits for the grabber thread before leaving it to finish on its own.
CLOSE_WAIT_S = 0.2


class LiveSource(FrameSource):
    """Base of the V4L2 and network sources: subclasses only say how to open a capture."""

    def __init__(self, url: str, options: SourceOptions | None = None) -> None:
        super().__init__(url)
        self._options = options or SourceOptions()
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._state = SourceState.OPENING
        self._latest: Frame | None = None
        self._latest_seq = 0
        self._consumed_seq = 0
        self._frames = 0
        self._captured = 0
        self._drops = 0
        self._corrupt = 0
        self._reconnects = 0
        self._last_frame_mono = 0.0
        self._rate = RateMeter()
        self._error = ""

    # -- what a subclass provides -----------------------------------------------------------
    @abstractmethod
    def _connect(self) -> VideoCaptureLike:
        """Open the capture once; raise SourceError (with a reason) if that fails."""

    def _capture_time(self, cap: VideoCaptureLike, received_mono: float,
                      read_s: float) -> float:
        """When the frame just read was captured (monotonic), given how long read() took.
        Default: when read() returned."""
        return received_mono

    # -- FrameSource ------------------------------------------------------------------------
    def open(self) -> None:
        if self._state is SourceState.CLOSED:
            raise SourceError(redact_text(self.url), "the source was closed; create a new one")
        if self._thread is not None:
            return
        cap: VideoCaptureLike | None = None
        if self._options.wait_at_start:
            # The first open happens on the grabber thread (state OPENING until it answers): an
            # RTSP open can take seconds, and the caller's loop must keep its watchdog and its
            # stop requests meanwhile.
            pass
        else:
            cap = self._connect()  # a source that cannot be opened at start is an error
            with self._cond:
                self._last_frame_mono = time.monotonic()
            self._set_state(SourceState.UP, "opened")
        self._thread = threading.Thread(
            target=self._run, args=(cap,), name=f"frame-source-{type(self).__name__}", daemon=True
        )
        self._thread.start()

    def read(self, timeout_s: float) -> Frame | None:
        deadline = time.monotonic() + max(0.0, timeout_s)
        with self._cond:
            while True:
                if self._state is SourceState.CLOSED:
                    return None
                if self._latest_seq > self._consumed_seq and self._latest is not None:
                    self._consumed_seq = self._latest_seq
                    self._frames += 1
                    return self._latest
                remaining = deadline - time.monotonic()
                if remaining <= 0.0:
                    return None
                self._cond.wait(remaining)

    @property
    def state(self) -> SourceState:
        with self._cond:
            return self._effective_state(time.monotonic())

    def stats(self) -> SourceStats:
        now = time.monotonic()
        with self._cond:
            return SourceStats(
                state=self._effective_state(now),
                frames=self._frames,
                captured=self._captured,
                drops=self._drops,
                corrupt=self._corrupt,
                reconnects=self._reconnects,
                fps=self._rate.rate(now),
                error=self._error or (
                    "no frame for more than the stall time"
                    if self._effective_state(now) is SourceState.DOWN else ""),
            )

    def close(self) -> None:
        self._stop.set()
        with self._cond:
            self._state = SourceState.CLOSED
            self._latest = None
            self._cond.notify_all()
        thread, self._thread = self._thread, None
        if thread is None:
            return
        # The grabber sees the stop after its current read or open. An open can take up to
        # open_timeout_s inside FFmpeg, and a stop must not wait for it (systemd's stop budget):
        # the thread is a daemon, releases its capture when the open returns, and dies with the
        # process at the latest.
        thread.join(CLOSE_WAIT_S)
        if thread.is_alive():
            log.info(
                "frame source %s: not waiting for the capture driver to return (it is opening "
                "or reading); it is released when it does",
                redact_text(self.url),
            )

    # -- internals --------------------------------------------------------------------------
    def _effective_state(self, now: float) -> SourceState:
        # A grabber blocked inside the driver cannot report the stall itself.
        if (
            self._state is SourceState.UP
            and now - self._last_frame_mono > self._options.stall_timeout_s
        ):
            return SourceState.DOWN
        return self._state

    def _set_state(self, new: SourceState, reason: str) -> None:
        reason = redact_text(reason)  # a library's error text may repeat the URL
        with self._cond:
            old = self._state
            if old is SourceState.CLOSED:
                return
            self._error = reason if new is SourceState.DOWN else ""
            if old is new:
                return
            self._state = new
            self._cond.notify_all()
        if new is SourceState.DOWN:
            log.warning(
                "frame source %s down: %s; re-opening with backoff (%g..%g s)",
                redact_text(self.url),
                reason,
                self._options.reconnect_min_s,
                self._options.reconnect_max_s,
            )
        else:
            log.info("frame source %s %s: %s", redact_text(self.url), new.value, reason)

    def _arrival_rate(self, now: float) -> float:
        """Frames per second arriving from the capture (0 until measured)."""
        with self._cond:
            return self._rate.rate(now)

    def _publish(self, image: object, t_capture: float, now: float) -> bool:
        converted = split_gray_color(image, self._options.keep_color)
        if converted is None:
            return False
        gray, color = converted
        with self._cond:
            if self._state is SourceState.CLOSED:
                # A read that returned after close(): nobody reads it, and it would hold a
                # frame's memory (a 1080p colour one) in a closed source.
                return True
            index = self._captured + self._corrupt
            self._captured += 1
            self._rate.tick(now)
            self._last_frame_mono = now
            if self._latest_seq > self._consumed_seq:
                self._drops += 1  # the consumer never saw the previous one
            self._latest = Frame(
                image=gray,
                index=index,
                t_monotonic=t_capture,
                t_wall=wall_time_of(t_capture),
                color=color,
            )
            self._latest_seq += 1
            self._cond.notify_all()
        return True

    def _count_corrupt(self, count: int) -> None:
        if count <= 0:
            return
        with self._cond:
            first = self._corrupt == 0
            self._corrupt += count
        if first:
            log.warning(
                "frame source %s: skipped an undecodable frame (further ones are only counted)",
                redact_text(self.url),
            )

    def _reconnect(self) -> VideoCaptureLike | None:
        """One re-open attempt (None on failure). The state goes UP with the first frame."""
        try:
            cap = self._connect()
        except SourceError as exc:
            self._set_state(SourceState.DOWN, exc.reason)
            return None
        except Exception as exc:  # a driver bug must not kill the thread: keep retrying
            self._set_state(SourceState.DOWN, f"re-open raised {exc!r}")
            return None
        with self._cond:
            self._last_frame_mono = time.monotonic()  # the stall clock restarts
        return cap

    def _run(self, first_cap: VideoCaptureLike | None) -> None:
        opts = self._options
        cap: VideoCaptureLike | None = first_cap
        # Re-opening a stream or a device that is not there fails at once and costs nothing, so
        # a young outage is probed four times a second: a camera back is seen within 0.25 s +
        # its open (for a stream: about 0.5 s + one key-frame interval).
        backoff = Backoff(opts.reconnect_min_s, opts.reconnect_max_s,
                          young_cap_s=min(0.25, opts.reconnect_max_s))
        failed_reads = 0
        frames_since_open = 0
        instant_failures = 0  # in a row
        try:
            while not self._stop.is_set():
                if cap is None:
                    cap = self._reconnect()
                    if cap is None:
                        self._stop.wait(backoff.next_delay(time.monotonic()))
                        continue
                    failed_reads = frames_since_open = 0
                read_from = time.monotonic()
                try:
                    ok, image = cap.read()
                except Exception:  # cv2.error from a broken driver = a failed read
                    ok, image = False, None
                now = time.monotonic()
                if ok and image is not None:
                    instant_failures = 0
                    # Failed reads followed by a good frame were frames the decoder refused:
                    # counted before it, so its index comes after theirs (the gap is where
                    # they were). Before the first frame after an open they are a stream
                    # joined mid-GOP, which fails reads up to its next key frame: not damage.
                    if frames_since_open > 0:
                        self._count_corrupt(failed_reads)
                    failed_reads = 0
                    t_capture = self._capture_time(cap, now, now - read_from)
                    if self._publish(image, t_capture, now):
                        frames_since_open += 1
                        if frames_since_open == 1:
                            self._recovered()
                            backoff.reset()
                        continue
                    self._count_corrupt(1)
                else:
                    failed_reads += 1
                    instant = now - read_from < INSTANT_FAILURE_S
                    instant_failures = instant_failures + 1 if instant else 0
                    if instant_failures >= INSTANT_FAILURES_BEFORE_PAUSE:
                        self._stop.wait(FAILED_READ_PAUSE_S)
                with self._cond:
                    silent_for = now - self._last_frame_mono
                # Right after an open, a stream joined mid-GOP fails reads until its next key
                # frame (OpenCV 4.6's FFmpeg returns them as failures at once): until the first
                # frame only the stall clock, restarted at the open, decides.
                too_many = failed_reads >= MAX_FAILED_READS and frames_since_open > 0
                if too_many or silent_for > opts.stall_timeout_s:
                    reason = (
                        f"no frame for {silent_for:.1f} s"
                        if silent_for > opts.stall_timeout_s
                        else f"{failed_reads} reads in a row failed (stream ended or camera gone)"
                    )
                    cap.release()
                    cap = None
                    self._set_state(SourceState.DOWN, reason)
                    if frames_since_open == 0:
                        # Opened but nothing came: back off, or a flapping device spins the CPU.
                        self._stop.wait(backoff.next_delay(time.monotonic()))
        finally:
            if cap is not None:
                cap.release()

    def _recovered(self) -> None:
        """The first frame after an open: UP again (counted as a reconnect if it was down)."""
        with self._cond:
            was_down = self._state is SourceState.DOWN
            if was_down:
                self._reconnects += 1
        if was_down:
            self._set_state(SourceState.UP, "frames flowing again")
