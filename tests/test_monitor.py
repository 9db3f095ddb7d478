"""`netpose monitor`: the view's bookkeeping, and the command run as a subprocess against a real
Zenoh publisher on loopback (explicit endpoints, scouting off, ports chosen at runtime)."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.net import free_port
from drivers.telemetry import TelemetrySettings, ZenohPublisher
from service.core.messages import (
    SCHEMA_VERSION,
    AutopilotHealth,
    CpuHealth,
    EstimateLatency,
    EstimateMessage,
    EstimatorHealth,
    FilteredView,
    FilterHealth,
    FrameSourceHealth,
    PreviewMeta,
    StateMessage,
    StatusMessage,
    schema_problems,
    to_json,
)
from service.core.redact import redact_config
from service.tools.monitor_view import MonitorState

pytestmark = pytest.mark.timeout(90)

VEHICLE = "rov5"


def free_endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


def estimate_message(seq: int, distance: float = 1.5, detected: bool = True) -> EstimateMessage:
    now = time.monotonic()
    return EstimateMessage(
        vehicle=VEHICLE, time_unix=time.time(), time_mono=now, seq=seq,
        frame_time_mono=now - 0.03, detected=detected, confidence=0.8 if detected else 0.1,
        distance_m=distance if detected else None, sigma_distance_m=0.02,
        range_m=distance * 1.02, tilt_deg=11.0, reason="" if detected else "x",
        filtered=FilteredView(valid=detected, autopilot="good" if detected else "none",
                              state="tracking" if detected else "lost", measurement="accepted",
                              distance_m=distance, sigma_distance_m=0.01,
                              autopilot_distance_m=distance * 1.02 if detected else None,
                              autopilot_along="optical_axis"),
        latency_ms=EstimateLatency(stages={"spectrum": 20.0}, estimator_total=20.0),
    )


def estimate_json(seq: int, distance: float = 1.5, detected: bool = True) -> dict[str, Any]:
    return to_json(estimate_message(seq, distance, detected))


def status_message() -> StatusMessage:
    return StatusMessage(
        vehicle=VEHICLE, time_unix=time.time(), time_mono=time.monotonic(), version="0.1.0",
        state="running", uptime_s=3.0, config_digest="sha256:00",
        frame_source=FrameSourceHealth(state="streaming", fps=10.0, dropped=0),
        autopilot=AutopilotHealth(state="connected"), estimator=EstimatorHealth(fps=10.0),
        cpu=CpuHealth(cores=2), filter=FilterHealth(state="tracking"),
    )


def status_json() -> dict[str, Any]:
    return to_json(status_message())


def encode(payload: dict[str, Any]) -> bytes:
    return json.dumps(payload).encode()


# --- the view ------------------------------------------------------------------------------


def test_rates_link_state_and_values_from_received_messages() -> None:
    state = MonitorState(stale_after_s=2.0, window_s=5.0)
    assert state.link_state(0.0) == "waiting"
    assert "waiting" in state.summary(0.0)
    t = 100.0
    for seq in range(60):  # 6 s of estimates at 10 Hz and status at 1 Hz
        t = 100.0 + seq * 0.1
        state.ingest(f"netpose/{VEHICLE}/estimate", encode(estimate_json(seq, 1.0 + seq / 100)), t)
        if seq % 10 == 0:
            state.ingest(f"netpose/{VEHICLE}/status", encode(status_json()), t)
    assert state.rate_hz(VEHICLE, "estimate", t) == pytest.approx(10.0, rel=1e-6)
    assert state.rate_hz(VEHICLE, "status", t) == pytest.approx(1.0, rel=1e-6)
    assert state.link_state(t + 1.9) == "live"
    assert state.link_state(t + 2.1) == "stale"
    assert state.link_state(t, "other") == "waiting"
    view = state.vehicles[VEHICLE]
    assert view.estimate is not None and view.estimate["seq"] == 59
    assert view.problems == set()
    summary = state.summary(t)
    assert f"{VEHICLE} live" in summary and "perp 1.59+/-0.020 m" in summary and "10.0Hz" in summary
    screen = "\n".join(state.render(t))
    assert "estimate" in screen and "cam streaming" in screen and "filtered" in screen
    # `perp` is perpendicular; what the autopilot gets (here along the axis) is said first.
    assert "autopilot 1.62 m along the camera axis" in screen
    assert (screen.index("  autopilot ") < screen.index("  estimate  perp")
            < screen.index("  filtered  "))
    assert summary.index("ap: 1.62 m") < summary.index("perp 1.59")
    assert "axis 1.62 m" in screen
    assert "searching" not in screen
    # Open water: the daemon says it searches at a paced rate, and the monitor shows it.
    searching = dataclasses.replace(
        status_message(), estimator=EstimatorHealth(fps=5.0, searching_hz=5.0))
    state.ingest(f"netpose/{VEHICLE}/status", encode(to_json(searching)), t)
    assert "searching 5/s (no net)" in "\n".join(state.render(t))
    # Net inspection's coverage beside its holes.
    from service.core.messages import InspectionHealth

    inspecting = dataclasses.replace(status_message(), inspection=InspectionHealth(
        inspected_frames=120, judged_cells=54000, holes=1))
    state.ingest(f"netpose/{VEHICLE}/status", encode(to_json(inspecting)), t)
    assert "inspected 120 frames (54000 cells), 1 holes" in "\n".join(state.render(t))
    # After the window the stream has no rate any more.
    assert state.rate_hz(VEHICLE, "estimate", t + 6.0) == 0.0


def test_estimates_that_stopped_are_not_shown_as_a_live_distance() -> None:
    """The camera stopped; the 1 Hz status kept the link "live", and the monitor went on
    showing the last estimate as "filtered valid True" and "autopilot 0.89 m", and its rate
    at 10 Hz for seconds, while the daemon said the filter was lost and sent nothing."""
    state = MonitorState(stale_after_s=2.0, window_s=5.0)
    t = 100.0
    for seq in range(30):  # 3 s of estimates at 10 Hz, then only status
        t = 100.0 + seq * 0.1
        state.ingest(f"netpose/{VEHICLE}/estimate", encode(estimate_json(seq)), t)
    lost = dataclasses.replace(status_message(), filter=FilterHealth(state="lost"))
    for k in range(1, 11):
        state.ingest(f"netpose/{VEHICLE}/status", encode(to_json(lost)), t + k)
    now = t + 10.0
    assert state.link_state(now) == "live"  # the vehicle still talks
    screen = "\n".join(state.render(now))
    assert "valid True" not in screen and "autopilot 1.62 m" not in screen, screen
    assert "no estimate for 10.0 s" in screen
    assert state.rate_hz(VEHICLE, "estimate", t + 1.0) < 10.0 * 0.7  # falls as soon as silent
    summary = state.summary(now)
    assert "no estimate for 10.0 s" in summary and "perp 1.50" not in summary


def test_what_the_autopilot_gets_is_said_with_the_link_and_the_filters_state() -> None:
    """With the link to the autopilot lost the monitor printed "autopilot 1.62 m along the
    camera axis" beside "ap lost", a coasting prediction read as "valid True" like a tracked
    distance, and the one-line summary had only the raw estimate, even while nothing was
    sent. The screen and the summary say the filter's state and what reaches the autopilot."""
    state = MonitorState(stale_after_s=2.0, window_s=5.0)
    coasting = estimate_json(1)
    coasting["filtered"]["state"] = "coasting"
    state.ingest(f"netpose/{VEHICLE}/estimate", encode(coasting), 100.0)
    sending = dataclasses.replace(status_message(), autopilot=AutopilotHealth(
        state="connected", sending_distance=True))
    state.ingest(f"netpose/{VEHICLE}/status", encode(to_json(sending)), 100.0)
    screen = "\n".join(state.render(100.0))
    assert "filtered  coasting  valid True" in screen
    assert "autopilot 1.53 m along the camera axis\n" in screen + "\n"
    assert "[coasting] ap: 1.53 m along the camera axis" in state.summary(100.0)
    for link, said in (("lost", "NOT reaching it: autopilot link lost"),
                       ("waiting", "NOT reaching one: no autopilot heard")):
        status = dataclasses.replace(status_message(), autopilot=AutopilotHealth(
            state=link, sending_distance=True))
        state.ingest(f"netpose/{VEHICLE}/status", encode(to_json(status)), 100.1)
        assert f"autopilot 1.53 m along the camera axis, {said}" in "\n".join(
            state.render(100.1))
        assert said in state.summary(100.1)
    stale = dataclasses.replace(status_message(), autopilot=AutopilotHealth(state="connected"))
    state.ingest(f"netpose/{VEHICLE}/status", encode(to_json(stale)), 100.2)
    assert "camera axis, NOT being sent now" in "\n".join(state.render(100.2))
    # The net-hold applet's input is said with it, and why it is not sent: "TRACKING, 1.00 m"
    # said nothing of why net hold did not act (pilot review).
    held = dataclasses.replace(status_message(), autopilot=AutopilotHealth(
        state="connected", sending_distance=True,
        net_plane="held: the autopilot's clock is not confirmed"))
    state.ingest(f"netpose/{VEHICLE}/status", encode(to_json(held)), 100.3)
    assert ("autopilot 1.53 m along the camera axis; net hold input: held: the autopilot's "
            "clock is not confirmed") in "\n".join(state.render(100.3))


