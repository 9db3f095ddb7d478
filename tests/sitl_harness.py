"""ArduSub SITL for closed-loop tests: the simulator in a scratch directory, and a ground station
that is the test's pilot and observer.

    with Sitl(binary, workdir, instance, params, scripts=[...]) as sitl:
        pilot = Pilot(sitl.port(1))        # SERIAL1, as the ground station (system id 255)
        ...

Facts this relies on (ArduSub 4.7.0-dev SITL, docs/net-hold.md): SERIALk listens on TCP
5760 + 10 * instance + 2 * k; scripts are read from ./scripts of the working directory; ArduSub
forwards other components' messages to a link only after it has heard from that link (the pilot
sends a heartbeat first); SIM_STATE (the simulator's true pose) flows at the rate asked for with
SET_MESSAGE_INTERVAL; ArduSub takes MANUAL_CONTROL only from the ground station's system id, and
turns it into RC overrides of channels 1-8 (joystick.cpp), as a pilot's joystick does.
"""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import threading
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any

MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_SET_MESSAGE_INTERVAL = 511
ARM_FORCE_MAGIC = 21196
MODE_ALT_HOLD = 2
EARTH_RADIUS_M = 6378137.0


def mavutil() -> Any:
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil as mu

    return mu


class Sitl:
    """An ArduSub SITL process, started in `workdir` with a defaults file; stopped on exit."""

    def __init__(self, binary: str, workdir: Path, instance: int, params: Mapping[str, float],
                 scripts: Iterable[Path] = (), home: str = "33.810313,-118.393867,0,0",
                 serials: int = 3, model: str = "vectored") -> None:
        self.binary = binary
        self.workdir = workdir
        self.instance = instance
        self.home = home
        workdir.mkdir(parents=True, exist_ok=True)
        (workdir / "defaults.parm").write_text(
            "".join(f"{name} {value:g}\n" for name, value in params.items()))
        if scripts:
            (workdir / "scripts").mkdir(exist_ok=True)
            for script in scripts:
                shutil.copy(script, workdir / "scripts" / script.name)
        # SERIAL0..serials-1 on TCP; the others off (never --serial9: it crashes with --defaults).
        self.args = [binary, "--model", model, "--speedup", "1", "-I", str(instance),
                     "--defaults", "defaults.parm", "--home", home]
        for k in range(9):
            self.args.append(f"--serial{k}=tcp:{2 * k}" if k < serials else f"--serial{k}=none")
        self.log_path = workdir / "sitl.log"
        self.proc: subprocess.Popen[bytes] | None = None

    def port(self, serial: int) -> int:
        return 5760 + 10 * self.instance + 2 * serial

    @property
    def home_lat_lon(self) -> tuple[float, float]:
        lat, lon = self.home.split(",")[:2]
        return float(lat), float(lon)

    def __enter__(self) -> Sitl:
        with self.log_path.open("wb") as log:
            self.proc = subprocess.Popen(self.args, cwd=self.workdir, stdout=log,
                                         stderr=subprocess.STDOUT)
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        proc = self.proc
        if proc is None:
            return
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()

    def log_tail(self, chars: int = 2000) -> str:
        try:
            return self.log_path.read_text(errors="replace")[-chars:]
        except OSError as exc:
            return f"(no SITL log: {exc})"


@dataclass
class Record:
    """What the pilot's link saw, each with its arrival time (time.monotonic)."""

    sim: list[tuple[float, Any]] = field(default_factory=list)
    rc: list[tuple[float, int, int]] = field(default_factory=list)  # t, yaw ch4, forward ch5
    texts: list[tuple[float, str]] = field(default_factory=list)
    named: list[tuple[float, str, float]] = field(default_factory=list)
    planes: list[tuple[float, int, float, float, float]] = field(default_factory=list)
    sticks: list[tuple[float, int, int, int, int, int]] = field(default_factory=list)
    acks: list[tuple[float, Any]] = field(default_factory=list)  # COMMAND_ACK


def connect(port: int, timeout_s: float = 60.0, **kwargs: Any) -> Any:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return mavutil().mavlink_connection(f"tcp:127.0.0.1:{port}", retries=0, **kwargs)
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)


