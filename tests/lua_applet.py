"""Run scripts/net_hold.lua in Lua 5.3 (ArduPilot's Lua version, through lupa) against a stand-in
of the ArduPilot bindings it uses, and a simple simulated vehicle in front of a net.

The stand-in implements exactly the calls the applet makes (param, Parameter, rc, mavlink, gcs,
sub, arming, vehicle, ahrs, logger, millis) and records what it is told; messages reach the
script as ArduPilot hands them over: the raw `mavlink_message_t` (header, then the payload at
byte 13). The script itself is the file that ships, loaded unchanged.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lupa.lua53 import LuaRuntime

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "net_hold.lua"
MSG_DEBUG_VECT = 250
MSG_MANUAL_CONTROL = 69
MSG_COMMAND_LONG = 76
MSG_COMMAND_INT = 75
MSG_RC_CHANNELS_OVERRIDE = 70
MAV_CMD_USER_1 = 31010
ALT_HOLD = 2

STUBS = r"""
-- ArduSub 4.7's own parameters the applet reads (its identity and the ground station's).
stub = {now_ms = 0, params = {MAV_SYSID = 1, MAV_GCS_SYSID = 255}, overrides = {}, history = {},
        texts = {}, too_long = {}, named = {},
        rx = {}, sent = {}, blocked = {}, buttons = {0, 0, 0, 0}, armed = true, mode = 2,
        roll = 0, pitch = 0, yaw = 0, logs = 0, rx_ids = {}}
function millis()
  -- The autopilot's uint32 millisecond clock: stub.clock_offset_ms moves it toward its wrap.
  local ms = (stub.now_ms + (stub.clock_offset_ms or 0)) % 4294967296
  return {tofloat = function(self) return ms end}
end
param = {}
function param:add_table(key, prefix, n) stub.prefix = prefix return true end
function param:add_param(key, idx, name, default)
  local full = stub.prefix .. name
  if stub.params[full] == nil then stub.params[full] = default end
  return true
end
function param:get(name) return stub.params[name] end
function param:set(name, v) stub.params[name] = v return true end
function Parameter(name)
  return {get = function(self) return stub.params[name] end}
end
rc = {}
function rc:get_pwm(n) return stub.overrides[n] or 1500 end
function rc:get_channel(n)
  return {set_override = function(self, pwm)
    stub.overrides[n] = pwm
    table.insert(stub.history, {stub.now_ms, n, pwm})
  end}
end
mavlink = {}
function mavlink:init(q, n) stub.mav_queue, stub.mav_init = q, n end
function mavlink:register_rx_msgid(id) table.insert(stub.rx_ids, id) return true end
function mavlink:block_command(id) stub.blocked[id] = true return true end
function mavlink:receive_chan()
  local m = table.remove(stub.rx, 1)
  if m == nil then return nil end
  return m[1], m[2], m[3]
end
function mavlink:send_chan(chan, msgid, payload)
  -- Kept as hex too: the bytes (a system id of 255) are not UTF-8 for the Python side.
  local hex = payload:gsub(".", function(c) return string.format("%02x", c:byte()) end)
  table.insert(stub.sent, {chan, msgid, payload, hex}) return true
end
gcs = {}
-- ArduPilot cuts a STATUSTEXT at 50 characters (GCS::send_text): a longer text loses its end
-- on the pilot's screen, so every text the applet sends must fit.
-- (Kept, not raised: the applet runs its update under pcall, which would turn an error here
-- into its own "internal error" text. The Python side checks after every update.)
function gcs:send_text(sev, text)
  if #text > 50 then table.insert(stub.too_long, text) end
  table.insert(stub.texts, {stub.now_ms, sev, text})
end
function gcs:send_named_float(name, v) stub.named[name] = v end
sub = {}
function sub:get_and_clear_button_count(i)
  local c = stub.buttons[i] stub.buttons[i] = 0 return c
end
arming = {}
function arming:is_armed() return stub.armed end
vehicle = {}
function vehicle:get_mode() return stub.mode end
ahrs = {}
""" + "{ahrs}" + r"""
logger = {}
function logger:write(...) stub.logs = stub.logs + 1 end
"""


# The attitude bindings by firmware: 4.7 added the *_rad names (ArduPilot PR #30222) and kept
# the old ones, deprecated; 4.5, the series BlueOS installs, has only the old ones.
AHRS_BINDINGS = {
    "4.7": r"""
