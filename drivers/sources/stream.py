"""Network video streams (RTSP, MPEG-TS over UDP/TCP, RTP via an SDP file, HTTP...) via FFmpeg.

On a BlueOS vehicle the camera manager owns the camera and serves H.264 over RTSP (port 8554)
and RTP/UDP (port 5600); netpose reads one of those instead of the device. OpenCV's FFmpeg
backend does the demuxing and decoding. What matters for a pose estimator is latency: FFmpeg's
default probing and buffering add frames of delay, so the capture is opened with
`fflags;nobuffer|flags;low_delay` (plus `fpsprobesize;0|rtsp_transport;tcp` for RTSP: on a
tether, lost UDP packets smear H.264 frames for a whole GOP, TCP only delays them) and the
grabber thread of LiveSource keeps only the newest decoded frame.

The decoder runs one frame thread per core (OpenCV's choice; OpenCV 4.6 has no way to change
it), and each thread past the first holds every frame back by one frame period: measured on
loopback, (1 for RTSP, 2 for MPEG-TS) + (threads - 1) frames from the encoder to read(), i.e.
3 frame periods more on a four-core Pi than with one thread. A frame's time is when read()
returned less the frames held, for a codec the decoder frame-threads (`decoder_frames_held`;
OpenCV 4.6 names no codec for MPEG-TS, whose frames stay late by it: docs/sources.md). Held
frames, not periods: a decoder holding H frames lets frame n out when frame n + H comes in, so
frame n came in when frame n - H came out, and that is its time. Counted in periods, a pause of
the stream (a tether hiccup) shrank the measured rate, so the first frame after it was stamped
seconds before it existed, and the frames held through it were stamped as new. When the stream
stops, FFmpeg's read gives up after the stall time and OpenCV drains the decoder: its frames
come out at once, with nothing going in, so frames that come out at once after a long read are
stamped no later than that read began.

`sdp:/path/to/stream.sdp` opens a raw RTP stream described by an SDP file (FFmpeg needs the
payload description that RTP itself does not carry), e.g. BlueOS's UDP 5600 stream.
"""

from __future__ import annotations

from collections import deque
from pathlib import Path

import cv2

from drivers.errors import SourceError
from drivers.sources.base import SourceOptions
from drivers.sources.live import LiveSource
from drivers.sources.opencv_capture import (
    VideoCaptureLike,
    decoder_frames_held,
    open_ffmpeg_capture,
)
from drivers.sources.url import url_error

# Low-latency demuxer/decoder flags for every network stream.
LOW_LATENCY_OPTIONS = "fflags;nobuffer|flags;low_delay"
# RTSP only: the frame rate is not probed (the frames carry their own times), which shortens an
# open by about 0.8 s (1.8 -> 1.0 s on loopback, OpenCV 4.6 and 5.0): what decides how fast a
# returning camera is seen. Not for MPEG-TS or raw H.264, whose parameter sets come in band:
# together with `nobuffer`, a stream joined mid-GOP then gave 4 frames in 8 s once the decoder
# had three or more frame threads (a Raspberry Pi 4 or 5 has four cores), and it did not shorten
# their open (0.8-0.9 s either way, 5.8 s on OpenCV 4.6's longer probe).
RTSP_OPTIONS = "fpsprobesize;0|rtsp_transport;tcp"
# A read that waited this share of the stall time (FFmpeg's read timeout) or more: a pause of
# the stream, or its end (then the read ends when the timeout interrupts it).
_LONG_READ_SHARE = 0.5
# A read that returned within this share of a frame period, and within 5 ms, gave a frame
# already decoded.
_INSTANT_READ_SHARE = 0.25
_INSTANT_READ_S = 0.005
# Frames beyond `frames_held` that may still come out of a drain (the demuxer's, the first).
_CAP_EXTRA_FRAMES = 3


def default_ffmpeg_options(url: str) -> str:
    """The FFmpeg capture options netpose uses for `url` (see the module docstring)."""
    options = LOW_LATENCY_OPTIONS
    if url.startswith(("rtsp://", "rtsps://")):
        options += "|" + RTSP_OPTIONS
    elif url.startswith("sdp:"):
        # An SDP file is read from disk, then points FFmpeg at UDP/RTP sockets.
        options += "|protocol_whitelist;file,udp,rtp,crypto,data"
    return options


def ffmpeg_target(url: str) -> str:
    """What FFmpeg opens for `url`: the URL itself, or the file behind `sdp:`."""
    if url.startswith("sdp:"):
        path = url[len("sdp:") :]
        return path[2:] if path.startswith("//") else path
    return url


