"""Network stream source against a real H.264 stream on loopback.

A real ffmpeg process (the imageio-ffmpeg binary) encodes numbered frames with x264 and sends
them as MPEG-TS over UDP, or as RTP described by an SDP file (what the BlueOS camera manager
sends to port 5600), or as RTP that a small RTSP server in this module relays over TCP (what
the camera manager serves on 8554). The source decodes them with OpenCV's FFmpeg backend, whose
RTSP client does the real RTSP handshake. The frame numbers drawn in the picture tell how fresh
each frame is; stopping the streamer or the server is a real stall.
"""

from __future__ import annotations

import collections
import contextlib
import itertools
import logging
import socket
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from drivers.errors import SourceError
from drivers.net import free_port
from drivers.sources import FrameSource, SourceOptions, SourceState, open_source, opencv_capture
from drivers.sources.fake_capture import read_pattern_number
from drivers.sources.stream import StreamSource
from tests.stream_peers import (
    FPS,
    HEIGHT,
    WIDTH,
    RtspServer,
    Streamer,
    ffmpeg_exe,
    rtp_to_rtsp,
    wait_for,
)

OPTIONS = SourceOptions(
    # Open time allows for the slower stream probing of the FFmpeg in OpenCV 4.6 (Debian
    # bookworm): 3-6 s for this low-bitrate MPEG-TS over UDP, against ~1 s with OpenCV 5.
    stall_timeout_s=1.0, open_timeout_s=10.0, reconnect_min_s=0.1, reconnect_max_s=0.5
)

pytestmark = pytest.mark.timeout(60)


def free_udp_port() -> int:
    return free_port(socket.SOCK_DGRAM)


@pytest.fixture
def streamers() -> Iterator[list[Streamer]]:
    started: list[Streamer] = []
    yield started
    for streamer in started:
        streamer.stop()


def mpegts_output(port: int) -> list[str]:
    return ["-f", "mpegts", "-muxdelay", "0", "-muxpreload", "0",
            f"udp://127.0.0.1:{port}?pkt_size=1316"]  # fmt: skip


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


_TIMEOUT_PARAMS = opencv_capture.timeout_params


def force_decoder_threads(monkeypatch: pytest.MonkeyPatch, threads: int) -> None:
    """The decoder's thread count, which OpenCV's FFmpeg backend sets to one per core (four on a
    Raspberry Pi 4 or 5, two on this machine): the hardware that decides it, emulated at the
    lowest edge, the capture's open parameters."""
    if not hasattr(cv2, "CAP_PROP_N_THREADS"):
        pytest.skip("this OpenCV cannot set the decoder's thread count (CAP_PROP_N_THREADS is "
                    "newer than OpenCV 4.6), so a four-core machine cannot be emulated")
    monkeypatch.setattr(opencv_capture, "timeout_params",
                        lambda open_s, read_s: [*_TIMEOUT_PARAMS(open_s, read_s),
                                                int(cv2.CAP_PROP_N_THREADS), threads])


@pytest.fixture
def four_decoder_threads(monkeypatch: pytest.MonkeyPatch) -> None:
    force_decoder_threads(monkeypatch, 4)


# Each decoder frame thread past the first holds every frame back by one frame.
FOUR_THREADS_LAG = 3


def _assert_steady_with_four_threads(source: FrameSource, streamer: Streamer) -> None:
    """Two seconds of frames, each newer than the last, fresh, without a re-open."""
    numbers = read_numbers(source, 2 * FPS, timeout_s=8.0)
    assert len(numbers) == 2 * FPS, numbers
    assert numbers == sorted(set(numbers))
    assert 0 <= streamer.sent - numbers[-1] <= 8 + FOUR_THREADS_LAG
    assert source.stats().reconnects == 0


@pytest.mark.usefixtures("four_decoder_threads")
def test_h264_over_udp_decodes_with_a_four_core_pi_s_decoder_threads(
    streamers: list[Streamer]
) -> None:
    # With `fpsprobesize;0` and `nobuffer` together, this stream (parameter sets in band,
    # joined mid-GOP) gave 4 frames in 8 s at three or four decoder threads, fine at one or two.
    exe, port = ffmpeg_exe(), free_udp_port()
    streamer = Streamer(exe, mpegts_output(port))
    streamers.append(streamer)
    with open_source(f"udp://127.0.0.1:{port}", OPTIONS) as source:
        _assert_steady_with_four_threads(source, streamer)


@pytest.mark.usefixtures("four_decoder_threads")
def test_rtsp_decodes_with_a_four_core_pi_s_decoder_threads(
    streamers: list[Streamer], tmp_path: Path
) -> None:
    with _rtsp_stream(streamers, tmp_path) as url, open_source(url, OPTIONS) as source:
        _assert_steady_with_four_threads(source, streamers[-1])


