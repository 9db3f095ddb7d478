"""The daemon's loop in-process: real synthetic source, estimator and filter; the outputs are the
drivers' recording stand-ins. Faults are injected at the lowest edge (the frame source)."""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, cast

import numpy as np
import pytest

from drivers.mavlink_link import RecordingAutopilotLink
from drivers.sdnotify import RecordingNotifier
from drivers.sources import create_source
from drivers.telemetry import RecordingPublisher
from service.config import Config
from service.daemon import Daemon, FrameSource, SignalFlags, load_daemon_config

REPO = Path(__file__).resolve().parents[1]
URL = "synthetic:?width=640&height=360&fps=10&realtime=1&trajectory=static&range=1.2&seed=5"


class CameraThatDies:
    """The real synthetic source, until `die_after` frames: then nothing (cable pulled)."""

    def __init__(self, url: str, die_after: int) -> None:
        self._inner = create_source(url)
        self._left = die_after
        self.camera = self._inner.camera

    def open(self) -> None:
        self._inner.open()

    def read(self, timeout_s: float) -> Any:
        if self._left <= 0:
            time.sleep(timeout_s)
            return None
        frame = self._inner.read(timeout_s)
        if frame is not None:
            self._left -= 1
        return frame

    def close(self) -> None:
        self._inner.close()


class WrongSizeFrames:
    """Frames of an aspect ratio the calibration cannot serve (a misconfigured camera)."""

    def __init__(self, url: str) -> None:
        self._inner = create_source(url)
        self.camera = self._inner.camera

    def open(self) -> None:
        self._inner.open()

    def read(self, timeout_s: float) -> Any:
        frame = self._inner.read(timeout_s)
        return None if frame is None else replace(frame, image=np.ascontiguousarray(
            frame.image[:, :360]))

    def close(self) -> None:
        self._inner.close()


def config(*overrides: str) -> Config:
    return load_daemon_config(str(REPO / "config" / "demo.toml"),
                              [f"camera.url={URL}", "service.status_interval_s=0.2", *overrides])


def make_daemon(cfg: Config, source: Any) -> tuple[Daemon, RecordingAutopilotLink,
                                                    RecordingPublisher, RecordingNotifier]:
    link = RecordingAutopilotLink()
    tel = RecordingPublisher()
    notifier = RecordingNotifier(watchdog_interval_s=1.0)

    def factory(_cfg: Config) -> FrameSource:
        return cast(FrameSource, source)

    daemon = Daemon(cfg, notifier, SignalFlags(), source_factory=factory, link=link,
                    telemetry=tel)
    return daemon, link, tel, notifier


def test_dead_camera_stops_the_distance_and_is_logged_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    cfg = config("filter.coast_timeout_s=0.6", "filter.report_coasting_s=0.2",
                 "camera.stale_after_s=0.5")
    daemon, link, tel, notifier = make_daemon(cfg, CameraThatDies(URL, die_after=25))
    caplog.set_level(logging.INFO, logger="netpose.daemon")
    assert daemon.run(duration_s=4.5) == 0
    valid = [(r, t) for r, t in link.ranges if r is not None]
    assert valid, "never sent a distance while the camera worked"
    # The synthetic net is static at 1.2 m on the optical axis.
    sent = np.array([r.distance_m for r, _ in valid])
    assert np.median(np.abs(sent / 1.2 - 1.0)) < 0.05
    last_valid_at = max(t for _, t in valid)
    last_frame_at = max(e["frame_time_mono"] for e in tel.estimates)
    # Readings are stamped with their capture time; the prediction is reported for at most
    # report_coasting_s after the last frame (plus one status tick of the no-frame path).
    assert last_valid_at - last_frame_at <= 0.2 + 0.25
    assert link.ranges[-1][0] is None  # withdrawn, not left standing
    messages = [r.getMessage() for r in caplog.records]
    assert sum("frame source down" in m for m in messages) == 1
    assert sum("net lost" in m for m in messages) == 1
    assert notifier.messages[0].startswith("READY=1")
    assert "STOPPING=1" in notifier.messages
    assert link.closed and tel.closed


