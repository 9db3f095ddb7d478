"""`netpose mavlink-check` against the recording fake autopilot over loopback UDP and TCP."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from drivers.mavlink_link import MavlinkLink
from drivers.mavlink_probe import (
    RANGEFINDER_INSTANCES,
    AutopilotReport,
    advise,
    instance_params,
)
from drivers.mavlink_settings import MavlinkSettings
from service.cli import main
from tests.fake_autopilot import (
    FakeAutopilot,
    PtyTransport,
    TcpServerTransport,
    UdpServerTransport,
)
from tests.test_mavlink_link import wait_status

pytestmark = pytest.mark.timeout(60)

ARDUSUB_45_DEFAULTS = {  # cm naming, rangefinder off, SURFTRAK's quality threshold
    "RNGFND1_TYPE": 0, "RNGFND1_ORIENT": 25, "RNGFND1_MIN_CM": 50, "RNGFND1_MAX_CM": 700,
    "RNGFND_SQ_MIN": 90, "SCR_ENABLE": 0,
}
READY_47 = {  # metre naming, set up for a forward MAVLink rangefinder
    "RNGFND1_TYPE": 10, "RNGFND1_ORIENT": 0, "RNGFND1_MIN": 0.2, "RNGFND1_MAX": 10,
    "RNGFND_SQ_MIN": 0, "SCR_ENABLE": 1, "NETH_ENABLE": 1, "NETH_DIST": 1.0,
}


def test_reports_identity_and_what_to_change(capsys: pytest.CaptureFixture[str]) -> None:
    with FakeAutopilot(UdpServerTransport(), params=ARDUSUB_45_DEFAULTS) as autopilot:
        code = main(["mavlink-check", "--url", autopilot.url, "--timeout", "1"])
        requests = autopilot.received("PARAM_REQUEST_READ")
    out = capsys.readouterr().out
    assert code == 3
    assert "MAV_TYPE_SUBMARINE (12)" in out and "firmware 4.5.3" in out
    assert "RNGFND1_MIN_CM   50" in out and "RNGFND1_MIN      (not on this firmware)" in out
    assert "set RNGFND1_TYPE = 10" in out
    assert "set RNGFND1_ORIENT = 0 (forward; now 25)" in out
    assert "set RNGFND1_MIN_CM = 30 (now 50 cm)" in out  # default minimum 0.3 m
    assert "set RNGFND1_MAX_CM = 800 (now 700 cm)" in out  # default maximum 8 m
    assert "SCR_ENABLE" not in out  # net hold not asked for
    # Every instance's type was asked for by name, from netpose's own identity, and the
    # settings of those that exist (here RNGFND1 only).
    asked = {r.msg.param_id for r in requests}
    assert asked >= {f"RNGFND{n}_TYPE" for n in RANGEFINDER_INSTANCES} | {"RNGFND_SQ_MIN"}
    assert asked >= set(instance_params("1")) and "RNGFND2_ORIENT" not in asked
    assert {r.src for r in requests} == {(1, 197)}


def test_ready_vehicle_with_metre_parameters_over_tcp(capsys: pytest.CaptureFixture[str]) -> None:
    with FakeAutopilot(TcpServerTransport(), params=READY_47) as autopilot:
        code = main(["mavlink-check", "--url", autopilot.url, "--timeout", "2", "--net-hold"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "RNGFND1_MAX      10" in out and "NETH_DIST        1" in out
    assert "Ready" in out and "To change" not in out


def test_downward_and_net_hold_advice(capsys: pytest.CaptureFixture[str]) -> None:
    params = {**ARDUSUB_45_DEFAULTS, "RNGFND1_TYPE": 10, "RNGFND1_MIN_CM": 20,
              "RNGFND1_MAX_CM": 1000}
    with FakeAutopilot(UdpServerTransport(), params=params) as autopilot:
        code = main(["mavlink-check", "--url", autopilot.url, "--timeout", "1",
                     "--orientation", "25", "--net-hold"])
    out = capsys.readouterr().out
    assert code == 3
    assert "set SCR_ENABLE = 1" in out
    assert "RNGFND1_ORIENT" not in out.split("To change:")[1]  # 25 is what we send
    assert "confidence below 0.90 is not used" in out


def test_net_hold_applet_missing(capsys: pytest.CaptureFixture[str]) -> None:
    params = {k: v for k, v in READY_47.items() if not k.startswith("NETH_")}
    with FakeAutopilot(UdpServerTransport(), params=params) as autopilot:
        code = main(["mavlink-check", "--url", autopilot.url, "--timeout", "1", "--net-hold"])
    out = capsys.readouterr().out
    assert code == 3
    assert "the net-hold applet is not running" in out and "SCR_ENABLE" in out


def test_vehicle_with_another_system_id(capsys: pytest.CaptureFixture[str]) -> None:
    with FakeAutopilot(UdpServerTransport(), sysid=2, params=READY_47) as autopilot:
        code = main(["mavlink-check", "--url", autopilot.url, "--timeout", "1"])
    assert code == 3
    assert "set mavlink.source_system = 2" in capsys.readouterr().out


def test_no_autopilot_is_a_one_line_error(capsys: pytest.CaptureFixture[str]) -> None:
    with FakeAutopilot(UdpServerTransport()) as silent:
        silent.heartbeats_enabled = False
        code = main(["mavlink-check", "--url", silent.url, "--timeout", "0.5"])
    err = capsys.readouterr().err
    assert code == 1
    assert "no autopilot heartbeat" in err and err.count("\n") == 1


def test_a_serial_port_at_the_wrong_rate_is_named_as_such(
    capsys: pytest.CaptureFixture[str]
) -> None:
    """Bytes that are no MAVLink (a UART at another rate than SERIALn_BAUD) said only "is the
    autopilot powered and the URL right?"."""
    port = PtyTransport()
    stop = threading.Event()

    def garbled() -> None:  # from when the port is open (opening it flushes what came before)
        while not stop.wait(0.02):
            with contextlib.suppress(OSError):
                port.write(bytes(range(0x10, 0xF0)))  # no frame start among them

    writer = threading.Thread(target=garbled, daemon=True)
    writer.start()
    try:
        code = main(["mavlink-check", "--url", port.url, "--baud", "57600", "--timeout", "0.5"])
    finally:
        stop.set()
        writer.join(timeout=2.0)
        port.close()
    err = capsys.readouterr().err
    assert code == 1 and err.count("\n") == 1
    assert "bytes arrived" in err and "--baud (57600)" in err, err


