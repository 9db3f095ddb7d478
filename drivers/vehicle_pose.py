"""The vehicle's pose, read from the autopilot over a MAVLink connection of its own.

Used by the `sim:` frame source to know where its simulated camera is. One owned thread does all
I/O: it connects (retrying with backoff), sends a heartbeat at 1 Hz first (ArduSub forwards
nothing to a link it has heard nothing from), asks for the messages below with
SET_MESSAGE_INTERVAL (per link, so other links are not affected; asked again every few seconds
until they flow, in case a request was lost or the autopilot rebooted) and keeps the newest pose.

  SIM_STATE            the simulator's true pose (SITL only): position from lat_int/lon_int
                       (1e-7 deg: steps of ~1 cm), altitude, roll/pitch/yaw. Preferred. The
                       steps are smoothed out with SIM_STATE's own (exact) velocity: the
                       position follows the velocity, pulled toward the stepped fixes with a
                       1 s time constant, so a rendered distance does not jump by a centimetre
                       (which, differenced over a frame, reads as 0.1 m/s).
  LOCAL_POSITION_NED   the EKF's position and ATTITUDE its attitude: used when no SIM_STATE
  + ATTITUDE           comes (a vehicle or simulator without it), once both are flowing.

Positions are local NED metres from the first pose's place (SIM_STATE) or from the EKF origin.
The pose's time is its arrival on this host's monotonic clock (SIM_STATE has no timestamp; on
loopback the delay is well under a millisecond).
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

from drivers.mavlink_link import MAV_AUTOPILOT_INVALID, MAV_STATE_ACTIVE, open_connection
from drivers.mavlink_settings import MavlinkSettings
from drivers.sim_world import VehiclePose
from service.core.backoff import Backoff
from service.core.redact import redact_text

log = logging.getLogger(__name__)

MSG_ID_ATTITUDE = 30
MSG_ID_LOCAL_POSITION_NED = 32
MSG_ID_SIM_STATE = 108
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_TYPE_GENERIC = 0
EARTH_RADIUS_M = 6378137.0
_HEARTBEAT_PERIOD_S = 1.0
_REQUEST_PERIOD_S = 3.0
# With SIM_STATE absent this long after the first request, the EKF's pose is used.
_SIM_STATE_GRACE_S = 3.0
# An EKF attitude older than this is not combined with a new position.
_ATTITUDE_MAX_AGE_S = 0.2
# Time constant of the pull of the velocity-propagated position toward SIM_STATE's fixes.
_SMOOTHING_S = 1.0

PoseSource = Literal["auto", "sim", "ekf"]


@dataclass(frozen=True)
class PoseFeedSettings:
    url: str  # a MAVLink URL as in [mavlink] url: tcp:HOST:PORT, udpin:..., udpout:..., serial
    source_system: int = 1
    source_component: int = 25  # MAV_COMP_ID_USER1: a simulation tool, not a vehicle part
    rate_hz: float = 20.0
    source: PoseSource = "auto"
    # Geodetic origin (lat, lon in degrees) of SIM_STATE's local coordinates; None: the first pose.
    origin: tuple[float, float] | None = None


class VehiclePoseFeed:
    """Newest vehicle pose from the autopilot; `start()` returns at once, `close()` joins."""

    def __init__(
        self,
        settings: PoseFeedSettings,
        clock: Callable[[], float] = time.monotonic,
        connection_factory: Callable[[MavlinkSettings, bytes | None], Any] = open_connection,
    ) -> None:
        self.settings = settings
        # Checked like the autopilot link's own settings (URL, ids).
        self._link_settings = MavlinkSettings(
            url=settings.url, source_system=settings.source_system,
            source_component=settings.source_component,
        )
        self._clock = clock
        self._factory = connection_factory
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._pose: VehiclePose | None = None
        self._origin: tuple[float, float, float] | None = None  # lat, lon (deg), alt (m)
        self._smoothed: tuple[float, float, float, float] | None = None  # t, north, east, down
        self._attitude: tuple[float, float, float, float] | None = None  # t, roll, pitch, yaw
        self._first_request: float | None = None
        self._sim_state_seen = False
        # The first pose's source is kept: the two have different origins.
        self._chosen: str | None = None
        self.poses = 0
        self.errors = 0
        self._url = redact_text(settings.url)

    def start(self) -> None:
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="netpose-vehicle-pose",
                                        daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        with self._changed:
            self._changed.notify_all()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(timeout=5.0)

    def newest(self) -> VehiclePose | None:
        with self._lock:
            return self._pose

    def wait_newer(self, than: float, timeout_s: float) -> VehiclePose | None:
        """The newest pose if it is newer than `than`, waiting for one at most `timeout_s`."""
        deadline = self._clock() + max(0.0, timeout_s)
        with self._changed:
            while not self._stop.is_set():
                pose = self._pose
                if pose is not None and pose.t > than:
                    return pose
                left = deadline - self._clock()
                if left <= 0:
                    return None
                self._changed.wait(left)
        return None

    # ---- thread ------------------------------------------------------------------------------
    def _run(self) -> None:
        backoff = Backoff(0.5, 5.0)
        while not self._stop.is_set():
            try:
                conn = self._factory(self._link_settings, None)
            except Exception as exc:
                self._failed(exc, backoff)
                continue
            backoff.reset()
            log.info("vehicle pose: MAVLink %s open", self._url)
            try:
                self._serve(conn)
            except Exception as exc:
                self._failed(exc, backoff)
            finally:
                with contextlib.suppress(Exception):
                    conn.close()

    def _failed(self, exc: Exception, backoff: Backoff) -> None:
        self.errors += 1
        if not backoff.in_outage:
            log.warning("vehicle pose: MAVLink %s unavailable (%s: %s); retrying", self._url,
                        type(exc).__name__, exc)
        self._stop.wait(backoff.next_delay(self._clock()))

    def _serve(self, conn: Any) -> None:
        next_heartbeat = next_request = self._clock()
        while not self._stop.is_set():
            now = self._clock()
            if now >= next_heartbeat:
                conn.mav.heartbeat_send(MAV_TYPE_GENERIC, MAV_AUTOPILOT_INVALID, 0, 0,
                                        MAV_STATE_ACTIVE)
                next_heartbeat = now + _HEARTBEAT_PERIOD_S
            if now >= next_request and not self._flowing(now):
                self._request(conn)
                if self._first_request is None:
                    self._first_request = now
                next_request = now + _REQUEST_PERIOD_S
            conn.select(0.05)
            while (msg := conn.recv_msg()) is not None:
                self._handle(msg, self._clock())

    def _flowing(self, now: float) -> bool:
        pose = self.newest()
        return pose is not None and now - pose.t < 1.0

    def _request(self, conn: Any) -> None:
        interval_us = int(1e6 / self.settings.rate_hz)
        wanted = {"auto": (MSG_ID_SIM_STATE, MSG_ID_LOCAL_POSITION_NED, MSG_ID_ATTITUDE),
                  "sim": (MSG_ID_SIM_STATE,),
                  "ekf": (MSG_ID_LOCAL_POSITION_NED, MSG_ID_ATTITUDE)}[self.settings.source]
        for msg_id in wanted:
            conn.mav.command_long_send(1, 1, MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id,
                                       interval_us, 0, 0, 0, 0, 0)

    def _handle(self, msg: Any, now: float) -> None:
        kind = msg.get_type()
        if kind == "SIM_STATE" and self.settings.source != "ekf" and self._chosen != "ekf":
            pose = self._from_sim_state(msg, now)
            if pose is not None:
                self._sim_state_seen = True
                self._publish(pose)
        elif kind == "ATTITUDE":
            self._attitude = (now, float(msg.roll), float(msg.pitch), float(msg.yaw))
        elif kind == "LOCAL_POSITION_NED" and self._use_ekf(now):
            att = self._attitude
            if att is None or now - att[0] > _ATTITUDE_MAX_AGE_S:
                return
            self._publish(VehiclePose(now, float(msg.x), float(msg.y), float(msg.z), att[1],
                                      att[2], att[3], source="ekf"))

    def _use_ekf(self, now: float) -> bool:
        if self.settings.source == "ekf":
            return True
        if self.settings.source == "sim" or self._sim_state_seen:
            return False
        if self._chosen == "ekf":
            return True
        return self._first_request is not None and now - self._first_request > _SIM_STATE_GRACE_S

    def _from_sim_state(self, msg: Any, now: float) -> VehiclePose | None:
        lat_int = getattr(msg, "lat_int", 0)
        lon_int = getattr(msg, "lon_int", 0)
        if not lat_int and not lon_int:
            return None  # an old SIM_STATE without the integer position: too coarse to use
        lat, lon, alt = lat_int * 1e-7, lon_int * 1e-7, float(msg.alt)
        if self._origin is None:
            given = self.settings.origin
            self._origin = (lat, lon, alt) if given is None else (given[0], given[1], alt)
        lat0, lon0, alt0 = self._origin
        north = math.radians(lat - lat0) * EARTH_RADIUS_M
        east = math.radians(lon - lon0) * EARTH_RADIUS_M * math.cos(math.radians(lat0))
        down = -(alt - alt0)
        previous = self._smoothed
        if previous is not None and 0.0 < now - previous[0] < 0.5:
            dt = now - previous[0]
            gain = min(1.0, dt / _SMOOTHING_S)
            velocity = (float(msg.vn), float(msg.ve), float(msg.vd))
            fix = (north, east, down)
            north, east, down = (
                p + v * dt + gain * (f - (p + v * dt))
                for p, v, f in zip(previous[1:], velocity, fix, strict=True)
            )
        self._smoothed = (now, north, east, down)
        return VehiclePose(now, north, east, down, float(msg.roll), float(msg.pitch),
                           float(msg.yaw), source="sim_state")

    def _publish(self, pose: VehiclePose) -> None:
        with self._changed:
            first = self._pose is None
            self._pose = pose
            self._chosen = pose.source
            self.poses += 1
            self._changed.notify_all()
        if first:
            log.info("vehicle pose: first pose from %s", pose.source)
