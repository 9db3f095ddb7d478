"""Source URLs: schemes, bare paths, typed options and the errors a typo gets."""

from __future__ import annotations

from pathlib import Path

import pytest

from drivers.sources import create_source
from drivers.sources.files import ImageFolderSource, VideoFileSource
from drivers.sources.stream import StreamSource, default_ffmpeg_options, ffmpeg_target
from drivers.sources.synthetic import SyntheticSource
from drivers.sources.url import is_network_url, parse_source_url
from drivers.sources.v4l2 import V4l2Source
from service.core.errors import ConfigError
from service.core.redact import redact_text


def test_own_schemes_split_into_path_and_options() -> None:
    parsed = parse_source_url("v4l2:/dev/video2?width=1280&height=720&fps=30&fourcc=MJPG")
    assert parsed.scheme == "v4l2"
    assert parsed.path == "/dev/video2"
    assert dict(parsed.options) == {"width": "1280", "height": "720", "fps": "30", "fourcc": "MJPG"}
    assert parse_source_url("file:///abs/dive.mp4?loop=1").path == "/abs/dive.mp4"
    assert parse_source_url("file:rel/dive.mp4").path == "rel/dive.mp4"
    assert parse_source_url("synthetic:").options == {}


def test_bare_paths_pick_the_scheme(tmp_path: Path) -> None:
    assert parse_source_url("/dev/video0").scheme == "v4l2"
    assert parse_source_url("/dev/v4l/by-id/usb-cam-video-index0").scheme == "v4l2"
    assert parse_source_url(str(tmp_path)).scheme == "images"
    assert parse_source_url(str(tmp_path / "dive.mp4")).scheme == "file"
    assert parse_source_url("dive.mkv?loop=1").options == {"loop": "1"}


@pytest.mark.parametrize(
    ("url", "kind"),
    [
        ("rtsp://192.168.2.2:8554/video_stream__dev_video2", StreamSource),
        ("udp://0.0.0.0:5600", StreamSource),
        ("sdp:/tmp/stream.sdp", StreamSource),
        ("v4l2:/dev/video0", V4l2Source),
        ("/dev/video0", V4l2Source),
        ("file:dive.mp4", VideoFileSource),
        ("dive.mp4", VideoFileSource),
        ("images:frames/", ImageFolderSource),
        ("synthetic:?realtime=0", SyntheticSource),
    ],
)
def test_factory_routes_each_scheme(url: str, kind: type) -> None:
    source = create_source(url)  # not opened: nothing is touched
    assert isinstance(source, kind)
    source.close()


@pytest.mark.parametrize(
    ("url", "words"),
    [
        ("v4l2:/dev/video0?widht=640", ["widht", "unknown"]),
        ("v4l2:/dev/video0?width=640", ["both width and height"]),
        ("v4l2:/dev/video0?width=abc&height=480", ["width", "not an integer"]),
        ("v4l2:/dev/video0?fourcc=MJPEG", ["fourcc", "4"]),
        ("v4l2:camera0", ["/dev"]),
        ("file:dive.mp4?loop=maybe", ["loop", "0 or 1"]),
        ("file:dive.mp4?fps=-3", ["fps", "outside"]),
        ("file:dive.mp4?loop=1&loop=0", ["twice"]),
        ("images:?fps=5", ["needs a path"]),
        ("sdp:", ["SDP file"]),  # it was blamed on the calibration
        ("synthetic:?trajectory=spiral", ["trajectory", "approach"]),
        ("synthetic:?gap=6-4", ["gap", "START<END"]),
        ("synthetic:?trajectory=approach&near=3&far=1", ["near", "far"]),
        ("synthetic:?width=640&height=480", ["16:9"]),
        ("synthetic:?bar=2", ["bar", "outside"]),
        ("", ["empty"]),
        # Mistyped schemes were taken for file names: refused as a recorded video, or retried
        # as "no such file" for ever.
        ("V4L2:/dev/video0", ["unknown scheme 'V4L2:'", "lower case: v4l2:"]),
        ("synthetc:?fps=30", ["unknown scheme 'synthetc:'", "synthetic:"]),
    ],
)
def test_url_mistakes_are_configuration_errors_naming_the_problem(
    url: str, words: list[str]
) -> None:
    with pytest.raises(ConfigError) as err:
        create_source(url)
    assert err.value.key == "camera.url"
    for word in words:
        assert word in str(err.value)


def test_passwords_never_reach_messages() -> None:
    url = "rtsp://admin:s3cret@192.168.2.10:554/stream1"
    assert redact_text(url) == "rtsp://admin:<redacted>@192.168.2.10:554/stream1"
    # Typed raw into the configuration, a password may hold '#', '/', '?' or a space: it was
    # left in clear in the log and in the published configuration.
    for password in ("Fish#Farm/2026", "Salmon?2026", "pa ss", "a@b/c?d#e"):
        raw = f"rtsp://admin:{password}@192.168.2.10:554/stream1"
        assert redact_text(raw) == "rtsp://admin:<redacted>@192.168.2.10:554/stream1", raw
        said = f"frame source {raw} down (timeout)"
        assert password.split(" ")[0] not in redact_text(said).replace("admin", ""), said
    assert "s3cret" not in repr(create_source(url))
    assert redact_text("udp://0.0.0.0:5600") == "udp://0.0.0.0:5600"


def test_network_urls_keep_their_query_for_ffmpeg() -> None:
    assert is_network_url("udp://127.0.0.1:5600?overrun_nonfatal=1&fifo_size=50000")
    assert not is_network_url("file:///tmp/x.mp4")
    assert not is_network_url("/tmp/x.mp4")
    assert ffmpeg_target("udp://127.0.0.1:5600?fifo_size=1") == "udp://127.0.0.1:5600?fifo_size=1"
    assert ffmpeg_target("sdp:///tmp/a.sdp") == "/tmp/a.sdp"
    assert "rtsp_transport;tcp" in default_ffmpeg_options("rtsp://host/x")
    assert "rtsp_transport" not in default_ffmpeg_options("udp://host:1")
    assert "protocol_whitelist;file,udp,rtp" in default_ffmpeg_options("sdp:/tmp/a.sdp")
    for url in ("rtsp://host/x", "udp://host:1"):
        assert "fflags;nobuffer" in default_ffmpeg_options(url)