function ahrs:get_roll_rad() return stub.roll end
function ahrs:get_pitch_rad() return stub.pitch end
function ahrs:get_yaw_rad() return stub.yaw end
function ahrs:get_roll() return stub.roll end
function ahrs:get_pitch() return stub.pitch end
function ahrs:get_yaw() return stub.yaw end
""",
    "4.5": r"""
function ahrs:get_roll() return stub.roll end
function ahrs:get_pitch() return stub.pitch end
function ahrs:get_yaw() return stub.yaw end
""",
}


def mavlink_struct(msgid: int, sysid: int, compid: int, payload: bytes) -> bytes:
    """A `mavlink_message_t` as ArduPilot hands it to scripts (payload zero-filled)."""
    header = struct.pack("<HBBBBBBB", 0, 0xFD, len(payload), 0, 0, 0, sysid, compid)
    return header + msgid.to_bytes(3, "little") + payload.ljust(280, b"\0")


def debug_vect(name: bytes, t_s: float, x: float, y: float, z: float, sysid: int = 1,
               compid: int = 197) -> bytes:
    return mavlink_struct(MSG_DEBUG_VECT, sysid, compid,
                          struct.pack("<Qfff10s", int(round(t_s * 1e6)), x, y, z, name))


def rc_override(channels: dict[int, int], sysid: int = 255, target: int = 1) -> bytes:
    """RC_CHANNELS_OVERRIDE: channels 1-18 (0: released, 65535: left alone)."""
    raw = [channels.get(i, 65535) for i in range(1, 19)]
    payload = struct.pack("<8HBB10H", *raw[:8], target, 1, *raw[8:])
    return mavlink_struct(MSG_RC_CHANNELS_OVERRIDE, sysid, 190, payload)


def manual_control(x: int = 0, y: int = 0, z: int = 500, r: int = 0, buttons: int = 0,
                   sysid: int = 255, target: int = 1) -> bytes:
    return mavlink_struct(MSG_MANUAL_CONTROL, sysid, 190,
                          struct.pack("<hhhhHB", x, y, z, r, buttons, target))


def command_int_user_1(on: bool, target: int = 1, sysid: int = 255) -> bytes:
    """MAV_CMD_USER_1 as COMMAND_INT: param1..4, x, y (int32), z, command, target."""
    payload = struct.pack("<ffffiifHBBBBB", 1.0 if on else 0.0, 0, 0, 0, 0, 0, 0,
                          MAV_CMD_USER_1, target, 1, 0, 0, 0)
    return mavlink_struct(MSG_COMMAND_INT, sysid, 190, payload)


def command_user_1(on: bool, target: int = 1, sysid: int = 255) -> bytes:
    payload = struct.pack("<fffffffHBBB", 1.0 if on else 0.0, 0, 0, 0, 0, 0, 0,
                          MAV_CMD_USER_1, target, 1, 0)
    return mavlink_struct(MSG_COMMAND_LONG, sysid, 190, payload)


class Applet:
    """The shipped script in a Lua 5.3 runtime with the stand-in bindings; time is simulated."""

    def __init__(self, params: dict[str, float] | None = None, firmware: str = "4.7") -> None:
        self.lua = LuaRuntime(unpack_returned_tuples=True)
        self.lua.execute(STUBS.replace("{ahrs}", AHRS_BINDINGS[firmware]))
        self.stub = self.lua.globals().stub
        for name, value in (params or {}).items():
            self.stub.params[name] = value
        self._fn, delay = self.lua.execute(SCRIPT.read_text())
        self.next_run_ms = float(delay)
        self.ended = False  # the script returned no next run: ArduPilot ends it
        # The simulated netpose and joystick (run_closed_loop): planes on their way, schedules.
        self.in_flight: list[tuple[float, bytes]] = []
        self.next_frame: float | None = None
        self.next_pilot: float | None = None

    # -- time and scheduling -----------------------------------------------------------------
    @property
    def now(self) -> float:
        return float(self.stub.now_ms) / 1000.0

    def run_until(self, t_s: float) -> None:
        """Run the script's update at the intervals it asks for, up to `t_s`."""
        while not self.ended and self.next_run_ms <= t_s * 1000.0:
            self.stub.now_ms = self.next_run_ms
            result = self._fn()
            if result is None:  # nothing returned
                self.ended = True
                break
            fn, delay = result
            self._fn = fn
            self.next_run_ms += float(delay)
            too_long = [str(t) for t in self.stub.too_long.values()]
            assert not too_long, f"STATUSTEXT over 50 characters: {too_long}"
        self.stub.now_ms = t_s * 1000.0

    def clock_s(self, t_s: float) -> float:
        """Simulated time `t_s` on the autopilot's clock (what netpose stamps planes with):
        the same unless `stub.clock_offset_ms` moved it toward its 49.7-day wrap."""
        offset = float(self.stub.clock_offset_ms or 0)
        return ((t_s * 1000.0 + offset) % 4294967296.0) / 1000.0

    def instructions_of_next_run(self) -> int:
        """Run the script's update once, now, counting the Lua VM instructions it takes (what
        ArduPilot limits with SCR_VM_I_COUNT, 10000 by default, per call)."""
        counter = self.lua.execute("""
            return function(fn)
              local n = 0
              debug.sethook(function() n = n + 1 end, "", 1)
              local next_fn, delay = fn()
              debug.sethook()
              return n, next_fn, delay
            end""")
        count, self._fn, _ = counter(self._fn)
        return int(count)

    # -- inputs --------------------------------------------------------------------------------
    def receive(self, message: bytes, chan: int = 0) -> None:
        rx = self.stub.rx
        rx[len(rx) + 1] = self.lua.table(message, chan, int(self.stub.now_ms))

    def press(self, button: int = 1) -> None:
        self.stub.buttons[button] = self.stub.buttons[button] + 1

    def set_param(self, name: str, value: float) -> None:
        self.stub.params[name] = value

    # -- outputs -------------------------------------------------------------------------------
    def override(self, channel: int) -> int | None:
        value = self.stub.overrides[channel]
        return None if value is None else int(value)

    def history(self) -> list[tuple[float, int, int]]:
        h = self.stub.history
        return [(float(h[i][1]) / 1000.0, int(h[i][2]), int(h[i][3])) for i in range(1, len(h) + 1)]

    def texts(self) -> list[tuple[float, str]]:
        t = self.stub.texts
        return [(float(t[i][1]) / 1000.0, str(t[i][3])) for i in range(1, len(t) + 1)]

    def named(self, name: str) -> float | None:
        value = self.stub.named[name]
        return None if value is None else float(value)

    def acks(self) -> list[tuple[int, int]]:
        """(command, result) of each COMMAND_ACK sent."""
        return [(command, result) for command, result, *_ in self.ack_fields()]

    def ack_fields(self) -> list[tuple[int, ...]]:
        """Every field of each COMMAND_ACK sent: command, result, progress, result_param2,
        target_system, target_component. ArduPilot's send_chan sends the message's full
        length (10 bytes) whatever the string holds: a shorter one is the autopilot's memory."""
        sent = self.stub.sent
        out = []
        for i in range(1, len(sent) + 1):
            raw = bytes.fromhex(str(sent[i][4]))
            assert len(raw) == 10, f"COMMAND_ACK of {len(raw)} bytes, not 10: {raw!r}"
            out.append(struct.unpack("<HBBiBB", raw))
        return out

    @property
    def engaged(self) -> bool:
        return self.named("NH_ON") == 1.0


