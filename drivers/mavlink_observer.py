"""A MAVLink peer on loopback UDP that keeps the DISTANCE_SENSOR messages it receives.

What a ground station (or, with `as_autopilot`, the autopilot) sees of netpose: the soak
benchmark and the end-to-end tests point the daemon's `udpout:` link at it. As the autopilot it
answers with HEARTBEAT and SYSTEM_TIME on its own boot clock (its monotonic time since it
started), so the link stamps every DISTANCE_SENSOR with the frame's capture time on a clock
this side can read: `capture_time(arrival)` is then the capture instant on our monotonic clock,
and capture-to-arrival latency needs no matching of values. Owns one thread; `close()` stops and
joins it.
"""

from __future__ import annotations

import socket
import threading
import time
from dataclasses import dataclass

from drivers.mavlink_link import import_mavutil

MAV_TYPE_SUBMARINE = 12
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
ANSWER_PERIOD_S = 0.5


@dataclass(frozen=True)
class DistanceArrival:
    t_received: float  # monotonic arrival time
    current_cm: int
    min_cm: int
    max_cm: int
    time_boot_ms: int
    signal_quality: int
    covariance: int


class DistanceObserver:
    def __init__(self, *, as_autopilot: bool = False) -> None:
        mavutil = import_mavutil()
        self._mav = mavutil.mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self._mav.robust_parsing = True
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind(("127.0.0.1", 0))
        self._sock.settimeout(0.05)
        self.url = f"udpout:127.0.0.1:{self._sock.getsockname()[1]}"
        self.as_autopilot = as_autopilot
        self.boot = time.monotonic()  # the autopilot's boot instant, when it plays one
        self._lock = threading.Lock()
        self._arrivals: list[DistanceArrival] = []
        self.heartbeats = 0
        self._peer: tuple[str, int] | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="mavlink-observer", daemon=True)
        self._thread.start()

    def capture_time(self, arrival: DistanceArrival) -> float:
        """The capture instant of the frame behind a message (our monotonic clock); meaningful
        when this observer plays the autopilot, whose boot clock the link stamps with."""
        return self.boot + arrival.time_boot_ms / 1000.0

    def _run(self) -> None:
        next_answer = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if self.as_autopilot and self._peer is not None and now >= next_answer:
                next_answer = now + ANSWER_PERIOD_S
                self._answer(now)
            try:
                data, peer = self._sock.recvfrom(65535)
            except TimeoutError:
                continue
            except OSError:
                return
            t = time.monotonic()
            self._peer = peer
            for msg in self._mav.parse_buffer(data) or []:
                kind = msg.get_type()
                with self._lock:
                    if kind == "DISTANCE_SENSOR":
                        self._arrivals.append(DistanceArrival(
                            t, int(msg.current_distance), int(msg.min_distance),
                            int(msg.max_distance), int(msg.time_boot_ms),
                            int(msg.signal_quality), int(msg.covariance)))
                    elif kind == "HEARTBEAT":
                        self.heartbeats += 1

    def _answer(self, now: float) -> None:
        assert self._peer is not None
        boot_ms = int((now - self.boot) * 1000.0)
        for message in (
            self._mav.heartbeat_encode(MAV_TYPE_SUBMARINE, MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4),
            self._mav.system_time_encode(int(time.time() * 1e6), boot_ms),
        ):
            try:
                self._sock.sendto(message.pack(self._mav), self._peer)
            except OSError:
                return

    def arrivals(self) -> list[DistanceArrival]:
        with self._lock:
            return list(self._arrivals)

    def snapshot(self) -> list[tuple[float, int]]:
        """(arrival time, current_distance cm) of every DISTANCE_SENSOR so far."""
        return [(a.t_received, a.current_cm) for a in self.arrivals()]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._sock.close()
