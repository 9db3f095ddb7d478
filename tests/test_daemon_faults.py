"""Fault injection: the real `netpose run` process through a scripted sequence of failures,
judged from the outside by what the autopilot and the topside saw.

Real peers on loopback: an H.264 camera stream served over RTSP (ffmpeg + the minimal RTSP
server of tests/stream_peers.py) showing a rendered net at a known distance, a MAVLink
autopilot on TCP (tests/fake_autopilot.py, pymavlink's codec), a Zenoh router in its own process
with a subscriber behind it, and systemd's NOTIFY_SOCKET. The sequence:

  1. the camera is missing at start, then plugged in;
  2. the stream stalls (the camera manager restarts) and returns;
  3. the autopilot link goes down and up;
  4. the Zenoh router goes down and up;
  5. SIGHUP with a broken configuration file, then a good one;
  6. SIGTERM while the stream is being re-opened against a camera that does not answer.

Throughout: nothing false reaches the autopilot (every distance within the estimator's
tolerance of the truth, none while there is no picture), each recovery takes <= 2 s after the
peer is back, and the process exits within a second of SIGTERM.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from drivers.net import free_port
from drivers.sources.synthetic import builtin_camera
from service.core.camera import save_camera
from tests.daemon_harness import render_frames
from tests.fake_autopilot import FakeAutopilot, TcpServerTransport
from tests.stream_peers import RtspServer, Streamer, ffmpeg_exe, rtp_to_rtsp
from tests.test_daemon_e2e import NotifyRecorder
from tests.test_telemetry import start_router

REPO = Path(__file__).resolve().parents[1]
DEMO = REPO / "config" / "demo.toml"
FPS = 10
# The camera's key-frame interval (frames): a returning stream is decoded from its next key
# frame, so it adds to every stream recovery. 0.5 s, what a BlueOS camera can be set to.
GOP = 5
RANGE_M = 1.2  # the rendered net, along the optical axis
# H.264 at the streamer's bitrate and the estimator on 640x360: measured within 1 %; 3 % is the
# limit for "believed distance" (the estimator's own target on real footage is 5 %).
RANGE_TOL = 0.03
RECOVERY_S = 2.0  # issue 17: after the peer is back
REPORT_COASTING_S = 0.3
MAX_AGE_S = 0.5
STALE_AFTER_S = 1.0

pytestmark = pytest.mark.timeout(240)


class Topside:
    """A Zenoh client behind the router: keeps (receive time, estimate) pairs."""

    def __init__(self, router: str) -> None:
        config = zenoh.Config()
        config.insert_json5("mode", '"client"')
        config.insert_json5("connect/endpoints", json.dumps([router]))
        config.insert_json5("scouting/multicast/enabled", "false")
        config.insert_json5("connect/retry", json.dumps(
            {"period_init_ms": 100, "period_max_ms": 250, "period_increase_factor": 2}))
        self._session = zenoh.open(config)
        self._lock = threading.Lock()
        self.estimates: list[tuple[float, dict[str, Any]]] = []
        self._sub = self._session.declare_subscriber("netpose/faults/estimate", self._on)

    def _on(self, sample: Any) -> None:
        payload = json.loads(sample.payload.to_bytes())
        with self._lock:
            self.estimates.append((time.monotonic(), payload))

    def first_after(self, t: float) -> float | None:
        """When the topside first received an estimate after `t` (its own clock)."""
        with self._lock:
            return next((rx for rx, _ in self.estimates if rx > t), None)

    def first_frame_after(self, t: float) -> float | None:
        """Capture time of the first frame after `t`: CLOCK_MONOTONIC is one clock for every
        process of the machine, so the daemon's frame times compare with ours."""
        with self._lock:
            return next((float(e["frame_time_mono"]) for _, e in self.estimates
                         if e.get("frame_time_mono") is not None
                         and float(e["frame_time_mono"]) > t), None)

    def close(self) -> None:
        self._sub.undeclare()
        self._session.close()