@contextlib.contextmanager
def _rtsp_stream(streamers: list[Streamer], tmp_path: Path,
                 pause: tuple[int, float] | None = None) -> Iterator[str]:
    """An RTSP server on loopback relaying a fresh H.264 stream (appended to `streamers`), as
    BlueOS's camera manager serves one; yields its URL."""
    sdp, rtp_in = rtp_to_rtsp(ffmpeg_exe(), tmp_path, streamers, pause=pause)
    server = RtspServer(sdp, rtp_in)
    try:
        yield f"rtsp://127.0.0.1:{server.port}/video_stream__dev_video2"
    finally:
        server.close()


def _frame_offsets(source: FrameSource, streamer: Streamer, count: int) -> list[float]:
    """Frame time minus when the frame went into the encoder, for up to `count` frames."""
    offsets: list[float] = []
    deadline = time.monotonic() + 15.0
    while len(offsets) < count and time.monotonic() < deadline:
        frame = source.read(0.5)
        if frame is not None:
            number = read_pattern_number(frame.image)
            offsets.append(frame.t_monotonic - streamer.sent_at[number])
    return offsets


def _capture_offsets(streamers: list[Streamer], count: int) -> list[float]:
    """`_frame_offsets` of a fresh MPEG-TS stream over UDP, past the rate's first estimates."""
    exe, port = ffmpeg_exe(), free_udp_port()
    streamer = Streamer(exe, mpegts_output(port))
    streamers.append(streamer)
    with open_source(f"udp://127.0.0.1:{port}", OPTIONS) as source:
        offsets = _frame_offsets(source, streamer, count)
    streamer.stop()
    return offsets[count // 3:]


def test_a_frames_time_does_not_count_the_decoders_threads(
    streamers: list[Streamer], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Four decoder threads hold each frame back three frame periods more than one thread does
    (120 ms at 25 frames/s); the frame's time must say when it was captured, not when the
    decoder let it go."""
    median = []
    for threads in (1, 4):
        force_decoder_threads(monkeypatch, threads)
        offsets = _capture_offsets(streamers, 60)
        assert len(offsets) >= 30
        median.append(float(np.median(offsets)))
    period = 1.0 / FPS
    assert median[0] > -0.5 * period  # never before the frame existed
    assert abs(median[1] - median[0]) < 0.5 * period, (median, period)


def test_an_rtsp_frames_time_leaves_out_the_decoders_threads(
    streamers: list[Streamer], tmp_path: Path
) -> None:
    """With the decoder's own thread count, one per core (OpenCV 4.6 cannot report it, and
    cannot be told another): RTSP over loopback delivers a frame one frame period after it went
    into the encoder with one decoder thread, and each thread past the first adds one. The
    frame's time must leave those out (on one core there are none to leave out)."""
    with _rtsp_stream(streamers, tmp_path) as url, open_source(url, OPTIONS) as source:
        offsets = _frame_offsets(source, streamers[-1], 60)
    assert len(offsets) >= 40
    median = float(np.median(offsets[20:]))
    period = 1.0 / FPS
    assert 0.0 < median < 1.5 * period, (median, period)


def test_a_pause_of_the_stream_neither_turns_time_back_nor_makes_held_frames_new(
    streamers: list[Streamer], tmp_path: Path, four_decoder_threads: None
) -> None:
    """RTSP with a four-core Pi's decoder threads, and a tether hiccup of one second (under
    the stall time, so no re-open). Counted in frame periods at the rate frames arrive, the
    decoder's hold made the first frame after the pause two seconds older than the frame
    before it (the rate had dropped to one a second), and the frames held through the pause
    came out stamped as new, a second fresher than they were. Frame times keep increasing,
    and a frame held back is stamped when it went into the decoder."""
    pause_at, pause_s = 100, 1.0  # 4 s in: the source has joined the stream by then
    with _rtsp_stream(streamers, tmp_path, pause=(pause_at, pause_s)) as url, \
            open_source(url, OPTIONS) as source:
        stamps: list[tuple[int, float]] = []
        deadline = time.monotonic() + 15.0
        while time.monotonic() < deadline and (not stamps or stamps[-1][0] < pause_at + 40):
            frame = source.read(0.5)
            if frame is not None:
                stamps.append((read_pattern_number(frame.image), frame.t_monotonic))
    sent_at = streamers[-1].sent_at
    numbers = [n for n, _ in stamps]
    assert min(numbers) < pause_at - 10 and max(numbers) >= pause_at + 30, numbers
    times = [t for _, t in stamps]
    assert all(b > a for a, b in itertools.pairwise(times)), "a frame time went back"
    period = 1.0 / FPS
    offsets = {n: t - sent_at[n] for n, t in stamps}
    assert min(offsets.values()) > -0.5 * period  # never before the frame existed
    # Fresher than it was by more than two periods: only a frame the RTSP relay itself held
    # through the pause (it sends a frame on when the next one comes: one frame).
    late = [n for n, offset in offsets.items() if offset > 2 * period]
    assert len(late) <= 1 and all(pause_at - 3 <= n < pause_at for n in late), offsets


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
        # Frames the decoder still held come out when FFmpeg gives up; nothing new does.
        late = []
        while (frame := source.read(0.3)) is not None:
            late.append(read_pattern_number(frame.image))
        assert len(late) <= 3 and all(n < first.sent for n in late), (late, first.sent)
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


def test_frames_drained_from_the_decoder_after_a_stall_are_not_passed_off_as_new(
    streamers: list[Streamer], four_decoder_threads: None
) -> None:
    """When the stream stops, FFmpeg's read gives up after the stall time and OpenCV drains
    the decoder: the frames it held come out one per read, with nothing new going in. Stamped
    by the rule for a running stream (frame n went in when frame n - H came out), all but the
    first were stamped as captured a stall time after they were: a net plane from before the
    outage reached the autopilot as fresh for about a second. No frame from before the stall
    may come out stamped later than it was sent."""
    exe, port = ffmpeg_exe(), free_udp_port()
    first = Streamer(exe, mpegts_output(port))
    streamers.append(first)
    with open_source(f"udp://127.0.0.1:{port}", OPTIONS) as source:
        assert len(read_numbers(source, 20, timeout_s=15.0)) == 20
        first.stop()
        frames = []
        deadline = time.monotonic() + OPTIONS.stall_timeout_s + 3.0
        while time.monotonic() < deadline:
            frame = source.read(0.2)
            if frame is not None:
                frames.append((read_pattern_number(frame.image), frame.t_monotonic))
    period = 1.0 / FPS
    late = {n: t - first.sent_at[n] for n, t in frames if n in first.sent_at}
    # MPEG-TS frames stay a period late (the demuxer's hold, docs/sources.md): ~2 periods.
    assert all(offset < 3 * period for offset in late.values()), sorted(late.items())[-8:]


class _StatedRate:
    """A capture as the stamping rule sees it: its stated frame rate, nothing else."""

    def __init__(self, fps: float) -> None:
        self.fps = fps

    def get(self, prop_id: int) -> float:
        return self.fps if prop_id == cv2.CAP_PROP_FPS else 0.0


def test_a_stream_stating_too_low_a_rate_is_stamped_as_it_goes_after_a_pause() -> None:
    """A stream that states 5 frames/s and sends 30: every read returns within a quarter of
    the stated period, so after one pause the cap on the frames drained from the decoder never
    lifted, and every later frame was stamped a microsecond after the pause began (the net
    planes looked older and older; net hold let go, with nothing in the log). The cap holds for
    the frames the decoder can have held, no more."""
    source = StreamSource("udp://127.0.0.1:9", OPTIONS)  # the rule alone: never opened
    cap = _StatedRate(5.0)
    source._frames_held = 2  # what an open finds out (`_connect`)
    source._period = 1.0 / cap.fps
    source._came_out = collections.deque(maxlen=2)
    t, period = 100.0, 1.0 / 30.0
    stamps = []
    for _ in range(30):
        t += period
        stamps.append(source._capture_time(cap, t, period))  # type: ignore[arg-type]
    t += 0.8  # over half the stall time: the decoder's frames come out at once after it
    stamps.append(source._capture_time(cap, t, 0.8))  # type: ignore[arg-type]
    for _ in range(30):
        t += period
        stamps.append(source._capture_time(cap, t, period))  # type: ignore[arg-type]
    assert all(b > a for a, b in itertools.pairwise(stamps))
    assert t - stamps[-1] < 3 * period, (t, stamps[-5:])


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


def test_rtsp_over_tcp_and_a_restarted_server(
    streamers: list[Streamer], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    exe = ffmpeg_exe()
    sdp, rtp_in = rtp_to_rtsp(exe, tmp_path, streamers)
    server = RtspServer(sdp, rtp_in)
    url = f"rtsp://127.0.0.1:{server.port}/video_stream__dev_video2"
    try:
        with caplog.at_level(logging.INFO, logger="drivers.sources"), open_source(
            url, OPTIONS
        ) as source:
            numbers = read_numbers(source, 5)
            assert len(numbers) == 5 and numbers == sorted(set(numbers))
            assert streamers[-1].sent - numbers[-1] <= 8  # fresh frames over TCP too
            server.close()  # the camera manager restarts
            assert wait_for(lambda: source.state is SourceState.DOWN, 10.0)
            server = RtspServer(sdp, rtp_in, port=server.port)
            assert wait_for(lambda: source.state is SourceState.UP, 15.0)
            again = read_numbers(source, 5)
            assert len(again) == 5 and again[0] > numbers[-1]
            assert source.stats().reconnects == 1
    finally:
        server.close()
        rtp_in.close()
    assert len([r for r in caplog.records if " down: " in r.getMessage()]) == 1


def test_a_missing_sdp_file_is_named(tmp_path: Path) -> None:
    """FFmpeg fails at once on an SDP file that is not there and says why only on stderr: the
    source said "nothing there, no stream yet" and retried for ever."""
    missing = tmp_path / "camera.sdp"
    with pytest.raises(SourceError, match="no such SDP file"):
        open_source(f"sdp:{missing}", SourceOptions(open_timeout_s=2.0))