def test_bad_arguments_are_configuration_errors(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["mavlink-check", "--source-system", "255"]) == 78
    assert "mavlink.source_system" in capsys.readouterr().err
    assert main(["mavlink-check", "--url", "serial0"]) == 78


def test_advice_on_missing_rangefinder_support() -> None:
    report = AutopilotReport(1, 1, 12, 3, 2, None, params={})
    advice = advise(report, MavlinkSettings())
    assert any("did not report RNGFND1_TYPE" in c for c in advice.changes)
    assert advice.instance is None
    assert report.firmware is None


def _version(major: int, minor: int, patch: int) -> int:
    """AUTOPILOT_VERSION.flight_sw_version of an official release."""
    return (major << 24) | (minor << 16) | (patch << 8) | 255


@pytest.mark.parametrize(("firmware", "too_old"), [((4, 1, 2), True), ((4, 4, 0), True),
                                                   ((4, 5, 0), False), ((4, 7, 0), False)])
def test_net_hold_needs_an_ardusub_with_the_applets_lua_bindings(
    firmware: tuple[int, int, int], too_old: bool
) -> None:
    """net_hold.lua uses sub:get_and_clear_button_count and mavlink:block_command, bindings
    added to ArduPilot in 2023 (ArduSub 4.5): on an older autopilot the applet does not load,
    and mavlink-check said "Ready" with every parameter right."""
    report = AutopilotReport(1, 1, 12, 3, 2, _version(*firmware), params=READY_47)
    changes = advise(report, MavlinkSettings(), net_hold=True).changes
    assert any("ArduSub 4.5 or later" in c for c in changes) == too_old, changes
    assert not advise(report, MavlinkSettings()).changes  # a distance alone: no such need
    dev = AutopilotReport(1, 1, 12, 3, 2, (4 << 24) | (7 << 16), params=READY_47)
    assert not advise(dev, MavlinkSettings(), net_hold=True).changes  # 4.7.0-dev


def ardusub_47(**instances: tuple[int, int]) -> dict[str, float]:
    """ArduSub 4.7's rangefinder parameters on a board with ten instances (every one is
    reported, off unless set): `instances` maps "1".."9", "A" to (TYPE, ORIENT)."""
    params: dict[str, float] = {"RNGFND_SQ_MIN": 0}
    for n in "123456789A":
        kind, orient = instances.get(f"i{n}", (0, 25))
        params |= {f"RNGFND{n}_TYPE": kind, f"RNGFND{n}_ORIENT": orient,
                   f"RNGFND{n}_MIN": 0.2, f"RNGFND{n}_MAX": 10}
    return params


