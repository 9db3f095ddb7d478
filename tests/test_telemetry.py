"""Telemetry: schema builders, settings, and the Zenoh publisher against real Zenoh sessions.

Every Zenoh test runs on loopback with explicit endpoints on ports chosen free at runtime and
multicast scouting off. Subscribers, routers and queriers run in other processes (real Zenoh
sessions in `python -c` children), so what is checked is what crosses the wire.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import re
import socket
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.net import free_port
from drivers.telemetry import (
    NullPublisher,
    RecordingPublisher,
    TelemetrySettings,
    ZenohPublisher,
    build_zenoh_config,
    make_publisher,
    token_change,
)
from service.config import build_section, config_digest
from service.core.errors import ConfigError
from service.core.messages import (
    ESTIMATE_SUFFIX,
    SCHEMA_VERSION,
    AutopilotHealth,
    CpuHealth,
    DamageMessage,
    EstimateLatency,
    EstimateMessage,
    EstimatorHealth,
    FilteredView,
    FilterHealth,
    FrameSourceHealth,
    PreviewMeta,
    StateMessage,
    StatusMessage,
    TelemetryHealth,
    encode,
    keys_of,
    schema_markdown,
    schema_problems,
    to_json,
)
from service.core.redact import REDACTED, redact_config, redact_text

pytestmark = pytest.mark.timeout(90)

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs" / "telemetry.md"
STATE_CONFIG = {"camera": {"url": "rtsp://u:secret@cam/s"}, "n": 1}


# --- helpers -------------------------------------------------------------------------------


def endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


def wait_for(condition: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.02)


def estimate_at(seq: int, vehicle: str = "rov9", now: float | None = None) -> EstimateMessage:
    t = time.monotonic() if now is None else now
    return EstimateMessage(
        vehicle=vehicle, time_unix=1.7e9 + t, time_mono=t, seq=seq,
        frame_time_unix=1.7e9 + t - 0.0625, frame_time_mono=t - 0.0625, detected=True,
        confidence=0.87, range_m=1.242, sigma_range_m=0.022, distance_m=1.234,
        sigma_distance_m=0.021, normal=(0.1, -0.05, -0.9937), tilt_deg=6.4,
        sigma_normal_deg=1.5, rois=15, rois_used=12,
        filtered=FilteredView(valid=True, autopilot="good", state="tracking",
                              measurement="accepted", distance_m=1.23, sigma_distance_m=0.01),
        latency_ms=EstimateLatency(stages={"spectrum": 12.5, "fit": 3.25}, estimator_total=15.75,
                                   frame_to_publish=62.5),
    )


def status_now(vehicle: str = "rov9", telemetry: TelemetryHealth | None = None) -> StatusMessage:
    return StatusMessage(
        vehicle=vehicle, time_unix=time.time(), time_mono=time.monotonic(), version="0.1.0",
        state="running", uptime_s=12.0, config_digest="sha256:0123456789abcdef",
        frame_source=FrameSourceHealth(state="streaming", fps=15.0, frames=180, dropped=2,
                                       last_frame_age_s=0.07),
        autopilot=AutopilotHealth(state="connected", heartbeat_age_s=0.4, messages_sent=170),
        estimator=EstimatorHealth(fps=14.8, frames=178, detected_fraction=0.9,
                                  latency_ms_mean=40.0, latency_ms_max=75.0),
        cpu=CpuHealth(cores=2, load_1m=0.5, process_percent=40.0),
        telemetry=telemetry,
        filter=FilterHealth(state="tracking", accepted=170, rejected=2, resets=0),
    )


# A subscriber / querier in another process: prints one JSON line per sample, then the answer
# of the state queryable, then exits once it has `want` estimates, a status and a preview.
SUBSCRIBER = textwrap.dedent(
    """
    import json, sys, threading, time, zenoh
    connect, prefix, want, limit = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
    # Zenoh's callback thread and the main thread both print: one whole line at a time (print()
    # writes the text and its newline separately, so two lines could interleave).
    out_lock = threading.Lock()
    def emit(obj):
        with out_lock:
            sys.stdout.write(json.dumps(obj) + "\\n")
            sys.stdout.flush()
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([connect]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    seen = {"estimate": 0, "status": 0, "preview": 0}
    def on_sample(sample):
        kind = str(sample.key_expr).rsplit("/", 1)[-1]
        seen[kind] = seen.get(kind, 0) + 1
        data = sample.payload.to_bytes()
        att = sample.attachment
        line = {"key": str(sample.key_expr), "encoding": str(sample.encoding), "size": len(data),
                "attachment": None if att is None else json.loads(att.to_bytes())}
        if kind != "preview":
            line["payload"] = json.loads(data)
        emit(line)
    sub = session.declare_subscriber(prefix + "/**", on_sample)
    emit({"ready": True})
    deadline = time.monotonic() + limit
    while time.monotonic() < deadline:
        if seen["estimate"] >= want and seen["status"] >= 1 and seen["preview"] >= 1:
            break
        time.sleep(0.02)
    for reply in session.get(prefix + "/state", timeout=5):
        if reply.ok is not None:
            emit({"reply": json.loads(reply.ok.payload.to_bytes()),
                  "encoding": str(reply.ok.encoding)})
    session.close()
    """
)

ROUTER = textwrap.dedent(
    """
    import json, sys, zenoh
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps([sys.argv[1]]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    print("ready", flush=True)
    sys.stdin.read()  # until the test closes our stdin or kills us
    session.close()
    """
)


def start_subscriber(
    connect: str, prefix: str, want: int, limit: float = 20.0
) -> subprocess.Popen[str]:
    proc = subprocess.Popen(
        [sys.executable, "-c", SUBSCRIBER, connect, prefix, str(want), str(limit)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    assert proc.stdout is not None
    first = proc.stdout.readline()
    assert json.loads(first) == {"ready": True}, first + (proc.stderr.read() if proc.stderr else "")
    return proc


def start_router(listen: str) -> subprocess.Popen[str]:
    proc = subprocess.Popen([sys.executable, "-c", ROUTER, listen], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
    return proc


def feed_until_exit(
    publisher: ZenohPublisher, proc: subprocess.Popen[str], limit: float = 25.0
) -> list[dict[str, Any]]:
    """Publish estimates (20 ms apart), a status and a preview per 10 until the child exits."""
    deadline = time.monotonic() + limit
    seq = 0
    while proc.poll() is None:
        assert time.monotonic() < deadline, "subscriber did not finish"
        publisher.publish_estimate(estimate_at(seq))
        if seq % 10 == 0:
            status = status_now(telemetry=publisher.status())
            publisher.publish_status(status)
            publisher.set_state(StateMessage(
                vehicle="rov9", time_unix=time.time(), time_mono=time.monotonic(),
                status=status, config=redact_config(STATE_CONFIG),
                estimate=estimate_at(seq)))
            meta = PreviewMeta(vehicle="rov9", seq=seq, time_unix=time.time(), width=4, height=3)
            publisher.publish_preview(b"\xff\xd8\xff\xe0fakejpeg", meta)
        seq += 1
        time.sleep(0.02)
    out, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    return [json.loads(line) for line in out.splitlines() if line.strip()]


@pytest.fixture
def publisher_factory() -> Iterator[Callable[..., ZenohPublisher]]:
    made: list[ZenohPublisher] = []

    def make(**kwargs: Any) -> ZenohPublisher:
        values: dict[str, Any] = {"vehicle": "rov9", "retry_initial_s": 0.1, "retry_max_s": 0.5}
        values.update(kwargs)
        publisher = ZenohPublisher(TelemetrySettings(**values))
        made.append(publisher)
        return publisher

    yield make
    for publisher in made:
        publisher.close(timeout=10.0)


# --- schema ---------------------------------------------------------------------------------


def test_estimate_message_on_the_wire_has_the_declared_keys() -> None:
    payload = to_json(estimate_at(7, now=1000.0))
    assert set(payload) == keys_of(EstimateMessage)
    assert payload["schema"] == SCHEMA_VERSION and payload["kind"] == "estimate"
    assert set(payload["filtered"]) == {f for f in FilteredView.__dataclass_fields__}
    assert payload["distance_m"] == 1.234 and payload["normal"] == [0.1, -0.05, -0.9937]
    # 62.5 ms is exact in binary, so the frame age comes out exactly.
    assert payload["latency_ms"]["frame_to_publish"] == 62.5
    assert payload["latency_ms"]["stages"] == {"spectrum": 12.5, "fit": 3.25}
    assert schema_problems(payload) == []
    assert json.loads(encode(estimate_at(7, now=1000.0))) == payload


def test_one_rounding_policy_and_strict_json_for_nan_and_infinity() -> None:
    message = EstimateMessage(vehicle="r", time_unix=math.nan, time_mono=5.0, seq=1,
                              confidence=math.nan, range_m=math.inf, distance_m=1.23456789123,
                              reason="no lattice")
    back = json.loads(encode(message))  # encode() refuses NaN: it never reaches the wire
    assert back["confidence"] is None and back["range_m"] is None and back["time_unix"] is None
    assert back["distance_m"] == 1.234568  # micrometres: the one policy for every float
    # No "-0.0" on the wire (a negated zero closing speed, a tiny negative rounded): some
    # parsers and every diff of logs trip over it.
    zero = EstimateMessage(vehicle="r", time_unix=1.0, time_mono=-0.0, seq=1,
                           confidence=-1e-9, range_m=1.0)
    assert b"-0.0" not in encode(zero) and json.loads(encode(zero))["confidence"] == 0.0
    # A file name that is not UTF-8 (surrogateescape) must not make the message invalid
    # Unicode: strict parsers (serde_json) refuse a lone surrogate, escaped or not.
    odd = EstimateMessage(vehicle="r", time_unix=1.0, time_mono=1.0, seq=1,
                          reason="cannot read frame_\udcff.png")
    wire = encode(odd)
    assert b"\\ud" not in wire.lower()
    assert json.loads(wire.decode("utf-8", errors="strict"))["reason"] == (
        "cannot read frame_\ufffd.png")
    assert back["detected"] is False and back["reason"] == "no lattice"
    assert back["latency_ms"]["frame_to_publish"] is None
    status = to_json(status_now(telemetry=TelemetryHealth(state="online", sent={"estimate": 3})))
    assert set(status) == keys_of(StatusMessage)
    assert set(status["frame_source"]) == set(FrameSourceHealth.__dataclass_fields__)
    assert status["telemetry"]["sent"] == {"estimate": 3}


def test_schema_problems_name_missing_keys_and_version() -> None:
    payload = to_json(estimate_at(1))
    del payload["distance_m"]
    payload["schema"] = 99
    problems = schema_problems(payload)
    assert any("distance_m" in p for p in problems)
    assert any("99" in p for p in problems)
    assert schema_problems({"kind": "banana"}) == ["unknown kind 'banana'"]


@pytest.mark.parametrize(
    ("text", "secret"),
    [
        ("rtsp://admin:hunter2@192.168.2.10:554/stream", "hunter2"),
        ("rtsp://admin:p@ss@word@cam/stream", "p@ss@word"),
        ("srt://10.0.0.2:9000?mode=caller&passphrase=supersecret1&latency=50", "supersecret1"),
        ("rtsp://cam/live?token=abc123&x=1", "abc123"),
        ("http://cam/video?user=me&password=pw42", "pw42"),
        ("frame source srt://h:1?passphrase=s3cr3t: connection refused", "s3cr3t"),
    ],
)
def test_one_redaction_covers_user_info_and_secret_parameters(text: str, secret: str) -> None:
    redacted = redact_text(text)
    assert secret not in redacted and REDACTED in redacted
    for kept in ("mode=caller", "latency=50", "x=1", "user=me", "connection refused"):
        if kept in text:
            assert kept in redacted


def test_redaction_removes_secrets_and_digest_ignores_them() -> None:
    config: dict[str, Any] = {
        "camera": {"url": "rtsp://admin:hunter2@192.168.2.10:554/stream", "password": "pw"},
        "mavlink": {"url": "tcp:127.0.0.1:5777", "api_key": "k", "tokens": ["a"]},
        "service": {"log_level": "INFO", "passthrough": 3},
    }
    redacted = redact_config(config)
    text = json.dumps(redacted)
    for secret in ("hunter2", '"pw"', '"k"', '"a"'):
        assert secret not in text
    assert redacted["camera"]["url"] == "rtsp://admin:<redacted>@192.168.2.10:554/stream"
    assert redacted["service"] == {"log_level": "INFO", "passthrough": 3}
    assert config["camera"]["password"] == "pw"  # the input is untouched
    digest = config_digest(config)
    assert re.fullmatch(r"sha256:[0-9a-f]{16}", digest)
    reordered = {k: config[k] for k in reversed(list(config))}
    assert config_digest(reordered) == digest
    other_secret = json.loads(json.dumps(config))
    other_secret["camera"]["password"] = "different"
    assert config_digest(other_secret) == digest
    other_value = json.loads(json.dumps(config))
    other_value["service"]["log_level"] = "DEBUG"
    assert config_digest(other_value) != digest


def test_docs_carry_the_schema_generated_from_the_message_types() -> None:
    """docs/telemetry.md holds `netpose schema`'s output verbatim: the types are the schema."""
    text = DOCS.read_text(encoding="utf-8")
    begin, end = "<!-- schema:begin (netpose schema) -->\n", "<!-- schema:end -->"
    assert begin in text and end in text
    documented = text.split(begin, 1)[1].split(end, 1)[0]
    assert documented == schema_markdown(), "regenerate: netpose schema --update docs/telemetry.md"
    settings = set(TelemetrySettings.__dataclass_fields__)
    assert sorted(k for k in settings if f"`{k}`" not in text) == []


def test_the_docs_examples_are_complete_messages_of_this_schema() -> None:
    """Integrators copy the examples into their parsers' fixtures: they lacked keys the daemon
    sends (seven of the estimate's, nested ones of the status), so a parser built from them
    failed on the first real message."""
    text = DOCS.read_text(encoding="utf-8")
    examples = [json.loads(block) for block in re.findall(r"```json\n(.*?)\n```", text, re.S)]
    assert sorted(e["kind"] for e in examples) == ["damage", "estimate", "status"]
    for example in examples:
        assert schema_problems(example) == [], example["kind"]


# --- settings ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("values", "key"),
    [
        ({"mode": "router"}, "telemetry.mode"),
        ({"vehicle": "rov/1"}, "telemetry.vehicle"),
        ({"vehicle": "*"}, "telemetry.vehicle"),
        ({"connect": ("127.0.0.1:7447",)}, "telemetry.connect"),
        ({"listen": ("tcp/",)}, "telemetry.listen"),
        ({"preview_hz": -1.0}, "telemetry.preview_hz"),
        ({"preview_quality": 0}, "telemetry.preview_quality"),
        ({"queue_size": 0}, "telemetry.queue_size"),
        ({"retry_initial_s": 5.0, "retry_max_s": 1.0}, "telemetry.retry_max_s"),
    ],
)
def test_settings_reject_bad_values_naming_the_key(values: dict[str, Any], key: str) -> None:
    with pytest.raises(ConfigError) as info:
        TelemetrySettings(**values)
    assert info.value.key == key


def test_settings_from_toml_through_the_one_coercer() -> None:
    settings = build_section("telemetry", TelemetrySettings, {
        "vehicle": "bluerov2", "mode": "peer", "listen": ["tcp/0.0.0.0:7447"], "connect": []})
    assert settings.listen == ("tcp/0.0.0.0:7447",) and settings.connect == ()
    assert settings.key(ESTIMATE_SUFFIX) == "netpose/bluerov2/estimate"
    with pytest.raises(ConfigError) as info:
        build_section("telemetry", TelemetrySettings, {"vehicel": "x"})
    assert info.value.key == "telemetry.vehicel"
    with pytest.raises(ConfigError) as info:
        build_section("telemetry", TelemetrySettings, {"enabled": "yes"})
    assert info.value.key == "telemetry.enabled"
    assert isinstance(make_publisher(settings), ZenohPublisher)
    assert isinstance(make_publisher(TelemetrySettings(enabled=False)), NullPublisher)


def test_zenoh_config_defaults_file_passthrough_and_overrides(tmp_path: Path) -> None:
    defaults = build_zenoh_config(TelemetrySettings())
    assert json.loads(defaults.get_json("mode")) == "client"
    assert json.loads(defaults.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(defaults.get_json("scouting/multicast/enabled")) is False

    file = tmp_path / "zenoh.json5"
    file.write_text("{ mode: 'peer', connect: { endpoints: ['tcp/10.0.0.1:7447'] },"
                    " transport: { unicast: { open_timeout: 1234 } } }")
    from_file = build_zenoh_config(TelemetrySettings(config_file=str(file)))
    assert json.loads(from_file.get_json("mode")) == "peer"  # the file decides
    assert json.loads(from_file.get_json("connect/endpoints")) == ["tcp/10.0.0.1:7447"]
    assert json.loads(from_file.get_json("transport/unicast/open_timeout")) == 1234
    overridden = build_zenoh_config(TelemetrySettings(config_file=str(file), mode="client"))
    assert json.loads(overridden.get_json("mode")) == "client"  # an explicit key wins

    with pytest.raises(ConfigError) as info:
        build_zenoh_config(TelemetrySettings(config_file=str(tmp_path / "missing.json5")))
    assert info.value.key == "telemetry.config_file"
    file.write_text("{ mode: 'peer', no_such_section: 1 }")
    with pytest.raises(ConfigError) as info:
        build_zenoh_config(TelemetrySettings(config_file=str(file)))
    assert info.value.key == "telemetry.config_file" and "no_such_section" in info.value.problem


# --- fakes ---------------------------------------------------------------------------------


def test_fakes_follow_the_interface() -> None:
    recorder = RecordingPublisher(TelemetrySettings(preview_hz=2.0))
    assert not recorder.wants_preview(0.0)  # not started: nobody to draw for
    with recorder:
        recorder.publish_estimate(estimate_at(1))
        assert recorder.wants_preview(10.0) and not recorder.wants_preview(10.4)
        assert recorder.wants_preview(10.5)  # 2 Hz
    assert recorder.closed and len(recorder.estimates) == 1
    null = NullPublisher(TelemetrySettings(enabled=False))
    null.start()
    null.publish_estimate(estimate_at(1))
    assert null.status().state == "disabled" and not null.wants_preview(0.0)


def test_queue_drops_oldest_and_counts() -> None:
    publisher = ZenohPublisher(TelemetrySettings(queue_size=8))
    publisher._online = True  # queue policy only: no worker runs, nothing drains
    for seq in range(100):
        publisher.publish_estimate(estimate_at(seq))
    assert publisher.status().queue_dropped == 92
    kept = [item.message for item in publisher._queue]
    assert [m.seq for m in kept if isinstance(m, EstimateMessage)] == list(range(92, 100))


# --- real Zenoh ----------------------------------------------------------------------------


def test_subscriber_in_another_process_receives_documented_schema_and_queryable_answers(
    publisher_factory: Callable[..., ZenohPublisher],
) -> None:
    listen = endpoint()
    publisher = publisher_factory(mode="peer", listen=(listen,), connect=())
    publisher.start()
    wait_for(lambda: publisher.online, 10, "peer session to open")
    subscriber = start_subscriber(listen, "netpose/rov9", want=20)
    lines = feed_until_exit(publisher, subscriber)

    estimates = [line for line in lines if line.get("key") == "netpose/rov9/estimate"]
    statuses = [line for line in lines if line.get("key") == "netpose/rov9/status"]
    previews = [line for line in lines if line.get("key") == "netpose/rov9/preview"]
    replies = [line for line in lines if "reply" in line]
    assert len(estimates) >= 20 and statuses and previews and len(replies) == 1
    for line in estimates + statuses:
        assert line["encoding"] == "application/json"
        assert schema_problems(line["payload"]) == []
    seqs = [line["payload"]["seq"] for line in estimates]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)  # in order, no duplicates
    assert estimates[0]["payload"]["distance_m"] == pytest.approx(1.234)
    assert previews[0]["encoding"] == "image/jpeg" and previews[0]["size"] == 12
    assert set(previews[0]["attachment"]) == keys_of(PreviewMeta)

    reply = replies[0]
    assert reply["encoding"] == "application/json"
    state = reply["reply"]
    assert schema_problems(state) == []
    assert state["config"] == {"camera": {"url": "rtsp://u:<redacted>@cam/s"}, "n": 1}
    assert state["status"]["kind"] == "status"  # the last published status
    assert state["estimate"]["kind"] == "estimate"
    status = publisher.status()
    assert status.errors == 0 and status.queries == 1
    assert status.sent["estimate"] >= 20


def test_publisher_survives_a_subscriber_that_disappears_and_comes_back(
    publisher_factory: Callable[..., ZenohPublisher],
) -> None:
    listen = endpoint()
    publisher = publisher_factory(mode="peer", listen=(listen,), connect=())
    publisher.start()
    wait_for(lambda: publisher.online, 10, "peer session to open")
    first = start_subscriber(listen, "netpose/rov9", want=1000, limit=60)
    assert first.stdout is not None
    for seq in range(30):
        publisher.publish_estimate(estimate_at(seq))
        time.sleep(0.01)
    wait_for(lambda: publisher.status().links == 1, 5, "the subscriber's link")
    first.kill()  # vanishes without a goodbye
    first.communicate(timeout=10)
    wait_for(lambda: publisher.status().links == 0, 30, "the dead link to be noticed")
    for seq in range(30, 60):  # publishing into the void must be harmless
        publisher.publish_estimate(estimate_at(seq))
    second = start_subscriber(listen, "netpose/rov9", want=10)
    lines = feed_until_exit(publisher, second)
    assert sum(1 for line in lines if line.get("key", "").endswith("/estimate")) >= 10
    status = publisher.status()
    assert status.state == "online" and status.errors == 0 and status.open_attempts == 1


def test_client_without_router_runs_then_recovers_when_the_router_appears(
    publisher_factory: Callable[..., ZenohPublisher], caplog: pytest.LogCaptureFixture
) -> None:
    router_endpoint = endpoint()
    publisher = publisher_factory(mode="client", connect=(router_endpoint,))
    caplog.set_level("WARNING", logger="drivers.telemetry")
    publisher.start()
    wait_for(lambda: publisher.status().open_attempts >= 3, 10, "retries")
    assert publisher.status().state == "connecting" and not publisher.online
    for seq in range(50):
        publisher.publish_estimate(estimate_at(seq))  # accepted and counted, not queued
    assert publisher.status().skipped_offline == 50
    warnings = [r for r in caplog.records if "cannot open Zenoh session" in r.getMessage()]
    assert len(warnings) == 1  # logged once, not per retry

    router = start_router(router_endpoint)
    try:
        wait_for(lambda: publisher.online, 15, "the publisher to find the router")
        subscriber = start_subscriber(router_endpoint, "netpose/rov9", want=10)
        lines = feed_until_exit(publisher, subscriber)
        assert sum(1 for line in lines if line.get("key", "").endswith("/estimate")) >= 10
        assert any("reply" in line for line in lines)  # queryable reachable through the router
    finally:
        router.kill()
        router.communicate(timeout=10)


DAMAGE_SUBSCRIBER = textwrap.dedent(
    """
    import json, sys, time, zenoh
    connect, key, want = sys.argv[1], sys.argv[2], int(sys.argv[3])
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([connect]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    holes = []
    sub = session.declare_subscriber(key, lambda s: holes.append(json.loads(s.payload.to_bytes())))
    print(json.dumps({"ready": True}), flush=True)
    deadline = time.monotonic() + 20
    while len(holes) < want and time.monotonic() < deadline:
        time.sleep(0.02)
    time.sleep(0.3)  # anything beyond `want` would show here
    print(json.dumps([h["hole_id"] for h in holes]), flush=True)
    session.close()
    """
)


def _topside_config(listen: str) -> Any:
    """A topside client's Zenoh configuration, connecting to the publisher at `listen`."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([listen]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


def _hole(hole_id: int) -> DamageMessage:
    return DamageMessage(
        vehicle="rov9", time_unix=time.time(), time_mono=time.monotonic(), hole_id=hole_id,
        width_m=0.04, height_m=0.02, cells=2, missing_bars=1, image_x_px=320.0,
        image_y_px=180.0, plane_x_m=0.1, plane_y_m=-0.05, position_m=(0.1, -0.05, 1.0),
        range_m=1.0, bearing="ahead", confidence=0.8, detections=3, looks=4)


def test_holes_confirmed_before_anyone_listens_are_delivered_once_someone_does(
    publisher_factory: Callable[..., ZenohPublisher],
) -> None:
    """A hole is reported once, so it must not be lost to a link that is not there yet: one
    confirmed before the session could open (no router) and one confirmed while the session is
    open but nobody subscribes both reach the topside subscriber when it joins, once each,
    in order; estimates of that time are not kept."""
    router_endpoint = endpoint()
    publisher = publisher_factory(mode="client", connect=(router_endpoint,))
    publisher.start()
    wait_for(lambda: publisher.status().open_attempts >= 2, 10, "retries")
    publisher.publish_damage(_hole(1))
    publisher.publish_estimate(estimate_at(0))
    assert publisher.status().damage_waiting == 1
    router = start_router(router_endpoint)
    try:
        wait_for(lambda: publisher.online, 15, "the publisher to find the router")
        publisher.publish_damage(_hole(2))
        time.sleep(1.2)  # two and more looks for a subscriber find none: the holes wait
        assert publisher.status().damage_waiting == 2
        proc = subprocess.Popen(
            [sys.executable, "-c", DAMAGE_SUBSCRIBER, router_endpoint, "netpose/rov9/damage", "2"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        out, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err
        lines = out.splitlines()
        assert json.loads(lines[0]) == {"ready": True}
        assert json.loads(lines[-1]) == [1, 2]
        status = publisher.status()
        assert status.damage_waiting == 0 and status.sent["damage"] == 2
        assert status.skipped_offline == 1  # the estimate
    finally:
        router.kill()
        router.communicate(timeout=10)


def test_client_reconnects_when_the_router_restarts(
    publisher_factory: Callable[..., ZenohPublisher],
) -> None:
    # BlueOS restarts its router on updates: the same endpoint goes away and comes back.
    router_endpoint = endpoint()
    router = start_router(router_endpoint)
    publisher = publisher_factory(mode="client", connect=(router_endpoint,))
    try:
        publisher.start()
        wait_for(lambda: publisher.online, 10, "the publisher to open via the router")
        wait_for(lambda: publisher.status().routers == 1, 5, "the router link")
        router.kill()
        router.communicate(timeout=10)
        wait_for(lambda: publisher.status().routers == 0, 30, "the router loss to be noticed")
        for seq in range(20):  # publishing while the router is away is harmless
            publisher.publish_estimate(estimate_at(seq))
        router = start_router(router_endpoint)
        wait_for(lambda: publisher.status().routers == 1, 20, "the publisher to reconnect")
        subscriber = start_subscriber(router_endpoint, "netpose/rov9", want=10)
        lines = feed_until_exit(publisher, subscriber)
        assert sum(1 for line in lines if line.get("key", "").endswith("/estimate")) >= 10
        status = publisher.status()
        assert status.open_attempts == 1 and status.errors == 0  # Zenoh reconnected
    finally:
        router.kill()
        router.communicate(timeout=10)


def test_frame_loop_never_waits_for_a_hanging_zenoh_open(tmp_path: Path) -> None:
    # A TCP listener that never speaks: the kernel accepts the connection, Zenoh's handshake
    # waits for an answer until its open timeout (set through the pass-through config file).
    black_hole = socket.socket()
    black_hole.bind(("127.0.0.1", 0))
    black_hole.listen(8)
    port = black_hole.getsockname()[1]
    zenoh_file = tmp_path / "zenoh.json5"
    zenoh_file.write_text("{ transport: { unicast: { open_timeout: 3000 } } }")
    publisher = ZenohPublisher(TelemetrySettings(
        vehicle="rov9", mode="client", connect=(f"tcp/127.0.0.1:{port}",),
        config_file=str(zenoh_file), retry_initial_s=5.0, retry_max_s=5.0,
    ))
    try:
        publisher.start()
        wait_for(lambda: publisher.status().open_attempts == 1, 5, "the first open")
        frames = 500
        for seq in range(frames):  # the frame loop: estimate every frame, status every 10th
            publisher.publish_estimate(estimate_at(seq))
            if seq % 10 == 0:
                publisher.publish_status(status_now())
                publisher.wants_preview(time.monotonic())
        status = publisher.status()
        # The first open has not even returned (no error recorded yet), yet every frame went by.
        assert status.open_attempts == 1 and status.last_error == ""
        assert status.skipped_offline == frames + frames // 10
        thread = publisher._thread
        assert thread is not None and thread.is_alive()
    finally:
        publisher.close(timeout=10.0)  # waits for the hanging open (3 s) and joins
        black_hole.close()
    assert thread is not None and not thread.is_alive()
    assert publisher.status().state == "closed"


def test_non_finite_values_go_out_as_null_and_the_stream_goes_on(
    publisher_factory: Callable[..., ZenohPublisher],
) -> None:
    import zenoh

    listen = endpoint()
    publisher = publisher_factory(mode="peer", listen=(listen,), connect=())
    publisher.start()
    wait_for(lambda: publisher.online, 10, "peer session to open")
    conf = _topside_config(listen)
    received: list[dict[str, Any]] = []
    with zenoh.open(conf) as session:
        subscriber = session.declare_subscriber(
            "netpose/rov9/estimate",
            lambda sample: received.append(json.loads(sample.payload.to_bytes())),
        )

        def warm_up() -> bool:  # seq -1 until one arrives: the subscription has reached us
            publisher.publish_estimate(estimate_at(-1))
            return bool(received)

        wait_for(warm_up, 10, "the subscription to reach the publisher")
        bad = dataclasses.replace(estimate_at(0), confidence=math.nan, range_m=math.inf)
        publisher.publish_estimate(bad)
        for seq in range(1, 4):
            publisher.publish_estimate(estimate_at(seq))
        wait_for(lambda: received[-1]["seq"] == 3, 5, "the estimates")
        subscriber.undeclare()
    payloads = [p for p in received if p["seq"] >= 0]
    assert [p["seq"] for p in payloads] == [0, 1, 2, 3]
    assert payloads[0]["confidence"] is None and payloads[0]["range_m"] is None
    assert publisher.status().errors == 0


def test_preview_is_wanted_only_when_someone_subscribes_to_it(
    publisher_factory: Callable[..., ZenohPublisher],
) -> None:
    import zenoh

    listen = endpoint()
    publisher = publisher_factory(mode="peer", listen=(listen,), connect=(), preview_hz=2.0)
    publisher.start()
    wait_for(lambda: publisher.online, 10, "peer session to open")
    now = [0.0]

    def wanted_a_period_later() -> bool:
        now[0] += 10.0  # a fake monotonic clock, far beyond the 0.5 s preview period
        return publisher.wants_preview(now[0])

    conf = _topside_config(listen)
    with zenoh.open(conf) as session:
        estimates_only = session.declare_subscriber("netpose/rov9/estimate", lambda s: None)
        wait_for(lambda: publisher.status().links == 1, 5, "the subscriber's link")
        time.sleep(0.3)  # let the subscription propagate
        assert not wanted_a_period_later()  # linked, but nobody asked for pictures
        previews = session.declare_subscriber("netpose/*/preview", lambda s: None)
        wait_for(wanted_a_period_later, 5, "the preview subscriber to be seen")
        granted = now[0]
        assert not publisher.wants_preview(granted + 0.4)  # 2 Hz at most
        assert publisher.wants_preview(granted + 0.5)
        previews.undeclare()
        wait_for(lambda: not wanted_a_period_later(), 5, "the preview subscriber to leave")
        estimates_only.undeclare()


def test_the_documented_tether_security_example_is_a_valid_zenoh_configuration(
    tmp_path: Path,
) -> None:
    """docs/telemetry.md's TLS + access-control file: every key exists in this Zenoh, and
    netpose builds its session configuration on top of it without overriding its endpoints."""
    text = DOCS.read_text(encoding="utf-8")
    example = text.split("### Securing the tether", 1)[1].split("```json5\n", 1)[1]
    example = example.split("```", 1)[0]
    path = tmp_path / "zenoh.json5"
    path.write_text(example)
    config = build_zenoh_config(TelemetrySettings(config_file=str(path)))
    assert json.loads(config.get_json("listen/endpoints")) == ["tls/192.168.2.2:7447"]
    assert json.loads(config.get_json("transport/link/tls/enable_mtls")) is True
    acl = json.loads(config.get_json("access_control"))
    assert acl["enabled"] and acl["default_permission"] == "deny"


@pytest.mark.parametrize(("fps", "hz"), [(10.0, 5.0), (10.0, 2.0), (30.0, 4.0)])
def test_previews_come_at_the_configured_rate(fps: float, hz: float) -> None:
    """With a 10 frames/s camera, preview_hz 5 gave 4 a second and 2 gave 1.75: each preview
    was due a period after the frame that drew the last, so a frame a hair early waited for
    the next. Over 20 s of frames with a millisecond of jitter, the rate is the one set."""
    recorder = RecordingPublisher(TelemetrySettings(preview_hz=hz))
    rng = np.random.default_rng(0)
    with recorder:
        frames = np.arange(0.0, 20.0, 1.0 / fps) + rng.uniform(-0.001, 0.001, int(20 * fps))
        drawn = sum(recorder.wants_preview(float(t)) for t in frames)
    assert abs(drawn - 20 * hz) <= 1


def test_holes_that_never_reached_the_topside_are_said_at_stop(
    publisher_factory: Callable[..., ZenohPublisher], caplog: pytest.LogCaptureFixture
) -> None:
    """A stop with holes still waiting for a subscriber (no router all dive) dropped them
    without a word: 'stopped cleanly' and nothing else."""
    publisher = publisher_factory(mode="client", connect=(endpoint(),))  # nobody there
    publisher.start()
    publisher.publish_damage(_hole(1))
    publisher.publish_damage(_hole(2))
    caplog.set_level(logging.WARNING)
    publisher.close()
    assert any("2 confirmed hole(s) never reached a subscriber" in r.getMessage()
               for r in caplog.records)


def test_a_stop_says_its_last_status_and_withdraws_the_liveliness_token(
    publisher_factory: Callable[..., ZenohPublisher],
) -> None:
    """A clean stop, a crash and a cut tether looked the same to a topside: the queue was
    thrown away at stop (the last status never left), and nothing said the vehicle went. The
    session now holds a liveliness token `<prefix>/<vehicle>/alive`, and what is queued at
    stop still goes before it is withdrawn."""
    import zenoh

    listen = endpoint()
    publisher = publisher_factory(mode="peer", listen=(listen,), connect=())
    publisher.start()
    wait_for(lambda: publisher.online, 10, "peer session to open")
    conf = _topside_config(listen)
    events: list[tuple[str, str]] = []  # (kind, key): data and liveliness, in arrival order
    lock = threading.Lock()

    def seen(kind: str, key: str) -> None:
        with lock:
            events.append((kind, key))

    with zenoh.open(conf) as session:
        alive = session.liveliness().declare_subscriber(
            "netpose/**", lambda s: seen(token_change(s), str(s.key_expr)),
            history=True)
        data = session.declare_subscriber(
            "netpose/rov9/status",
            lambda s: seen(json.loads(s.payload.to_bytes())["state"], str(s.key_expr)))
        wait_for(lambda: ("PUT", "netpose/rov9/alive") in events, 10, "the liveliness token")

        def warm_up() -> bool:  # until one status arrives: the subscription has reached us
            publisher.publish_status(status_now())
            return any(kind == "running" for kind, _ in events)

        wait_for(warm_up, 10, "the subscription to reach the publisher")
        for _ in range(3):
            publisher.publish_status(status_now())
        publisher.publish_status(dataclasses.replace(status_now(), state="stopping"))
        publisher.close()  # at once: the messages above are still queued
        wait_for(lambda: ("DELETE", "netpose/rov9/alive") in events, 10, "the token to go")
        alive.undeclare()
        data.undeclare()
        # Zenoh sends the withdrawal ahead of data: on a loaded machine the last status may
        # come just after it (the docs say so); it must come.
        wait_for(lambda: any(kind == "stopping" for kind, _ in events), 5, "the last status")
    kinds = [kind for kind, _ in events]
    assert kinds.count("stopping") == 1 and kinds.count("DELETE") == 1, kinds


def test_a_dashboard_that_joins_late_gets_the_runs_holes_by_asking(
    publisher_factory: Callable[..., ZenohPublisher],
) -> None:
    """A hole is published once: a dashboard that joined after it was delivered (to another
    subscriber, a recorder, a bridge) or restarted mid-dive saw `status.inspection.holes: 2`
    and had no way to get the two. A `get` on `damage/*` answers every hole of the run, each
    on its own key `damage/<hole_id>`, as published."""
    import zenoh

    listen = endpoint()
    publisher = publisher_factory(mode="peer", listen=(listen,), connect=())
    publisher.start()
    wait_for(lambda: publisher.online, 10, "peer session to open")
    conf = _topside_config(listen)
    with zenoh.open(conf) as early:
        delivered: list[int] = []
        sub = early.declare_subscriber(
            "netpose/rov9/damage",
            lambda s: delivered.append(json.loads(s.payload.to_bytes())["hole_id"]))
        time.sleep(0.5)  # the subscription reaches the publisher
        publisher.publish_damage(_hole(1))
        publisher.publish_damage(_hole(2))
        wait_for(lambda: delivered == [1, 2], 10, "the holes to be delivered")
        sub.undeclare()
    with zenoh.open(conf) as late:
        replies = list(late.get("netpose/rov9/damage/*", timeout=5.0))
        one = list(late.get("netpose/rov9/damage/2", timeout=5.0))
    holes = [json.loads(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]
    assert sorted(h["hole_id"] for h in holes) == [1, 2]
    assert [str(r.ok.key_expr) for r in one if r.ok is not None] == ["netpose/rov9/damage/2"]
    assert all(schema_problems(h) == [] for h in holes)
    assert publisher.status().damage_waiting == 0
