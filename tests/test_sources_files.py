"""`file:` and `images:` sources against real encoded videos and images, decoded by OpenCV.

Each test frame shows its own number as big blocks (drivers.sources.fake_capture), so after a
real encode/decode round trip the test can check that frame `index` really is frame `index`.
"""

from __future__ import annotations

import logging
import shutil
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from drivers.errors import SourceError
from drivers.sources import Frame, FrameSource, SourceOptions, SourceState, open_source
from drivers.sources.fake_capture import numbered_pattern, read_pattern_number
from drivers.sources.paced import MediaFrame, PacedSource

FRAMES = 30
FPS = 20.0
SIZE = (320, 240)


def write_opencv_video(
    path: Path, fourcc: str, frames: int = FRAMES, fps: float = FPS
) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*fourcc), fps, SIZE)
    assert writer.isOpened(), f"OpenCV cannot write {fourcc} here"
    for n in range(frames):
        writer.write(cv2.cvtColor(numbered_pattern(n, *SIZE), cv2.COLOR_GRAY2BGR))
    writer.release()
    return path


def write_h264_video(path: Path, frames: int = FRAMES) -> Path:
    av = pytest.importorskip("av")
    try:
        av.codec.Codec("libx264", "w")
    except Exception:  # PyAV built without an H.264 encoder
        pytest.skip("no H.264 encoder in this PyAV")
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=int(FPS))
        stream.width, stream.height, stream.pix_fmt = SIZE[0], SIZE[1], "yuv420p"
        stream.options = {"preset": "ultrafast"}
        for n in range(frames):
            frame = av.VideoFrame.from_ndarray(numbered_pattern(n, *SIZE), format="gray")
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return path


def write_timed_video(path: Path, times_s: list[float], stated_fps: int = 30) -> Path:
    """Numbered frames presented at `times_s` (a variable rate), in a container that states
    `stated_fps` (MPEG-4 part 2: in PyAV's own FFmpeg whatever else it was built with)."""
    from fractions import Fraction

    av = pytest.importorskip("av")
    with av.open(str(path), "w") as container:
        stream = container.add_stream("mpeg4", rate=stated_fps)
        stream.width, stream.height, stream.pix_fmt = SIZE[0], SIZE[1], "yuv420p"
        stream.time_base = stream.codec_context.time_base = Fraction(1, 1000)
        for n, t in enumerate(times_s):
            frame = av.VideoFrame.from_ndarray(numbered_pattern(n, *SIZE), format="gray")
            frame.pts, frame.time_base = round(1000 * t), Fraction(1, 1000)
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return path