def test_uncertainty_and_closing_speed_read_as_what_they_are() -> None:
    """A sigma of 1.7 mm read "+/-0.00 m", and the filter's closing speed (positive toward the
    net) stood beside the distance as "rate", which reads as d's own rate: the wrong sign."""
    state = MonitorState()
    message = to_json(estimate_message(1, 1.5))
    message["sigma_distance_m"] = 0.0017
    message["filtered"]["sigma_distance_m"] = 0.0017
    message["filtered"]["closing_speed_mps"] = 0.16
    state.ingest(f"netpose/{VEHICLE}/estimate", encode(message), 100.0)
    screen = "\n".join(state.render(100.0))
    assert "+/-0.00 m" not in screen and "+/- 0.00 m" not in screen
    assert "0.002 m" in screen
    assert "closing 0.16 m/s" in screen and "rate 0.16" not in screen
    # With the scale's error (service/core/scale.py) the monitor shows the total.
    message["sigma_distance_total_m"] = 0.0345
    message["filtered"]["sigma_distance_total_m"] = 0.0336
    state.ingest(f"netpose/{VEHICLE}/estimate", encode(message), 100.1)
    screen = "\n".join(state.render(100.1))
    assert "+/-0.035 m" in screen and "+/- 0.034 m" in screen and "0.002 m" not in screen


