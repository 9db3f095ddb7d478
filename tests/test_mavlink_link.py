"""The MAVLink link against a real pymavlink peer (tests/fake_autopilot.py) over loopback UDP,
TCP and a pseudo-terminal, and optionally against ArduSub SITL (NETPOSE_ARDUSUB_SITL)."""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import json
import logging
import math
import os
import socket
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.mavlink_link import MavlinkLink, RecordingAutopilotLink
from drivers.mavlink_settings import MavlinkSettings, load_signing_key
from drivers.mavlink_wire import covariance_cm2, distance_sensor_fields, signal_quality
from drivers.net import free_port
from service.config import build_section
from service.core.errors import ConfigError
from service.core.messages import AutopilotHealth, json_value
from service.core.readings import NetPlane, RangeReading, RangeStatus
from tests.fake_autopilot import (
    FakeAutopilot,
    PtyTransport,
    TcpServerTransport,
    UdpClientTransport,
    UdpServerTransport,
)

pytestmark = pytest.mark.timeout(60)

READING = RangeReading(RangeStatus.GOOD, t_capture=0.0, distance_m=2.346, sigma_m=0.03,
                       quality=0.87)
# Short timeouts so loss and recovery happen within a second of test time.
FAST = {"heartbeat_timeout_s": 0.5, "retry_initial_s": 0.05, "retry_max_s": 0.4}


def settings(url: str, **overrides: Any) -> MavlinkSettings:
    return MavlinkSettings(url=url, **{**FAST, **overrides})


@contextmanager
def feeding(link: MavlinkLink, reading: RangeReading | None = READING,
            plane: NetPlane | None = None, period: float = 0.05) -> Iterator[None]:
    """Play the frame loop: hand the link a fresh value every `period` seconds."""
    stop = threading.Event()

    def run() -> None:
        while not stop.is_set():
            now = time.monotonic()
            link.set_range(fresh(reading, now))
            if plane is not None:
                link.set_net_plane(dataclasses.replace(plane, t_capture=now))
            stop.wait(period)

    thread = threading.Thread(target=run, name="test-frame-loop")
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()


def fresh(reading: RangeReading | None, t: float) -> RangeReading:
    """`reading` as from a frame captured at `t` (None: a frame without a distance)."""
    if reading is None:
        return RangeReading.none(t)
    return dataclasses.replace(reading, t_capture=t)


def wait_status(link: MavlinkLink, key: str, value: Any, timeout: float = 5.0) -> AutopilotHealth:
    deadline = time.monotonic() + timeout
    while True:
        status = link.status()
        if getattr(status, key) == value:
            return status
        if time.monotonic() > deadline:
            raise AssertionError(f"status.{key} stayed {getattr(status, key)!r}, wanted {value!r}")
        time.sleep(0.01)


def from_link(r: Any) -> bool:
    return bool(r.src == (1, 197))


# ---- settings and pure mappings -------------------------------------------------------------


@pytest.mark.parametrize(
    ("key", "kwargs"),
    [
        ("url", {"url": "http://127.0.0.1:5777"}),
        ("url", {"url": "tcp:127.0.0.1"}),
        ("url", {"url": "ttyACM0"}),
        # The baud rate belongs in mavlink.baud: these were opened as a device of that name.
        ("url", {"url": "/dev/ttyACM0:921600"}),
        ("url", {"url": "serial:/dev/serial0,921600"}),
        # "Too close" goes out at the minimum: at 0 cm an autopilot whose own RNGFNDn_MIN is 0
        # reads it as a Good reading of 0.00 m, not as out of range.
        ("min_distance_m", {"min_distance_m": 0.0}),
        ("source_system", {"source_system": 255}),
        ("source_system", {"source_system": 0}),
        ("source_component", {"source_component": 191}),
        ("source_component", {"source_component": 1}),
        ("source_component", {"source_component": 102}),
        ("rate_hz", {"rate_hz": 2.0}),
        ("max_age_s", {"max_age_s": 0.0}),
        ("orientation", {"orientation": 100}),
        ("max_distance_m", {"min_distance_m": 5.0, "max_distance_m": 2.0}),
        ("fov_horizontal_deg", {"fov_horizontal_deg": math.nan}),
        ("baud", {"url": "/dev/ttyACM0", "baud": 0}),
    ],
)
def test_settings_name_the_bad_key(key: str, kwargs: dict[str, Any]) -> None:
    with pytest.raises(ConfigError) as info:
        MavlinkSettings(**kwargs)
    assert info.value.key == f"mavlink.{key}"


def test_settings_from_toml_through_the_one_coercer() -> None:
    s = build_section("mavlink", MavlinkSettings, {"url": "udpout:127.0.0.1:14660",
                                                   "rate_hz": 20, "send_net_plane": False})
    assert (s.url, s.rate_hz, s.send_net_plane, s.source_component) == (
        "udpout:127.0.0.1:14660", 20.0, False, 197)
    with pytest.raises(ConfigError, match="unknown key") as info:
        build_section("mavlink", MavlinkSettings, {"rate": 10})
    assert info.value.key == "mavlink.rate"
    with pytest.raises(ConfigError) as info:
        build_section("mavlink", MavlinkSettings, {"send_net_plane": "yes"})
    assert info.value.key == "mavlink.send_net_plane"


def test_signal_quality_keeps_zero_for_unknown_and_one_for_invalid() -> None:
    """0 is "unknown", 1 "invalid signal" (MAVLink common.xml): a reading netpose sends is
    neither, however weak."""
    assert signal_quality(math.nan) == 0
    assert [signal_quality(q) for q in (0.0, 0.004, 0.5, 0.87, 1.0, 1.7)] == [2, 2, 50, 87, 100,
                                                                               100]


def test_covariance_is_variance_in_cm2_or_unknown() -> None:
    assert covariance_cm2(0.03) == 9  # (3 cm)^2
    assert covariance_cm2(0.1) == 100
    assert covariance_cm2(0.159) == 253
    assert covariance_cm2(0.004) == covariance_cm2(0.0) == 1  # never 0, a "perfect" sensor
    assert covariance_cm2(0.2) == 255  # 400 cm^2 does not fit: unknown, not a false 254
    assert covariance_cm2(math.nan) == 255