@dataclass
class NetVehicle:
    """A vehicle in front of a flat net: distance along the net normal and heading error only,
    with the dynamics measured on ArduSub SITL's vectored model in depth hold.

    Forward: steady speed (pwm - 1500) * 0.00515 m/s per us (1550/1600/1700 us gave
    0.26/0.52/1.03 m/s), drag mostly quadratic (coasting from 0.48 m/s: 0.21 m/s after 0.6 s,
    0.09 after 2 s, 0.045 after 4.6 s: dv/dt = -0.22 v - 2.18 v|v|), thrust scaled to match the
    steady speeds, none within the ESCs' 25 us dead band (SIM_Submarine.cpp); drag on the speed
    through the water, so a current toward the net needs steady thrust away. Yaw: rate
    (pwm - 1500 - dead zone) * ~0.33 deg/s per us past a ~20 us dead zone, reached with a lag of
    ~0.4 s; heading held otherwise.
    """

    distance_m: float = 2.0
    heading_error_deg: float = 20.0  # yaw right by this to face the net
    speed_mps: float = 0.0  # toward the net
    fwd_mps_per_us: float = 0.00515
    drag_linear: float = 0.22
    drag_quadratic: float = 2.18
    esc_dead_band_us: float = 25.0
    yaw_dps_per_us: float = 0.33
    yaw_dz_us: float = 20.0
    yaw_tau_s: float = 0.4
    yaw_rate_dps: float = 0.0
    cam_tilt_deg: float = 0.0  # camera looking down by this much
    current_mps: float = 0.0  # the water's speed toward the net (SITL: SIM_WIND_*, SIM_WIND_T 1)
    min_distance_seen: float = field(default=math.inf)

    def _drag(self, v: float) -> float:
        return self.drag_linear * v + self.drag_quadratic * v * abs(v)

    def step(self, dt: float, fwd_pwm: int | None, yaw_pwm: int | None) -> None:
        offset = (fwd_pwm or 1500) - 1500
        if abs(offset) <= self.esc_dead_band_us:  # SIM_Submarine.cpp: no thrust within 25 us
            offset = 0
        thrust = self._drag(offset * self.fwd_mps_per_us)
        # Drag acts on the speed through the water: a current carries a vehicle without thrust.
        self.speed_mps += (thrust - self._drag(self.speed_mps - self.current_mps)) * dt
        self.distance_m -= self.speed_mps * dt
        offset = (yaw_pwm or 1500) - 1500
        target = 0.0
        if abs(offset) > self.yaw_dz_us:
            target = math.copysign((abs(offset) - self.yaw_dz_us) * self.yaw_dps_per_us, offset)
        self.yaw_rate_dps += (target - self.yaw_rate_dps) * min(1.0, dt / self.yaw_tau_s)
        self.heading_error_deg -= self.yaw_rate_dps * dt
        self.min_distance_seen = min(self.min_distance_seen, self.distance_m)

    def plane(self) -> tuple[float, float, float]:
        """The camera-to-net vector the camera measures (x right, y down, z forward)."""
        a, tilt = math.radians(self.heading_error_deg), math.radians(self.cam_tilt_deg)
        forward, right = self.distance_m * math.cos(a), self.distance_m * math.sin(a)
        return (right, -math.sin(tilt) * forward, math.cos(tilt) * forward)


