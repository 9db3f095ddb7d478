"""scripts/net_hold.lua, the shipped file, in Lua 5.3 against stand-in ArduPilot bindings and a
simple simulated vehicle (tests/lua_applet.py). The same rules are proved against ArduSub SITL
in tests/test_net_hold_sitl.py."""

from __future__ import annotations

import pytest

from tests.lua_applet import (
    MAV_CMD_USER_1,
    MSG_COMMAND_LONG,
    MSG_DEBUG_VECT,
    MSG_MANUAL_CONTROL,
    SCRIPT,
    Applet,
    NetVehicle,
    command_user_1,
    debug_vect,
    manual_control,
    run_closed_loop,
)

FWD, YAW = 5, 4


def engaged_applet(vehicle: NetVehicle, **params: float) -> Applet:
    applet = Applet({f"NETH_{k}": v for k, v in params.items()})
    run_closed_loop(applet, vehicle, 1.0, t0=0.0)
    applet.press(1)
    run_closed_loop(applet, vehicle, 0.1)
    assert applet.engaged, applet.texts()
    return applet


def test_loads_with_its_parameters_and_listens_for_its_messages() -> None:
    applet = Applet()
    applet.run_until(2.0)
    stub = applet.stub
    assert stub.params["NETH_DIST"] == 1.0 and stub.params["NETH_DIST_MIN"] == 0.4
    assert stub.params["NETH_TIMEOUT"] == pytest.approx(0.4)
    assert set(stub.rx_ids.values()) == {MSG_DEBUG_VECT, MSG_MANUAL_CONTROL, MSG_COMMAND_LONG}
    assert stub.blocked[MAV_CMD_USER_1]
    assert any("loaded, set point 1.00 m" in text for _, text in applet.texts())
    assert applet.override(FWD) is None and applet.override(YAW) is None  # nothing unasked


def test_holds_the_set_distance_and_squares_the_heading() -> None:
    vehicle = NetVehicle(distance_m=2.0, heading_error_deg=20.0)
    applet = engaged_applet(vehicle)
    trace = run_closed_loop(applet, vehicle, 40.0)
    t0 = trace[0][0]
    settled = next(t for t, d, *_ in trace if abs(d - 1.0) < 0.05) - t0
    assert settled < 15.0
    tail = [row for row in trace if row[0] > t0 + 25.0]
    # The ESCs' 25 us dead band leaves a few centimetres of play (as in SITL).
    assert max(abs(d - 1.0) for _, d, *_ in tail) < 0.06
    assert max(abs(h) for _, _, h, *_ in tail) < 3.0
    assert vehicle.min_distance_seen > 0.9  # no large overshoot toward the net
    # Speed toward the net stays within NETH_SPD_MAX (0.3 m/s) plus the vehicle's lag.
    speeds = [(trace[i][1] - trace[i + 1][1]) / 0.01 for i in range(len(trace) - 1)]
    assert max(speeds) < 0.33
    assert applet.engaged


def test_refuses_to_engage_without_a_fresh_net() -> None:
    applet = Applet()
    applet.run_until(1.0)
    applet.press(1)
    applet.run_until(1.1)
    assert not applet.engaged and applet.override(FWD) is None
    assert "not engaged: no net in view" in applet.texts()[-1][1]
    applet.receive(debug_vect(b"NET_PLANE", 0.5, 0.0, 0.0, 1.5))  # 0.6 s old
    applet.press(1)
    applet.run_until(1.2)
    assert not applet.engaged
    applet.receive(debug_vect(b"NET_PLANE", 1.15, 0.0, 0.0, 5.0))  # fresh but too far
    applet.press(1)
    applet.run_until(1.3)
    assert not applet.engaged and "net at 5.00 m" in applet.texts()[-1][1]


@pytest.mark.parametrize("how", ["camera blocked", "netpose gone"])
def test_no_net_stops_thrust_within_half_a_second_then_disengages(how: str) -> None:
    """Blocked camera: netpose's frames say "no net" (zero vector), thrust stops on the first
    one. netpose gone: nothing arrives, thrust stops at NETH_TIMEOUT. Both: off after
    NETH_GRACE (3 s), and told."""
    vehicle = NetVehicle(distance_m=2.0, heading_error_deg=10.0)
    applet = engaged_applet(vehicle)
    run_closed_loop(applet, vehicle, 3.0)
    assert vehicle.speed_mps > 0.15 and (applet.override(FWD) or 0) > 1500  # approaching
    blocked_at = applet.now
    if how == "camera blocked":
        trace = run_closed_loop(applet, vehicle, 4.0, sees_net=lambda t: t < blocked_at)
    else:
        trace = run_closed_loop(applet, vehicle, 4.0, netpose_alive=lambda t: t < blocked_at)
    # Thrust toward the net ends when the forward channel is last above neutral.
    stopped = max((t for t, _, _, fwd, _ in trace if fwd > 1500), default=blocked_at)
    # The first frame without the net arrives after one frame and the latency (0.1 + 0.15 s).
    limit = 0.3 if how == "camera blocked" else 0.5
    assert stopped - blocked_at <= limit
    texts = applet.texts()
    paused = next(t for t, text in texts if "thrust stopped" in text)
    assert all((fwd, yaw) == (1500, 1500) for t, _, _, fwd, yaw in trace if t > paused)
    off = next(t for t, text in texts if "OFF, net lost" in text)
    assert paused - blocked_at <= limit and 2.5 <= off - blocked_at <= 3.3  # NETH_GRACE 3 s
    assert not applet.engaged


