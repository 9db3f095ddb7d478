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
seconds before it existed, and the frames held through it were stamped as new.

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
        self._came_out = deque(maxlen=max(1, self._frames_held))
        return cap

    def _capture_time(self, cap: VideoCaptureLike, received_mono: float) -> float:
        """When the frame went into the decoder: when the frame `frames_held` before it came
        out (module docstring). The first frames of an open have none: when they came out,
        less that many frame periods at the stream's own rate."""
        held = self._frames_held
        if held <= 0:
            return received_mono
        came_out = self._came_out
        if len(came_out) == held:
            t = came_out[0]
        else:
            fps = float(cap.get(cv2.CAP_PROP_FPS))
            t = received_mono - held / fps if 0.5 <= fps <= 1000.0 else received_mono
        came_out.append(received_mono)
        # Never after the time it came out, never before the frame stamped last.
        t = min(max(t, self._last_stamp + 1e-6), received_mono)
        self._last_stamp = t
        return t