def test_signing_key_file_formats(tmp_path: Path) -> None:
    raw = bytes(range(32))
    (tmp_path / "raw.key").write_bytes(raw)
    (tmp_path / "hex.key").write_text(raw.hex() + "\n")
    (tmp_path / "short.key").write_bytes(b"secret")
    assert load_signing_key(str(tmp_path / "raw.key")) == raw
    assert load_signing_key(str(tmp_path / "hex.key")) == raw
    for name in ("short.key", "missing.key"):
        with pytest.raises(ConfigError) as info:
            MavlinkLink(settings("udpout:127.0.0.1:9", signing_key_file=str(tmp_path / name)))
        assert info.value.key == "mavlink.signing_key_file"


@pytest.mark.parametrize(("env_dialect", "expected"),
                         [(None, "ardupilotmega"), ("common", "common")])
def test_mavutil_speaks_mavlink2_with_ardupilots_dialect_and_loads_no_other(
    env_dialect: str | None, expected: str
) -> None:
    """In a fresh interpreter (the daemon's start): MAVLink 2, ArduPilot's dialect unless the
    user chose one, and neither pymavlink's "all" dialect nor its MAVLink 1 twin loaded, while
    an explicit import of the latter still works afterwards."""
    code = (
        "import json, sys\n"
        "from drivers.mavlink_link import import_mavutil\n"
        "m = import_mavutil()\n"
        "loaded = sorted(k for k in sys.modules if k.startswith('pymavlink.dialects.'))\n"
        "import importlib; later = importlib.import_module('pymavlink.dialects.v10.all').__name__\n"
        "print(json.dumps([m.mavlink.__name__, m.mavlink.WIRE_PROTOCOL_VERSION, loaded, later]))\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("MAVLINK_DIALECT", "MAVLINK20")}
    if env_dialect is not None:
        env["MAVLINK_DIALECT"] = env_dialect
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=60, check=True, cwd=Path(__file__).resolve().parents[1])
    name, wire, loaded, later = json.loads(out.stdout.strip().splitlines()[-1])
    assert name == f"pymavlink.dialects.v20.{expected}" and wire == "2.0"
    assert loaded == ["pymavlink.dialects.v10", "pymavlink.dialects.v20", name]
    assert later == "pymavlink.dialects.v10.all"


# ---- over real sockets ----------------------------------------------------------------------


def test_heartbeat_and_distance_sensor_over_udp() -> None:
    with FakeAutopilot(UdpServerTransport()) as autopilot:
        link = MavlinkLink(settings(autopilot.url, sensor_id=3, fov_horizontal_deg=60.0,
                                    fov_vertical_deg=45.0))
        with link, feeding(link):
            heartbeats = autopilot.wait_for("HEARTBEAT", count=2, timeout=4.0, where=from_link)
            sensors = autopilot.wait_for("DISTANCE_SENSOR", count=16, where=from_link)
            status = link.status()

    hb = heartbeats[0].msg
    assert (hb.type, hb.autopilot) == (18, 8)  # onboard controller, not an autopilot
    assert hb.get_msgbuf()[0] == 0xFD  # MAVLink 2 framing
    assert heartbeats[1].t - heartbeats[0].t == pytest.approx(1.0, abs=0.25)

    last = sensors[-1].msg
    assert abs(last.current_distance - 100 * READING.distance_m) <= 0.5  # cm, rounded
    assert (last.min_distance, last.max_distance) == (30, 800)
    assert (last.orientation, last.id, last.type) == (0, 3, 4)
    assert last.covariance == 9  # sigma 3 cm -> 9 cm^2
    assert last.signal_quality == 87
    assert last.horizontal_fov == pytest.approx(math.radians(60.0), rel=1e-6)
    assert last.vertical_fov == pytest.approx(math.radians(45.0), rel=1e-6)
    # time_boot_ms follows the autopilot's clock (learnt from its SYSTEM_TIME), minus transit.
    lag_ms = autopilot.boot_ms(sensors[-1].t) - last.time_boot_ms
    assert -5 <= lag_ms <= 100
    # At least 10 Hz: frames handed over at 20 Hz go out as they come (two would be a period
    # apart, on the limit). The median gap is robust to one late turn on a busy machine.
    gaps = [b.t - a.t for a, b in itertools.pairwise(sensors[5:])]
    assert statistics.median(gaps) == pytest.approx(0.05, abs=0.015)
    assert status.state == "connected"
    assert status.autopilot is not None
    assert status.autopilot.type == 12 and status.autopilot.sysid == 1
    assert json.loads(json.dumps(json_value(status)))  # ready for telemetry as it is


def test_too_close_goes_out_below_the_minimum_over_udp() -> None:
    """A net too close to resolve, on the wire: DISTANCE_SENSOR with a distance below its own
    min_distance, so ArduPilot reports OutOfRangeLow (proved against ArduSub SITL below);
    never a believable distance inside the range, never silence."""
    too_close = RangeReading(RangeStatus.TOO_CLOSE, t_capture=0.0, quality=0.9)
    with FakeAutopilot(UdpServerTransport()) as autopilot:
        link = MavlinkLink(settings(autopilot.url))
        with link, feeding(link, reading=too_close):
            sensors = autopilot.wait_for("DISTANCE_SENSOR", count=5, where=from_link)
    for r in sensors:
        assert r.msg.min_distance == 30 and r.msg.current_distance < r.msg.min_distance
        assert r.msg.current_distance == 29  # 1 cm below: ArduPilot's test is a strict '<'


def test_nothing_sent_without_a_valid_distance() -> None:
    with FakeAutopilot(UdpServerTransport()) as autopilot:
        link = MavlinkLink(settings(autopilot.url))
        link.set_range(RangeReading.none(time.monotonic()))
        with link:
            autopilot.wait_for("HEARTBEAT", count=1, where=from_link)
            with feeding(link, None):
                time.sleep(0.4)
            with pytest.raises(ValueError):  # a GOOD reading without a distance cannot exist
                RangeReading(RangeStatus.GOOD, 0.0, distance_m=math.nan)
            with feeding(link, RangeReading(RangeStatus.NONE, 0.0, 1.5, 0.01, 0.9)):
                time.sleep(0.4)
            status = link.status()
    assert autopilot.received("DISTANCE_SENSOR") == []
    assert status.sending_distance is False and status.sent["DISTANCE_SENSOR"] == 0