def test_a_short_dropout_pauses_then_resumes() -> None:
    vehicle = NetVehicle(distance_m=2.0, heading_error_deg=0.0)
    applet = engaged_applet(vehicle)
    run_closed_loop(applet, vehicle, 3.0)
    gap = (applet.now, applet.now + 0.9)  # a fish in front of the camera
    trace = run_closed_loop(applet, vehicle, 3.0, sees_net=lambda t: not gap[0] <= t < gap[1])
    assert any(fwd == 1500 for t, _, _, fwd, _ in trace if gap[0] + 0.5 <= t < gap[1])
    last_two = [text for _, text in applet.texts()][-2:]
    assert "thrust stopped" in last_two[0] and last_two[1] == "NetHold: net back, holding again"
    assert applet.engaged  # holding again: steering, not neutral
    assert any(fwd != 1500 for t, _, _, fwd, _ in trace if t > gap[1] + 0.5)


def test_pilot_stick_on_forward_or_yaw_hands_back_at_once_lateral_does_not() -> None:
    vehicle = NetVehicle(distance_m=1.5, heading_error_deg=5.0)
    applet = engaged_applet(vehicle)
    # Lateral sweep: the pilot's axis, net hold stays on.
    run_closed_loop(applet, vehicle, 2.0, pilot=lambda t: (0, 0))
    applet.receive(manual_control(y=400))
    run_closed_loop(applet, vehicle, 1.0)
    assert applet.engaged
    # Forward stick: off at the script's next run (10 ms), and no further override from it.
    applet.receive(manual_control(x=300))
    t_input = applet.now
    applet.run_until(t_input + 0.02)
    assert not applet.engaged
    assert "OFF, pilot input" in applet.texts()[-1][1]
    writes_after = [h for h in applet.history() if h[0] > t_input + 0.011]
    run_closed_loop(applet, vehicle, 1.0)
    assert [h for h in applet.history() if h[0] > t_input + 0.011] == writes_after == []


def test_yaw_stick_and_other_senders_and_messages() -> None:
    vehicle = NetVehicle(distance_m=1.5, heading_error_deg=5.0)
    applet = engaged_applet(vehicle)
    applet.receive(manual_control(r=500, sysid=200))  # not the ground station: ignored
    applet.receive(manual_control(r=500, target=7))  # not aimed at us: ignored
    applet.receive(debug_vect(b"OTHER", applet.now, 0.0, 0.0, 0.2))  # someone else's vector
    run_closed_loop(applet, vehicle, 0.5)
    assert applet.engaged
    applet.receive(manual_control(r=-150))
    applet.run_until(applet.now + 0.02)
    assert not applet.engaged and "pilot input" in applet.texts()[-1][1]


@pytest.mark.parametrize("what", ["mode", "disarm", "button", "disable"])
def test_mode_change_disarm_button_and_disable_hand_back_with_neutral(what: str) -> None:
    vehicle = NetVehicle(distance_m=2.0, heading_error_deg=10.0)
    applet = engaged_applet(vehicle)
    run_closed_loop(applet, vehicle, 2.0)
    assert applet.override(FWD) != 1500
    if what == "mode":
        applet.stub.mode = 0
    elif what == "disarm":
        applet.stub.armed = False
    elif what == "button":
        applet.press(1)
    else:
        applet.set_param("NETH_ENABLE", 0)
    applet.run_until(applet.now + 0.02)
    assert not applet.engaged
    assert (applet.override(FWD), applet.override(YAW)) == (1500, 1500)
    expected = {"mode": "mode changed", "disarm": "disarmed", "button": "button",
                "disable": "disabled"}[what]
    assert applet.texts()[-1][1] == f"NetHold: OFF, {expected}"


def test_hard_minimum_distance_is_never_crossed_with_thrust() -> None:
    # A set point below the minimum (a mistake) still stops short of the minimum.
    vehicle = NetVehicle(distance_m=2.0, heading_error_deg=0.0)
    applet = engaged_applet(vehicle, DIST=0.5, DIST_MIN=0.8)
    run_closed_loop(applet, vehicle, 30.0)
    assert vehicle.min_distance_seen > 0.8 - 0.03


