"""Network stream source against a real H.264 stream on loopback.

A real ffmpeg process (the imageio-ffmpeg binary) encodes numbered frames with x264 and sends
them as MPEG-TS over UDP, or as RTP described by an SDP file (what the BlueOS camera manager
sends to port 5600), or as RTP that a small RTSP server in this module relays over TCP (what
the camera manager serves on 8554). The source decodes them with OpenCV's FFmpeg backend, whose
RTSP client does the real RTSP handshake. The frame numbers drawn in the picture tell how fresh
each frame is; stopping the streamer or the server is a real stall.
"""

from __future__ import annotations

import contextlib
import logging
import re
import socket
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from drivers.errors import SourceError
from drivers.net import free_port
from drivers.sources import FrameSource, SourceOptions, SourceState, open_source
from drivers.sources.fake_capture import numbered_pattern, read_pattern_number

FPS = 25
WIDTH, HEIGHT = 320, 240
OPTIONS = SourceOptions(
    # Open time allows for the slower stream probing of the FFmpeg in OpenCV 4.6 (Debian
    # bookworm): 3-6 s for this low-bitrate MPEG-TS over UDP, against ~1 s with OpenCV 5.
    stall_timeout_s=1.0, open_timeout_s=10.0, reconnect_min_s=0.1, reconnect_max_s=0.5
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
    return free_port(socket.SOCK_DGRAM)


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


class RtspServer:
    """The smallest RTSP server FFmpeg's client accepts: one H.264 track, RTP interleaved on
    the RTSP TCP connection (RFC 2326 section 10.12), fed with the RTP packets ffmpeg sends to a
    UDP socket. Its threads belong to it and are joined by close()."""

    SESSION = "4711"

    def __init__(self, sdp: str, rtp_in: socket.socket, port: int = 0) -> None:
        self._sdp = sdp
        self._rtp_in = rtp_in
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listener.bind(("127.0.0.1", port))
        self._listener.listen(4)
        self._listener.settimeout(0.1)
        self.port: int = self._listener.getsockname()[1]
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._playing: list[socket.socket] = []
        self._threads = [
            threading.Thread(target=self._accept, name="test-rtsp-accept", daemon=True),
            threading.Thread(target=self._relay, name="test-rtsp-relay", daemon=True),
        ]
        for thread in self._threads:
            thread.start()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._listener.accept()
            except TimeoutError:
                continue
            thread = threading.Thread(target=self._serve, args=(conn,), daemon=True)
            with self._lock:
                self._threads.append(thread)
            thread.start()

    def _relay(self) -> None:
        self._rtp_in.settimeout(0.1)
        while not self._stop.is_set():
            try:
                packet = self._rtp_in.recv(65536)
            except TimeoutError:
                continue
            chunk = b"$\x00" + len(packet).to_bytes(2, "big") + packet  # channel 0: RTP
            with self._lock:
                for conn in list(self._playing):
                    try:
                        conn.sendall(chunk)
                    except OSError:
                        self._playing.remove(conn)

    def _reply(self, method: str, url: str) -> tuple[str, str]:
        if method == "OPTIONS":
            return "Public: OPTIONS, DESCRIBE, SETUP, PLAY, TEARDOWN\r\n", ""
        if method == "DESCRIBE":
            return (f"Content-Base: {url}/\r\nContent-Type: application/sdp\r\n"
                    f"Content-Length: {len(self._sdp)}\r\n", self._sdp)
        if method == "SETUP":
            return ("Transport: RTP/AVP/TCP;unicast;interleaved=0-1\r\n"
                    f"Session: {self.SESSION}\r\n", "")
        return f"Session: {self.SESSION}\r\n", ""

    def _serve(self, conn: socket.socket) -> None:
        conn.settimeout(0.1)
        pending = b""
        try:
            while not self._stop.is_set():
                try:
                    data = conn.recv(4096)
                except TimeoutError:
                    continue
                if not data:
                    return
                pending += data
                while True:
                    if pending[:1] == b"$":  # interleaved RTCP from the client: skip it
                        if len(pending) < 4:
                            break
                        size = 4 + int.from_bytes(pending[2:4], "big")
                        if len(pending) < size:
                            break
                        pending = pending[size:]
                        continue
                    if b"\r\n\r\n" not in pending:
                        break
                    head, pending = pending.split(b"\r\n\r\n", 1)
                    lines = head.decode("ascii").split("\r\n")
                    method, url, _ = lines[0].split(" ")
                    cseq = next(v for k, _, v in (ln.partition(":") for ln in lines)
                                if k.lower() == "cseq").strip()
                    headers, body = self._reply(method, url)
                    conn.sendall(f"RTSP/1.0 200 OK\r\nCSeq: {cseq}\r\n{headers}\r\n{body}".encode())
                    if method == "PLAY":
                        with self._lock:
                            self._playing.append(conn)
        except OSError:
            return
        finally:
            with self._lock:
                if conn in self._playing:
                    self._playing.remove(conn)
            conn.close()

    def close(self) -> None:
        self._stop.set()
        with self._lock:
            threads = list(self._threads)
        for thread in threads:
            thread.join(5.0)
        self._listener.close()


def rtp_to_rtsp(exe: str, tmp_path: Path, streamers: list[Streamer]) -> tuple[str, socket.socket]:
    """Start an RTP streamer into a fresh UDP socket; the SDP the RTSP server will describe."""
    rtp_in = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rtp_in.bind(("127.0.0.1", 0))
    sdp_file = tmp_path / "rtsp.sdp"
    streamers.append(Streamer(exe, ["-f", "rtp", "-sdp_file", str(sdp_file),
                                    f"rtp://127.0.0.1:{rtp_in.getsockname()[1]}"]))
    assert wait_for(lambda: sdp_file.exists() and "rtpmap" in sdp_file.read_text(), 10.0)
    sdp = re.sub(r"c=IN IP4 \S+", "c=IN IP4 0.0.0.0", sdp_file.read_text()).strip()
    return "\r\n".join([*sdp.splitlines(), "a=control:trackID=0", ""]), rtp_in


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