class Pilot:
    """The ground station: the pilot's joystick (MANUAL_CONTROL at 25 Hz, as QGroundControl and
    Cockpit send it, neutral unless told otherwise) and the test's observer. Owns one thread."""

    def __init__(self, port: int, manual_hz: float = 25.0) -> None:
        self.conn = connect(port, source_system=255, source_component=190)
        self.manual_period = 1.0 / manual_hz
        self.sticks = {"x": 0, "y": 0, "z": 500, "r": 0, "buttons": 0}
        self.joystick = True
        self.record = Record()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sitl-pilot", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.conn.close()

    # -- commands -------------------------------------------------------------------------------
    def set_sticks(self, **values: int) -> float:
        with self._lock:
            self.sticks.update(values)
        return time.monotonic()

    def press(self, button_index: int, hold_s: float = 0.3) -> None:
        self.set_sticks(buttons=1 << button_index)
        time.sleep(hold_s)
        self.set_sticks(buttons=0)

    def interval(self, msg_id: int, hz: float) -> None:
        with self._lock:
            self.conn.mav.command_long_send(1, 1, MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id,
                                            int(1e6 / hz), 0, 0, 0, 0, 0)

    def arm(self) -> None:
        with self._lock:
            self.conn.mav.command_long_send(1, 1, MAV_CMD_COMPONENT_ARM_DISARM, 0, 1,
                                            ARM_FORCE_MAGIC, 0, 0, 0, 0, 0)

    def command(self, command: int, param1: float) -> float:
        """COMMAND_LONG to the autopilot; returns when it was sent."""
        with self._lock:
            self.conn.mav.command_long_send(1, 1, command, 0, param1, 0, 0, 0, 0, 0, 0)
        return time.monotonic()

    def ack(self, command: int, after: float) -> Any:
        """The first COMMAND_ACK for `command` that came after `after`, or None."""
        with self._lock:
            return next((m for t, m in self.record.acks
                         if t >= after and m.command == command), None)

    def mode(self, mode: int) -> None:
        with self._lock:
            self.conn.mav.set_mode_send(1, 1, mode)

    def param(self, name: str, value: float) -> None:
        with self._lock:
            self.conn.mav.param_set_send(1, 1, name.encode(), float(value), 9)

    # -- observations ---------------------------------------------------------------------------
    def newest_sim(self) -> tuple[float, Any] | None:
        with self._lock:
            return self.record.sim[-1] if self.record.sim else None

    def wait_text(self, contains: str, after: float, timeout_s: float) -> tuple[float, str]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self._lock:
                for t, text in self.record.texts:
                    if t >= after and contains in text:
                        return t, text
            time.sleep(0.02)
        with self._lock:
            texts = [text for t, text in self.record.texts if t >= after - 5]
        raise AssertionError(f"no STATUSTEXT containing {contains!r} within {timeout_s} s; "
                             f"got {texts}")

    def wait_for(self, what: str, predicate: Any, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while not predicate():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out waiting for {what}")
            time.sleep(0.05)

    # -- thread ---------------------------------------------------------------------------------
    def _run(self) -> None:
        next_heartbeat = next_manual = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            with self._lock:
                if now >= next_heartbeat:
                    self.conn.mav.heartbeat_send(6, 8, 0, 0, 4)  # GCS, MAV_AUTOPILOT_INVALID
                    next_heartbeat = now + 1.0
                if self.joystick and now >= next_manual:
                    s = self.sticks
                    self.conn.mav.manual_control_send(1, s["x"], s["y"], s["z"], s["r"],
                                                      s["buttons"])
                    self.record.sticks.append((now, s["x"], s["y"], s["z"], s["r"],
                                               s["buttons"]))
                    next_manual += self.manual_period
                    if next_manual < now:
                        next_manual = now + self.manual_period
            self.conn.select(0.005)
            while (msg := self.conn.recv_msg()) is not None:
                self._handle(msg, time.monotonic())

    def _handle(self, msg: Any, now: float) -> None:
        kind = msg.get_type()
        rec = self.record
        with self._lock:
            if kind == "SIM_STATE":
                rec.sim.append((now, msg))
            elif kind == "RC_CHANNELS":
                rec.rc.append((now, msg.chan4_raw, msg.chan5_raw))
            elif kind == "STATUSTEXT":
                rec.texts.append((now, msg.text))
            elif kind == "NAMED_VALUE_FLOAT":
                rec.named.append((now, msg.name, msg.value))
            elif kind == "COMMAND_ACK":
                rec.acks.append((now, msg))
            elif kind == "DEBUG_VECT" and msg.name == "NET_PLANE":
                rec.planes.append((now, msg.time_usec, msg.x, msg.y, msg.z))


def local_ne(msg: Any, origin: tuple[float, float]) -> tuple[float, float]:
    """SIM_STATE's position in metres north and east of `origin` (lat, lon in degrees)."""
    lat, lon = msg.lat_int * 1e-7, msg.lon_int * 1e-7
    north = math.radians(lat - origin[0]) * EARTH_RADIUS_M
    east = math.radians(lon - origin[1]) * EARTH_RADIUS_M * math.cos(math.radians(origin[0]))
    return north, east