def test_stale_reading_is_not_repeated() -> None:
    with FakeAutopilot(UdpServerTransport()) as autopilot:
        link = MavlinkLink(settings(autopilot.url, max_age_s=0.3))
        with link:
            autopilot.wait_for("HEARTBEAT", count=1, where=from_link)
            t_frame = time.monotonic()
            link.set_range(fresh(READING, t_frame))
            autopilot.wait_for("DISTANCE_SENSOR", count=1)
            time.sleep(0.8)  # far beyond max_age: the reading is stale
            status = link.status()
    sent = autopilot.received("DISTANCE_SENSOR")
    # At 10 Hz a reading can be sent at most max_age * rate + 1 times, all within max_age.
    assert 1 <= len(sent) <= 4
    assert sent[-1].t - t_frame <= 0.3 + 0.05
    assert status.sending_distance is False


@pytest.mark.parametrize(("fps", "frames_per_send"), [(30.0, 2), (15.0, 1)])
def test_a_new_reading_goes_out_as_it_arrives(fps: float, frames_per_send: int) -> None:
    """Frames are sent as they are handed over, as many as keep them at most a period (0.1 s)
    apart: at 30 frames/s every second one, at 15 every one. A fixed 10 Hz schedule made a
    reading wait for its slot: on average half a frame interval (17 ms at 30 frames/s, 33 ms at
    15); the median wait is checked against half that."""
    handed_over: dict[int, float] = {}  # current_distance (cm) -> when the loop handed it over
    stop = threading.Event()

    def frame_loop(link: MavlinkLink) -> None:
        for i in range(200):  # 100..299 cm: each frame's reading is told apart by its value
            if stop.is_set():
                return
            now = time.monotonic()
            handed_over[100 + i] = now
            link.set_range(dataclasses.replace(READING, t_capture=now - 0.01,
                                               distance_m=(100 + i) / 100.0))
            stop.wait(1.0 / fps)

    with FakeAutopilot(UdpServerTransport()) as autopilot:
        link = MavlinkLink(settings(autopilot.url))
        with link:
            autopilot.wait_for("HEARTBEAT", count=1, where=from_link)
            thread = threading.Thread(target=frame_loop, args=(link,), name="test-frame-loop")
            thread.start()
            try:
                sensors = autopilot.wait_for("DISTANCE_SENSOR", count=30, where=from_link)
            finally:
                stop.set()
                thread.join()
    steady = sensors[8:]  # after the frame interval has been measured
    waits = [r.t - handed_over[r.msg.current_distance] for r in steady]
    assert statistics.median(waits) < 0.25 / fps, waits
    values = [r.msg.current_distance for r in steady]
    assert len(set(values)) >= 0.9 * len(values), values  # new readings, not repeats
    gaps = [b.t - a.t for a, b in itertools.pairwise(steady)]
    # Medians: one late turn of either thread on a busy machine must not decide the test.
    assert statistics.median(gaps) == pytest.approx(frames_per_send / fps, abs=0.2 / fps)


def test_autopilot_heartbeat_lost_and_back(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="drivers.mavlink_link")
    with FakeAutopilot(UdpServerTransport()) as autopilot:
        link = MavlinkLink(settings(autopilot.url))
        with link:
            assert link.status().state == "waiting"
            wait_status(link, "state", "connected")
            autopilot.heartbeats_enabled = False
            lost = wait_status(link, "state", "lost")
            time.sleep(0.3)  # several more loop turns while lost: still logged only once
            autopilot.heartbeats_enabled = True
            wait_status(link, "state", "connected")
    assert lost.heartbeat_age_s is not None and lost.heartbeat_age_s > 0.5
    messages = [r.getMessage() for r in caplog.records]
    assert sum("heartbeat lost" in m for m in messages) == 1
    assert sum("heartbeat back" in m for m in messages) == 1


def test_armed_is_what_the_last_heartbeat_said() -> None:
    """The web page's settings wait for a disarmed vehicle (settings_editor.ARMED): the link
    says armed from the autopilot's HEARTBEAT (base_mode's SAFETY_ARMED), and keeps its last
    word while the heartbeat is lost. It said None then, which unlocked the page: a mesh typo
    saved during a tether glitch reached the still-armed vehicle as ten times the distance
    when the heartbeat came back (pilot review). Heard disarmed again, it unlocks."""
    with FakeAutopilot(UdpServerTransport()) as autopilot:
        link = MavlinkLink(settings(autopilot.url))
        with link:
            assert link.status().armed is None  # no autopilot heard yet
            wait_status(link, "armed", False)
            autopilot.armed = True
            wait_status(link, "armed", True)
            autopilot.armed = False
            wait_status(link, "armed", False)
            autopilot.armed = True
            wait_status(link, "armed", True)
            autopilot.heartbeats_enabled = False
            lost = wait_status(link, "state", "lost")
            assert lost.armed is True
            autopilot.armed = False
            autopilot.heartbeats_enabled = True
            wait_status(link, "armed", False)


def test_own_echo_and_other_components_are_not_the_autopilot() -> None:
    with FakeAutopilot(UdpServerTransport(), echo=True) as autopilot:
        autopilot.heartbeats_enabled = False
        link = MavlinkLink(settings(autopilot.url))
        with link, feeding(link):
            autopilot.wait_for("DISTANCE_SENSOR", count=5)
            # A ground station and BlueOS's own onboard computer share the router.
            autopilot.send_heartbeat_as(255, 190, mav_type=6, autopilot=8)
            autopilot.send_heartbeat_as(1, 191, mav_type=18, autopilot=8)
            # An autopilot of another vehicle (system id 2) is not ours either.
            autopilot.send_heartbeat_as(2, 1, mav_type=12, autopilot=3)
            deadline = time.monotonic() + 5.0
            while link.status().received < 3 and time.monotonic() < deadline:
                time.sleep(0.01)
            time.sleep(0.2)  # more echoes arrive meanwhile
            status = link.status()
    # Dozens of our own messages came back; only the three foreign heartbeats count.
    assert status.received == 3
    assert status.state == "waiting" and status.autopilot is None


