"""Net hold in a closed loop: ArduSub SITL moves the vehicle, netpose (the real daemon process,
`sim:` source) sees the net from the vehicle's pose, and scripts/net_hold.lua on the autopilot
steers by what netpose measures. The test's ground station is the pilot (MANUAL_CONTROL at
25 Hz, as a joystick sends it) and the observer; the truth is the simulator's own pose
(SIM_STATE) against the net fixed in the world.

Runs only when NETPOSE_ARDUSUB_SITL names an ArduSub SITL binary (field notes section 8);
NETPOSE_NET_HOLD_PLOT=path also writes the plot there (docs/net-hold.png). Takes ~3 minutes.
"""

from __future__ import annotations

import itertools
import math
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from drivers.sim_world import CameraMount, VehiclePose, WorldNet, camera_view
from service.core.mesh import MeshGeometry
from tests.lua_applet import MAV_CMD_USER_1
from tests.sitl_harness import MODE_ALT_HOLD, Pilot, Sitl, local_ne

SITL = os.environ.get("NETPOSE_ARDUSUB_SITL")
REPO = Path(__file__).resolve().parents[1]
MESH = MeshGeometry(0.025, 90.0)
MOUNT = CameraMount(forward_m=0.2)
SET_POINT, START, TURN_DEG, DIST_MIN = 1.0, 2.0, 20.0, 0.4
CURRENT_MPS = 0.2  # toward the net: a modest tidal current at a fish farm
SITL_TIMEOUT_S = 0.45
MSG_RC_CHANNELS, MSG_SIM_STATE = 65, 108
PARAMS = {
    "SCR_ENABLE": 1, "ARMING_CHECK": 0, "BTN0_FUNCTION": 108,  # joystick button 0 = script 1
    "RNGFND1_TYPE": 10, "RNGFND1_ORIENT": 0, "RNGFND1_MIN": 0.2, "RNGFND1_MAX": 8,
    "SERIAL2_PROTOCOL": 2,
}

pytestmark = [
    pytest.mark.skipif(not SITL, reason="set NETPOSE_ARDUSUB_SITL to an ArduSub SITL binary "
                       "to run the closed-loop net-hold test"),
    pytest.mark.timeout(900),
]


@dataclass
class Truth:
    net: WorldNet
    origin: tuple[float, float]

    def view(self, msg: Any) -> Any:
        north, east = local_ne(msg, self.origin)
        pose = VehiclePose(0.0, north, east, -float(msg.alt), float(msg.roll),
                           float(msg.pitch), float(msg.yaw))
        return camera_view(self.net, MOUNT, pose, MESH)

    def series(self, pilot: Pilot, start: float, end: float) -> list[tuple[float, Any]]:
        return [(t, self.view(m)) for t, m in list(pilot.record.sim) if start <= t <= end]


def fresh_planes(pilot: Pilot, seconds: float) -> bool:
    """netpose's planes have been arriving without a gap over 0.3 s for `seconds`."""
    now = time.monotonic()
    times = [t for t, _, x, y, z in list(pilot.record.planes)
             if t >= now - seconds and (x, y, z) != (0.0, 0.0, 0.0)]
    if not times or times[0] > now - seconds + 0.3 or now - times[-1] > 0.3:
        return False
    return all(b - a <= 0.3 for a, b in itertools.pairwise(times))


def forward_pwm_after(pilot: Pilot, t: float) -> list[tuple[float, int]]:
    return [(tr, ch5) for tr, _, ch5 in list(pilot.record.rc) if tr >= t]


