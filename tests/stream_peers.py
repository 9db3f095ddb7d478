"""Real video-stream peers on loopback for tests: an ffmpeg H.264 streamer and a minimal RTSP
server (what the BlueOS camera manager serves on 8554), owned by the test that starts them."""

from __future__ import annotations

import contextlib
import re
import socket
import subprocess
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

from drivers.sources.fake_capture import numbered_pattern

FPS = 25
WIDTH, HEIGHT = 320, 240


def ffmpeg_exe() -> str:
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    exe: str = imageio_ffmpeg.get_ffmpeg_exe()
    encoders = subprocess.run(
        [exe, "-hide_banner", "-encoders"], capture_output=True, text=True, timeout=20
    ).stdout
    if "libx264" not in encoders:
        pytest.skip("this ffmpeg has no libx264")
    return exe


class Streamer:
    """An ffmpeg process fed frames at `fps` by a thread this object owns: by default numbered
    test patterns (the number tells how fresh a frame is), or `frames` (grey images, looped)."""

    def __init__(self, exe: str, output: list[str], first_number: int = 0, *,
                 frames: Sequence[npt.NDArray[np.uint8]] | None = None, fps: int = FPS,
                 gop: int | None = None, pause: tuple[int, float] | None = None) -> None:
        """`pause`: (frame number, seconds) — before that frame, nothing is sent for that
        long (a tether hiccup), then the stream goes on at its rate. `held` (an Event): while
        set, nothing is sent (ffmpeg waits for input: no flush), then the stream goes on."""
        self._frames = frames
        self._pause = pause
        height, width = (HEIGHT, WIDTH) if frames is None else frames[0].shape[:2]
        self._size = (width, height)
        self._fps = fps
        self._proc = subprocess.Popen(
            [
                exe, "-hide_banner", "-loglevel", "error",
                "-f", "rawvideo", "-pix_fmt", "gray", "-s", f"{width}x{height}", "-r", str(fps),
                "-i", "-",
                "-c:v", "libx264", "-preset", "ultrafast", "-tune", "zerolatency",
                "-g", str(gop or fps), "-pix_fmt", "yuv420p", "-flush_packets", "1",
                *output,
            ],
            stdin=subprocess.PIPE,
        )  # fmt: skip
        self.sent = first_number
        # When each frame was handed to the encoder (frame number -> time.monotonic()).
        self.sent_at: dict[int, float] = {}
        self._stop = threading.Event()
        self.held = threading.Event()
        self._thread = threading.Thread(target=self._feed, name="test-streamer", daemon=True)
        self._thread.start()

    def _feed(self) -> None:
        assert self._proc.stdin is not None
        start, first = time.monotonic(), self.sent
        try:
            while not self._stop.is_set():
                if self._pause is not None and self.sent == self._pause[0]:
                    self._stop.wait(self._pause[1])
                    start += self._pause[1]
                while self.held.is_set() and not self._stop.is_set():
                    waited = time.monotonic()
                    self._stop.wait(0.02)
                    start += time.monotonic() - waited
                if self._frames is None:
                    image = numbered_pattern(self.sent, *self._size)
                else:
                    image = self._frames[self.sent % len(self._frames)]
                self.sent_at[self.sent] = time.monotonic()
                self._proc.stdin.write(np.ascontiguousarray(image).tobytes())
                self._proc.stdin.flush()
                self.sent += 1
                time.sleep(max(0.0, start + (self.sent - first) / self._fps - time.monotonic()))
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


def wait_for(condition: Callable[[], bool], timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.02)
    return condition()


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
        own = [
            threading.Thread(target=self._accept, name="test-rtsp-accept", daemon=True),
            threading.Thread(target=self._relay, name="test-rtsp-relay", daemon=True),
        ]
        # A client connecting at once makes _accept append its thread to _threads (started
        # there): start only these two, from a list nobody else appends to.
        self._threads = list(own)
        for thread in own:
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


def rtp_to_rtsp(exe: str, tmp_path: Path, streamers: list[Streamer],
                frames: Sequence[npt.NDArray[np.uint8]] | None = None,
                fps: int = FPS, gop: int | None = None,
                pause: tuple[int, float] | None = None) -> tuple[str, socket.socket]:
    """Start an RTP streamer into a fresh UDP socket; the SDP the RTSP server will describe."""
    rtp_in = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rtp_in.bind(("127.0.0.1", 0))
    sdp_file = tmp_path / "rtsp.sdp"
    streamers.append(Streamer(exe, ["-f", "rtp", "-sdp_file", str(sdp_file),
                                    f"rtp://127.0.0.1:{rtp_in.getsockname()[1]}"],
                              frames=frames, fps=fps, gop=gop, pause=pause))
    assert wait_for(lambda: sdp_file.exists() and "rtpmap" in sdp_file.read_text(), 10.0)
    sdp = re.sub(r"c=IN IP4 \S+", "c=IN IP4 0.0.0.0", sdp_file.read_text()).strip()
    return "\r\n".join([*sdp.splitlines(), "a=control:trackID=0", ""]), rtp_in


