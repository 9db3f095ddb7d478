"""Frame sources: cameras, network streams, recordings and the renderer behind one interface.

    from drivers.sources import open_source
    with open_source("rtsp://192.168.2.2:8554/video_stream__dev_video2") as source:
        frame = source.read(timeout_s=0.2)      # newest frame, or None

URL schemes (docs/sources.md):
    v4l2:/dev/video0?width=1920&height=1080&fps=30&fourcc=MJPG    V4L2 camera (or /dev/video0)
    rtsp://..., udp://..., tcp://..., http://..., srt://...      network stream through FFmpeg
    sdp:/path/stream.sdp                                        RTP stream described by SDP
    file:recording.mp4?loop=1&realtime=1                       video file (or a bare path)
    images:folder/?fps=10                                      image folder or glob pattern
    recording:folder/?realtime=1                               a recording of the daemon
    synthetic:?trajectory=approach&...                         rendered net with ground truth
    sim:tcp:127.0.0.1:5764?distance=2&turn=20                   rendered from the vehicle's pose
"""

from __future__ import annotations

from drivers.sources.base import (
    Frame,
    FrameSource,
    SourceOptions,
    SourceState,
    SourceStats,
)
from drivers.sources.files import ImageFolderSource, VideoFileSource
from drivers.sources.recording import RecordingSource
from drivers.sources.sim import SimSource
from drivers.sources.stream import StreamSource
from drivers.sources.synthetic import SyntheticSource
from drivers.sources.url import is_network_url, parse_source_url, url_error
from drivers.sources.v4l2 import V4l2Source

__all__ = [
    "Frame",
    "FrameSource",
    "SourceOptions",
    "SourceState",
    "SourceStats",
    "create_source",
    "open_source",
]


def create_source(url: str, options: SourceOptions | None = None) -> FrameSource:
    """The source for `url`, not yet opened. URL mistakes raise ConfigError (camera.url)."""
    text = url.strip()
    if text.startswith("sdp:") or is_network_url(text):
        return StreamSource(text, options)
    parsed = parse_source_url(text)
    if parsed.scheme == "v4l2":
        return V4l2Source(parsed.raw, options)
    if parsed.scheme == "file":
        return VideoFileSource(parsed.raw, options)
    if parsed.scheme == "images":
        return ImageFolderSource(parsed.raw, options)
    if parsed.scheme == "synthetic":
        return SyntheticSource(parsed.raw, options)
    if parsed.scheme == "sim":
        return SimSource(parsed.raw, options)
    if parsed.scheme == "recording":
        return RecordingSource(parsed.raw, options)
    raise url_error(url, f"unknown scheme {parsed.scheme!r}")  # pragma: no cover - parser guards


def open_source(url: str, options: SourceOptions | None = None) -> FrameSource:
    """The source for `url`, opened: SourceError (naming the URL) if it cannot be opened now."""
    source = create_source(url, options)
    try:
        source.open()
    except BaseException:
        source.close()
        raise
    return source