def test_a_net_seen_without_a_distance_is_shown_as_such() -> None:
    """A frame whose plane was too uncertain for a distance: the pilot reads that a net is in
    view and roughly how far, not "no net" (and not a distance)."""
    import dataclasses

    state = MonitorState(stale_after_s=2.0, window_s=5.0)
    seen = dataclasses.replace(
        estimate_message(1, detected=False), net_seen=True, approx_range_m=0.83,
        approx_sigma_range_m=0.031,
        reason="plane too uncertain (range +- 4%, normal +- 2 deg): the ROIs that see ...")
    payload = to_json(seen)
    assert schema_problems(payload) == []
    state.ingest(f"netpose/{VEHICLE}/estimate", encode(payload), 100.0)
    text = "\n".join(state.render(100.0))
    assert "net seen, ~0.83+/-0.03 m, no distance (plane too uncertain" in text
    assert "no net" not in text


def test_a_clean_stop_and_a_lost_vehicle_are_told_apart() -> None:
    """After a clean stop the monitor said `stale ... running` for ever, as after a crash.
    The daemon's liveliness token going tells the monitor it is gone; its last status says
    whether it stopped (`stopping`) or was lost."""
    for last_state, shown in (("stopping", "stopped"), ("running", "gone")):
        state = MonitorState()
        alive = f"netpose/{VEHICLE}/alive"
        state.ingest(alive, b"PUT", 0.0)
        state.ingest(f"netpose/{VEHICLE}/status",
                     encode(to_json(dataclasses.replace(status_message(), state=last_state))), 0.5)
        assert state.link_state(0.6, VEHICLE) == "live"
        state.ingest(alive, b"DELETE", 1.0)
        assert state.link_state(1.1, VEHICLE) == shown
        assert f"{VEHICLE} {shown}" in state.summary(1.1)


