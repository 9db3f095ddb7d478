"""Network stream source against a real H.264 stream on loopback.

A real ffmpeg process (the imageio-ffmpeg binary) encodes numbered frames with x264 and sends
them as MPEG-TS over UDP, or as RTP described by an SDP file (what the BlueOS camera manager
sends to port 5600). The source decodes them with OpenCV's FFmpeg backend. The frame numbers
drawn in the picture tell how fresh each frame is; stopping the streamer is a real stall.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from drivers.errors import SourceError
from drivers.sources import FrameSource, SourceOptions, SourceState, open_source
from drivers.sources.fake_capture import numbered_pattern, read_pattern_number

FPS = 25
WIDTH, HEIGHT = 320, 240
OPTIONS = SourceOptions(
    stall_timeout_s=1.0, open_timeout_s=2.0, reconnect_min_s=0.1, reconnect_max_s=0.5
)

pytestmark = pytest.mark.timeout(60)


def ffmpeg_exe() -> str:
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    exe: str = imageio_ffmpeg.get_ffmpeg_exe()
    encoders = subprocess.run(
        [exe, "-hide_banner", "-encoders"], capture_output=True, text=True, timeout=20
    ).stdout
    if "libx264" not in encoders:
        pytest.skip("this ffmpeg has no libx264")
    return exe


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
    return port


class Streamer:
    """An ffmpeg process fed numbered frames at FPS by a thread this object owns."""

    def __init__(self, exe: str, output: list[str], first_number: int = 0) -> None:
        self._proc = subprocess.Popen(
            [
                exe, "-hide_banner", "-loglevel", "error",
                "-f", "rawvideo", "-pix_fmt", "gray", "-s", f"{WIDTH}x{HEIGHT}", "-r", str(FPS),
                "-i", "-",
                "-c:v", "libx264", "-preset", "ultrafast", "-tune", "zerolatency",
                "-g", str(FPS), "-pix_fmt", "yuv420p", "-flush_packets", "1",
                *output,
            ],
            stdin=subprocess.PIPE,
        )  # fmt: skip
        self.sent = first_number
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._feed, name="test-streamer", daemon=True)
        self._thread.start()

    def _feed(self) -> None:
        assert self._proc.stdin is not None
        start, first = time.monotonic(), self.sent
        try:
            while not self._stop.is_set():
                self._proc.stdin.write(numbered_pattern(self.sent, WIDTH, HEIGHT).tobytes())
                self._proc.stdin.flush()
                self.sent += 1
                time.sleep(max(0.0, start + (self.sent - first) / FPS - time.monotonic()))
        except (BrokenPipeError, ValueError):
            pass

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        if self._proc.stdin is not None:
            with contextlib.suppress(BrokenPipeError):
                self._proc.stdin.close()
        self._proc.terminate()
        try:
            self._proc.wait(5.0)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait(5.0)


@pytest.fixture
def streamers() -> Iterator[list[Streamer]]:
    started: list[Streamer] = []
    yield started
    for streamer in started:
        streamer.stop()


def mpegts_output(port: int) -> list[str]:
    return ["-f", "mpegts", "-muxdelay", "0", "-muxpreload", "0",
            f"udp://127.0.0.1:{port}?pkt_size=1316"]  # fmt: skip


def wait_for(condition: Callable[[], bool], timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.02)
    return condition()


def read_numbers(source: FrameSource, count: int, timeout_s: float = 5.0) -> list[int]:
    numbers: list[int] = []
    deadline = time.monotonic() + timeout_s
    while len(numbers) < count and time.monotonic() < deadline:
        frame = source.read(0.2)
        if frame is not None:
            numbers.append(read_pattern_number(frame.image))
    return numbers


def test_h264_over_udp_gives_the_newest_frame(streamers: list[Streamer]) -> None:
    exe, port = ffmpeg_exe(), free_udp_port()
    streamer = Streamer(exe, mpegts_output(port))
    streamers.append(streamer)
    with open_source(f"udp://127.0.0.1:{port}", OPTIONS) as source:
        numbers = read_numbers(source, 10)
        assert len(numbers) == 10
        assert numbers == sorted(set(numbers)), "each read returns a newer frame"
        frame = source.read(1.0)
        assert frame is not None and frame.image.shape == (HEIGHT, WIDTH)
        time.sleep(1.0)  # a consumer busy for 25 frame periods
        sent_before = streamer.sent
        frame = source.read(1.0)
        assert frame is not None
        lag = sent_before - read_pattern_number(frame.image)
        # Encoder, UDP and decoder pipeline: a few frames. A source that queued frames would
        # now hand out one from about 25 frames ago.
        assert 0 <= lag <= 8, lag
        stats = source.stats()
        assert stats.drops >= FPS - 5 - lag
        assert stats.captured - stats.frames - stats.drops in (0, 1)
        assert stats.corrupt == 0 and stats.reconnects == 0


def test_stalled_stream_goes_down_and_recovers_when_restarted(
    streamers: list[Streamer], caplog: pytest.LogCaptureFixture
) -> None:
    exe, port = ffmpeg_exe(), free_udp_port()
    first = Streamer(exe, mpegts_output(port))
    streamers.append(first)
    with caplog.at_level(logging.INFO, logger="drivers.sources"), open_source(
        f"udp://127.0.0.1:{port}", OPTIONS
    ) as source:
        assert len(read_numbers(source, 5)) == 5
        first.stop()  # the camera manager restarts, the link drops: no more packets
        assert wait_for(lambda: source.state is SourceState.DOWN, OPTIONS.stall_timeout_s + 3)
        while source.read(0.0) is not None:  # frames decoded before the stall
            pass
        assert source.read(0.3) is None
        second = Streamer(exe, mpegts_output(port), first_number=5000)
        streamers.append(second)
        assert wait_for(lambda: source.state is SourceState.UP, 15.0)
        numbers = read_numbers(source, 5)
        assert len(numbers) == 5 and all(n >= 5000 for n in numbers)
        stats = source.stats()
        assert stats.reconnects == 1
    downs = [r for r in caplog.records if " down: " in r.getMessage()]
    assert len(downs) == 1, [r.getMessage() for r in downs]
    assert any("frames flowing again" in r.getMessage() for r in caplog.records)


def test_rtp_stream_described_by_sdp(streamers: list[Streamer], tmp_path: Path) -> None:
    # BlueOS sends RTP/H.264 to UDP 5600; FFmpeg needs the SDP that describes the payload.
    exe, port = ffmpeg_exe(), free_udp_port()
    sdp = tmp_path / "stream.sdp"
    streamers.append(Streamer(exe, ["-f", "rtp", "-sdp_file", str(sdp), f"rtp://127.0.0.1:{port}"]))
    assert wait_for(sdp.exists, 10.0)
    with open_source(f"sdp:{sdp}", OPTIONS) as source:
        numbers = read_numbers(source, 5)
    assert len(numbers) == 5 and numbers == sorted(set(numbers))


def test_nothing_to_receive_at_start_is_an_error_naming_the_url() -> None:
    port = free_udp_port()
    options = SourceOptions(open_timeout_s=0.5, stall_timeout_s=0.5)
    with pytest.raises(SourceError) as err:
        open_source(f"udp://127.0.0.1:{port}", options)
    assert err.value.url == f"udp://127.0.0.1:{port}"
    assert "0.5 s" in err.value.reason