PING = 23  # Blue Robotics Ping, the BlueROV2's downward altimeter


def test_a_ping_altimeter_on_rngfnd1_is_left_alone(capsys: pytest.CaptureFixture[str]) -> None:
    """ArduPilot hands a DISTANCE_SENSOR to every rangefinder instance that is not off, and a
    MAVLink instance keeps those of its orientation: netpose can use any free instance. The
    check asked about RNGFND1 only and told a BlueROV2's owner to turn the Ping altimeter
    (RNGFND1, facing down, what SURFTRAK holds altitude with) into netpose's."""
    with FakeAutopilot(UdpServerTransport(), params=ardusub_47(i1=(PING, 25))) as autopilot:
        code = main(["mavlink-check", "--url", autopilot.url, "--timeout", "1"])
    out = capsys.readouterr().out
    assert code == 3
    changes = out.split("To change:")[1]
    assert "set RNGFND2_TYPE = 10" in changes and "set RNGFND2_ORIENT = 0" in changes
    assert "RNGFND1" not in changes
    assert "RNGFND1_TYPE     23" in out  # shown, as the sensor it is

    # Set up that way, the vehicle is ready.
    ready = ardusub_47(i1=(PING, 25), i2=(10, 0))
    with FakeAutopilot(UdpServerTransport(), params=ready) as autopilot:
        code = main(["mavlink-check", "--url", autopilot.url, "--timeout", "1"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "RNGFND2_MAX      10" in out and "RNGFND3_TYPE" not in out  # free ones not listed


def test_another_sensor_facing_the_same_way_is_named() -> None:
    """The autopilot answers "the forward rangefinder" with the first instance of that
    orientation that has a good reading: a second forward sensor would stand in for netpose's
    whenever netpose has none (no net in view), and the net-hold applet would follow it."""
    report = AutopilotReport(1, 1, 12, 3, 2, None, params=ardusub_47(i1=(PING, 0), i3=(10, 0)))
    advice = advise(report, MavlinkSettings())
    assert advice.instance == "3"
    assert len(advice.changes) == 1
    assert "RNGFND1 (Blue Robotics Ping) also faces forward" in advice.changes[0]


def test_a_mavlink_instance_facing_elsewhere_is_not_taken_over() -> None:
    """A MAVLink instance facing down may be another companion sensor's (a DVL's altitude):
    netpose gets a free instance of its own while there is one."""
    params = ardusub_47(i1=(10, 25))
    advice = advise(AutopilotReport(1, 1, 12, 3, 2, None, params=params), MavlinkSettings())
    assert advice.instance == "2"
    assert any("RNGFND1 is a MAVLink rangefinder facing down" in n for n in advice.notes)
    # With no instance free (a board with one), the MAVLink one is re-pointed.
    one = {k: v for k, v in params.items() if k.startswith(("RNGFND1_", "RNGFND_"))}
    advice = advise(AutopilotReport(1, 1, 12, 3, 2, None, params=one), MavlinkSettings())
    assert advice.instance == "1"
    assert advice.changes == ["set RNGFND1_ORIENT = 0 (forward; now 25): the autopilot ignores "
                              "DISTANCE_SENSOR of any other orientation"]


def test_a_board_with_every_instance_in_use_gives_up_the_one_not_facing_down() -> None:
    params: dict[str, float] = {"RNGFND1_TYPE": PING, "RNGFND1_ORIENT": 25, "RNGFND2_TYPE": 1,
              "RNGFND2_ORIENT": 24}  # a board with two instances: the altimeter, an up-looker
    advice = advise(AutopilotReport(1, 1, 12, 3, 2, None, params=params), MavlinkSettings())
    assert advice.instance == "2"
    assert "set RNGFND2_TYPE = 10 (MAVLink; now type 1, which this replaces" in advice.changes[0]


def test_command_line_entry_point(tmp_path: Path) -> None:
    with FakeAutopilot(UdpServerTransport(), params=ARDUSUB_45_DEFAULTS) as autopilot:
        done = subprocess.run(
            [sys.executable, "-m", "service.cli", "mavlink-check", "--url", autopilot.url,
             "--timeout", "1"],
            capture_output=True, text=True, timeout=30, cwd=Path(__file__).parents[1],
        )
    assert done.returncode == 3, done.stderr
    assert "set RNGFND1_TYPE = 10" in done.stdout


def test_a_serial_port_the_service_holds_is_not_shared(
    capsys: pytest.CaptureFixture[str]
) -> None:
    """A tty opened twice splits the autopilot's bytes between the readers: run beside the
    service, the check lost half the parameters and advised "a firmware with rangefinder
    support" while the service lost its link. The port is held by one netpose at a time."""
    with FakeAutopilot(PtyTransport(), params=READY_47) as autopilot:
        service_link = MavlinkLink(MavlinkSettings(url=autopilot.url))
        service_link.start()
        try:
            wait_status(service_link, "state", "connected", timeout=10.0)
            code = main(["mavlink-check", "--url", autopilot.url, "--timeout", "1"])
            err = capsys.readouterr().err
            assert code == 1
            assert "is in use by another netpose process" in err and err.count("\n") == 1
            assert service_link.status().state == "connected"  # the service kept its link
        finally:
            service_link.close()
        # Once the service lets go, the check has the port.
        assert main(["mavlink-check", "--url", autopilot.url, "--timeout", "2"]) == 0


def test_a_refused_second_netpose_leaves_the_services_line_speed_alone(
    capsys: pytest.CaptureFixture[str]
) -> None:
    """The speed of a serial line belongs to the device, not to one open of it: pymavlink's
    open set the check's baud rate before the lock refused it, and the service's link at
    57600 was left at 115200."""
    import termios

    with FakeAutopilot(PtyTransport(), params=READY_47) as autopilot:
        service_link = MavlinkLink(MavlinkSettings(url=autopilot.url, baud=57600))
        service_link.start()
        try:
            wait_status(service_link, "state", "connected", timeout=10.0)
            fd = os.open(autopilot.url, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
            try:
                before = termios.tcgetattr(fd)[4:6]
                assert main(["mavlink-check", "--url", autopilot.url, "--baud", "115200",
                             "--timeout", "1"]) == 1
                assert termios.tcgetattr(fd)[4:6] == before == [termios.B57600] * 2
            finally:
                os.close(fd)
            assert "in use by another netpose" in capsys.readouterr().err
        finally:
            service_link.close()


def test_the_check_reads_the_services_configuration(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A plain Pi's user had to retype the service's URL, baud, orientation and limits by
    hand; `--config` takes them from its [mavlink], and the options still win."""
    params = {**READY_47, "RNGFND1_ORIENT": 25, "RNGFND1_MIN": 0.5}
    with FakeAutopilot(UdpServerTransport(), params=params) as autopilot:
        config = tmp_path / "netpose.toml"
        config.write_text(f'[mesh]\nbar_length_m = 0.0275\n\n[mavlink]\nurl = "{autopilot.url}"\n'
                          "orientation = 25\nmin_distance_m = 0.5\n")
        assert main(["mavlink-check", "--config", str(config), "--timeout", "1"]) == 0
        assert "Ready" in capsys.readouterr().out
        # An option given on the command line overrides the file's.
        code = main(["mavlink-check", "-c", str(config), "--orientation", "0", "--timeout", "1"])
        assert code == 3
        assert "set RNGFND1_ORIENT = 0 (forward; now 25)" in capsys.readouterr().out
    config.write_text('[mavlink]\norientation = "ahead"\n')
    assert main(["mavlink-check", "--config", str(config)]) == 78
    assert "mavlink.orientation" in capsys.readouterr().err


@pytest.mark.parametrize("answer_s", [0.005, 0.15])  # a quick link, a busy radio
def test_every_parameter_is_read_from_an_autopilot_that_queues_twenty_requests(
    capsys: pytest.CaptureFixture[str], answer_s: float
) -> None:
    """ArduPilot queues at most 20 parameter requests and drops the rest (GCS_Param.cpp). Asked
    for all 64 at once (ten rangefinder instances), ArduSub SITL answered 22-26: a second
    forward sensor on RNGFND8 went unseen ("Ready") and SCR_ENABLE = 1 was advised when it
    was 1. Requests go out a few at a time; one still queued at a slow autopilot is not taken
    for one the firmware lacks (answers every 0.15 s had lost RNGFND8 again)."""
    params = {**ardusub_47(i1=(PING, 25), i2=(10, 0), i8=(100, 0)), "SCR_ENABLE": 1,
              "NETH_ENABLE": 1, "NETH_DIST": 1.0}
    with FakeAutopilot(UdpServerTransport(), params=params, param_queue=20,
                       param_answer_s=answer_s) as autopilot:
        code = main(["mavlink-check", "--url", autopilot.url, "--timeout", "2", "--net-hold"])
    out = capsys.readouterr().out
    assert code == 3, out
    changes = out.split("To change:")[1]
    assert "RNGFND8 (type 100) also faces forward" in changes
    assert "SCR_ENABLE" not in changes and "RNGFND_SQ_MIN    0" in out
