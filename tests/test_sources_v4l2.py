"""V4L2 camera source: URL settings, format negotiation, and the live-source machinery (newest
frame, drops, corrupt buffers, unplug/replug with backoff) against a fake camera device.

The camera is the one thing that cannot exist here, so the fake sits at the lowest edge: the
object cv2.VideoCapture(device, CAP_V4L2) would return. Everything above it is the real code.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import pytest

from drivers.errors import SourceError
from drivers.sources import Frame, SourceOptions, SourceState, open_source
from drivers.sources.fake_capture import CameraMode, FakeCamera, read_pattern_number
from drivers.sources.v4l2 import (
    V4L2_SELECT_TIMEOUT_ENV,
    V4l2Settings,
    V4l2Source,
    negotiate,
    parse_v4l2_url,
)

MODES = [
    CameraMode("YUYV", 640, 480, 30.0),
    CameraMode("YUYV", 1280, 720, 10.0),
    CameraMode("MJPG", 1920, 1080, 30.0),
    CameraMode("MJPG", 1280, 720, 60.0),
    CameraMode("MJPG", 320, 240, 100.0),
    CameraMode("MJPG", 320, 240, 200.0),
]
FAST = SourceOptions(stall_timeout_s=0.5, reconnect_min_s=0.05, reconnect_max_s=0.2)


def wait_for(condition: Callable[[], bool], timeout_s: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.01)
    return condition()


def fast_source(camera: FakeCamera, options: SourceOptions = FAST) -> V4l2Source:
    source = V4l2Source(
        "v4l2:/dev/video0?width=320&height=240&fps=200&fourcc=MJPG",
        options,
        capture_factory=camera.open,
    )
    source.open()
    return source


def test_url_becomes_settings() -> None:
    s = parse_v4l2_url("v4l2:/dev/video2?width=1920&height=1080&fps=30&fourcc=mjpg&buffers=3")
    assert s == V4l2Settings("/dev/video2", 1920, 1080, 30.0, "MJPG", 3)
    assert parse_v4l2_url("v4l2:") == V4l2Settings("/dev/video0")
    assert parse_v4l2_url("v4l2:1").device == "1"


def test_negotiation_sets_format_then_size_then_rate() -> None:
    cap = FakeCamera(MODES).open("/dev/video0")
    url = "v4l2:/dev/video0?width=1280&height=720&fps=60&fourcc=MJPG"
    granted = negotiate(cap, parse_v4l2_url(url))
    assert (granted.width, granted.height, granted.fps, granted.fourcc) == (1280, 720, 60.0, "MJPG")
    order = [prop for prop, _ in cap.set_calls]
    assert order.index(cv2.CAP_PROP_FOURCC) < order.index(cv2.CAP_PROP_FRAME_WIDTH)
    assert order.index(cv2.CAP_PROP_FRAME_HEIGHT) < order.index(cv2.CAP_PROP_FPS)
    assert (cv2.CAP_PROP_BUFFERSIZE, 2.0) in cap.set_calls


def test_negotiation_reports_what_the_driver_granted(caplog: pytest.LogCaptureFixture) -> None:
    cap = FakeCamera(MODES).open("/dev/video0")
    with caplog.at_level(logging.INFO, logger="drivers.sources.v4l2"):
        url = "v4l2:/dev/video0?width=1600&height=900&fps=25&fourcc=YUYV"
        granted = negotiate(cap, parse_v4l2_url(url))
    # The driver snaps to its nearest YUYV mode: 1280x720, which only runs at 10 fps.
    assert (granted.width, granted.height, granted.fps, granted.fourcc) == (1280, 720, 10.0, "YUYV")
    warning = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warning) == 1
    assert "1280x720 at 10 fps, YUYV" in warning[0].getMessage()
    assert "size 1600x900" in warning[0].getMessage() and "fps 25" in warning[0].getMessage()


def test_unknown_pixel_format_keeps_the_current_one() -> None:
    cap = FakeCamera(MODES).open("/dev/video0")
    granted = negotiate(cap, V4l2Settings("/dev/video0", fourcc="H264"))
    assert granted.fourcc == "YUYV"


def test_frames_arrive_grey_numbered_and_stamped_by_the_driver() -> None:
    camera = FakeCamera(MODES)
    with fast_source(camera) as source:
        assert source.state is SourceState.UP
        assert source.granted is not None and source.granted.fps == 200.0
        frames: list[tuple[Frame, float, float]] = []
        while len(frames) < 20:
            before = time.monotonic()
            frame = source.read(1.0)
            assert frame is not None
            frames.append((frame, before, time.monotonic()))
        for frame, _, after in frames:
            assert frame.image.ndim == 2 and frame.image.shape == (240, 320)
            assert frame.color is None
            assert read_pattern_number(frame.image) == frame.index  # no corrupt frames here
            # The driver's buffer stamp (2 ms before dequeue) is used, on the monotonic clock.
            assert after - 0.5 < frame.t_monotonic <= after
            assert abs((frame.t_wall - time.time()) - (frame.t_monotonic - time.monotonic())) < 0.05
        indices = [f.index for f, _, _ in frames]
        assert indices == sorted(set(indices))
        stats = source.stats()
        assert stats.frames == 20
        # Every captured frame was delivered, dropped, or is the one waiting to be read.
        assert stats.captured - stats.frames - stats.drops in (0, 1)


def test_slow_consumer_gets_the_newest_frame_and_drops_are_counted() -> None:
    camera = FakeCamera(MODES)
    with fast_source(camera) as source:
        assert source.read(1.0) is not None
        time.sleep(0.3)  # the consumer is busy for ~60 frame periods
        made_before = camera.frames_made
        frame = source.read(1.0)
        assert frame is not None
        number = read_pattern_number(frame.image)
        # Newest frame: made at most a couple of frame periods before the read returned.
        assert number >= made_before - 3
        stats = source.stats()
        assert stats.drops >= 40
        assert stats.captured - stats.frames - stats.drops in (0, 1)
        assert frame.index - 1 >= stats.drops - 1  # the skipped numbers are the drops


def test_corrupt_buffers_are_counted_and_skipped() -> None:
    camera = FakeCamera(MODES)
    with fast_source(camera) as source:
        assert source.read(1.0) is not None
        camera.corrupt_next(3)
        assert wait_for(lambda: source.stats().corrupt == 3)
        frame = source.read(1.0)
        assert frame is not None
        assert source.state is SourceState.UP
        assert source.stats().reconnects == 0
        # Corrupt frames keep their numbers: the index still matches what the camera drew.
        later = source.read(1.0)
        assert later is not None and read_pattern_number(later.image) == later.index


def test_a_failed_read_keeps_its_number_in_the_next_frames_index() -> None:
    """A frame the decoder refused (read returns False) is counted as corrupt only once the
    next good frame had been published with the refused frame's number: the gap showed one
    frame late (new-driver review). The frame after it has its own number."""
    camera = FakeCamera(MODES)
    with fast_source(camera) as source:
        first = source.read(1.0)
        assert first is not None
        camera.fail_next(1)
        assert wait_for(lambda: source.stats().corrupt == 1)
        after = source.read(1.0)
        assert after is not None and read_pattern_number(after.image) == after.index
        assert source.state is SourceState.UP and source.stats().reconnects == 0


def test_reads_that_fail_at_once_before_a_first_frame_do_not_take_a_core() -> None:
    """A stream joined between key frames (OpenCV 4.6's FFmpeg), or a server that answers and
    closes, fails every read at once until a frame comes: read back to back, 3 million reads
    in 2 s took a whole core until the stall time (new-driver review). After 200 at full speed
    (packets buffered at the open) they are paced at 5 ms: half a second holds at most ~300,
    and those failures are not damage (not counted corrupt)."""
    camera = FakeCamera(MODES)
    camera.fail_next(1_000_000)
    with fast_source(camera, SourceOptions(stall_timeout_s=3.0)) as source:
        time.sleep(0.5)
        reads = camera.frames_made
        assert 200 <= reads <= 400, reads
        assert source.stats().corrupt == 0
        camera.stop_failing()  # the key frame comes
        frame = source.read(2.0)
        assert frame is not None and source.stats().corrupt == 0


def test_unplugged_camera_goes_down_and_comes_back(caplog: pytest.LogCaptureFixture) -> None:
    camera = FakeCamera(MODES)
    with caplog.at_level(logging.INFO, logger="drivers.sources"), fast_source(camera) as source:
        assert source.read(1.0) is not None
        camera.unplug()
        assert wait_for(lambda: source.state is SourceState.DOWN)
        opens_when_down = camera.opens
        assert wait_for(lambda: camera.opens >= opens_when_down + 3)  # retrying with backoff
        while source.read(0.0) is not None:  # whatever was captured before the unplug
            pass
        assert source.read(0.2) is None
        camera.plug()
        assert wait_for(lambda: source.state is SourceState.UP)
        frame = source.read(1.0)
        assert frame is not None
        stats = source.stats()
        assert stats.reconnects == 1
    downs = [r for r in caplog.records if "down" in r.getMessage()]
    ups = [r for r in caplog.records if "frames flowing again" in r.getMessage()]
    assert len(downs) == 1, "logged once per state change, not per attempt"
    assert len(ups) == 1
    assert "re-opening with backoff" in downs[0].getMessage()


def test_backoff_grows_while_the_camera_stays_away() -> None:
    camera = FakeCamera(MODES)
    options = SourceOptions(stall_timeout_s=0.5, reconnect_min_s=0.05, reconnect_max_s=0.4)
    with fast_source(camera, options) as source:
        camera.unplug()
        assert wait_for(lambda: source.state is SourceState.DOWN)
        start_opens, start = camera.opens, time.monotonic()
        time.sleep(1.5)
        attempts = camera.opens - start_opens
        elapsed = time.monotonic() - start
    # Doubling from 0.05 s to the 0.4 s cap: about 0.05+0.1+0.2+0.4+0.4+... -> 5-7 attempts in
    # 1.5 s; without backoff a tight loop would make thousands.
    assert 2 <= attempts <= elapsed / 0.05


def test_close_stops_and_joins_the_grabber() -> None:
    camera = FakeCamera(MODES)
    source = fast_source(camera)
    assert any(t.name.startswith("frame-source-") for t in threading.enumerate())
    source.close()
    assert not any(t.name.startswith("frame-source-") for t in threading.enumerate())
    assert source.state is SourceState.CLOSED
    assert source.read(0.05) is None
    source.close()  # idempotent


def test_missing_device_is_a_clear_error_naming_the_url() -> None:
    # The real OpenCV V4L2 backend on a device that does not exist.
    with pytest.raises(SourceError) as err:
        open_source("v4l2:/dev/video97?width=640&height=480")
    assert err.value.url.startswith("v4l2:/dev/video97")
    assert "/dev/video97" in str(err.value) and "cannot open" in str(err.value)


def test_a_cameras_second_node_is_named_as_its_metadata(tmp_path: Path) -> None:
    """A UVC camera shows as two nodes, /dev/video0 for its frames and /dev/video1 for their
    metadata, which gives no frames: picking it said only "missing, unplugged, no
    permission". The kernel numbers a device's nodes (sysfs `index`); one that is not 0 is
    named as such, with the name that stays right."""
    sysfs = tmp_path / "sys"
    (sysfs / "video1").mkdir(parents=True)
    (sysfs / "video1" / "index").write_text("1\n")
    camera = FakeCamera(MODES)
    camera.unplug()
    source = V4l2Source("v4l2:/dev/video1", FAST, capture_factory=camera.open, sysfs=sysfs)
    with pytest.raises(SourceError) as err:
        source.open()
    source.close()
    assert "node 1 of its device" in str(err.value) and "video-index0" in str(err.value)
    (sysfs / "video1" / "index").write_text("0\n")  # a camera's own node: no such hint
    source = V4l2Source("v4l2:/dev/video1", FAST, capture_factory=camera.open, sysfs=sysfs)
    with pytest.raises(SourceError) as err:
        source.open()
    source.close()
    assert "node" not in str(err.value)


def test_a_camera_absent_at_start_is_an_error_not_a_retry() -> None:
    camera = FakeCamera(MODES)
    camera.unplug()
    source = V4l2Source("v4l2:/dev/video0", FAST, capture_factory=camera.open)
    with pytest.raises(SourceError, match="cannot open /dev/video0"):
        source.open()
    source.close()
    assert camera.opens == 1


def test_v4l2_read_time_limit_follows_the_stall_timeout(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(V4L2_SELECT_TIMEOUT_ENV, raising=False)
    options = SourceOptions(stall_timeout_s=2.5, reconnect_min_s=0.05, reconnect_max_s=0.2)
    with fast_source(FakeCamera(MODES), options):
        assert os.environ[V4L2_SELECT_TIMEOUT_ENV] == "3"  # whole seconds, rounded up
    monkeypatch.setenv(V4L2_SELECT_TIMEOUT_ENV, "7")  # the user's choice wins
    with fast_source(FakeCamera(MODES), options):
        assert os.environ[V4L2_SELECT_TIMEOUT_ENV] == "7"


def test_a_service_waits_for_a_camera_absent_at_start(caplog: pytest.LogCaptureFixture) -> None:
    """wait_at_start (what the daemon asks for): the camera manager may start after netpose, so
    a missing camera is an outage to ride out, not an error; it is found within a backoff."""
    camera = FakeCamera(MODES)
    camera.unplug()
    options = SourceOptions(stall_timeout_s=0.5, reconnect_min_s=0.05, reconnect_max_s=0.2,
                            wait_at_start=True)
    source = V4l2Source("v4l2:/dev/video0?width=320&height=240&fps=200&fourcc=MJPG", options,
                        capture_factory=camera.open)
    with caplog.at_level(logging.INFO, logger="drivers.sources"):
        source.open()  # returns at once: the first open happens on the grabber thread
        try:
            assert wait_for(lambda: source.state is SourceState.DOWN)
            assert "cannot open /dev/video0" in source.stats().error
            assert source.read(0.1) is None
            assert wait_for(lambda: camera.opens >= 3)  # retried with backoff
            plugged_at = time.monotonic()
            camera.plug()
            frame = source.read(2.0)
            found_after = time.monotonic() - plugged_at
        finally:
            source.close()
    assert frame is not None and found_after < 0.2 + 0.1  # within one backoff step
    assert source.stats().error == ""
    downs = [r for r in caplog.records if " down: " in r.getMessage()]
    assert len(downs) == 1 and "cannot open /dev/video0" in downs[0].getMessage()


def test_close_does_not_wait_for_a_driver_stuck_in_open() -> None:
    """A stop must not wait for FFmpeg's open time limit (systemd's stop budget is seconds)."""
    camera = FakeCamera(MODES)
    release = threading.Event()

    def slow_open(device: str) -> object:
        release.wait(5.0)  # an RTSP open against a camera that does not answer
        return camera.open(device)

    options = SourceOptions(stall_timeout_s=0.5, reconnect_min_s=0.05, reconnect_max_s=0.2,
                            wait_at_start=True)
    source = V4l2Source("v4l2:/dev/video0", options, capture_factory=slow_open)  # type: ignore[arg-type]
    source.open()
    time.sleep(0.1)
    started = time.monotonic()
    source.close()
    took = time.monotonic() - started
    release.set()
    assert took < 0.5
    assert source.state is SourceState.CLOSED


def test_a_read_that_returns_after_close_is_not_kept() -> None:
    """close() does not wait for a driver stuck in a read (systemd's stop budget); the frame
    that read returned was published into the closed source, which held it (a 1080p colour
    frame) for as long as the source object lived (new-driver review)."""
    camera = FakeCamera(MODES)
    blocked, release = threading.Event(), threading.Event()

    class StuckRead:
        def __init__(self, device: str) -> None:
            self._capture = camera.open(device)
            self._reads = 0

        def __getattr__(self, name: str) -> object:
            return getattr(self._capture, name)

        def read(self) -> tuple[bool, object]:
            self._reads += 1
            if self._reads == 3:
                blocked.set()
                release.wait(5.0)
            return self._capture.read()

    source = V4l2Source("v4l2:/dev/video0", FAST, capture_factory=StuckRead)  # type: ignore[arg-type]
    source.open()
    assert blocked.wait(2.0)
    source.close()
    grabber = [t for t in threading.enumerate() if t.name.startswith("frame-source-")]
    release.set()
    for thread in grabber:
        thread.join(2.0)
    assert source._latest is None and source.read(0.0) is None