def test_bad_and_foreign_payloads_are_flagged_not_fatal() -> None:
    state = MonitorState()
    assert state.ingest(f"netpose/{VEHICLE}/estimate", b"\x00not json", 1.0) is None
    broken = estimate_json(1)
    del broken["confidence"]
    broken["schema"] = SCHEMA_VERSION + 1  # a newer publisher's
    received = state.ingest(f"netpose/{VEHICLE}/estimate", encode(broken), 2.0)
    assert received is not None
    problems = " ".join(state.vehicles[VEHICLE].problems)
    assert "not a JSON object" in problems and "confidence" in problems
    assert f"schema {SCHEMA_VERSION + 1}" in problems
    assert state.ingest("netpose/x", b"{}", 3.0) is None  # too short to be ours
    assert state.ingest(f"netpose/{VEHICLE}/unknown", b"{}", 3.0) is None
    meta = to_json(PreviewMeta(vehicle=VEHICLE, seq=3, time_unix=1.0, width=320, height=180))
    preview = state.ingest(f"netpose/{VEHICLE}/preview", b"\xff\xd8" * 50, 4.0, encode(meta))
    assert preview is not None
    record = preview.record(1234.5)
    assert record["bytes"] == 100 and record["meta"] == meta and "payload" not in record
    assert "320x180" in "\n".join(state.render(4.0))


@pytest.mark.parametrize(("kind", "change"), [
    ("status", {"frame_source": "up"}),
    ("estimate", {"filtered": "x"}),
    ("estimate", {"normal": "up", "distance_m": "far"}),
    ("status", {"autopilot": [1, 2]}),
])
def test_a_payload_of_the_wrong_shape_is_flagged_and_not_shown(
        kind: str, change: dict[str, object]) -> None:
    """Any peer on the bus (another netpose version, a test tool) published a status whose
    frame_source was a string: the monitor died with AttributeError, taking the pilot's
    topside view with it. Values of the wrong type are flagged like missing keys, and the
    last good message stays on screen."""
    state = MonitorState()
    good = estimate_json(1) if kind == "estimate" else to_json(status_message())
    state.ingest(f"netpose/{VEHICLE}/{kind}", encode(good), 1.0)
    bad = {**good, **change}
    state.ingest(f"netpose/{VEHICLE}/{kind}", json.dumps(bad).encode(), 2.0)
    view = state.vehicles[VEHICLE]
    flagged = " ".join(view.problems)
    assert all(f"{kind}: {key}" in flagged for key in change), flagged
    assert (view.estimate if kind == "estimate" else view.status) == good
    text = "\n".join(state.render(2.0)) + state.summary(2.0)
    assert VEHICLE in text


# --- the command against a real publisher --------------------------------------------------


@pytest.fixture
def publisher() -> Iterator[tuple[ZenohPublisher, str]]:
    listen = free_endpoint()
    pub = ZenohPublisher(TelemetrySettings(vehicle=VEHICLE, mode="peer", listen=(listen,),
                                           connect=()))
    pub.start()
    deadline = time.monotonic() + 10
    while not pub.online:
        assert time.monotonic() < deadline, "publisher session did not open"
        time.sleep(0.02)
    yield pub, listen
    pub.close(timeout=10.0)


def monitor(*args: str) -> subprocess.Popen[str]:
    env = dict(os.environ, MPLBACKEND="Agg")
    return subprocess.Popen(
        [sys.executable, "-m", "service.cli", "monitor", *args],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )


