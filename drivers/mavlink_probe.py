"""One-shot autopilot probe for `netpose mavlink-check`: identity, rangefinder parameters, and
what an operator must change so ArduSub accepts netpose's DISTANCE_SENSOR.

`probe_autopilot` does the I/O (blocking, bounded by a timeout); `advise` is pure.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

from drivers.errors import MavlinkLinkError
from drivers.mavlink_link import (
    MAV_AUTOPILOT_INVALID,
    MAV_COMP_ID_AUTOPILOT1,
    MAV_STATE_ACTIVE,
    MAV_TYPE_ONBOARD_CONTROLLER,
    NON_AUTOPILOT_TYPES,
    baud_hint,
    open_connection,
)
from drivers.mavlink_settings import MavlinkSettings, load_signing_key

# ArduPilot has ten rangefinder instances, RNGFND1_ .. RNGFND9_ and RNGFNDA_ (every build with
# rangefinders: AP_RangeFinder.h), and hands every DISTANCE_SENSOR to each instance that is
# not off; an instance of type MAVLink keeps the readings of its own orientation. So netpose can
# use any free instance: a BlueROV2's Ping altimeter (usually RNGFND1, facing down for SURFTRAK)
# stays as it is.
RANGEFINDER_INSTANCES = tuple("123456789A")
# ArduSub 4.5 names the limits in cm (RNGFNDn_MIN_CM/MAX_CM), 4.7 in metres (RNGFNDn_MIN/MAX);
# asking for both tells which firmware generation answered.
INSTANCE_SUFFIXES = ("TYPE", "ORIENT", "MIN_CM", "MAX_CM", "MIN", "MAX")
# The first ArduSub whose Lua has what scripts/net_hold.lua calls.
NET_HOLD_MIN_FIRMWARE = (4, 5, 0)


def instance_params(instance: str) -> tuple[str, ...]:
    return tuple(f"RNGFND{instance}_{suffix}" for suffix in INSTANCE_SUFFIXES)


RANGEFINDER_PARAMS = (
    *(name for instance in RANGEFINDER_INSTANCES for name in instance_params(instance)),
    "RNGFND_SQ_MIN",
)
# Lua scripting, and two parameters the net-hold applet (scripts/net_hold.lua) creates once it runs.
NET_HOLD_PARAMS = ("SCR_ENABLE", "NETH_ENABLE", "NETH_DIST")

RNGFND_TYPE_NONE = 0
RNGFND_TYPE_MAVLINK = 10
# The types a companion computer's operator meets (AP_RangeFinder_Params.cpp), for the advice.
RNGFND_TYPE_NAMES = MappingProxyType({0: "none", 10: "MAVLink", 23: "Blue Robotics Ping"})
ORIENTATION_NAMES = MappingProxyType({0: "forward", 4: "backward", 24: "up", 25: "down"})
_MAV_CMD_REQUEST_MESSAGE = 512
_MSG_ID_AUTOPILOT_VERSION = 148


@dataclass(frozen=True)
class AutopilotReport:
    sysid: int
    compid: int
    mav_type: int
    autopilot: int
    mavlink_version: int
    flight_sw_version: int | None
    params: dict[str, float] = field(default_factory=dict)

    @property
    def version(self) -> tuple[int, int, int] | None:
        """(major, minor, patch) from AUTOPILOT_VERSION."""
        v = self.flight_sw_version
        return None if v is None else ((v >> 24) & 0xFF, (v >> 16) & 0xFF, (v >> 8) & 0xFF)

    @property
    def firmware(self) -> str | None:
        """'4.5.3' (+ ' beta' etc. unless an official release) from AUTOPILOT_VERSION."""
        v = self.flight_sw_version
        if v is None:
            return None
        kinds = {0: "dev", 64: "alpha", 128: "beta", 192: "rc", 255: ""}
        kind = kinds.get(v & 0xFF, f"type {v & 0xFF}")
        text = f"{(v >> 24) & 0xFF}.{(v >> 16) & 0xFF}.{(v >> 8) & 0xFF}"
        return f"{text} {kind}".strip()


@dataclass(frozen=True)
class Advice:
    changes: list[str]  # parameter or configuration changes that are needed
    notes: list[str]  # things worth knowing that need no change
    # The rangefinder instance ("1" .. "9", "A") that takes netpose's readings, or should;
    # None when the autopilot reported none.
    instance: str | None = None


def _is_autopilot_heartbeat(msg: Any) -> bool:
    return bool(
        msg.get_type() == "HEARTBEAT"
        and msg.autopilot != MAV_AUTOPILOT_INVALID
        and msg.type not in NON_AUTOPILOT_TYPES
        and msg.get_srcComponent() == MAV_COMP_ID_AUTOPILOT1
    )


def probe_autopilot(
    settings: MavlinkSettings,
    timeout_s: float = 5.0,
    param_names: tuple[str, ...] = RANGEFINDER_PARAMS + NET_HOLD_PARAMS,
) -> AutopilotReport:
    """Wait for the autopilot's heartbeat, ask for AUTOPILOT_VERSION and the named parameters.

    Parameters the firmware does not have are simply absent from the report (ArduPilot does not
    answer PARAM_REQUEST_READ for unknown names). Raises MavlinkLinkError when the link cannot be
    opened or no autopilot heartbeat arrives within `timeout_s`.
    """
    key = load_signing_key(settings.signing_key_file) if settings.signing_key_file else None
    try:
        conn = open_connection(settings, key)
    except MavlinkLinkError:
        raise  # already says what and why
    except Exception as exc:
        raise MavlinkLinkError(f"cannot open {settings.url}: {exc}") from exc
    try:
        return _probe(conn, settings, timeout_s, param_names)
    finally:
        conn.close()


def _heartbeat(conn: Any) -> None:
    # Our own heartbeat also tells a UDP peer or router where to send its answers.
    conn.mav.heartbeat_send(MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0,
                            MAV_STATE_ACTIVE)


def _probe(
    conn: Any, settings: MavlinkSettings, timeout_s: float, param_names: tuple[str, ...]
) -> AutopilotReport:
    deadline = time.monotonic() + timeout_s
    next_heartbeat = 0.0
    heartbeat = None
    while heartbeat is None:
        now = time.monotonic()
        if now > deadline:
            received = int(getattr(conn.mav, "total_bytes_received", 0))
            why = ("is the autopilot powered and the URL right?" if not settings.is_serial
                   or received == 0 else baud_hint(received, settings.baud, "--baud",
                                                   "an autopilot's heartbeat"))
            raise MavlinkLinkError(
                f"no autopilot heartbeat on {settings.url} within {timeout_s:g} s ({why})"
            )
        if now >= next_heartbeat:
            _heartbeat(conn)
            next_heartbeat = now + 1.0
        msg = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=0.2)
        if msg is not None and _is_autopilot_heartbeat(msg):
            heartbeat = msg
    sysid, compid = heartbeat.get_srcSystem(), heartbeat.get_srcComponent()
    # An instance's settings are asked for once it says it exists (its TYPE answered): every
    # unanswered name costs PARAM_TRIES waits, and a board may have fewer than ten.
    first = tuple(n for n in param_names if _instance_setting(n) is None)
    params = _read_params(conn, sysid, compid, first, timeout_s)
    # Of the instances that are off, only the first matters: the one netpose would take.
    off = [i for i in RANGEFINDER_INSTANCES
           if params.get(f"RNGFND{i}_TYPE") == RNGFND_TYPE_NONE]
    wanted = {i for i in RANGEFINDER_INSTANCES
              if f"RNGFND{i}_TYPE" in params and (i not in off or i == off[0])}
    rest = tuple(n for n in param_names if _instance_setting(n) in wanted)
    params |= _read_params(conn, sysid, compid, rest, timeout_s)
    version = _read_version(conn, sysid, compid)
    return AutopilotReport(
        sysid=sysid,
        compid=compid,
        mav_type=heartbeat.type,
        autopilot=heartbeat.autopilot,
        mavlink_version=2 if heartbeat.get_msgbuf()[0] == 0xFD else 1,
        flight_sw_version=version,
        params=params,
    )


# ArduPilot queues at most 20 parameter requests (all links together, GCS_Param.cpp) and drops
# the rest: 64 asked at once came back 22-26. A few at a time leave room for a ground station's.
PARAM_WINDOW = 8
PARAM_ANSWER_S = 0.5  # asked again after this long without an answer
PARAM_TRIES = 2  # then the firmware has no such parameter (it never answers for those)


def _instance_setting(name: str) -> str | None:
    """The rangefinder instance ("1" .. "A") whose setting (other than TYPE) `name` is."""
    for instance in RANGEFINDER_INSTANCES:
        prefix = f"RNGFND{instance}_"
        if name.startswith(prefix) and name != f"{prefix}TYPE":
            return instance
    return None


def _read_params(conn: Any, sysid: int, compid: int, names: tuple[str, ...],
                 timeout_s: float) -> dict[str, float]:
    """The named parameters the autopilot has, asked for PARAM_WINDOW at a time.

    A name is asked again, then given up as not on this firmware, only after PARAM_ANSWER_S
    in which nothing was answered at all: an autopilot that answers slowly (a busy radio
    link) still has the request queued, and a repeat would only queue behind it."""
    waiting = list(names)
    asked: dict[str, tuple[float, int]] = {}  # name -> (when last asked, times asked)
    params: dict[str, float] = {}
    last_answer = time.monotonic()
    deadline = time.monotonic() + max(5.0, timeout_s) + len(names) * 0.5
    while (waiting or asked) and time.monotonic() < deadline:
        now = time.monotonic()
        for name, (when, tries) in list(asked.items()):
            if now - max(when, last_answer) < PARAM_ANSWER_S:
                continue
            if tries >= PARAM_TRIES:
                del asked[name]  # not on this firmware
            else:
                conn.mav.param_request_read_send(sysid, compid, name.encode("ascii"), -1)
                asked[name] = (now, tries + 1)
        while waiting and len(asked) < PARAM_WINDOW:
            name = waiting.pop(0)
            conn.mav.param_request_read_send(sysid, compid, name.encode("ascii"), -1)
            asked[name] = (now, 1)
        msg = conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=0.05)
        if msg is None or (msg.get_srcSystem(), msg.get_srcComponent()) != (sysid, compid):
            continue
        if msg.param_id in names:
            params[msg.param_id] = float(msg.param_value)
            if msg.param_id in asked:
                last_answer = time.monotonic()
            asked.pop(msg.param_id, None)
            if msg.param_id in waiting:
                waiting.remove(msg.param_id)
    return params


def _read_version(conn: Any, sysid: int, compid: int) -> int | None:
    """AUTOPILOT_VERSION.flight_sw_version (asked twice), or None."""
    for _ in range(2):
        conn.mav.command_long_send(sysid, compid, _MAV_CMD_REQUEST_MESSAGE, 0,
                                   _MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0)
        deadline = time.monotonic() + 1.0
        while time.monotonic() < deadline:
            msg = conn.recv_match(type="AUTOPILOT_VERSION", blocking=True, timeout=0.1)
            if msg is not None and (msg.get_srcSystem(), msg.get_srcComponent()) == (sysid,
                                                                                        compid):
                return int(msg.flight_sw_version)
    return None


def _fmt(value: float) -> str:
    return str(int(value)) if float(value).is_integer() else f"{value:g}"


def advise(report: AutopilotReport, settings: MavlinkSettings, net_hold: bool = False) -> Advice:
    """What to change on the autopilot (or in netpose's [mavlink] settings) and why."""
    p = report.params
    changes: list[str] = []
    notes: list[str] = []
    if report.sysid != settings.source_system:
        changes.append(f"set mavlink.source_system = {report.sysid} in netpose's configuration "
                       "(netpose must use the vehicle's system id)")
    want = settings.orientation
    instance = _rangefinder_changes(p, want, changes, notes)
    if instance is not None:
        changes.extend(_limit_changes(p, instance, settings, notes))
    sq_min = p.get("RNGFND_SQ_MIN")
    if sq_min is not None and sq_min > 0:
        if want == 25:
            notes.append(f"RNGFND_SQ_MIN = {_fmt(sq_min)}: SURFTRAK ignores readings whose "
                         f"signal_quality is below it; netpose sends round(100 * confidence), so "
                         f"confidence below {sq_min / 100:.2f} is not used")
        else:
            notes.append(f"RNGFND_SQ_MIN = {_fmt(sq_min)} applies only to the downward "
                         "rangefinder (SURFTRAK); a forward reading is stored, logged and "
                         "readable from Lua scripts whatever its quality")
    if net_hold:
        version = report.version
        if version is not None and version < NET_HOLD_MIN_FIRMWARE:
            # The applet's Lua bindings (sub:get_and_clear_button_count, mavlink:block_command)
            # came in 2023: on an older firmware the script does not load at all.
            changes.append(f"update the autopilot to ArduSub 4.5 or later (it runs "
                           f"{report.firmware}): the net-hold applet needs its Lua bindings")
        if p.get("SCR_ENABLE") is None or int(p["SCR_ENABLE"]) != 1:
            changes.append("set SCR_ENABLE = 1 (Lua scripting, for the net-hold applet) and "
                           "reboot the autopilot")
        elif "NETH_ENABLE" not in p:
            changes.append("the net-hold applet is not running: copy scripts/net_hold.lua to the "
                           "autopilot's scripts folder and reboot (docs/net-hold.md)")
        if not settings.send_net_plane:
            changes.append("set mavlink.send_net_plane = true: the applet needs the net plane")
    return Advice(changes=changes, notes=notes, instance=instance)


def _type_name(value: float) -> str:
    return RNGFND_TYPE_NAMES.get(int(value), f"type {_fmt(value)}")


def _orientation_name(value: float) -> str:
    return ORIENTATION_NAMES.get(int(value), f"rotation {_fmt(value)}")


def _orientation_of(value: float | None) -> str:
    return "an orientation it did not report" if value is None else _orientation_name(value)


def _rangefinder_changes(
    p: dict[str, float], want: int, changes: list[str], notes: list[str]
) -> str | None:
    """Which rangefinder instance takes netpose's readings (or should), and what to change so
    it does; None when the autopilot reported no rangefinder parameters at all."""
    present = [n for n in RANGEFINDER_INSTANCES if f"RNGFND{n}_TYPE" in p]
    if not present:
        changes.append("the autopilot did not report RNGFND1_TYPE: use a firmware with "
                       "rangefinder support")
        return None

    def kind(n: str) -> int:
        return int(p[f"RNGFND{n}_TYPE"])

    def facing(n: str) -> int | None:
        value = p.get(f"RNGFND{n}_ORIENT")
        return None if value is None else int(value)

    want_name = _orientation_name(want)
    ours = [n for n in present if kind(n) == RNGFND_TYPE_MAVLINK and facing(n) == want]
    chosen = ours[0] if ours else None
    free = [n for n in present if kind(n) == RNGFND_TYPE_NONE]
    elsewhere = [n for n in present if kind(n) == RNGFND_TYPE_MAVLINK]
    if chosen is None:
        if free:
            chosen = free[0]
            changes.append(f"set RNGFND{chosen}_TYPE = {RNGFND_TYPE_MAVLINK} (MAVLink; a free "
                           "rangefinder instance) and reboot the autopilot")
            for n in elsewhere:
                notes.append(f"RNGFND{n} is a MAVLink rangefinder facing "
                             f"{_orientation_of(facing(n))}: left as it is (another "
                             f"sensor may send to it); netpose's readings face {want_name}")
        elif elsewhere:
            chosen = elsewhere[0]
        else:
            # Every instance holds a sensor: one of them has to give way; not the one facing down
            # if there is a choice (ArduSub's SURFTRAK and the pilot's altitude read it).
            chosen = next((n for n in present if facing(n) != 25), present[0])
            changes.append(f"set RNGFND{chosen}_TYPE = {RNGFND_TYPE_MAVLINK} (MAVLink; now "
                           f"{_type_name(kind(chosen))}, which this replaces: every rangefinder "
                           "instance of this autopilot is in use) and reboot the autopilot")
    orient = facing(chosen)
    if orient is not None and orient != want:
        changes.append(f"set RNGFND{chosen}_ORIENT = {want} ({want_name}; now {_fmt(orient)}):"
                       " the autopilot ignores DISTANCE_SENSOR of any other orientation")
    # Asked for "the forward rangefinder" (the net-hold applet, the ground station), the
    # autopilot answers with the first instance of that orientation that has a good reading,
    # else the first of it: another sensor facing the same way would answer for netpose
    # whenever netpose has nothing, or whenever it comes first.
    for n in present:
        if (n != chosen and kind(n) not in (RNGFND_TYPE_NONE, RNGFND_TYPE_MAVLINK)
                and facing(n) == want):
            changes.append(
                f"RNGFND{n} ({_type_name(kind(n))}) also faces {want_name}: the autopilot "
                f"would read it as netpose's (RNGFND{chosen}); set RNGFND{n}_ORIENT to where "
                f"that sensor really looks, or RNGFND{n}_TYPE = 0")
    return chosen


def _limit_changes(
    p: dict[str, float], instance: str, settings: MavlinkSettings, notes: list[str]
) -> list[str]:
    # ArduPilot uses the narrower of its parameters and the message's min/max, so its minimum
    # must not exceed ours and its maximum must not fall short of ours.
    ours_min, ours_max = settings.min_distance_m, settings.max_distance_m
    changes: list[str] = []
    prefix = f"RNGFND{instance}_"
    for low, high, scale, unit in (
        (f"{prefix}MIN_CM", f"{prefix}MAX_CM", 100.0, "cm"),
        (f"{prefix}MIN", f"{prefix}MAX", 1.0, "m"),
    ):
        if low not in p and high not in p:
            continue
        if low in p and p[low] > ours_min * scale + 1e-6:
            changes.append(f"set {low} = {_fmt(round(ours_min * scale, 2))} (now "
                           f"{_fmt(p[low])} {unit}): readings below it are 'out of range'")
        if high in p and p[high] < ours_max * scale - 1e-6:
            changes.append(f"set {high} = {_fmt(round(ours_max * scale, 2))} (now "
                           f"{_fmt(p[high])} {unit}): readings above it are 'out of range'")
        return changes
    notes.append(f"neither {prefix}MIN_CM/MAX_CM nor {prefix}MIN/MAX reported: range limits "
                 "not checked")
    return changes