def run_closed_loop(applet: Applet, vehicle: NetVehicle, seconds: float, *,
                    t0: float | None = None, frame_period_s: float = 0.1,
                    latency_s: float = 0.15, sees_net: Any = None, netpose_alive: Any = None,
                    pilot: Any = None, pilot_period_s: float = 0.04,
                    dt: float = 0.01) -> list[tuple[float, float, float, int, int]]:
    """Simulate `seconds`: netpose sends a plane per frame (capture time = frame time, arriving
    `latency_s` later; a zero vector while `sees_net(t)` is false, nothing while
    `netpose_alive(t)` is false); the pilot's joystick sends MANUAL_CONTROL every `pilot_period_s`
    (`pilot(t)` gives (x, r), default neutral). Returns (t, distance, heading error, fwd, yaw)."""
    t = applet.now if t0 is None else t0
    end = t + seconds
    pending = applet.in_flight
    next_frame = t if applet.next_frame is None else applet.next_frame
    next_pilot = t if applet.next_pilot is None else applet.next_pilot
    trace = []
    while t < end:
        if t >= next_frame:
            if netpose_alive is not None and not netpose_alive(t):
                pass  # netpose (or its link) is gone: nothing at all
            elif sees_net is None or sees_net(t):
                x, y, z = vehicle.plane()
                pending.append((t + latency_s,
                                debug_vect(b"NET_PLANE", applet.clock_s(t), x, y, z)))
            else:  # netpose says "no net in this frame" with a zero vector
                pending.append((t + latency_s,
                                debug_vect(b"NET_PLANE", applet.clock_s(t), 0.0, 0.0, 0.0)))
            next_frame += frame_period_s
        if t >= next_pilot:
            px, pr = pilot(t) if pilot is not None else (0, 0)
            # ArduSub turns the pilot's MANUAL_CONTROL into the same overrides the script
            # writes (joystick.cpp, JS gain 0.5): the last writer wins until the next write.
            applet.stub.overrides[5] = 1500 + int(px * 0.2)
            applet.stub.overrides[4] = 1500 + int(pr * 0.2)
            applet.receive(manual_control(x=px, r=pr))
            next_pilot += pilot_period_s
        while pending and pending[0][0] <= t:
            applet.receive(pending.pop(0)[1])
        applet.stub.yaw = -math.radians(vehicle.heading_error_deg)  # the AHRS heading
        applet.run_until(t)
        fwd, yaw = applet.override(5), applet.override(4)
        vehicle.step(dt, fwd, yaw)
        trace.append((t, vehicle.distance_m, vehicle.heading_error_deg, fwd or 1500, yaw or 1500))
        t += dt
    applet.next_frame, applet.next_pilot = next_frame, next_pilot
    return trace