def test_net_hold_closed_loop_in_sitl(tmp_path: Path) -> None:
    assert SITL is not None
    instance = int(os.environ.get("NETPOSE_ARDUSUB_SITL_INSTANCE", "8"))
    blind = tmp_path / "camera-blocked"
    # The daemon's configuration, as a file of its own: phase F changes its mesh (a reload,
    # refused while armed, then a restart).
    config = tmp_path / "netpose.toml"
    config.write_text((REPO / "config" / "sitl.toml").read_text())
    results: dict[str, float] = {}
    with Sitl(SITL, tmp_path / "sitl", instance, PARAMS,
              scripts=[REPO / "scripts" / "net_hold.lua"]) as sitl:
        pilot = Pilot(sitl.port(1))
        daemon: subprocess.Popen[str] | None = None
        daemon_log = tmp_path / "netpose.log"
        try:
            pilot.conn.wait_heartbeat(timeout=60)
            pilot.interval(MSG_SIM_STATE, 20)
            pilot.interval(MSG_RC_CHANNELS, 25)
            pilot.wait_for("SIM_STATE", lambda: pilot.newest_sim() is not None, 30)
            # Arm in depth hold and dive to ~1.5 m, as a pilot would.
            time.sleep(3.0)
            pilot.arm()
            time.sleep(1.0)
            pilot.mode(MODE_ALT_HOLD)
            pilot.set_sticks(z=250)
            time.sleep(4.0)
            pilot.set_sticks(z=500)
            time.sleep(3.0)
            # Place the net in the world: START m ahead of the camera, turned TURN_DEG.
            _, first = pilot.newest_sim()  # type: ignore[misc]
            origin = sitl.home_lat_lon
            north, east = local_ne(first, origin)
            vehicle = VehiclePose(0.0, north, east, 0.0, 0.0, 0.0, float(first.yaw))
            cam = vehicle.position + vehicle.body_to_world() @ MOUNT.offset
            net = WorldNet.ahead_of((cam[0], cam[1]), float(first.yaw), START,
                                    math.radians(TURN_DEG))
            truth = Truth(net, origin)
            url = (f"sim:tcp:127.0.0.1:{sitl.port(2)}?origin={origin[0]},{origin[1]}"
                   f"&facing={math.degrees(net.facing)}&net_north={net.point_ne[0]}"
                   f"&net_east={net.point_ne[1]}&cam_forward={MOUNT.forward_m}"
                   f"&fps=10&width=960&height=540&blind={blind}")
            daemon_command = [sys.executable, "-m", "service.cli", "run", "--config",
                              str(config), "--set", f"camera.url={url}",
                              "--set", f"mavlink.url=tcp:127.0.0.1:{sitl.port(0)}",
                              "--set", "telemetry.enabled=false",
                              "--set", f"mavlink.max_age_s={SITL_TIMEOUT_S}"]
            with daemon_log.open("w") as log:
                daemon = subprocess.Popen(daemon_command, cwd=REPO, stdout=log,
                                          stderr=subprocess.STDOUT, text=True,
                                          env=dict(os.environ, PYTHONUNBUFFERED="1"))
            pilot.wait_for("netpose's net plane through ArduSub",
                           lambda: len(pilot.record.planes) > 20, 90)  # "no net" ones too
            # Rendering adds ~0.1-0.3 s to every frame on this (shared, 2-core) machine, which a
            # camera does not: allow planes up to 0.45 s old (field default 0.4 s); the
            # blocked-camera check below still requires thrust to end within 0.5 s.
            pilot.param("NETH_TIMEOUT", SITL_TIMEOUT_S)
            pilot.wait_for("netpose tracking", lambda: fresh_planes(pilot, 2.0), 30)

            # -- The applet's COMMAND_ACK, decoded by pymavlink: every field, to the asker -------
            asked_at = pilot.command(MAV_CMD_USER_1, 0.0)  # off while off: accepted, no change
            pilot.wait_for("the applet's COMMAND_ACK",
                           lambda: pilot.ack(MAV_CMD_USER_1, asked_at) is not None, 5)
            ack = pilot.ack(MAV_CMD_USER_1, asked_at)
            ack_fields = (ack.result, ack.progress, ack.result_param2, ack.target_system,
                          ack.target_component)

            # -- A: engage from START m, TURN_DEG off; settle; hold ------------------------------
            engage_at = time.monotonic()
            start_view = truth.view(pilot.newest_sim()[1])  # type: ignore[index]
            pilot.press(0)
            pilot.wait_text("NetHold: ON", engage_at, 5)
            time.sleep(62.0)
            hold = truth.series(pilot, engage_at, time.monotonic())
            settled_at = next(t for t, v in hold if abs(v.distance_m - SET_POINT) < 0.05)
            window = [v for t, v in hold if settled_at <= t <= settled_at + 30.0]
            results["start_distance_m"] = start_view.distance_m
            results["start_heading_error_deg"] = start_view.heading_error_deg
            results["settle_s"] = settled_at - engage_at
            results["rms_m"] = math.sqrt(sum((v.distance_m - SET_POINT) ** 2 for v in window)
                                         / len(window))
            results["heading_error_deg"] = max(abs(v.heading_error_deg) for t, v in hold
                                               if t >= settled_at + 20.0)
            approach = truth.series(pilot, engage_at, settled_at)
            results["max_closing_mps"] = max(
                (a[1].distance_m - b[1].distance_m) / (b[0] - a[0])
                for a, b in zip(approach[::10], approach[10::10], strict=False))

            # -- B: the pilot sweeps sideways along the net at ~0.2 m/s ----------------------
            sweep_at = time.monotonic()
            pilot.set_sticks(y=200)
            time.sleep(15.0)
            pilot.set_sticks(y=-200)
            time.sleep(15.0)
            pilot.set_sticks(y=0)
            time.sleep(3.0)
            sweep = truth.series(pilot, sweep_at, time.monotonic())
            results["sweep_max_error_m"] = max(abs(v.distance_m - SET_POINT) for _, v in sweep)
            along = [(t, v) for t, v in sweep if sweep_at + 3.0 <= t <= sweep_at + 15.0]
            moved = math.hypot(along[-1][1].camera_position[0] - along[0][1].camera_position[0],
                               along[-1][1].camera_position[1] - along[0][1].camera_position[1])
            results["sweep_speed_mps"] = moved / (along[-1][0] - along[0][0])
            still_on = not any("OFF" in text for t, text in pilot.record.texts if t >= sweep_at)

            # -- B2: a steady current toward the net ------------------------------------------
            # SITL's wind acts on the submarine's drag as a water current once it is the same
            # at every height (SIM_WIND_T 1; the default profile is zero below the surface).
            # Coming from behind the vehicle, it pushes it toward the net: a hold by P alone
            # settled 13 cm nearer at 0.2 m/s; the integral learns the thrust it needs.
            pilot.param("SIM_WIND_T", 1)
            pilot.param("SIM_WIND_DIR", (math.degrees(net.facing) + 180.0) % 360.0)
            current_at = time.monotonic()
            pilot.param("SIM_WIND_SPD", CURRENT_MPS)
            time.sleep(45.0)
            slack_at = time.monotonic()
            pilot.param("SIM_WIND_SPD", 0.0)
            time.sleep(15.0)
            flow = truth.series(pilot, current_at, slack_at)
            trimmed = [v.distance_m for t, v in flow if t >= current_at + 25.0]
            results["current_mean_m"] = sum(trimmed) / len(trimmed)
            results["current_max_error_m"] = max(abs(d - SET_POINT) for d in trimmed)
            results["current_min_m"] = min(v.distance_m for _, v in flow)
            slack = truth.series(pilot, slack_at, time.monotonic())
            results["slack_max_error_m"] = max(abs(v.distance_m - SET_POINT) for _, v in slack)
            results["slack_min_m"] = min(v.distance_m for _, v in slack)
            still_on = still_on and not any("OFF" in text for t, text in pilot.record.texts
                                            if t >= current_at)

            # -- C: pilot forward stick hands control back at once ---------------------------
            stick_at = pilot.set_sticks(x=300)
            off_at, _ = pilot.wait_text("OFF, pilot input", stick_at, 2)
            time.sleep(1.0)
            pilot_pwm = [pwm for t, pwm in forward_pwm_after(pilot, stick_at + 0.3)]
            pilot.set_sticks(x=0)
            results["pilot_handback_s"] = off_at - stick_at

            # -- D: back off, re-engage, block the camera during the approach ----------------
            pilot.set_sticks(x=-200)
            time.sleep(4.0)
            pilot.set_sticks(x=0)
            time.sleep(2.0)
            pilot.wait_for("netpose tracking again", lambda: fresh_planes(pilot, 2.0), 20)
            reengage_at = time.monotonic()
            pilot.press(0)
            pilot.wait_text("NetHold: ON", reengage_at, 5)
            # Block the camera the moment the applet is seen thrusting toward the net.
            pilot.wait_for("thrust toward the net", lambda: any(
                pwm > 1520 for _, pwm in forward_pwm_after(pilot, time.monotonic() - 0.05)), 15)
            blind.touch()
            blocked_at = time.monotonic()
            pilot.wait_text("OFF, net lost", blocked_at, 6)  # after NETH_GRACE
            time.sleep(6.0)
            # Thrust toward the net ends when the forward channel is last seen above neutral.
            after = forward_pwm_after(pilot, blocked_at)
            pushing = [t for t, pwm in after if pwm > 1500]
            stopped_at = pushing[-1] if pushing else blocked_at
            thrust_after_stop = [pwm for t, pwm in after if t > stopped_at]
            results["blocked_stop_s"] = stopped_at - blocked_at
            after_block = truth.series(pilot, blocked_at, time.monotonic())
            results["blocked_min_distance_m"] = min(v.distance_m for _, v in after_block)

            # -- E: the pilot's joystick falls silent while holding ---------------------------
            # (ArduSub's own pilot failsafe, FS_PILOT_INPUT, disarms after FS_PILOT_TIMEOUT, 3 s,
            # in this build, and may be set to warn only: the applet hands back by itself
            # first.)
            blind.unlink()
            pilot.wait_for("netpose tracking again", lambda: fresh_planes(pilot, 2.0), 20)
            holding_at = time.monotonic()
            pilot.press(0)
            pilot.wait_text("NetHold: ON", holding_at, 5)
            time.sleep(5.0)
            silent_at = time.monotonic()
            pilot.joystick = False
            off_at, _ = pilot.wait_text("OFF, no pilot input", silent_at, 3)
            time.sleep(1.0)
            pilot.joystick = True
            results["no_pilot_handback_s"] = off_at - silent_at
            # The applet's last word on the forward channel is neutral (no MANUAL_CONTROL
            # rewrites it meanwhile).
            unattended = forward_pwm_after(pilot, off_at + 0.2)
            results["no_pilot_last_fwd"] = float(unattended[-1][1]) if unattended else 1500.0

            # -- F: a mesh size edited mid-dive ------------------------------------------------
            # F1: set to twice the net's and reloaded (SIGHUP) while ArduSub says armed: the
            # reload is refused (a digit dropped in a hand edit would double every distance a
            # second later), the pilot is told, and the hold goes on undisturbed.
            pilot.wait_for("netpose tracking again", lambda: fresh_planes(pilot, 2.0), 20)
            doubled_engage_at = time.monotonic()
            pilot.press(0)
            pilot.wait_text("NetHold: ON", doubled_engage_at, 5)
            time.sleep(5.0)
            config.write_text(config.read_text().replace("bar_length_m = 0.025",
                                                         "bar_length_m = 0.05"))
            refused_at = time.monotonic()
            daemon.send_signal(signal.SIGHUP)
            pilot.wait_text("mesh change refused: vehicle armed", refused_at, 10)
            time.sleep(4.0)
            results["refused_reload_still_on"] = float(not any(
                "OFF" in text for t, text in pilot.record.texts if t >= refused_at))
            kept = truth.series(pilot, refused_at, time.monotonic())
            results["refused_reload_max_error_m"] = max(abs(v.distance_m - SET_POINT)
                                                        for _, v in kept)
            # F2: the edited file still reaches the daemon by a restart (`systemctl restart`,
            # or a crash's), and after its gap the readings come back at twice the distance.
            # The hold must not drive toward a net it places 2 m off: it hands back (on the
            # gap, measured 0.84 s after the stop; the applet's tests prove its jump check on
            # doubled readings after a shorter gap) and never comes nearer.
            daemon.send_signal(signal.SIGTERM)
            daemon.wait(timeout=10)
            doubled_at = time.monotonic()
            with daemon_log.open("a") as log:
                daemon = subprocess.Popen(daemon_command, cwd=REPO, stdout=log,
                                          stderr=subprocess.STDOUT, text=True,
                                          env=dict(os.environ, PYTHONUNBUFFERED="1"))
            off_at, _ = pilot.wait_text("NetHold: OFF", doubled_at, 30)
            pilot.wait_for("netpose tracking at the doubled scale",
                           lambda: fresh_planes(pilot, 2.0), 60)
            time.sleep(4.0)
            results["doubled_handback_s"] = off_at - doubled_at
            after_doubling = truth.series(pilot, doubled_at, time.monotonic())
            results["doubled_min_distance_m"] = min(v.distance_m for _, v in after_doubling)
            everything = truth.series(pilot, engage_at, time.monotonic())
            results["min_distance_m"] = min(v.distance_m for _, v in everything)
            assert daemon.poll() is None, daemon_log.read_text()[-3000:]
        finally:
            dump_record(pilot, tmp_path / "record.txt", locals().get("truth"))
            if daemon is not None and daemon.poll() is None:
                daemon.terminate()
                try:
                    daemon.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    daemon.kill()
            pilot.close()
        context = (f"results {results}\nSITL: {sitl.log_tail(800)}\nnetpose: "
                   f"{daemon_log.read_text()[-2000:]}")
        plot = write_plot(pilot, truth, engage_at, tmp_path / "net-hold.png",
                          {"sweep": sweep_at, "current": current_at, "slack": slack_at,
                           "pilot": stick_at, "blocked": blocked_at})
        target = os.environ.get("NETPOSE_NET_HOLD_PLOT")
        if target:
            Path(target).write_bytes(plot.read_bytes())
        print("net hold SITL results:", {k: round(v, 4) for k, v in results.items()})

    # A 3-byte ACK string sent 7 bytes of the autopilot's memory: target 95/84, param2 22096.
    assert ack_fields == (0, 0, 0, 255, 190), context
    assert abs(results["start_distance_m"] - START) < 0.15, context
    assert abs(results["start_heading_error_deg"] - TURN_DEG) < 3.0, context
    assert results["settle_s"] <= 30.0, context
    assert results["rms_m"] <= 0.03, context
    assert results["heading_error_deg"] <= 3.0, context
    assert results["max_closing_mps"] <= 0.3 * 1.25, context  # NETH_SPD_MAX, with lag
    assert still_on and results["sweep_max_error_m"] <= 0.10, context
    assert results["sweep_speed_mps"] >= 0.15, context  # the sweep really happened
    # In the current: the offset trimmed out (a 0.03 m mean allows the dead band's play).
    # Before the trim is learned the current's onset (over SIM_WIND_TC, 5 s) carries the
    # vehicle in by what the speed feedback lets through (9 cm measured), and when it stops the
    # trim carries it away (12 cm) while it unwinds: bounded, and the second away from the net.
    assert abs(results["current_mean_m"] - SET_POINT) <= 0.03, context
    assert results["current_max_error_m"] <= 0.06, context
    assert results["current_min_m"] >= SET_POINT - 0.15, context
    assert results["slack_max_error_m"] <= 0.2, context
    assert results["slack_min_m"] >= SET_POINT - 0.05, context
    assert results["pilot_handback_s"] < 0.3, context
    # After hand-back the forward channel is the pilot's alone: one steady value, forward.
    assert pilot_pwm and len(set(pilot_pwm)) == 1 and pilot_pwm[0] > 1500, (pilot_pwm, context)
    assert results["blocked_stop_s"] <= 0.5, context
    assert all(pwm <= 1500 for pwm in thrust_after_stop), context
    assert results["blocked_min_distance_m"] >= DIST_MIN, context
    assert results["min_distance_m"] >= 0.3, context
    # No joystick for a second: off within about a second (the applet's 1 s, the GCS link's
    # and the 10 ms run's latency), and nothing but neutral after.
    assert 0.9 <= results["no_pilot_handback_s"] <= 1.6, context
    # Readings at twice the distance after a gap: handed back, never nearer than the hold was
    # (it drove to half the set point before).
    assert results["doubled_min_distance_m"] >= SET_POINT - 0.1, context
    assert results["refused_reload_still_on"] == 1.0, context
    assert results["refused_reload_max_error_m"] <= 0.1, context
    assert results["no_pilot_last_fwd"] == 1500.0, context