def wait(condition: Callable[[], bool], timeout: float, what: str) -> float:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out after {timeout} s waiting for {what}"
        time.sleep(0.02)
    return time.monotonic()


def first_distance_after(autopilot: FakeAutopilot, t: float) -> float | None:
    return next((r.t for r in autopilot.received("DISTANCE_SENSOR") if r.t > t), None)


def test_faults_in_sequence_nothing_false_fast_recovery_prompt_exit(tmp_path: Path) -> None:
    exe = ffmpeg_exe()
    frames = [f.image for f in render_frames(
        f"synthetic:?width=640&height=360&fps={FPS}&trajectory=static&range={RANGE_M}&tilt=15"
        "&seed=8", 40)]
    calibration = tmp_path / "camera.yaml"
    save_camera(builtin_camera(640, 360), calibration)
    config = tmp_path / "netpose.toml"
    config.write_text(DEMO.read_text())
    rtsp_port, ap_port = free_port(), free_port()
    router_endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = start_router(router_endpoint)
    topside = Topside(router_endpoint)
    autopilot = FakeAutopilot(TcpServerTransport(ap_port)).start()
    notify = NotifyRecorder(tmp_path / "notify.sock")
    streamers: list[Streamer] = []
    server: RtspServer | None = None
    overrides = [
        f"camera.url=rtsp://127.0.0.1:{rtsp_port}/video_stream__dev_video2",
        f"camera.calibration={calibration}", "mesh.bar_length_m=0.025",
        f"camera.stale_after_s={STALE_AFTER_S}",
        f"mavlink.url=tcp:127.0.0.1:{ap_port}", "mavlink.rate_hz=10",
        f"mavlink.max_age_s={MAX_AGE_S}", "mavlink.allow_simulated=false",
        f"filter.report_coasting_s={REPORT_COASTING_S}",
        "telemetry.vehicle=faults", "telemetry.mode=client",
        f"telemetry.connect=['{router_endpoint}']", "telemetry.listen=[]",
        "service.status_interval_s=0.5",
    ]
    cmd = [sys.executable, "-m", "service.cli", "run", "--config", str(config)]
    for o in overrides:
        cmd += ["--set", o]
    env = dict(os.environ, NOTIFY_SOCKET=str(notify.path), PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    stderr = ""
    marks: dict[str, float] = {}
    try:
        # 1. No camera at start: the service runs, says so, sends no distance.
        wait(lambda: any("READY=1" in m for _, m in notify.snapshot()), 30, "READY=1")
        time.sleep(2.0)
        assert proc.poll() is None, "the daemon exited for want of a camera"
        assert autopilot.received("DISTANCE_SENSOR") == []
        assert any(m.startswith("STATUS=no frames") for _, m in notify.snapshot())
        sdp, rtp_in = rtp_to_rtsp(exe, tmp_path, streamers, frames=frames, fps=FPS, gop=GOP)
        server = RtspServer(sdp, rtp_in, port=rtsp_port)
        marks["camera plugged in"] = time.monotonic()
        wait(lambda: topside.first_frame_after(marks["camera plugged in"]) is not None, 20,
             "frames from the new camera")
        wait(lambda: first_distance_after(autopilot, marks["camera plugged in"]) is not None, 10,
             "a distance once the camera streams")

        # 2. The camera manager restarts: the stream stalls, then returns on the same port.
        time.sleep(1.5)
        server.close()
        marks["stream stalled"] = time.monotonic()
        time.sleep(3.0)
        server = RtspServer(sdp, rtp_in, port=rtsp_port)
        marks["stream back"] = time.monotonic()
        wait(lambda: topside.first_frame_after(marks["stream back"]) is not None, 20,
             "frames after the stream returned")

        # 3. The autopilot link goes down and comes back on the same port.
        time.sleep(1.5)
        autopilot.close()
        before = autopilot
        time.sleep(3.0)
        autopilot = FakeAutopilot(TcpServerTransport(ap_port)).start()
        marks["autopilot back"] = time.monotonic()
        wait(lambda: first_distance_after(autopilot, marks["autopilot back"]) is not None, 20,
             "distances to the returning autopilot")

        # 4. The Zenoh router goes down and comes back on the same endpoint.
        time.sleep(1.0)
        router.kill()
        router.communicate(timeout=10)
        time.sleep(3.0)
        router = start_router(router_endpoint)
        marks["router back"] = time.monotonic()
        wait(lambda: topside.first_after(marks["router back"]) is not None, 20,
             "telemetry through the returning router")

        # 5. SIGHUP with a broken file: rejected, still running; then a good one: applied.
        config.write_text("[filter\n")
        proc.send_signal(signal.SIGHUP)
        time.sleep(1.0)
        assert proc.poll() is None
        config.write_text(DEMO.read_text() + "\n[filter]\ngate_sigma = 5.0\n")
        proc.send_signal(signal.SIGHUP)
        time.sleep(1.0)
        marks["after reloads"] = time.monotonic()
        wait(lambda: first_distance_after(autopilot, marks["after reloads"]) is not None, 10,
             "distances after the reloads")

        # 6. SIGTERM while the source re-opens against a camera that accepts and never answers.
        server.close()
        server = None
        black_hole = socket.socket()
        black_hole.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        black_hole.bind(("127.0.0.1", rtsp_port))
        black_hole.listen(8)
        time.sleep(STALE_AFTER_S + 2.0)  # stalled, down, and re-opening into the black hole
        marks["SIGTERM"] = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        _, stderr = proc.communicate(timeout=10)
        marks["exited"] = time.monotonic()
        black_hole.close()
    finally:
        if proc.poll() is None:
            proc.kill()
            _, stderr = proc.communicate()
        if server is not None:
            server.close()
        for streamer in streamers:
            streamer.stop()
        autopilot.close()
        topside.close()
        router.kill()
        router.communicate(timeout=10)
        notify.close()

    distances = [(r.t, r.msg.current_distance / 100.0)
                 for r in [*before.received("DISTANCE_SENSOR"),
                           *autopilot.received("DISTANCE_SENSOR")]]
    recoveries = {
        "camera plugged in -> first frame":
            topside.first_frame_after(marks["camera plugged in"])  # type: ignore[operator]
            - marks["camera plugged in"],
        "stream back -> first frame": topside.first_frame_after(marks["stream back"])  # type: ignore[operator]
        - marks["stream back"],
        "autopilot back -> first DISTANCE_SENSOR":
            first_distance_after(autopilot, marks["autopilot back"])  # type: ignore[operator]
            - marks["autopilot back"],
        "router back -> first estimate topside": topside.first_after(marks["router back"])  # type: ignore[operator]
        - marks["router back"],
        "SIGTERM -> exit": marks["exited"] - marks["SIGTERM"],
    }
    print("\n" + "\n".join(f"{k}: {v:.2f} s" for k, v in recoveries.items()))
    assert proc.returncode == 0, stderr[-3000:]
    # Nothing false: every distance the autopilot got is the rendered net's, within tolerance.
    values = np.array([d for _, d in distances])
    assert len(values) > 50
    assert np.all(np.abs(values / RANGE_M - 1.0) < RANGE_TOL), values.min(initial=0)
    # None before the camera, none long after a stall began, none after SIGTERM.
    silent_limit = REPORT_COASTING_S + MAX_AGE_S + 0.2
    assert not [t for t, _ in distances if t < marks["camera plugged in"]]
    stall_end = marks["stream back"]
    late = [t - marks["stream stalled"] for t, _ in distances
            if marks["stream stalled"] + silent_limit < t < stall_end]
    assert not late, f"distances {late} s into the stall"
    assert not [t for t, _ in distances if t > marks["SIGTERM"] + 0.1]
    for name, seconds in recoveries.items():
        limit = 1.0 if name == "SIGTERM -> exit" else RECOVERY_S
        assert seconds <= limit, f"{name}: {seconds:.2f} s (limit {limit} s)"
    assert "configuration reload rejected" in stderr
    assert "configuration reloaded" in stderr and "changed: filter" in stderr
    assert "Traceback" not in stderr