@pytest.fixture(scope="module")
def videos(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("videos")
    return {
        "mjpg": write_opencv_video(folder / "mjpg.avi", "MJPG"),
        "mp4v": write_opencv_video(folder / "mp4v.mp4", "mp4v"),
    }


def read_all(url: str, limit: int = 1000, options: SourceOptions | None = None) -> list[Frame]:
    frames: list[Frame] = []
    with open_source(url, options) as source:
        while len(frames) < limit:
            frame = source.read(1.0)
            if frame is None:
                break
            frames.append(frame)
        assert source.state in (SourceState.ENDED, SourceState.UP)
    return frames


@pytest.mark.parametrize("codec", ["mjpg", "mp4v", "h264"])
def test_every_frame_comes_back_in_order_with_media_timestamps(
    codec: str, videos: dict[str, Path], tmp_path: Path
) -> None:
    path = write_h264_video(tmp_path / "h264.mp4") if codec == "h264" else videos[codec]
    with open_source(f"file:{path}") as source:
        frames = []
        while (frame := source.read(1.0)) is not None:
            frames.append(frame)
        assert source.state is SourceState.ENDED
        stats = source.stats()
        started = time.monotonic()
        assert source.read(0.05) is None
        assert time.monotonic() - started >= 0.04  # an ended source waits, a poller won't spin
    assert [f.index for f in frames] == list(range(FRAMES))
    assert [read_pattern_number(f.image) for f in frames] == list(range(FRAMES))
    assert all(f.image.shape == (SIZE[1], SIZE[0]) and f.image.dtype == np.uint8 for f in frames)
    # Replay keeps the recording's spacing whatever the reading speed.
    steps = np.diff([f.t_monotonic for f in frames])
    assert np.allclose(steps, 1.0 / FPS, atol=1e-3)
    assert np.allclose(np.diff([f.t_wall for f in frames]), steps, atol=1e-6)
    assert (stats.frames, stats.drops, stats.corrupt) == (FRAMES, 0, 0)


def test_colour_is_kept_only_when_asked(videos: dict[str, Path]) -> None:
    plain = read_all(f"file:{videos['mjpg']}", limit=1)[0]
    assert plain.color is None
    colour = SourceOptions(keep_color=True)
    coloured = read_all(f"file:{videos['mjpg']}", limit=1, options=colour)[0]
    assert coloured.color is not None and coloured.color.shape == (SIZE[1], SIZE[0], 3)
    assert np.array_equal(coloured.image, cv2.cvtColor(coloured.color, cv2.COLOR_BGR2GRAY))


def corrupt_jpeg_frames(src: Path, dst: Path, frames: list[int]) -> None:
    """Overwrite the table headers of the given MJPEG frames with garbage (damage to the
    entropy-coded data itself is concealed by the decoder and comes out as a smeared frame)."""
    data = bytearray(src.read_bytes())
    starts = [i for i in range(len(data) - 2) if data[i : i + 3] == b"\xff\xd8\xff"]
    assert len(starts) == FRAMES
    rng = np.random.default_rng(7)
    for n in frames:
        begin = starts[n] + 100  # the quantisation and Huffman tables: undecodable
        data[begin : begin + 300] = rng.integers(0, 256, 300, dtype=np.uint8).tobytes()
    dst.write_bytes(bytes(data))


def test_corrupt_frames_are_counted_and_skipped(videos: dict[str, Path], tmp_path: Path) -> None:
    damaged = tmp_path / "damaged.avi"
    bad = [7, 8, 19]
    corrupt_jpeg_frames(videos["mjpg"], damaged, bad)
    with open_source(f"file:{damaged}") as source:
        frames = []
        while (frame := source.read(1.0)) is not None:
            frames.append(frame)
        stats = source.stats()
    good = [n for n in range(FRAMES) if n not in bad]
    assert [f.index for f in frames] == good  # gaps where the damaged frames were
    assert [read_pattern_number(f.image) for f in frames] == good
    assert stats.corrupt == len(bad)
    assert stats.frames == len(good)


def test_truncated_recording_plays_what_is_there(videos: dict[str, Path], tmp_path: Path) -> None:
    data = videos["mjpg"].read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: len(data) // 2])
    frames = read_all(f"file:{cut}")
    assert 5 <= len(frames) < FRAMES
    assert [read_pattern_number(f.image) for f in frames] == list(range(len(frames)))


def test_unreadable_files_are_clear_errors(videos: dict[str, Path], tmp_path: Path) -> None:
    with pytest.raises(SourceError, match="no such file"):
        open_source(f"file:{tmp_path / 'missing.mp4'}")
    headless = tmp_path / "headless.mp4"  # an mp4 cut before its index: unreadable
    headless.write_bytes(videos["mp4v"].read_bytes()[:2000])
    with pytest.raises(SourceError) as err:
        open_source(f"file:{headless}")
    assert err.value.url == f"file:{headless}"
    assert "truncated" in err.value.reason
    text = tmp_path / "notes.mp4"
    text.write_text("not a video\n" * 100)
    with pytest.raises(SourceError, match=r"notes\.mp4"):
        open_source(str(text))


def test_loop_restarts_and_keeps_counting(videos: dict[str, Path]) -> None:
    frames = read_all(f"file:{videos['mp4v']}?loop=1", limit=2 * FRAMES + 5)
    assert [f.index for f in frames] == list(range(2 * FRAMES + 5))
    assert [read_pattern_number(f.image) for f in frames] == [i % FRAMES for i in range(65)]
    assert np.allclose(np.diff([f.t_monotonic for f in frames]), 1.0 / FPS, atol=1e-3)


def test_realtime_pacing_drops_what_a_slow_consumer_misses(videos: dict[str, Path]) -> None:
    with open_source(f"file:{videos['mjpg']}?realtime=1") as source:
        frames = []
        returned_at = []
        while (frame := source.read(1.0)) is not None:
            returned_at.append(time.monotonic())
            frames.append(frame)
            time.sleep(2.5 / FPS)  # a consumer that needs 2.5 frame periods per frame
        stats = source.stats()
    indices = [f.index for f in frames]
    assert indices == sorted(set(indices))
    assert stats.drops > 0 and stats.frames + stats.drops == FRAMES
    assert [read_pattern_number(f.image) for f in frames] == indices
    # A frame is handed out once due, and is then the newest due frame.
    for frame, at in zip(frames, returned_at, strict=True):
        assert frame.t_monotonic <= at + 1e-3
        assert at - frame.t_monotonic < 1.0 / FPS + 0.05


def test_realtime_consumer_late_past_a_loops_end_gets_a_frame_due_now(tmp_path: Path) -> None:
    # A consumer busy past the end of a looping file: the frame it gets is the one due now in
    # the next pass, not the pass's first frame stamped as long ago as the consumer was late.
    clip = write_opencv_video(tmp_path / "clip.avi", "MJPG", frames=10, fps=20.0)  # 0.5 s
    with open_source(f"file:{clip}?realtime=1&loop=1") as source:
        assert source.read(1.0) is not None
        time.sleep(0.5 + 0.3)  # past the end of the pass, 0.3 s (6 frames) into the next
        frame = source.read(1.0)
        got_at = time.monotonic()
        assert frame is not None
        assert got_at - frame.t_monotonic < 1.0 / 20.0 + 0.05
        assert frame.index >= 10 + 5  # the next pass's, counted on
        assert read_pattern_number(frame.image) == frame.index - 10
        # ... and the pass goes on on one clock: times follow the numbers.
        later = [source.read(1.0) for _ in range(3)]
        assert all(f is not None for f in later)
        for f in later:
            assert f is not None
            assert f.t_monotonic - frame.t_monotonic == pytest.approx(
                (f.index - frame.index) / 20.0, abs=1e-3)


class _SlowRender(PacedSource):
    """A medium whose every frame takes `render_s` to make (a renderer, a slow decoder)."""

    def __init__(self, render_s: float, period_s: float) -> None:
        super().__init__("slow:", realtime=True)
        self.render_s, self.period = render_s, period_s
        self.number = 0
        self.renders = 0

    def _start(self) -> None:
        pass

    def _next_media(self) -> MediaFrame:
        time.sleep(self.render_s)
        self.renders += 1
        media = MediaFrame(image=np.zeros((8, 8), np.uint8), number=self.number,
                           media_time_s=self.number * self.period)
        self.number += 1
        return media

    def _skip_to(self, number: int) -> int:
        passed = max(0, number - self.number)
        self.number += passed
        return passed

    def _rewind(self) -> None:
        self.number = 0

    def _stop(self) -> None:
        pass

    @property
    def frame_period_s(self) -> float:
        return self.period


def test_a_medium_slower_than_its_frame_rate_is_not_made_twice_per_frame() -> None:
    """Rendering that takes 1.2 frame periods: each frame is late by the time it is made. The
    once-more skip for an overdue frame (meant for a jump past a loop's end) threw it away and
    made another: half the frames for the same work (13 delivered of 26 made in 3 s; 25 of 25
    before it)."""
    source = _SlowRender(0.06, 0.05)
    source.open()
    started, delivered = time.monotonic(), 0
    while time.monotonic() - started < 1.5:
        if source.read(1.0) is not None:
            delivered += 1
    assert delivered >= 0.85 * source.renders, (delivered, source.renders)


def test_realtime_read_returns_none_when_nothing_is_due(tmp_path: Path) -> None:
    slow = write_opencv_video(tmp_path / "slow.avi", "MJPG", frames=3, fps=2.0)
    with open_source(f"file:{slow}?realtime=1") as source:
        first = source.read(1.0)
        assert first is not None and first.index == 0
        started = time.monotonic()
        assert source.read(0.05) is None  # the next frame is due 0.5 s after the first
        assert time.monotonic() - started < 0.4  # never much longer than the timeout
        second = source.read(1.0)
        assert second is not None and second.index == 1
        assert second.t_monotonic - first.t_monotonic == pytest.approx(0.5, abs=1e-3)


def write_images(folder: Path, count: int) -> None:
    folder.mkdir()
    for n in range(count):
        cv2.imwrite(str(folder / f"frame_{n:04d}.png"), numbered_pattern(n, *SIZE))


def test_image_folder_in_name_order_with_a_damaged_file(tmp_path: Path) -> None:
    folder = tmp_path / "frames"
    write_images(folder, 6)
    (folder / "frame_0003.png").write_bytes(b"\x89PNG\r\n\x1a\n broken")
    (folder / "notes.txt").write_text("ignored")
    with open_source(f"images:{folder}?fps=4") as source:
        frames = []
        while (frame := source.read(1.0)) is not None:
            frames.append(frame)
        stats = source.stats()
    assert [f.index for f in frames] == [0, 1, 2, 4, 5]
    assert [read_pattern_number(f.image) for f in frames] == [0, 1, 2, 4, 5]
    assert stats.corrupt == 1
    assert np.allclose(np.diff([f.t_monotonic for f in frames]), [0.25, 0.25, 0.5, 0.25])


def test_hidden_files_in_an_image_folder_are_not_frames(tmp_path: Path) -> None:
    """A folder copied from a Mac to exFAT or SMB has a "._frame_0000.png" (AppleDouble
    metadata) beside every image: they sorted first, failed to decode and took the first frame
    numbers, so every real frame (and its ground truth) moved by as many."""
    folder = tmp_path / "frames"
    write_images(folder, 4)
    for n in range(4):
        (folder / f"._frame_{n:04d}.png").write_bytes(b"\x00\x05\x16\x07" + b"\0" * 60)
    frames = read_all(f"images:{folder}")
    assert [f.index for f in frames] == [0, 1, 2, 3]
    assert [read_pattern_number(f.image) for f in frames] == [0, 1, 2, 3]


def test_image_glob_and_bare_folder(tmp_path: Path) -> None:
    folder = tmp_path / "frames"
    write_images(folder, 4)
    cv2.imwrite(str(folder / "zz_extra.jpg"), numbered_pattern(9, *SIZE))
    assert [f.index for f in read_all(f"images:{folder}/*.png")] == [0, 1, 2, 3]
    coloured = read_all(str(folder), options=SourceOptions(keep_color=True))
    assert len(coloured) == 5 and coloured[-1].color is not None
    assert read_pattern_number(coloured[-1].image) == 9  # "zz_extra.jpg" sorts last


def test_empty_image_folder_is_an_error(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    with pytest.raises(SourceError, match="no images"):
        open_source(f"images:{tmp_path / 'empty'}")
    with pytest.raises(SourceError, match="no such folder"):
        open_source(f"images:{tmp_path / 'nowhere'}/")


def test_looped_damaged_file_keeps_frame_numbers_per_pass(
    videos: dict[str, Path], tmp_path: Path
) -> None:
    damaged = tmp_path / "damaged.avi"
    bad = [0, 13, 28]  # including the first frame of a pass and one next to the last
    corrupt_jpeg_frames(videos["mjpg"], damaged, bad)
    good = [n for n in range(FRAMES) if n not in bad]
    with open_source(f"file:{damaged}?loop=1") as source:
        frames = read_frames_up_to(source, 2 * len(good))
        assert source.stats().corrupt == 2 * len(bad)
    assert [f.index for f in frames] == good + [FRAMES + n for n in good]
    assert [read_pattern_number(f.image) for f in frames] == good + good
    # The clock runs on through the loop: frame n of pass p is at (p * FRAMES + n) / FPS.
    t0 = frames[0].t_monotonic - good[0] / FPS
    assert np.allclose([f.t_monotonic - t0 for f in frames], [f.index / FPS for f in frames])


def read_frames_up_to(source: FrameSource, count: int) -> list[Frame]:
    frames: list[Frame] = []
    while len(frames) < count and (frame := source.read(1.0)) is not None:
        frames.append(frame)
    return frames


def test_truncated_jpeg_in_a_folder_is_skipped_with_its_reason(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """libjpeg can decode a truncated JPEG with a grey band and only a warning on stderr: such a
    frame would be measured as if it were whole. It is refused, counted and said why."""
    folder = tmp_path / "frames"
    folder.mkdir()
    for n in range(4):
        cv2.imwrite(str(folder / f"f{n}.jpg"), numbered_pattern(n, *SIZE))
    whole = (folder / "f2.jpg").read_bytes()
    # Depending on the OpenCV build, imdecode returns the padded picture or nothing: the
    # container check decides the same either way.
    (folder / "f2.jpg").write_bytes(whole[: len(whole) * 2 // 3])
    with caplog.at_level(logging.WARNING, logger="drivers.sources"):
        frames = read_all(f"images:{folder}")
    assert [f.index for f in frames] == [0, 1, 3]
    assert "truncated JPEG" in caplog.text


def test_looping_folder_emptied_and_refilled_comes_back(tmp_path: Path) -> None:
    """An images: source of a service (wait_at_start) rides out a folder that goes away for a
    while (a card re-mounted): DOWN with the reason, then frames again, never ENDED for good."""
    folder = tmp_path / "frames"
    write_images(folder, 3)
    options = SourceOptions(wait_at_start=True, reconnect_min_s=0.05, reconnect_max_s=0.2)
    with open_source(f"images:{folder}?loop=1", options) as source:
        first = [source.read(0.5) for _ in range(3)]
        assert all(f is not None for f in first)
        moved = tmp_path / "away"
        folder.rename(moved)
        states = []
        for _ in range(10):
            if source.read(0.1) is not None:
                continue
            states.append(source.state)
        assert SourceState.DOWN in states and SourceState.ENDED not in states
        assert "no such folder" in source.stats().error
        moved.rename(folder)
        back = [f for f in (source.read(0.3) for _ in range(10)) if f is not None]
    assert back, "frames did not come back after the folder returned"
    assert back[0].index > max(f.index for f in first if f is not None)  # numbering carries on


def test_looping_file_removed_and_put_back_comes_back(
    videos: dict[str, Path], tmp_path: Path
) -> None:
    """The same for a looping video file that goes away between passes (a demo's clip
    replaced): DOWN with the reason, then frames again; read() never raises."""
    clip = tmp_path / "clip.avi"
    clip.write_bytes(videos["mjpg"].read_bytes())
    options = SourceOptions(wait_at_start=True, reconnect_min_s=0.05, reconnect_max_s=0.2)
    with open_source(f"file:{clip}?loop=1", options) as source:
        first = [source.read(0.5) for _ in range(3)]
        assert all(f is not None for f in first)
        moved = tmp_path / "away.avi"
        clip.rename(moved)
        states = []
        for _ in range(FRAMES + 10):  # through the end of the pass, into the rewind
            if source.read(0.1) is None:
                states.append(source.state)
        assert SourceState.DOWN in states and SourceState.ENDED not in states
        assert "no such file" in source.stats().error
        moved.rename(clip)
        back = [f for f in (source.read(0.3) for _ in range(10)) if f is not None]
    assert back, "frames did not come back after the file returned"


def test_an_image_folder_deleted_under_the_service_is_an_outage(tmp_path: Path) -> None:
    """The folder deleted mid-run: each vanished file counted as a corrupt frame, and the
    status said "streaming" for the 2 s until the stall timeout. Down at once, with the
    reason; frames again when the folder is back."""
    folder = tmp_path / "frames"
    write_images(folder, 6)
    options = SourceOptions(wait_at_start=True, reconnect_min_s=0.05, reconnect_max_s=0.2)
    with open_source(f"images:{folder}?loop=1", options) as source:
        assert source.read(0.5) is not None and source.read(0.5) is not None
        shutil.rmtree(folder)
        assert source.read(0.1) is None
        assert source.state is SourceState.DOWN and "is gone" in source.stats().error
        assert source.stats().corrupt == 0
        write_images(folder, 3)
        back = [f for f in (source.read(0.3) for _ in range(10)) if f is not None]
    assert back


def test_a_missing_file_at_start_is_waited_for(videos: dict[str, Path], tmp_path: Path) -> None:
    target = tmp_path / "later.avi"
    options = SourceOptions(wait_at_start=True, reconnect_min_s=0.05, reconnect_max_s=0.2)
    with open_source(f"file:{target}", options) as source:
        assert source.state is SourceState.DOWN and "no such file" in source.stats().error
        assert source.read(0.1) is None
        target.write_bytes(videos["mjpg"].read_bytes())
        frame = next((f for f in (source.read(0.3) for _ in range(10)) if f is not None), None)
    assert frame is not None and frame.index == 0


def test_a_recording_paced_in_real_time_skips_what_a_slow_reader_missed(tmp_path: Path) -> None:
    """A recording's frame numbers are the vehicle's, which start where the recording started
    (70,000 frames into a dive, for one made from the web page). Paced in real time (the
    service's default), it compared those numbers with the frame periods since open() and
    never skipped: a reader slower than the recording fell behind without end (3.5 s after
    16 s, the distance withheld as stale). It skips by recorded time, like a camera."""
    import json

    folder = tmp_path / "rec"
    folder.mkdir()
    (folder / "recording.json").write_text("{}")
    period = 1.0 / 90.0
    rows = []
    for i in range(180):
        name = f"f{i:04d}.png"
        cv2.imwrite(str(folder / name), numbered_pattern(i, 160, 120))
        rows.append(json.dumps({"frame": name, "index": 70_000 + i, "t_mono": 5000.0 + i * period,
                                "t_unix": 1.7e9 + i * period}))
    (folder / "frames.jsonl").write_text("\n".join(rows) + "\n")
    ages = []
    with open_source(f"recording:{folder}?realtime=1") as source:
        deadline = time.monotonic() + 1.0
        while time.monotonic() < deadline:
            frame = source.read(0.5)
            if frame is None:
                break
            ages.append(time.monotonic() - frame.t_monotonic)
            time.sleep(0.03)  # a reader slower than 90 frames/s
        drops = source.stats().drops
    assert len(ages) >= 10
    assert drops > len(ages)  # about two of three frames came due while the reader slept
    assert max(ages) < 2 * period + 0.01, max(ages)  # the newest frame, not a growing backlog


def _joined_ts(tmp_path: Path, parts: list[tuple[str, int, int]]) -> Path:
    """MPEG-TS files of 50 numbered frames at 25 fps each, (name, first number, timestamp
    offset in s), joined end to end."""
    import subprocess

    from tests.stream_peers import ffmpeg_exe

    exe = ffmpeg_exe()
    data = []
    for name, first, offset in parts:
        path = tmp_path / f"{name}.ts"
        frames = np.stack([numbered_pattern(first + i, 160, 120) for i in range(50)])
        subprocess.run([exe, "-hide_banner", "-loglevel", "error", "-f", "rawvideo",
                        "-pix_fmt", "gray", "-s", "160x120", "-r", "25", "-i", "-",
                        "-c:v", "libx264", "-preset", "ultrafast", "-pix_fmt", "yuv420p",
                        "-output_ts_offset", str(offset), "-f", "mpegts", str(path)],
                       input=frames.tobytes(), check=True, timeout=60)
        data.append(path.read_bytes())
    joined = tmp_path / "joined.ts"
    joined.write_bytes(b"".join(data))
    return joined


def test_a_real_gap_in_a_video_is_kept(tmp_path: Path) -> None:
    """A camera that missed 3 s: the frames after it come 3 s later, numbered on by what was
    missed (a replay shows the outage; only a jump longer than any outage is a join)."""
    joined = _joined_ts(tmp_path, [("before", 0, 0), ("after", 100, 5)])
    with open_source(f"file:{joined}?realtime=0") as source:
        frames = [f for f in iter(lambda: source.read(0.5), None)]
    numbers = [read_pattern_number(f.image) for f in frames]
    assert 100 in numbers, numbers[-5:]
    after = numbers.index(100)
    gap_s = frames[after].t_monotonic - frames[after - 1].t_monotonic
    assert gap_s == pytest.approx(3.04, abs=0.05)
    assert frames[after].index - frames[after - 1].index == pytest.approx(76, abs=1)


def test_a_video_whose_timestamps_jump_plays_on(tmp_path: Path) -> None:
    """Two MPEG-TS files joined end to end (an encoder restarted mid-dive, a recording cut and
    rejoined): the second one's timestamps start afresh. Read as a frame number, the jump was
    about 26 hours, and a file paced in real time waited that long for its next frame, up and
    without an error. A jump in the timestamps is played on without the gap, and said."""
    joined = _joined_ts(tmp_path, [("late", 0, 36_000), ("early", 100, 0)])
    numbers: list[int] = []
    with open_source(f"file:{joined}?realtime=1") as source:
        deadline = time.monotonic() + 6.0
        while time.monotonic() < deadline and (not numbers or numbers[-1] < 140):
            frame = source.read(0.5)
            if frame is not None:
                numbers.append(read_pattern_number(frame.image))
                last_index = frame.index
    assert numbers and numbers[-1] >= 140, numbers[-5:]  # into the second part, on time
    assert last_index < 200  # numbered on, not 26 hours on


# A phone's or a browser's recording (Cockpit records the pilot's video in the browser): its
# frames come when they come. Stated 30 fps, steps of 100, 300 and 50 ms.
VARIABLE_TIMES = [0.1 * i for i in range(6)] + [0.5 + 0.3 * i for i in range(1, 5)] + [
    1.7 + 0.05 * i for i in range(1, 9)]


@pytest.mark.parametrize("container", ["mkv", "mp4"])
def test_a_variable_rate_video_is_numbered_as_it_comes_and_timed_by_its_timestamps(
    tmp_path: Path, container: str
) -> None:
    """Numbered by its stated (or average) rate, a 30-frame, 4.45 s phone recording came out
    as frames up to 35 with gaps and 5.3 s long, so a frame-numbered truth file met the wrong
    frames and the filter's steps were wrong. Frames are numbered in order, timed by their
    timestamps, and none counted as dropped."""
    path = write_timed_video(tmp_path / f"variable.{container}", VARIABLE_TIMES)
    with open_source(f"file:{path}") as source:
        frames = [f for f in iter(lambda: source.read(1.0), None)]
        stats = source.stats()
    count = len(VARIABLE_TIMES)
    assert [f.index for f in frames] == list(range(count))
    assert [read_pattern_number(f.image) for f in frames] == list(range(count))
    times = [f.t_monotonic - frames[0].t_monotonic for f in frames]
    assert times == pytest.approx(VARIABLE_TIMES, abs=1.5e-3)  # the container's 1 ms ticks
    assert (stats.frames, stats.drops, stats.corrupt) == (count, 0, 0)


@pytest.mark.parametrize("stall_at", [4.0, 1.0])
def test_a_constant_rate_video_that_lost_frames_keeps_its_own_rate(
    tmp_path: Path, stall_at: float
) -> None:
    """A 10 fps recording whose camera stalled for a second: its container states the average
    rate (frames over duration: 9.3 fps here), not the frames' own. Numbered and timed at that
    rate, every frame before the stall came later than it was presented (0.1 s off at 4 s, and
    growing with the file), the stall read as 0.2 s and only two of its ten lost frames were
    missing numbers. The frames' own steps give the rate: each frame at its own time, the
    stall whole, its ten frames counted as dropped. Also where the stall lies inside the first
    frames read at open (1.0 s)."""
    times = [0.1 * i for i in range(int(round(stall_at * 10)) + 1)]
    times += [times[-1] + 1.1 + 0.1 * i for i in range(120 - len(times))]
    path = write_timed_video(tmp_path / "stalled.mp4", times, stated_fps=10)
    with open_source(f"file:{path}") as source:
        frames = [f for f in iter(lambda: source.read(1.0), None)]
        stats = source.stats()
    assert [read_pattern_number(f.image) for f in frames] == list(range(len(times)))
    assert [f.index for f in frames] == [round(10 * t) for t in times]
    elapsed = [f.t_monotonic - frames[0].t_monotonic for f in frames]
    assert elapsed == pytest.approx(times, abs=1.5e-3)  # the container's 1 ms ticks
    assert (stats.frames, stats.drops, stats.corrupt) == (len(times), 10, 0)


def test_a_camera_that_halves_its_rate_loses_no_frames(tmp_path: Path) -> None:
    """A UVC camera halves its rate in low light: 30 fps for 4 s, then 15 fps; nothing lost.
    Its container states the average (21 fps); taken for a 30 fps camera with gaps, every step
    after the change was numbered as a lost frame, 15 of them, and every later number was 15
    too high (diff review). A rate more than a tenth from the stated one is a change of rate,
    not lost frames: numbered as they come."""
    times = [i / 30 for i in range(120)] + [4 + i / 15 for i in range(90)]
    path = write_timed_video(tmp_path / "halves.mp4", times, stated_fps=30)
    with open_source(f"file:{path}") as source:
        frames = [f for f in iter(lambda: source.read(1.0), None)]
        stats = source.stats()
    assert [read_pattern_number(f.image) for f in frames] == list(range(len(times)))
    assert [f.index for f in frames] == list(range(len(times)))
    assert (stats.frames, stats.drops) == (len(times), 0)


def test_unpadded_frame_numbers_are_read_in_number_order(tmp_path: Path) -> None:
    """Exporters often name frames frame_0.png ... frame_43.png: read in text order, row
    "frame 2" was frame_10.png, so every pairing with a truth table keyed by the file's number
    was wrong, without a word (research review). Numbers in names count by value; padded
    names keep their order; `netpose estimate` and `netpose calibrate` read folders alike."""
    from service.core.grey import frame_order

    folder = tmp_path / "frames"
    folder.mkdir()
    for n in range(12):
        assert cv2.imwrite(str(folder / f"frame_{n}.png"), numbered_pattern(n, *SIZE))
    with open_source(f"images:{folder}?fps=10") as source:
        frames = [f for f in iter(lambda: source.read(1.0), None)]
    assert [read_pattern_number(f.image) for f in frames] == list(range(12))
    padded = [Path(f"{n:04d}.png") for n in (10, 2, 0, 111)]
    assert sorted(padded, key=frame_order) == sorted(padded)
    assert [p.name for p in sorted([Path("b2.png"), Path("a10.png"), Path("a9.png")],
                                   key=frame_order)] == ["a9.png", "a10.png", "b2.png"]


def test_a_variable_rate_video_loops_on_in_time(tmp_path: Path) -> None:
    """The next pass starts after the last frame's own time, not after as many stated periods
    as there were frames (1 s for 18 frames stated at 30 fps, of a 2.1 s recording): time
    going back at the loop restarted the filter's track."""
    path = write_timed_video(tmp_path / "variable.mkv", VARIABLE_TIMES)
    count = len(VARIABLE_TIMES)
    frames = read_all(f"file:{path}?loop=1", limit=2 * count)
    assert [f.index for f in frames] == list(range(2 * count))
    steps = np.diff([f.t_monotonic for f in frames])
    assert steps.min() > 0.0
    assert steps[count - 1] == pytest.approx(0.05, abs=0.06)  # about a typical step


def test_realtime_pacing_keeps_a_variable_rate_videos_timing(tmp_path: Path) -> None:
    """Paced in real time, each frame comes when its timestamp says, none skipped for a reader
    that keeps up."""
    path = write_timed_video(tmp_path / "variable.mkv", VARIABLE_TIMES)
    with open_source(f"file:{path}?realtime=1") as source:
        frames, lateness = [], []
        while (frame := source.read(1.0)) is not None:
            lateness.append(time.monotonic() - frame.t_monotonic)
            frames.append(frame)
    assert [f.index for f in frames] == list(range(len(VARIABLE_TIMES)))
    assert min(lateness) >= -1e-3 and max(lateness) < 0.05


def test_a_rate_that_starts_varying_late_keeps_time_going_forward(tmp_path: Path) -> None:
    """Steady at the stated 30 fps past the look at open (100 frames, 3.3 s), then frames
    0.8 of a period apart, then one half a period after the last: numbered by the stated rate
    until then, the times given ran ahead of the timestamps, and when the rate was found to
    vary they went back 177 ms (which restarts the filter's track). They go on forward."""
    period = 1.0 / 30.0
    times = [i * period for i in range(100)]
    for _ in range(10):
        times.append(times[-1] + 0.8 * period)
    for _ in range(5):
        times.append(times[-1] + 0.5 * period)
    path = write_timed_video(tmp_path / "late.mkv", times)
    frames = read_all(f"file:{path}")
    assert [read_pattern_number(f.image) for f in frames] == list(range(len(times)))
    stamps = [f.t_monotonic for f in frames]
    assert min(np.diff(stamps)) > 0.0
    # At most the frames the stated rate numbered ahead (8 of them at 0.2 of a period).
    assert stamps[-1] - stamps[0] == pytest.approx(times[-1], abs=0.1)
