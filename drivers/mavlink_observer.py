"""A MAVLink peer on loopback UDP that keeps the DISTANCE_SENSOR messages it receives.

What a ground station sees of netpose: the soak benchmark and the end-to-end tests point the
daemon's `udpout:` link at it. Owns one thread; `close()` stops and joins it.
"""

from __future__ import annotations

import socket
import threading
import time
from dataclasses import dataclass

from drivers.mavlink_link import import_mavutil


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
    def __init__(self) -> None:
        mavutil = import_mavutil()
        self._mav = mavutil.mavlink.MAVLink(None)
        self._mav.robust_parsing = True
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind(("127.0.0.1", 0))
        self._sock.settimeout(0.1)
        self.url = f"udpout:127.0.0.1:{self._sock.getsockname()[1]}"
        self._lock = threading.Lock()
        self._arrivals: list[DistanceArrival] = []
        self.heartbeats = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="mavlink-observer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self._sock.recv(65535)
            except TimeoutError:
                continue
            except OSError:
                return
            t = time.monotonic()
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
