"""End-to-end: the real daemon process (`netpose run`) on the synthetic source, with a recording
MAVLink autopilot on loopback UDP (real pymavlink decoding), a real Zenoh subscriber on
loopback, and a datagram socket standing in for systemd's NOTIFY_SOCKET.

One daemon run (module fixture) serves the trajectory, dropout, watchdog and SIGTERM checks, so
the module stays well under a minute on two cores.
"""

from __future__ import annotations

import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.telemetry_subscriber import TelemetrySubscriber
from service.core.messages import schema_problems
from tests.fake_autopilot import FakeAutopilot, UdpServerTransport

REPO = Path(__file__).resolve().parents[1]
DEMO = REPO / "config" / "demo.toml"

# The scripted scene (synthetic source options, docs/sources.md): the net approaches and recedes
# between NEAR and FAR metres (sinusoid of PERIOD seconds); it is out of view between GAP_START
# and GAP_END seconds of source time.
FPS = 10.0
NEAR, FAR, PERIOD = 0.8, 1.8, 12.0
GAP_START, GAP_END = 9.0, 12.0
RUN_S = 16.0
REPORT_COASTING_S = 0.3
# mavlink.max_age_s: the link sends nothing older. Rendering a frame and estimating take 0.1-0.3 s
# on a loaded two-core CI machine, so the default 0.3 s would make the link flap.
MAX_AGE_S = 0.5
LINK_HZ = 20.0
ESTIMATOR_TOL = 0.01  # relative range error allowed on these ideal synthetic frames
# systemd would kill the daemon after this long without a ping: tighter than the unit's 10 s
# (systemd/netpose.service), looser than the 2 s this was: a bookworm CI run on a two-core
# machine shared with two benchmarks saw one 3.0 s pass of the loop right after start-up.
WATCHDOG_USEC = 4_000_000


def synthetic_url() -> str:
    return (f"synthetic:?width=640&height=360&fps={FPS:g}&realtime=1&trajectory=approach"
            f"&near={NEAR:g}&far={FAR:g}"
            f"&period={PERIOD:g}&gap={GAP_START:g}-{GAP_END:g}&seed=3")