def test_unusable_frames_are_reported_once_and_nothing_is_sent(
    caplog: pytest.LogCaptureFixture,
) -> None:
    daemon, link, tel, _ = make_daemon(config(), WrongSizeFrames(URL))
    caplog.set_level(logging.INFO, logger="netpose.daemon")
    assert daemon.run(duration_s=2.0) == 0
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and "estimator cannot use frames" in warnings[0]
    assert "aspect ratio" in warnings[0]
    assert len(tel.estimates) >= 5  # kept running and reporting
    assert all(e["reason"] == "estimator error" for e in tel.estimates)
    assert all(r is None for r, _ in link.ranges)


def test_status_line_and_status_payload(caplog: pytest.LogCaptureFixture) -> None:
    daemon, _, tel, notifier = make_daemon(config(), CameraThatDies(URL, die_after=1000))
    assert daemon.run(duration_s=3.0) == 0
    statuses = [m for m in notifier.messages if m.startswith("STATUS=")]
    assert any(s.startswith("STATUS=tracking 1.") for s in statuses), statuses
    status = tel.statuses[-1]
    assert status["config_digest"] == daemon.config.digest
    assert status["filter"]["accepted"] > 5
    assert status["frame_source"]["state"] == "streaming"


def test_reload_applies_filter_and_rejects_a_broken_file(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "netpose.toml"
    base = (REPO / "config" / "demo.toml").read_text()
    path.write_text(base)
    cfg = load_daemon_config(str(path), [f"camera.url={URL}"])
    daemon, _, _, notifier = make_daemon(cfg, CameraThatDies(URL, die_after=1000))
    caplog.set_level(logging.INFO, logger="netpose.daemon")
    path.write_text(base + "\n[filter]\ngate_sigma = 6.0\n")
    assert daemon.reload()
    assert daemon.tracker.settings.gate_sigma == 6.0
    assert daemon.config.filter.gate_sigma == 6.0
    assert "rate_hz = 10.0" in base
    path.write_text(base.replace("rate_hz = 10.0", "rate_hz = 20.0", 1)
                    + "\n[filter]\ngate_sigma = 6.0\n")
    assert daemon.reload()
    # The link is not re-created: the running value stays, and the digest says so.
    assert daemon.config.effective["mavlink"]["rate_hz"] == 10.0
    assert any("restart needed for: mavlink" in r.getMessage() for r in caplog.records)
    path.write_text("[filter\n")
    assert not daemon.reload()
    assert daemon.config.filter.gate_sigma == 6.0
    assert any("reload rejected" in r.getMessage() for r in caplog.records)
    assert sum(m.startswith("RELOADING=1") for m in notifier.messages) == 3


def test_unreachable_outputs_do_not_stall_the_loop(caplog: pytest.LogCaptureFixture) -> None:
    """The real MAVLink link towards a TCP port where nobody listens and a real Zenoh client
    towards a router that is not there: both retry on their own threads while the loop keeps
    processing every frame a slow (5 frames/s) camera delivers."""
    from drivers.mavlink_link import MavlinkLink
    from drivers.mavlink_settings import MavlinkSettings
    from drivers.telemetry import TelemetrySettings, make_publisher
    from service.benchmarks.soak import free_port

    dead_tcp = free_port()  # free a moment ago, nobody listens
    dead_router = free_port()
    cfg = config()
    link = MavlinkLink(MavlinkSettings(url=f"tcp:127.0.0.1:{dead_tcp}"))
    tel = make_publisher(TelemetrySettings(
        mode="client", connect=(f"tcp/127.0.0.1:{dead_router}",), scouting=False))
    source = create_source(URL.replace("fps=10", "fps=5"))
    notifier = RecordingNotifier(watchdog_interval_s=1.0)

    def factory(_cfg: Config) -> FrameSource:
        return cast(FrameSource, source)

    daemon = Daemon(cfg, notifier, SignalFlags(), source_factory=factory, link=link,
                    telemetry=tel)
    caplog.set_level(logging.INFO, logger="netpose.daemon")
    assert daemon.run(duration_s=3.0) == 0
    stats = source.stats()
    summary = next(r.getMessage() for r in caplog.records if "final summary" in r.getMessage())
    processed = int(summary.split(" frames")[0].rsplit(" ", 1)[1])
    # 5 frames/s for 3 s: the loop took (nearly) every frame the camera produced; none went
    # stale waiting for an output.
    assert processed >= 0.8 * 5 * 3, summary
    assert stats.drops <= 1, stats
    assert "MAVLink link connecting" in caplog.text
    assert not tel.online