def test_tcp_link_survives_router_restart(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG, logger="drivers.mavlink_link")
    first = FakeAutopilot(TcpServerTransport()).start()
    port = first.transport.port  # type: ignore[attr-defined]
    link = MavlinkLink(settings(first.url))
    try:
        with link, feeding(link):
            first.wait_for("DISTANCE_SENSOR", count=3)
            wait_status(link, "state", "connected")
            assert link.status().sending_distance
            first.close()  # router gone: connection closed, then refused
            wait_status(link, "transport", "down")
            # Nothing goes out: the page and the monitor showed "1.42 m, to the autopilot".
            assert link.status().sending_distance is False
            deadline = time.monotonic() + 5.0
            while link.status().errors < 4 and time.monotonic() < deadline:
                time.sleep(0.02)
            assert link.status().state == "lost"
            with FakeAutopilot(TcpServerTransport(port)) as second:
                second.wait_for("DISTANCE_SENSOR", count=3, timeout=5.0)
                status = wait_status(link, "state", "connected")
                warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    finally:
        first.close()
    assert status.reconnects == 1 and status.errors >= 4
    assert sum("retrying" in r.getMessage() for r in warnings) == 1  # once per outage
    assert sum("up again" in r.getMessage() for r in caplog.records) == 1


def test_link_waits_for_a_router_that_starts_later() -> None:
    port = free_port(socket.SOCK_STREAM)
    link = MavlinkLink(settings(f"tcp:127.0.0.1:{port}"))
    link.start()
    try:
        # The frame loop keeps handing over values while nothing is listening.
        for _ in range(5):
            link.set_range(fresh(READING, time.monotonic()))
            time.sleep(0.05)
        status = link.status()
        assert (status.state, status.transport) == ("waiting", "down")
        assert status.errors >= 1
        with FakeAutopilot(TcpServerTransport(port)) as autopilot, feeding(link):
            autopilot.wait_for("DISTANCE_SENSOR", count=2)
            wait_status(link, "state", "connected")
    finally:
        link.close()
    assert not any(t.name == "netpose-mavlink" for t in threading.enumerate())


def test_serial_link_through_a_pseudo_terminal() -> None:
    with FakeAutopilot(PtyTransport()) as autopilot:
        link = MavlinkLink(settings(autopilot.url, baud=57600))
        with link, feeding(link):
            sensors = autopilot.wait_for("DISTANCE_SENSOR", count=5)
            wait_status(link, "state", "connected")
    assert all(r.msg.current_distance == 235 for r in sensors)


def test_a_serial_path_with_colons_is_opened_as_serial(tmp_path: Path) -> None:
    """A Pi's stable names for a USB autopilot, /dev/serial/by-path/...-usb-0:1.3:1.0-port0,
    hold colons, and pymavlink's URL parser takes any device with a colon for UDP
    ("UDP ports must be specified as host:port"): no DISTANCE_SENSOR ever went out."""
    with FakeAutopilot(PtyTransport()) as autopilot:
        by_path = tmp_path / "platform-fd500000.pcie-pci-0000:01:00.0-usb-0:1.3:1.0-port0"
        by_path.symlink_to(autopilot.url)
        link = MavlinkLink(settings(f"serial:{by_path}", baud=57600))
        with link, feeding(link):
            sensors = autopilot.wait_for("DISTANCE_SENSOR", count=3)
            wait_status(link, "state", "connected")
    assert all(r.msg.current_distance == 235 for r in sensors)


def test_unplugged_serial_device_is_retried_and_logged_once_per_reason(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, logger="drivers.mavlink_link")
    autopilot = FakeAutopilot(PtyTransport()).start()
    link = MavlinkLink(settings(autopilot.url))
    with link, feeding(link):
        try:
            wait_status(link, "state", "connected")
        finally:
            autopilot.close()  # both ends of the pty vanish, like a USB autopilot unplugged
        status = wait_status(link, "transport", "down")
        deadline = time.monotonic() + 5.0
        while link.status().errors < 3 and time.monotonic() < deadline:
            time.sleep(0.02)
        status = link.status()
    assert status.state == "lost" and status.errors >= 3
    assert f"cannot open {autopilot.url}: No such file" in status.last_error
    # Once per reason, not per retry: the loss, then why it cannot open again.
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 2 and "lost" in warnings[0], warnings
    assert "still down, now" in warnings[1] and "No such file" in warnings[1]


def test_a_new_reason_for_the_same_outage_is_logged(
    tmp_path: Path, caplog: pytest.LogCaptureFixture,
) -> None:
    """Only the first failure of an outage was logged: when the reason then changed (the
    device appeared, but the unit's sandbox refused it), the journal still said "No such file
    or directory" and nothing pointed at the real fault. Each new reason is logged once."""
    caplog.set_level(logging.INFO, logger="drivers.mavlink_link")
    device = tmp_path / "ttyACM0"
    link = MavlinkLink(settings(f"serial:{device}"))
    with link:
        deadline = time.monotonic() + 5.0
        while link.status().errors < 2 and time.monotonic() < deadline:
            time.sleep(0.02)
        device.mkdir()  # now it exists, and opening it fails another way
        while "Is a directory" not in link.status().last_error and time.monotonic() < deadline:
            time.sleep(0.02)
        while link.status().errors < 6 and time.monotonic() < deadline:
            time.sleep(0.02)
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 2, warnings
    assert "No such file" in warnings[0] and "Is a directory" in warnings[1]