def feed(pub: ZenohPublisher, proc: subprocess.Popen[str], jpeg: bytes) -> int:
    """Publish 20 Hz estimates, 1 Hz status, previews until the monitor exits; returns count."""
    seq = 0
    deadline = time.monotonic() + 30
    while proc.poll() is None:
        assert time.monotonic() < deadline, "monitor did not stop after --duration"
        pub.publish_estimate(estimate_message(seq, 1.0 + 0.5 * float(np.sin(seq / 20))))
        if seq % 20 == 0:
            pub.publish_status(status_message())
            meta = PreviewMeta(vehicle=VEHICLE, seq=seq, time_unix=time.time(), width=64,
                               height=48)
            pub.publish_preview(jpeg, meta)
        seq += 1
        time.sleep(0.05)
    return seq


def test_monitor_saves_prints_plots_and_keeps_the_preview(
    publisher: tuple[ZenohPublisher, str], tmp_path: Path
) -> None:
    import cv2

    pub, endpoint = publisher
    image = np.zeros((48, 64, 3), np.uint8)
    image[:, 32:] = (0, 0, 255)
    ok, jpeg = cv2.imencode(".jpg", image)
    assert ok
    save, png, preview = tmp_path / "stream.jsonl", tmp_path / "plot.png", tmp_path / "p.jpg"
    duration = 4.0
    proc = monitor("--connect", endpoint, "--vehicle", VEHICLE, "--duration", str(duration),
                   "--save", str(save), "--plot-png", str(png), "--save-preview", str(preview))
    published = feed(pub, proc, jpeg.tobytes())
    out, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err

    records = [json.loads(line) for line in save.read_text().splitlines()]
    estimates = [r for r in records if r["kind"] == "estimate"]
    statuses = [r for r in records if r["kind"] == "status"]
    previews = [r for r in records if r["kind"] == "preview"]
    # The monitor connects while we publish: allow for its start-up, not for losses after it.
    assert len(estimates) >= 0.5 * duration / 0.05 and len(estimates) <= published
    seqs = [r["payload"]["seq"] for r in estimates]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # nothing lost once subscribed
    assert statuses and previews
    for record in estimates + statuses:
        assert record["key"] == f"netpose/{VEHICLE}/{record['kind']}"
        assert schema_problems(record["payload"]) == []
    assert previews[0]["bytes"] == len(jpeg) and previews[0]["meta"]["width"] == 64
    # The daemon's liveliness token, there all along (history), is in the record too.
    assert any(r["kind"] == "alive" and r["payload"] == {"token": "PUT"} for r in records)

    # Not a terminal: one summary line per second.
    lines = [line for line in out.splitlines() if line.strip()]
    assert duration - 1 <= len(lines) <= duration + 1
    assert any(f"{VEHICLE} live" in line and "est " in line for line in lines)

    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    plotted = cv2.imread(str(png))
    assert plotted is not None and plotted.shape[1] == 800  # 8 in x 100 dpi
    kept = cv2.imread(str(preview))
    assert kept is not None and kept.shape == (48, 64, 3)
    assert kept[:, 40:, 2].mean() > 200 and kept[:, :24, 2].mean() < 40  # red half survived


def test_monitor_query_prints_state_with_redacted_config(
    publisher: tuple[ZenohPublisher, str],
) -> None:
    pub, endpoint = publisher
    pub.set_state(StateMessage(
        vehicle=VEHICLE, time_unix=time.time(), time_mono=time.monotonic(),
        status=status_message(), config=redact_config({"camera": {"url": "rtsp://a:b@cam/"},
                                                       "x": 1})))
    proc = monitor("--connect", endpoint, "--vehicle", VEHICLE, "--query", "--duration", "5")
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    answers = [json.loads(line) for line in out.splitlines() if line.strip()]
    assert len(answers) == 1
    state = answers[0]
    assert schema_problems(state) == []
    assert state["config"] == {"camera": {"url": "rtsp://a:<redacted>@cam/"}, "x": 1}
    assert state["status"]["frame_source"]["state"] == "streaming"