@pytest.mark.parametrize("speed_mps", [0.0, -0.3, -0.6])
def test_inside_the_hard_minimum_there_is_no_thrust_toward_the_net(speed_mps: float) -> None:
    """Pushed inside NETH_DIST_MIN (a wave, the pilot), still or moving away: the loop would
    brake a fast retreat, i.e. thrust toward the net, and a still vehicle too near would be
    held where it is. Neither inside the minimum: every frame there has no forward thrust,
    and the vehicle ends outside it."""
    vehicle = NetVehicle(distance_m=1.2, heading_error_deg=0.0)
    applet = engaged_applet(vehicle)
    run_closed_loop(applet, vehicle, 5.0)
    vehicle.distance_m, vehicle.speed_mps = 0.3, -speed_mps  # moving away at |speed|
    trace = run_closed_loop(applet, vehicle, 10.0)
    inside = [(d, fwd) for _, d, _, fwd, _ in trace if d <= 0.4]
    assert len(inside) >= 20  # the rule was exercised
    assert all(fwd <= 1500 for _, fwd in inside), [f for _, f in inside if f > 1500][:5]
    assert vehicle.distance_m > 0.4 and applet.engaged


def test_engage_and_disengage_by_command_with_acks() -> None:
    vehicle = NetVehicle(distance_m=1.5, heading_error_deg=0.0)
    applet = Applet()
    run_closed_loop(applet, vehicle, 1.0, t0=0.0)
    applet.receive(command_user_1(True), chan=2)
    run_closed_loop(applet, vehicle, 0.5)
    assert applet.engaged
    applet.receive(command_user_1(False), chan=2)
    run_closed_loop(applet, vehicle, 0.1)
    assert not applet.engaged and applet.override(FWD) == 1500
    assert applet.acks() == [(MAV_CMD_USER_1, 0), (MAV_CMD_USER_1, 0)]
    applet.stub.armed = False
    applet.receive(command_user_1(True))
    run_closed_loop(applet, vehicle, 0.1)
    assert applet.acks()[-1] == (MAV_CMD_USER_1, 2)  # denied: disarmed


def test_an_internal_error_leaves_no_thrust_behind() -> None:
    vehicle = NetVehicle(distance_m=2.0, heading_error_deg=0.0)
    applet = engaged_applet(vehicle)
    run_closed_loop(applet, vehicle, 2.0)
    applet.stub.params["NETH_KP"] = applet.lua.table()  # arithmetic on a table: a Lua error
    applet.run_until(applet.now + 0.05)
    assert applet.override(FWD) == 1500 and applet.override(YAW) == 1500
    assert "internal error, OFF" in applet.texts()[-1][1]
    applet.stub.params["NETH_KP"] = 0.6
    run_closed_loop(applet, vehicle, 0.5)  # still running, still off until asked again
    assert applet.override(FWD) == 1500


def test_camera_tilt_is_taken_out_of_the_heading() -> None:
    # The net 10 deg to the right, seen by a camera tilted 30 deg down on a level vehicle.
    vehicle = NetVehicle(distance_m=1.2, heading_error_deg=10.0, cam_tilt_deg=30.0)
    applet = engaged_applet(vehicle, CAM_TILT=30.0)
    run_closed_loop(applet, vehicle, 0.3)
    assert applet.named("NH_YAWERR") == pytest.approx(10.0, abs=1.0)
    run_closed_loop(applet, vehicle, 15.0)
    assert abs(vehicle.heading_error_deg) < 1.5


def test_every_parameter_is_documented_with_its_default() -> None:
    applet = Applet()
    docs = (SCRIPT.parents[1] / "docs" / "net-hold.md").read_text()
    params = {str(k): float(v) for k, v in applet.stub.params.items()
              if str(k).startswith("NETH_")}
    assert len(params) >= 20
    for name, default in params.items():
        row = next((line for line in docs.splitlines() if line.startswith(f"| `{name}` |")), "")
        assert row, f"{name} is not in docs/net-hold.md's parameter table"
        assert f"| {default:g}" in row, (name, default, row)


def test_the_dead_band_step_only_while_the_thrusters_idle() -> None:
    """Stepping over the ESC dead band is right at rest, and wrong while the pilot sweeps
    sideways (the thrusters are out of the dead band already)."""
    outputs = {}
    for lateral in (1500, 1560):
        vehicle = NetVehicle(distance_m=1.03, heading_error_deg=0.0)
        applet = engaged_applet(vehicle)
        applet.stub.overrides[6] = lateral
        applet.receive(debug_vect(b"NET_PLANE", applet.now, 0.0, 0.0, 1.03))
        applet.run_until(applet.now + 0.02)
        outputs[lateral] = (applet.override(FWD) or 1500) - 1500
    assert outputs[1500] >= 20 + outputs[1560] - 1 and 0 < outputs[1560] < 20, outputs
