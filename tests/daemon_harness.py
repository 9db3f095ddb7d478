"""Drive the real daemon loop in-process, frame by frame, on a fake clock.

The frames are real renders of the synthetic source (made once and re-stamped), the estimator,
filter and loop are the production ones; only time and the outputs are stand-ins: a clock the
test advances, the recording link and publisher, a recording notifier. Nothing sleeps.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from drivers.mavlink_link import RecordingAutopilotLink
from drivers.sdnotify import RecordingNotifier
from drivers.sources import Frame, SourceState, SourceStats, create_source
from drivers.sources.synthetic import builtin_camera
from drivers.telemetry import RecordingPublisher
from service.config import Config
from service.core.camera import CameraModel
from service.daemon.loop import Daemon, DaemonParts
from service.daemon.wiring import load_daemon_config

REPO = Path(__file__).resolve().parents[1]
WALL_OFFSET = 1.7e9  # the fake wall clock is the fake monotonic clock plus this


class FakeClock:
    def __init__(self, start: float = 100.0) -> None:
        self.now = start

    def __call__(self) -> float:
        return self.now

    def wall(self) -> float:
        return self.now + WALL_OFFSET


def render_frames(url: str, count: int) -> list[Frame]:
    """`count` frames of a synthetic: URL (rendered as fast as possible)."""
    source = create_source(url + ("&" if "?" in url else "?") + "realtime=0")
    source.open()
    try:
        frames: list[Frame] = []
        while len(frames) < count:
            frame = source.read(1.0)
            assert frame is not None
            frames.append(frame)
        return frames
    finally:
        source.close()


@dataclass
class Step:
    """One read of the scripted source: a frame (`image` given) or nothing for `wait_s`."""

    frame: Frame | None = None
    wait_s: float = 0.0
    processing_s: float = 0.02  # time the loop spends on a frame (the clock moves on)
    # False: the frame's stamp does not bring the clock along (a file read faster than real
    # time, a recording's own clock): only processing_s passes.
    clock_follows: bool = True


class ScriptedSource:
    """A frame source that plays a script on the fake clock: each frame arrives at its capture
    time (the clock jumps there), a gap lets the read time out."""

    def __init__(self, script: Iterable[Step], clock: FakeClock, *, ends: bool = False) -> None:
        self._script: Iterator[Step] = iter(script)
        self._clock = clock
        self.opened = self.closed = False
        self.exhausted = False
        # As a real source counts them: frames it never handed over (the gaps in the frame
        # numbers it did), and whether it is a file that ends with its script.
        self._ends = ends
        self._last_index: int | None = None
        self._delivered = 0
        self.drops = 0

    def open(self) -> None:
        self.opened = True

    def read(self, timeout_s: float) -> Frame | None:
        step = next(self._script, None)
        self.exhausted = step is None
        if step is None or step.frame is None:
            self._clock.now += timeout_s if step is None else max(step.wait_s, 0.0)
            return None
        if step.clock_follows:
            self._clock.now = max(self._clock.now, step.frame.t_monotonic + step.processing_s)
        else:
            self._clock.now += step.processing_s
        if self._last_index is not None and step.frame.index > self._last_index + 1:
            self.drops += step.frame.index - self._last_index - 1
        self._last_index = step.frame.index
        self._delivered += 1
        return step.frame

    def stats(self) -> SourceStats:
        ended = self._ends and self.exhausted
        return SourceStats(state=SourceState.ENDED if ended else SourceState.UP,
                           frames=self._delivered, captured=self._delivered + self.drops,
                           drops=self.drops, corrupt=0, reconnects=0, fps=0.0)

    def close(self) -> None:
        self.closed = True


def frames_at(frames: list[Frame], fps: float, start: float,
              image: Callable[[np.ndarray], np.ndarray] | None = None) -> list[Frame]:
    """The frames re-stamped at `fps` from `start` on the fake clock (optionally altered)."""
    out = []
    for i, f in enumerate(frames):
        t = start + i / fps
        out.append(dataclasses.replace(
            f, index=i, t_monotonic=t, t_wall=t + WALL_OFFSET,
            image=f.image if image is None else np.ascontiguousarray(image(f.image))))
    return out


@dataclass
class Harness:
    daemon: Daemon
    clock: FakeClock
    source: ScriptedSource
    link: RecordingAutopilotLink
    telemetry: RecordingPublisher
    notifier: RecordingNotifier
    results: list[Any] = field(default_factory=list)

    def run_script(self) -> None:
        """iterate() until the script is used up."""
        while not self.source.exhausted:
            self.results.append(self.daemon.iterate())

    def iterate(self, n: int) -> None:
        for _ in range(n):
            self.results.append(self.daemon.iterate())


def demo_config(*overrides: str, path: Path | None = None) -> Config:
    return load_daemon_config(str(path or REPO / "config" / "demo.toml"), list(overrides))


class RecordingObserver:
    """A frame observer that keeps what the loop hands it."""

    def __init__(self) -> None:
        self.started = self.closed = False
        self.frames: list[tuple[int, Any]] = []
        self.statuses: list[Any] = []
        self.damages: list[Any] = []
        self.reloads: list[frozenset[str]] = []

    def start(self) -> None:
        self.started = True

    def observe(self, frame: Frame, result: Any, message: Any) -> None:
        self.frames.append((frame.index, message))

    def observe_status(self, message: Any) -> None:
        self.statuses.append(message)

    def observe_damage(self, message: Any) -> None:
        self.damages.append(message)

    def observe_reload(self, changed: frozenset[str]) -> None:
        self.reloads.append(changed)

    def close(self) -> None:
        self.closed = True


def make_harness(config: Config, script: Iterable[Step], *, start: float = 100.0,
                 load_config: Callable[[], Config] | None = None,
                 observers: tuple[Any, ...] = (), source_ends: bool = False,
                 camera: CameraModel | None = None) -> Harness:
    clock = FakeClock(start)
    source = ScriptedSource(script, clock, ends=source_ends)
    link = RecordingAutopilotLink()
    telemetry = RecordingPublisher()
    notifier = RecordingNotifier(watchdog_interval_s=1.0)
    parts = DaemonParts(source=source, link=link, telemetry=telemetry, notifier=notifier,
                        camera=camera or builtin_camera(640, 360), vehicle="test",
                        observers=observers)
    daemon = Daemon(config, parts, clock=clock, wall_clock=clock.wall, load_config=load_config)
    daemon.start()
    return Harness(daemon, clock, source, link, telemetry, notifier)