def test_monitor_without_a_router_gives_up_with_a_clear_message() -> None:
    proc = monitor("--connect", free_endpoint(), "--duration", "1.5")
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 1
    assert "no Zenoh link" in err and "Traceback" not in err


def test_monitor_rejects_bad_options_as_configuration_errors() -> None:
    proc = monitor("--connect", "not-an-endpoint", "--duration", "1")
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 78 and "--connect" in err and "Traceback" not in err
    proc = monitor("--vehicle", "a/b", "--duration", "1")
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 78 and "--vehicle" in err
    # A plot file that cannot be written died at the first redraw, after connecting; a Zenoh
    # file that is not there was blamed on --config-file (no such option).
    for args, option in ((("--plot-png", "/nonexistent/plot.png"), "--plot-png"),
                         (("--zenoh-config", "/nonexistent.json5"), "--zenoh-config")):
        proc = monitor(*args, "--duration", "1")
        _, err = proc.communicate(timeout=30)
        assert proc.returncode == 78 and f"configuration error: {option}" in err, err
        assert "Traceback" not in err


def test_the_plot_breaks_where_telemetry_stopped(tmp_path: Path) -> None:
    """A 9 s outage (the tether) was drawn as straight lines across it, as if the net had
    been tracked throughout; the plot breaks there now."""
    from service.commands.monitor import LivePlot

    plot = LivePlot(tmp_path / "plot.png")
    state = MonitorState()
    for t in (*np.arange(0.0, 2.0, 0.1), *np.arange(11.0, 12.0, 0.1)):
        received = state.ingest(f"netpose/{VEHICLE}/estimate", encode(estimate_json(int(t * 10))),
                                float(t))
        assert received is not None
        plot.add(float(t), received)
    times = [row[0] for row in plot.samples]
    gap = next(i for i in range(1, len(times)) if times[i] - times[i - 1] > 1.0)
    assert all(math.isnan(v) for v in plot.samples[gap - 1][1:])  # the break before the gap
    plot.update()
    assert (tmp_path / "plot.png").stat().st_size > 1000


def test_two_daemons_under_one_vehicle_name_are_flagged() -> None:
    """Two daemons publishing as 'demo' were shown as one vehicle whose distance jumped between
    theirs, live and unflagged. Their interleaved seq gives them away (one restart, a seq that
    goes back once, does not)."""
    state = MonitorState()
    state.ingest(f"netpose/{VEHICLE}/estimate", encode(estimate_json(500)), 0.0)
    state.ingest(f"netpose/{VEHICLE}/estimate", encode(estimate_json(1)), 0.1)  # a restart
    for i in range(2, 12):
        state.ingest(f"netpose/{VEHICLE}/estimate", encode(estimate_json(i)), 0.1 * i)
    assert not any("two daemons" in p for p in state.vehicles[VEHICLE].problems)
    for i in range(12, 24):  # another daemon, 1000 frames ahead, interleaved
        state.ingest(f"netpose/{VEHICLE}/estimate", encode(estimate_json(i)), 0.1 * i)
        state.ingest(f"netpose/{VEHICLE}/estimate", encode(estimate_json(i + 1000)), 0.1 * i)
    assert any("two daemons publish as" in p for p in state.vehicles[VEHICLE].problems)


def test_a_daemon_from_before_the_autopilot_keys_is_shown_without_none() -> None:
    """Topside and vehicle run different versions: an estimate without `autopilot_along`
    printed "1.20 m None"."""
    from service.tools.monitor_view import _autopilot_text

    assert _autopilot_text({"autopilot": "good", "autopilot_distance_m": 1.2}) == (
        "a distance is sent")
    assert _autopilot_text({"autopilot": "good", "autopilot_distance_m": 1.2,
                            "autopilot_along": "perpendicular"}) == (
        "1.20 m perpendicular to the net")
    assert _autopilot_text({"autopilot": "none"}) == "nothing sent"