class StreamSource(LiveSource):
    """A live network stream, re-opened with backoff when it stalls or ends."""

    def __init__(self, url: str, options: SourceOptions | None = None) -> None:
        super().__init__(url, options)
        if url.startswith("sdp:") and not ffmpeg_target(url).strip():
            raise url_error(url, "sdp: needs the path of the stream's SDP file")
        opts = self._options
        self._ffmpeg_options = (
            opts.ffmpeg_options if opts.ffmpeg_options is not None else default_ffmpeg_options(url)
        )
        self._frames_held = 0  # by the decoder of the capture open now (decoder_frames_held)
        # When the capture's last `frames_held` frames came out of read() (monotonic).
        self._came_out: deque[float] = deque(maxlen=1)
        self._last_stamp = float("-inf")
        # Start of the last long read, while the frames after it come out at once.
        self._waited_from: float | None = None
        self._capped_left = 0  # frames the cap may still hold back
        self._period = 0.0  # the stream's stated frame period, read once per open

    @property
    def ffmpeg_options(self) -> str:
        return self._ffmpeg_options

    def _connect(self) -> VideoCaptureLike:
        opts = self._options
        if self.url.startswith("sdp:"):
            # FFmpeg fails at once on a missing file and says so only on stderr: the log said
            # "nothing there, no stream yet" for ever.
            sdp = Path(ffmpeg_target(self.url)).expanduser()
            if not sdp.is_file():
                raise SourceError(self.url, f"no such SDP file: {sdp.resolve()}")
        # The read time limit is the stall timeout: a stream that sends nothing for that long
        # makes read() fail instead of blocking, and the grabber re-opens it.
        cap = open_ffmpeg_capture(
            self.url,
            ffmpeg_target(self.url),
            options=self._ffmpeg_options,
            open_timeout_s=opts.open_timeout_s,
            read_timeout_s=opts.stall_timeout_s,
        )
        self._frames_held = decoder_frames_held(cap)
        self._period = _stated_period(cap)
        self._waited_from = None
        self._capped_left = 0
        self._came_out = deque(maxlen=max(1, self._frames_held))
        return cap

    def _capture_time(self, cap: VideoCaptureLike, received_mono: float,
                      read_s: float) -> float:
        """When the frame went into the decoder: when the frame `frames_held` before it came
        out (module docstring). The first frames of an open have none: when they came out,
        less that many frame periods at the stream's own rate."""
        # The frames that come out at once after a read that waited long were all in the
        # decoder before that wait: when the stream stops, FFmpeg's read gives up after the
        # stall time and OpenCV drains the decoder, one frame per read with nothing new going
        # in, and the rule below stamped them as captured a stall time after they were (a net
        # plane from before the outage reached the autopilot as fresh). The cap holds while
        # frames come out at once (within 5 ms, and a quarter of the stated period), for at
        # most a few frames more than the decoder holds (the demuxer held two more than
        # `frames_held` counts, MPEG-TS with four threads): a stream that states too low a rate
        # has every read within a quarter of it, and a lasting cap froze its stamps at a pause.
        period = self._period
        # (Not before the first frame of an open: what comes out at once after joining a
        # stream is new.)
        if read_s >= _LONG_READ_SHARE * self._options.stall_timeout_s and self._came_out:
            self._waited_from = received_mono - read_s
            self._capped_left = self._frames_held + _CAP_EXTRA_FRAMES
        elif read_s > min(_INSTANT_READ_SHARE * period if period > 0.0 else _INSTANT_READ_S,
                          _INSTANT_READ_S) or self._capped_left <= 0:
            self._waited_from = None  # a frame that needed new input: the rule holds again
        self._capped_left = max(0, self._capped_left - 1)
        held = self._frames_held
        if held <= 0:
            return received_mono if self._waited_from is None else min(received_mono,
                                                                        self._waited_from)
        came_out = self._came_out
        if len(came_out) == held:
            t = came_out[0]
        else:
            t = received_mono - held * period if period > 0.0 else received_mono
        came_out.append(received_mono)
        if self._waited_from is not None:
            t = min(t, self._waited_from)
        # Never after the time it came out, never before the frame stamped last.
        t = min(max(t, self._last_stamp + 1e-6), received_mono)
        self._last_stamp = t
        return t


def _stated_period(cap: VideoCaptureLike) -> float:
    """The stream's frame period from the rate it states at the open (0 when it states none)."""
    fps = float(cap.get(cv2.CAP_PROP_FPS))
    return 1.0 / fps if 0.5 <= fps <= 1000.0 else 0.0