def test_bytes_that_are_not_mavlink_on_a_serial_port_point_at_the_baud_rate(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """At another baud rate than the autopilot's SERIALn_BAUD every byte arrives garbled: the
    link said "open", then "waiting" for ever, and nothing pointed at mavlink.baud. What a UART
    at the wrong rate delivers (bytes, none of them a MAVLink frame) is said once, naming it."""
    caplog.set_level(logging.INFO, logger="drivers.mavlink_link")
    port = PtyTransport()
    stop = threading.Event()
    rng = np.random.default_rng(5)

    def garbled() -> None:
        while not stop.wait(0.02):
            # No 0xFD/0xFE start bytes: nothing for the parser to try.
            noise = rng.integers(0, 0xF0, 64, dtype=np.uint8).tobytes()
            with contextlib.suppress(OSError):
                port.write(noise)

    writer = threading.Thread(target=garbled, daemon=True)
    writer.start()
    try:
        link = MavlinkLink(settings(port.url, baud=57600))
        with link:
            deadline = time.monotonic() + 5.0
            while "baud" not in (link.status().last_error or "") and time.monotonic() < deadline:
                time.sleep(0.05)
            status = link.status()
    finally:
        stop.set()
        writer.join(timeout=2.0)
        port.close()
    assert "mavlink.baud (57600)" in (status.last_error or ""), status
    said = [r.getMessage() for r in caplog.records if "baud" in r.getMessage()]
    assert len(said) == 1 and "SERIALn_BAUD" in said[0], said


def test_udpin_answers_the_autopilot() -> None:
    with FakeAutopilot(UdpClientTransport()) as autopilot:
        link = MavlinkLink(settings(autopilot.url))
        with link, feeding(link):
            sensors = autopilot.wait_for("DISTANCE_SENSOR", count=3)
            wait_status(link, "state", "connected")
    assert sensors[0].msg.current_distance == 235


def test_net_plane_can_be_switched_off() -> None:
    plane = NetPlane.from_distance_normal(0.0, 1.2, (0.1, 0.0, -0.995))
    with FakeAutopilot(UdpServerTransport()) as autopilot:
        link = MavlinkLink(settings(autopilot.url, send_net_plane=False))
        with link, feeding(link, plane=plane):
            autopilot.wait_for("DISTANCE_SENSOR", count=5)
            assert link.status().net_plane == "off"
    assert autopilot.received("DEBUG_VECT") == []


def test_net_plane_fields_time_and_staleness() -> None:
    """DEBUG_VECT NET_PLANE: the foot vector in the camera frame, stamped with the capture time
    on the autopilot's clock; a plane older than max_age_s is never sent."""
    normal = (0.17364818, 0.0, -0.98480775)  # net turned 10 degrees, facing the camera
    plane = NetPlane.from_distance_normal(0.0, 1.25, normal)
    with FakeAutopilot(UdpServerTransport()) as autopilot:
        link = MavlinkLink(settings(autopilot.url))
        with link:
            # Once the autopilot's clock is known (before, the link's own start is the origin).
            wait_status(link, "state", "connected")
            with feeding(link, plane=plane):
                first = autopilot.wait_for("DEBUG_VECT", count=3)
                assert link.status().net_plane == "sent"
            link.set_net_plane(dataclasses.replace(plane, t_capture=time.monotonic() - 1.0))
            time.sleep(0.2)  # anything already on its way has arrived
            count = len(autopilot.received("DEBUG_VECT"))
            time.sleep(0.5)
            stale = autopilot.received("DEBUG_VECT")[count:]
            status = link.status()
    msg = first[-1].msg
    assert msg.name == "NET_PLANE"
    assert (msg.x, msg.y, msg.z) == pytest.approx((-1.25 * normal[0], 0.0, -1.25 * normal[2]),
                                                  rel=1e-6)
    assert math.sqrt(msg.x**2 + msg.y**2 + msg.z**2) == pytest.approx(1.25, rel=1e-6)
    lag_us = autopilot.boot_ms(first[-1].t) * 1000 - msg.time_usec
    assert -5_000 <= lag_us <= 100_000  # the frame's capture time, not the send time
    assert stale == [] and status.sending_net_plane is False
    assert status.net_plane.startswith("newest plane 1.")  # and says why, for the page


def test_no_net_plane_is_stamped_in_a_rebooted_autopilots_future() -> None:
    """ArduSub rebooted (SITL: up again in 1.3 s) while netpose ran: its heartbeats came back
    at once, its time_boot_ms streams 1.2 s later, and until then every NET_PLANE went out
    stamped on the old boot clock, 19 s in the new one's future (the old uptime, hours on a
    vehicle). The link now asks the autopilot's clock itself (TIMESYNC, as ArduPilot answers)
    and holds the plane while the clock is not confirmed: nothing in the future, and planes
    again soon after the reboot."""
    plane = NetPlane.from_distance_normal(0.0, 1.25, (0.0, 0.0, -1.0))
    with FakeAutopilot(UdpServerTransport()) as autopilot:
        link = MavlinkLink(settings(autopilot.url))
        with link:
            wait_status(link, "state", "connected")
            with feeding(link, plane=plane):
                autopilot.wait_for("DEBUG_VECT", count=3)
                autopilot.reboot(down_s=1.3, streams_after_s=1.2)
                rebooted_at = time.monotonic() - 1.2
                time.sleep(1.0)
            planes = [r for r in autopilot.received("DEBUG_VECT") if r.t >= rebooted_at]
    assert planes, "no net plane after the reboot"
    ahead_ms = [r.msg.time_usec / 1000 - autopilot.boot_ms(r.t) for r in planes]
    assert max(ahead_ms) <= 5.0, max(ahead_ms)
    assert planes[0].t - rebooted_at <= 1.0  # asked for, not waited for the streams


def test_signed_link_is_accepted_only_with_the_right_key(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    key = os.urandom(32)
    (tmp_path / "good.key").write_bytes(key)
    (tmp_path / "bad.key").write_bytes(bytes(32))
    with FakeAutopilot(UdpServerTransport(), signing_key=key) as autopilot:
        link = MavlinkLink(settings(autopilot.url, signing_key_file=str(tmp_path / "good.key")))
        with link, feeding(link):
            sensors = autopilot.wait_for("DISTANCE_SENSOR", count=3)
            wait_status(link, "state", "connected")
    assert all(r.msg.get_signed() for r in sensors)

    with FakeAutopilot(UdpServerTransport(), signing_key=key) as autopilot, \
            caplog.at_level(logging.INFO, logger="drivers.mavlink_link"):
        link = MavlinkLink(settings(autopilot.url, signing_key_file=str(tmp_path / "bad.key")))
        with link, feeding(link):
            time.sleep(1.5)
            status = link.status()
    assert status.sent["DISTANCE_SENSOR"] >= 3
    assert autopilot.received() == []  # every message rejected by the signature check
    # Said once, naming the key to fix, and in the status: the autopilot's own messages carry
    # another key's signature, so it rejects netpose's (it said "connected" and nothing more).
    warned = [r.getMessage() for r in caplog.records if "another key" in r.getMessage()]
    assert len(warned) == 1 and "signing_key_file" in warned[0], warned
    assert "signing_key_file" in status.last_error


def test_recording_link_stands_in_for_the_daemon() -> None:
    link = RecordingAutopilotLink()
    with link:
        link.set_range(fresh(READING, 1.0))
        link.set_range(RangeReading.none(2.0))
        assert link.status().state == "connected"
    assert [r.status for r in link.ranges] == [RangeStatus.GOOD, RangeStatus.NONE]
    assert link.sent == [fresh(READING, 1.0)] and link.closed


# ---- ArduSub SITL (only when its binary is named) -------------------------------------------

SITL = os.environ.get("NETPOSE_ARDUSUB_SITL")
# RNGFND1_MAX in this file; ArduSub's default (7 m) would show up as 700 cm in its report.
SITL_MIN_CM, SITL_MAX_CM = 20, 1000


def sitl_log_tail(path: Path, chars: int = 2000) -> str:
    """The end of SITL's console output, for a failure message."""
    try:
        return path.read_text(errors="replace")[-chars:]
    except OSError as exc:
        return f"(no SITL log: {exc})"


@dataclasses.dataclass
class Sitl:
    """A running ArduSub SITL: our link on SERIAL0, an observer (acting as the GCS) on SERIAL1."""

    link: MavlinkLink
    observer: Any
    log_path: Path

    def context(self) -> str:
        return f"SITL output ends:\n{sitl_log_tail(self.log_path)}"


@contextmanager
def ardusub_sitl(tmp_path: Path, settings_for: Any, *, lua: str | None = None,
                 reading: RangeReading = READING, instance_of_ours: str = "1",
                 other_params: str = "", probe_port: bool = False) -> Iterator[Sitl]:
    """ArduSub SITL with a MAVLink rangefinder (and, optionally, a Lua script), our link
    feeding `reading`, and an observer that has sent its heartbeat (ArduSub forwards to a link
    only after hearing from it). Verified against ArduSub 4.7.0-dev SITL: `--model vectored`,
    SERIAL0 is TCP 5760 + 10 * instance (the link), SERIAL1 is + 2 (the observer), and with
    `probe_port` SERIAL2 is + 4 (for `mavlink-check`); unknown names in a `--defaults` file are
    skipped silently. netpose's rangefinder is RNGFND`instance_of_ours`; `other_params` are
    more lines of the defaults file."""
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    instance = int(os.environ.get("NETPOSE_ARDUSUB_SITL_INSTANCE", "7"))
    base_port = 5760 + 10 * instance
    # Both parameter namings: 4.5 knows the *_CM pair, 4.7 the metre pair (since Jan 2025);
    # AP_Param::read_param_defaults_file skips names the firmware does not know.
    n = instance_of_ours
    defaults = (
        f"RNGFND{n}_TYPE 10\nRNGFND{n}_ORIENT 0\nRNGFND{n}_MIN_CM {SITL_MIN_CM}\n"
        f"RNGFND{n}_MAX_CM {SITL_MAX_CM}\nRNGFND{n}_MIN {SITL_MIN_CM / 100}\n"
        f"RNGFND{n}_MAX {SITL_MAX_CM / 100}\n{other_params}"
    )
    if lua is not None:
        defaults += "SCR_ENABLE 1\n"
        (tmp_path / "scripts").mkdir()
        (tmp_path / "scripts" / "netpose_test.lua").write_text(lua)
    (tmp_path / "netpose.parm").write_text(defaults)
    model = os.environ.get("NETPOSE_ARDUSUB_MODEL", "vectored")
    log_path = tmp_path / "sitl.log"
    # Never --serial9 (crashes with --defaults).
    serials = [(f"--serial{k}", "tcp:4" if k == 2 and probe_port else "none")
               for k in range(2, 9)]
    with log_path.open("wb") as log_file:
        sitl = subprocess.Popen(
            [str(SITL), "--model", model, "--speedup", "1", "-I", str(instance), "-w",
             "--defaults", str(tmp_path / "netpose.parm"),
             "--home", "33.810313,-118.393867,0,185",
             *[arg for pair in serials for arg in pair]],
            cwd=tmp_path, stdout=log_file, stderr=subprocess.STDOUT,
        )
    link = MavlinkLink(settings_for(f"tcp:127.0.0.1:{base_port}"))
    observer = None
    try:
        link.start()
        with feeding(link, reading):
            wait_status(link, "state", "connected", timeout=60.0)
            deadline = time.monotonic() + 30.0
            while observer is None:
                try:
                    observer = mavutil.mavlink_connection(
                        f"tcp:127.0.0.1:{base_port + 2}", source_system=255, retries=0)
                except OSError:
                    if time.monotonic() > deadline:
                        raise
                    time.sleep(0.5)
            observer.wait_heartbeat(timeout=30)
            observer.mav.heartbeat_send(6, 8, 0, 0, 0)  # MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID
            yield Sitl(link, observer, log_path)
    finally:
        link.close()
        if observer is not None:
            observer.close()
        sitl.terminate()
        try:
            sitl.wait(timeout=10)
        except subprocess.TimeoutExpired:
            sitl.kill()
            sitl.wait()


def sitl_forward_report(sitl: Sitl) -> Any:
    """ArduSub's own forward DISTANCE_SENSOR (component 1, not ours routed through it), asked
    for at 10 Hz; None if none comes within 30 s."""
    from pymavlink import mavutil

    sitl.observer.mav.command_long_send(
        1, 1, mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
        mavutil.mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR, 100_000, 0, 0, 0, 0, 0)
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline:
        msg = sitl.observer.recv_match(type="DISTANCE_SENSOR", blocking=True, timeout=1.0)
        if msg is not None and msg.get_srcComponent() == 1 and msg.orientation == 0:
            return msg
    return None


def sitl_mavlink_check(*extra: str) -> subprocess.CompletedProcess[str]:
    """`netpose mavlink-check` on the SITL's SERIAL2 (`ardusub_sitl(probe_port=True)`), with
    the SITL's range limits."""
    port = 5760 + 10 * int(os.environ.get("NETPOSE_ARDUSUB_SITL_INSTANCE", "7")) + 4
    return subprocess.run(
        [sys.executable, "-m", "service.cli", "mavlink-check", "--url", f"tcp:127.0.0.1:{port}",
         "--min-distance", str(SITL_MIN_CM / 100), "--max-distance", str(SITL_MAX_CM / 100),
         "--timeout", "20", *extra],
        capture_output=True, text=True, timeout=90, cwd=Path(__file__).parents[1],
    )


def sitl_settings(url: str) -> MavlinkSettings:
    return MavlinkSettings(url=url, min_distance_m=SITL_MIN_CM / 100,
                           max_distance_m=SITL_MAX_CM / 100)


@pytest.mark.skipif(not SITL, reason="set NETPOSE_ARDUSUB_SITL to an ArduSub SITL binary")
@pytest.mark.timeout(180)
def test_ardusub_sitl_reports_our_distance(tmp_path: Path) -> None:
    """ArduSub's own DISTANCE_SENSOR (component 1) reports our distance within 1 cm."""

    sent_cm = distance_sensor_fields(READING, sitl_settings("tcp:127.0.0.1:1")).current_distance
    with ardusub_sitl(tmp_path, sitl_settings) as sitl:
        echoed = sitl_forward_report(sitl)
        context = sitl.context()
    assert echoed is not None, f"ArduSub never reported a forward DISTANCE_SENSOR\n{context}"
    # It reports min(its parameter, our message) for the limits: 1000 cm proves the defaults
    # file was applied (ArduSub's own RNGFND1_MAX is 7 m).
    assert (echoed.min_distance, echoed.max_distance) == (SITL_MIN_CM, SITL_MAX_CM), context
    # ArduPilot stores current_distance * 0.01 as a float and truncates float * 100 back to
    # whole cm, so some values (235 among them) come back 1 cm low; never anything else.
    assert echoed.current_distance in (sent_cm, sent_cm - 1), (echoed.current_distance, sent_cm)
    # The requirement: within 1 cm of the distance handed to the link.
    assert abs(echoed.current_distance - 100 * READING.distance_m) <= 1.0


@pytest.mark.skipif(not SITL, reason="set NETPOSE_ARDUSUB_SITL to an ArduSub SITL binary")
@pytest.mark.timeout(180)
def test_ardusub_sitl_takes_our_distance_beside_a_downward_altimeter(tmp_path: Path) -> None:
    """A BlueROV2 keeps its Ping altimeter on RNGFND1 (here SITL's simulated rangefinder,
    type 100, facing down); netpose's readings go to RNGFND2. ArduSub reports our forward
    distance, and `netpose mavlink-check` finds the vehicle ready without touching RNGFND1."""

    sent_cm = distance_sensor_fields(READING, sitl_settings("tcp:127.0.0.1:1")).current_distance
    with ardusub_sitl(tmp_path, sitl_settings, instance_of_ours="2", probe_port=True,
                      other_params="RNGFND1_TYPE 100\nRNGFND1_ORIENT 25\n") as sitl:
        forward = sitl_forward_report(sitl)
        check = sitl_mavlink_check()
        context = sitl.context()
    assert forward is not None, f"ArduSub never reported a forward DISTANCE_SENSOR\n{context}"
    assert forward.current_distance in (sent_cm, sent_cm - 1), (forward.current_distance, sent_cm)
    assert check.returncode == 0, check.stdout + check.stderr
    assert "RNGFND1_TYPE     100" in check.stdout and "RNGFND2_TYPE     10" in check.stdout


@pytest.mark.skipif(not SITL, reason="set NETPOSE_ARDUSUB_SITL to an ArduSub SITL binary")
@pytest.mark.timeout(180)
def test_ardusub_sitl_answers_the_check_about_every_instance(tmp_path: Path) -> None:
    """ArduSub queues 20 parameter requests and drops the rest: asked for all at once, the
    check never heard of RNGFND7 and later, so a second forward sensor on RNGFND8 went unseen
    ("Ready") and SCR_ENABLE = 1 was advised when it was 1."""
    with ardusub_sitl(tmp_path, sitl_settings, instance_of_ours="2", probe_port=True,
                      other_params="RNGFND1_TYPE 100\nRNGFND1_ORIENT 25\nRNGFND8_TYPE 100\n"
                                   "RNGFND8_ORIENT 0\nSCR_ENABLE 1\n") as sitl:
        check = sitl_mavlink_check("--net-hold")
        context = sitl.context()
    assert check.returncode == 3, check.stdout + check.stderr + context
    changes = check.stdout.split("To change:")[1]
    assert "RNGFND8 (type 100) also faces forward" in changes, check.stdout
    assert "set SCR_ENABLE" not in changes, check.stdout


# ArduPilot's RangeFinder::Status, as Lua's rangefinder:status_orient() returns it.
RANGEFINDER_STATUS = {0: "NotConnected", 1: "NoData", 2: "OutOfRangeLow", 3: "OutOfRangeHigh",
                      4: "Good"}
STATUS_LUA = """
-- netpose test: report the forward rangefinder's status to the GCS twice a second.
function update()
  gcs:send_text(6, string.format("RFND %d %.2f", rangefinder:status_orient(0),
                                 rangefinder:distance_orient(0)))
  return update, 500
end
return update, 2000
"""


@pytest.mark.skipif(not SITL, reason="set NETPOSE_ARDUSUB_SITL to an ArduSub SITL binary")
@pytest.mark.timeout(180)
def test_ardusub_sitl_reads_too_close_as_out_of_range_low(tmp_path: Path) -> None:
    """A net too close to resolve is a TOO_CLOSE reading: ArduSub's rangefinder must call it
    OutOfRangeLow (the truth: something is there, nearer than measurable), not NoData (what
    silence gives, the same as open water). Checked with ArduPilot's own Lua binding."""
    too_close = RangeReading(RangeStatus.TOO_CLOSE, t_capture=0.0, quality=0.9)
    seen: list[str] = []
    with ardusub_sitl(tmp_path, sitl_settings, lua=STATUS_LUA, reading=too_close) as sitl:
        deadline = time.monotonic() + 40.0
        while time.monotonic() < deadline and seen.count("OutOfRangeLow") < 3:
            msg = sitl.observer.recv_match(type="STATUSTEXT", blocking=True, timeout=1.0)
            if msg is not None and msg.text.startswith("RFND "):
                seen.append(RANGEFINDER_STATUS.get(int(msg.text.split()[1]), msg.text))
        context = sitl.context()
    assert seen.count("OutOfRangeLow") >= 3, f"{seen}\n{context}"
    assert "NoData" not in seen[-3:]


def test_pilot_notices_go_out_as_statustext_in_order() -> None:
    with FakeAutopilot(UdpServerTransport()) as autopilot:
        link = MavlinkLink(settings(autopilot.url))
        with link:
            autopilot.wait_for("HEARTBEAT", count=1, where=from_link)
            link.notify_pilot("netpose: net too close to measure")
            link.notify_pilot("x" * 80, severity=5)
            texts = autopilot.wait_for("STATUSTEXT", count=2)
    assert [(r.msg.severity, r.msg.text) for r in texts] == [
        (4, "netpose: net too close to measure"), (5, "x" * 50)]
    assert link.status().sent["STATUSTEXT"] == 2


def test_a_pilot_notice_queued_as_the_service_stops_still_goes_out() -> None:
    """The daemon's close flushes the last hole's text to the link, then closes the link at
    once: texts went out only on the link's 10 Hz schedule, so that one was lost."""
    with FakeAutopilot(UdpServerTransport()) as autopilot:
        link = MavlinkLink(settings(autopilot.url, rate_hz=4.0))
        with link:
            autopilot.wait_for("HEARTBEAT", count=1, where=from_link)
            time.sleep(0.05)  # just after a scheduled turn: the next is 0.2 s away
            link.notify_pilot("netpose: hole 1 ~6x4 cm ahead at 1.1 m")
        texts = autopilot.wait_for("STATUSTEXT", count=1)
    assert texts[0].msg.text == "netpose: hole 1 ~6x4 cm ahead at 1.1 m"


def test_a_pilot_text_that_waited_out_a_link_outage_is_not_sent_late(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Texts queued while the router was away went out in one burst when it came back: "net
    too close to measure, back off" reached the ground station 20 s late, an instruction about
    a moment long gone. A text that waited longer than TEXT_MAX_WAIT_S is dropped (and said in
    the log); one queued just before the link came back goes out. (The limit is shortened
    here so that the test waits less.)"""
    from drivers import mavlink_link

    monkeypatch.setattr(mavlink_link, "TEXT_MAX_WAIT_S", 0.5)
    port = free_port(socket.SOCK_STREAM)
    link = MavlinkLink(settings(f"tcp:127.0.0.1:{port}"))
    with link:
        link.notify_pilot("netpose: net too close to measure, back off")
        time.sleep(0.8)  # the router is away longer than the text is news
        link.notify_pilot("netpose: net ~1.9 m, too little in view")
        with FakeAutopilot(TcpServerTransport(port)) as autopilot:
            texts = autopilot.wait_for("STATUSTEXT", count=1, timeout=5.0)
            time.sleep(0.3)
            texts = autopilot.received("STATUSTEXT")
            dropped = link.status().texts_dropped
    assert [t.msg.text for t in texts] == ["netpose: net ~1.9 m, too little in view"]
    assert dropped == 1  # said, so the daemon says again what still holds


def test_a_frame_without_the_net_is_sent_as_a_zero_plane() -> None:
    """So the net-hold applet stops on the first frame without the net, not at its timeout."""
    with FakeAutopilot(UdpServerTransport()) as autopilot:
        link = MavlinkLink(settings(autopilot.url))
        with link, feeding(link, plane=NetPlane.none(0.0)):
            zero = autopilot.wait_for("DEBUG_VECT", count=2)[-1].msg
            status = link.status()
    assert (zero.name, zero.x, zero.y, zero.z) == ("NET_PLANE", 0.0, 0.0, 0.0)
    assert status.sending_net_plane is False  # nothing valid is being sent
    assert status.net_plane == "zero vector: the newest frame did not confirm the net"


def test_a_flapping_net_plane_is_sent_frame_by_frame_but_logged_once_a_second(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A loaded Pi that finds the net in every other frame: the applet gets every frame's
    plane (a real one, then a zero vector), but the log gets at most one line a second about
    it (issue 13), naming what happened rather than "not fresh"."""
    caplog.set_level(logging.INFO, logger="drivers.mavlink_link")
    plane = NetPlane.from_distance_normal(0.0, 1.2, (0.1, 0.0, -0.995))
    stop = threading.Event()
    with FakeAutopilot(UdpServerTransport()) as autopilot:
        link = MavlinkLink(settings(autopilot.url))

        def flapping_frames() -> None:
            for k in itertools.count():
                now = time.monotonic()
                link.set_range(fresh(READING, now))
                shown = plane if k % 2 == 0 else NetPlane.none(now)
                link.set_net_plane(dataclasses.replace(shown, t_capture=now))
                if stop.wait(0.03):
                    return

        feeder = threading.Thread(target=flapping_frames)
        with link:
            feeder.start()
            started = time.monotonic()
            time.sleep(2.5)
            stop.set()
            feeder.join()
            elapsed = time.monotonic() - started
    vectors = [r.msg for r in autopilot.received("DEBUG_VECT")]
    zeros = sum((v.x, v.y, v.z) == (0.0, 0.0, 0.0) for v in vectors)
    assert zeros >= 3 and len(vectors) - zeros >= 3  # both kinds reach the autopilot
    lines = [r.getMessage() for r in caplog.records if "net plane" in r.getMessage()]
    assert 1 <= len(lines) <= math.ceil(elapsed) + 1, lines
    assert not any("not fresh" in line for line in lines), lines


@pytest.mark.parametrize("ppm", [-100.0, 100.0])
def test_capture_stamps_follow_an_autopilot_clock_that_drifts(ppm: float) -> None:
    """The autopilot's boot is learnt from its messages' time_boot_ms; keeping the earliest
    estimate (the least transit in it) let the stamps run ahead of a clock a little slower than
    ours, 0.36 s after 1 h at 100 ppm and up to 1 s before a re-base: a net plane stamped in
    the autopilot's future, which the net-hold applet cannot age. Followed now, whichever way
    the crystal errs; transit (2-12 ms here) still only ever makes a stamp earlier."""
    now = {"t": 1000.0}
    link = MavlinkLink(settings("udpout:127.0.0.1:9"), clock=lambda: now["t"])
    boot = 900.0  # on our clock, the instant the autopilot booted
    rate = 1.0 + ppm * 1e-6  # autopilot seconds per second of ours
    for i in range(3 * 3600):  # SYSTEM_TIME at 1 Hz for three hours
        now["t"] = 1000.0 + i
        transit = 0.002 + 0.01 * ((i * 7919) % 13) / 13.0
        autopilot_s = (now["t"] - transit - boot) * rate
        link._update_boot_time(now["t"] - autopilot_s, now["t"])
    capture = now["t"] - 0.05
    true_ms = (capture - boot) * rate * 1000.0
    ahead_ms = link._autopilot_time_ms(capture) - true_ms
    assert -15.0 <= ahead_ms <= 1.0