class NotifyRecorder:
    """The service manager's end of NOTIFY_SOCKET: records (monotonic time, message)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.bind(str(path))
        self._sock.settimeout(0.1)
        self.messages: list[tuple[float, str]] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self._sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            with self._lock:
                self.messages.append((time.monotonic(), data.decode()))

    def snapshot(self) -> list[tuple[float, str]]:
        with self._lock:
            return list(self.messages)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._sock.close()


@dataclass
class DaemonRun:
    returncode: int
    stderr: str
    stop_latency_s: float
    started: float
    distances: list[tuple[float, float]]  # (monotonic arrival, metres) of DISTANCE_SENSOR
    estimates: list[dict[str, Any]]
    statuses: list[dict[str, Any]]
    notify: list[tuple[float, str]]
    extra: dict[str, Any] = field(default_factory=dict)


def wait_ready(proc: subprocess.Popen[str], notify: NotifyRecorder,
               timeout_s: float = 30.0) -> None:
    """Until the daemon says READY=1 (imports and start-up done); it must not exit first."""
    deadline = time.monotonic() + timeout_s
    while not any("READY=1" in m for _, m in notify.snapshot()):
        assert proc.poll() is None, proc.communicate()[1]
        assert time.monotonic() < deadline, f"no READY=1 within {timeout_s:g} s"
        time.sleep(0.05)


def daemon_command(config: Path, overrides: list[str]) -> list[str]:
    cmd = [sys.executable, "-m", "service.cli", "run", "--config", str(config)]
    for o in overrides:
        cmd += ["--set", o]
    return cmd


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[DaemonRun]:
    tmp = tmp_path_factory.mktemp("daemon")
    notify = NotifyRecorder(tmp / "notify.sock")
    tel = TelemetrySubscriber(vehicle="e2e")
    autopilot = FakeAutopilot(UdpServerTransport()).start()
    overrides = [
        f"camera.url={synthetic_url()}",
        f"mavlink.url={autopilot.url}",
        f"mavlink.rate_hz={LINK_HZ:g}",
        f"mavlink.max_age_s={MAX_AGE_S:g}",
        "telemetry.vehicle=e2e",
        f"filter.report_coasting_s={REPORT_COASTING_S}",
        "service.status_interval_s=0.5",
        *tel.daemon_overrides(),
    ]
    env = dict(os.environ, NOTIFY_SOCKET=str(notify.path), WATCHDOG_USEC=str(WATCHDOG_USEC),
               PYTHONUNBUFFERED="1")
    env.pop("WATCHDOG_PID", None)
    started = time.monotonic()
    proc = subprocess.Popen(daemon_command(DEMO, overrides), cwd=REPO, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        # Wait for READY (imports and start-up), then let the scene play.
        wait_ready(proc, notify)
        time.sleep(RUN_S)
        assert proc.poll() is None, "daemon died: " + proc.communicate()[1]
        t_term = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        _, stderr = proc.communicate(timeout=10.0)
        stop_latency = time.monotonic() - t_term
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        autopilot.close()
        deadline = time.monotonic() + 3.0  # the token's withdrawal follows the exit closely
        while not any(kind == "DELETE" for kind, _, _ in tel.tokens()) and (
                time.monotonic() < deadline):
            time.sleep(0.05)
        estimates, statuses = tel.snapshot()
        tokens = tel.tokens()
        tel.close()
        notify.close()
    distances = [(r.t, r.msg.current_distance / 100.0)
                 for r in autopilot.received("DISTANCE_SENSOR")]
    yield DaemonRun(proc.returncode, stderr, stop_latency, started, distances, estimates,
                    statuses, notify.snapshot(), extra={"tokens": tokens})


def _truth(e: dict[str, Any]) -> dict[str, Any] | None:
    truth = e.get("truth")
    return truth if isinstance(truth, dict) else None


def test_sigterm_exits_cleanly_within_a_second(run: DaemonRun) -> None:
    assert run.returncode == 0, run.stderr
    assert run.stop_latency_s < 1.0 + 0.5  # 1 s budget; 0.5 s for interpreter teardown
    assert "Traceback" not in run.stderr
    assert "SIGTERM received: stopping" in run.stderr
    assert any(m == "STOPPING=1" for _, m in run.notify)


def test_ready_then_regular_watchdog(run: DaemonRun) -> None:
    kinds = [m.split("\n")[0] for _, m in run.notify]
    assert kinds[0] == "READY=1"
    interval = WATCHDOG_USEC / 1e6
    ready_t = run.notify[0][0]
    pings = [t for t, m in run.notify if m == "WATCHDOG=1"]
    # Pinged at half the interval (sd_watchdog_enabled(3)), and never as late as the interval
    # itself, which is when systemd would kill the service.
    assert len(pings) >= 0.8 * RUN_S / (interval / 2)
    stalls = [line for line in run.stderr.splitlines() if "stalled" in line]
    assert float(np.max(np.diff([ready_t, *pings]))) < interval, stalls
    assert float(np.min(np.diff(pings))) >= interval / 2 - 0.01  # rate-limited, not per frame
    statuses = [m for _, m in run.notify if m.startswith("STATUS=")]
    assert len(statuses) >= RUN_S / 0.5 * 0.5
    assert any(" m |" in s for s in statuses), statuses[-3:]


def test_autopilot_distance_follows_ground_truth(run: DaemonRun) -> None:
    """The filtered distance the autopilot receives, compared with the ground truth of the
    frame it came from, outside the gap and after acquisition."""
    est = [e for e in run.estimates if _truth(e) and _truth(e).get("net_present")]  # type: ignore[union-attr]
    assert len(est) > FPS * 5
    detected = [e for e in est if e["detected"]]
    assert len(detected) / len(est) > 0.8
    # Estimates: raw and filtered against truth (the range along the optical axis).
    rel_raw, rel_filt = [], []
    for e in detected:
        truth = _truth(e)
        assert truth is not None
        rel_raw.append(e["range_m"] / truth["range_m"] - 1.0)
        f = e["filtered"]
        if f["valid"]:
            rel_filt.append(f["range_m"] / truth["range_m"] - 1.0)
    print(f"\nraw range error: median |e| {np.median(np.abs(rel_raw)):.2%}, filtered: median "
          f"|e| {np.median(np.abs(rel_filt)):.2%}, p95 {np.percentile(np.abs(rel_filt), 95):.2%}"
          f" ({len(rel_filt)} frames)")
    # The estimator's own target on ideal synthetic frames is well below 1 % (the paper's 4 %
    # is for real water); the filter must not add more than its lag on this motion.
    assert np.median(np.abs(rel_raw)) < ESTIMATOR_TOL
    assert np.median(np.abs(rel_filt)) < ESTIMATOR_TOL
    assert np.percentile(np.abs(rel_filt), 95) < 3 * ESTIMATOR_TOL
    # MAVLink: each DISTANCE_SENSOR against the truth of the newest frame captured before it.
    table = sorted((e["frame_time_mono"], _truth(e)["range_m"]) for e in est)  # type: ignore[index]
    t_frames = np.array([t for t, _ in table])
    errors = []
    for t_rx, d in run.distances:
        i = int(np.searchsorted(t_frames, t_rx)) - 1
        if i >= 0 and t_rx - t_frames[i] < 0.5:
            errors.append(d / table[i][1] - 1.0)
    assert len(errors) > 20
    print(f"MAVLink distance error: median |e| {np.median(np.abs(errors)):.2%}, p95 "
          f"{np.percentile(np.abs(errors), 95):.2%} ({len(errors)} messages)")
    # A message carries the reading of a frame up to one frame period plus the capture-to-link
    # latency older than the newest frame: on top of the estimator's tolerance, the net may
    # have moved by (max speed) x (that age). Typical age ~0.15 s; the link's max_age bounds it.
    v_max = 0.5 * (FAR - NEAR) * 2 * math.pi / PERIOD
    typical = ESTIMATOR_TOL + v_max * (1.0 / FPS + 0.15) / NEAR
    worst = ESTIMATOR_TOL + v_max * (1.0 / FPS + MAX_AGE_S) / NEAR
    assert np.median(np.abs(errors)) < typical
    assert np.max(np.abs(errors)) < worst


def test_distance_stops_when_the_net_disappears_and_resumes(run: DaemonRun) -> None:
    frames = sorted((e["frame_time_mono"], bool(_truth(e)["net_present"]))  # type: ignore[index]
                    for e in run.estimates if _truth(e))
    first_absent = next(i for i, (_, present) in enumerate(frames) if not present)
    last_present_t = frames[first_absent - 1][0]
    back = next(t for t, present in frames[first_absent:] if present)
    before = [t for t, _ in run.distances if t <= last_present_t]
    during = [t for t, _ in run.distances if last_present_t < t < back]
    after = [t for t, _ in run.distances if t >= back]
    assert before, "no distance before the gap"
    # After the last frame showing the net, the filter may report its prediction for
    # report_coasting_s, stamped with the capture time; the link sends nothing older than
    # max_age_s; one link period and scheduling slack on top.
    limit = REPORT_COASTING_S + MAX_AGE_S + 1.0 / LINK_HZ + 0.1
    late = [t - last_present_t for t in during if t - last_present_t > limit]
    last_in_gap = max(during, default=last_present_t) - last_present_t
    print(f"last distance {last_in_gap:.2f} s after the last frame with the net (limit "
          f"{limit:.2f} s)")
    assert not late, f"distance still sent {max(late):.2f} s into the gap (limit {limit:.2f})"
    assert back - last_present_t > 2.5  # the gap really was seen (3 s scripted)
    assert after, "distance did not resume after the net came back"
    # Back after acquire_count (3) detections, each one frame period apart, plus latency.
    print(f"resumed {min(after) - back:.2f} s after the net came back")
    assert min(after) - back < 3 / FPS + MAX_AGE_S + 0.5
    assert any("net lost" in line for line in run.stderr.splitlines())
    assert sum("net acquired" in line for line in run.stderr.splitlines()) >= 2


def test_logs_are_state_changes_not_frames(run: DaemonRun) -> None:
    lines = [ln for ln in run.stderr.splitlines() if ln.strip()]
    frames = len(run.estimates)
    assert frames > 50
    # The daemon's own lines: start, source up, link, telemetry, net acquired/lost (twice),
    # stop, summaries; the drivers add theirs on their state changes.
    own = [ln for ln in lines if "netpose.daemon" in ln]
    assert len(own) < 20, "\n".join(own)
    assert len(lines) < frames / 3, "\n".join(lines)


def test_the_topside_can_tell_a_clean_stop_from_a_lost_vehicle(run: DaemonRun) -> None:
    """The last status says "stopping", and the liveliness token `netpose/e2e/alive` that
    was there while the daemon ran is withdrawn: a crash or a cut tether withdraws the token
    without that status."""
    assert run.statuses[-1]["state"] == "stopping"
    assert [s["state"] for s in run.statuses].count("stopping") == 1
    assert [(kind, key) for kind, key, _ in run.extra["tokens"]] == [
        ("PUT", "netpose/e2e/alive"), ("DELETE", "netpose/e2e/alive")]


def test_telemetry_estimates_and_status_match_the_schema(run: DaemonRun) -> None:
    assert run.estimates and run.statuses
    assert not schema_problems(run.estimates[-1])
    assert not schema_problems(run.statuses[-1])
    status = run.statuses[-1]
    assert status["config_digest"].startswith("sha256:")
    assert status["frame_source"]["state"] == "streaming"
    assert status["autopilot"]["state"] == "connected"
    filtered = [e["filtered"] for e in run.estimates if e["filtered"]["valid"]]
    assert filtered and all(f["state"] in ("tracking", "coasting") for f in filtered)


def _run_briefly(args: list[str], timeout: float = 60.0,
                 env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(args, cwd=REPO, capture_output=True, text=True, timeout=timeout,
                          env=env)


def test_bad_configuration_exits_78_naming_the_key(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text(DEMO.read_text().replace("[mavlink]", "[mavlink]\nrate_hzz = 10.0", 1))
    sock_path = tmp_path / "n.sock"
    notify = NotifyRecorder(sock_path)
    try:
        env = dict(os.environ, NOTIFY_SOCKET=str(sock_path))
        proc = _run_briefly(daemon_command(bad, []), env=env)
    finally:
        notify.close()
    assert proc.returncode == 78
    assert proc.stderr.strip().splitlines()[-1].startswith(
        "netpose: configuration error: mavlink.rate_hzz: unknown key")
    assert not any("READY=1" in m for _, m in notify.snapshot())


def test_a_watchdog_abort_writes_where_every_thread_was_to_the_log(tmp_path: Path) -> None:
    """systemd's watchdog kills a hung daemon with SIGABRT. It left no Python traceback in the
    journal (and, without LimitCORE=0, a 355 MB core on the SD card): nothing said where it
    hung. The daemon's threads' stacks now go to stderr."""
    sock_path = tmp_path / "n.sock"
    notify = NotifyRecorder(sock_path)
    env = dict(os.environ, NOTIFY_SOCKET=str(sock_path), PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(daemon_command(DEMO, ["telemetry.enabled=false"]), cwd=REPO,
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    try:
        wait_ready(proc, notify)
        proc.send_signal(signal.SIGABRT)
        _, stderr = proc.communicate(timeout=10.0)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        notify.close()
    assert proc.returncode == -signal.SIGABRT
    assert "Fatal Python error: Aborted" in stderr, stderr[-2000:]
    # The frame loop's thread (the main one) and the link's, each with its stack.
    assert "Current thread" in stderr and stderr.count("hread 0x") >= 2, stderr[-2000:]
    assert "service/daemon/" in stderr, stderr[-2000:]


def test_the_unit_writes_no_core_dump() -> None:
    unit = (REPO / "systemd" / "netpose.service").read_text()
    assert "\nLimitCORE=0\n" in unit


def test_check_validates_without_running() -> None:
    ok = _run_briefly(daemon_command(DEMO, []) + ["--check"])
    assert ok.returncode == 0, ok.stderr
    assert ok.stdout.startswith("configuration OK") and "sha256:" in ok.stdout
    typo = _run_briefly(daemon_command(DEMO, ["camera.url=synthetic:?fsp=30"]) + ["--check"])
    assert typo.returncode == 78
    assert "camera.url" in typo.stderr and "fsp" in typo.stderr


def test_missing_calibration_file_exits_78(tmp_path: Path) -> None:
    proc = _run_briefly(daemon_command(DEMO, ["camera.url=rtsp://127.0.0.1:1/none",
                                              "camera.calibration=absent.yaml"]))
    assert proc.returncode == 78
    assert "camera.calibration: file not found" in proc.stderr


def test_sighup_reloads_filter_settings(tmp_path: Path) -> None:
    cfg = tmp_path / "netpose.toml"
    cfg.write_text(DEMO.read_text())
    sock_path = tmp_path / "n.sock"
    notify = NotifyRecorder(sock_path)
    overrides = ["camera.url=synthetic:?width=320&height=180&fps=5&realtime=1",
                 "mavlink.url=udpout:127.0.0.1:9", "telemetry.enabled=false"]
    env = dict(os.environ, NOTIFY_SOCKET=str(sock_path))
    proc = subprocess.Popen(daemon_command(cfg, overrides), cwd=REPO, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        wait_ready(proc, notify)
        cfg.write_text(DEMO.read_text() + "\n[filter]\ngate_sigma = 6.0\n")
        proc.send_signal(signal.SIGHUP)
        deadline = time.monotonic() + 10.0
        while not any(m.startswith("RELOADING=1") for _, m in notify.snapshot()):
            assert time.monotonic() < deadline, "no RELOADING=1 after SIGHUP"
            time.sleep(0.05)
        # A broken file is rejected and the daemon keeps running on the previous one.
        time.sleep(0.5)
        cfg.write_text("[filter\n")
        proc.send_signal(signal.SIGHUP)
        time.sleep(1.0)
        assert proc.poll() is None
        proc.send_signal(signal.SIGINT)
        _, stderr = proc.communicate(timeout=10.0)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        notify.close()
    assert proc.returncode == 0, stderr
    assert "configuration reloaded" in stderr and "changed: filter" in stderr
    assert "configuration reload rejected, keeping the running one" in stderr


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze absent")
def test_unit_file_passes_systemd_analyze_verify(tmp_path: Path) -> None:
    unit = (REPO / "systemd" / "netpose.service").read_text()
    netpose = Path(sys.executable).with_name("netpose")
    assert "/opt/netpose/venv/bin/netpose" in unit
    # verify needs the ExecStart binary to exist: point it at this venv's entry point.
    (tmp_path / "netpose.service").write_text(
        unit.replace("/opt/netpose/venv/bin/netpose", str(netpose)))
    proc = _run_briefly(["systemd-analyze", "verify", str(tmp_path / "netpose.service")])
    assert proc.returncode == 0, proc.stderr
    assert "netpose.service" not in proc.stderr, proc.stderr  # no warnings about our unit
    for line in ("Type=notify", "WatchdogSec=", "Restart=on-failure",
                 "RestartPreventExitStatus=78", "User=netpose", "DevicePolicy=closed"):
        assert line in unit
    settings = [ln for ln in unit.splitlines() if ln and not ln.startswith("#")]
    assert not [ln for ln in settings if ln.startswith(("PrivateDevices", "PrivateNetwork"))]


def test_install_script_is_valid_shell() -> None:
    proc = _run_briefly(["sh", "-n", str(REPO / "systemd" / "install.sh")])
    assert proc.returncode == 0, proc.stderr