def dump_record(pilot: Pilot, path: Path, truth: Truth | None) -> None:
    """What the pilot saw, for a failure's post-mortem (next to the SITL and netpose logs)."""
    rec = pilot.record
    lines = [f"{t:.2f} TEXT {text}" for t, text in rec.texts]
    lines += [f"{t:.2f} RC yaw {yaw} fwd {fwd}" for t, yaw, fwd in rec.rc[::5]]
    lines += [f"{t:.2f} PLANE {usec} {math.sqrt(x * x + y * y + z * z):.3f}"
              for t, usec, x, y, z in rec.planes[::5]]
    if truth is not None:
        for t, m in rec.sim[::10]:
            v = truth.view(m)
            lines.append(f"{t:.2f} TRUTH d {v.distance_m:.3f} heading {v.heading_error_deg:.2f}")
    path.write_text("\n".join(sorted(lines, key=lambda line: float(line.split()[0]))))


def write_plot(pilot: Pilot, truth: Truth, t0: float, path: Path,
               marks: dict[str, float]) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sim = [(t - t0, truth.view(m).distance_m) for t, m in pilot.record.sim if t >= t0 - 5]
    # netpose's distance, at its frame's capture time (ArduSub boot clock -> arrival clock).
    planes = pilot.record.planes
    offset = min(t - usec * 1e-6 for t, usec, *_ in planes)
    measured = [(usec * 1e-6 + offset - t0, math.sqrt(x * x + y * y + z * z))
                for t, usec, x, y, z in planes if t >= t0 - 5 and (x, y, z) != (0, 0, 0)]
    fig, ax = plt.subplots(figsize=(9, 3.6), dpi=100)
    ax.plot([s[0] for s in sim], [s[1] for s in sim], lw=1.2, label="true distance (SIM_STATE)")
    ax.plot([m[0] for m in measured], [m[1] for m in measured], ".", ms=2, alpha=0.6,
            label="netpose distance (NET_PLANE)")
    ax.axhline(SET_POINT, color="k", lw=0.8, ls="--", label="set point")
    ax.axhline(DIST_MIN, color="r", lw=0.8, ls=":", label="hard minimum")
    for name, t in marks.items():
        ax.axvline(t - t0, color="grey", lw=0.6)
        ax.text(t - t0 + 0.5, 2.25, name, fontsize=8, color="grey")
    ax.set_xlabel("time since net hold engaged (s)")
    ax.set_ylabel("camera to net (m)")
    ax.set_ylim(0.0, 2.4)
    ax.legend(loc="lower left", fontsize=8)
    ax.set_title("Net hold in ArduSub SITL: engage at 2 m / 20 deg, sweep, 0.2 m/s current, "
                 "pilot, camera blocked", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path
