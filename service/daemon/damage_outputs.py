"""Confirmed holes in the net to the topside and the pilot: the `damage` message and a
rate-limited STATUSTEXT ("net: hole ~6x4 cm ahead-left at 1.1 m").

Both happen once per hole, when `service.core.damage_track` confirms it; nothing here waits
for I/O (the publisher and the link queue what they are given).
"""

from __future__ import annotations

import base64
import collections
import logging
from collections.abc import Callable

from service.core.damage_track import ConfirmedHole
from service.core.errors import NetposeError
from service.core.messages import DamageMessage
from service.daemon.ports import AutopilotLink, Frame, FrameObserver, TelemetrySink
from service.tools.preview import encode_jpeg

RECENT_TEXTS = 32  # the last pilot texts, kept to be read back (tests, a debugger)

log = logging.getLogger("netpose.daemon")

MAV_SEVERITY_NOTICE = 5
# Where the camera looks, as the pilot's text says it, by its MAV_SENSOR_ORIENTATION
# (mavlink.orientation): 0 forward, yaw 90/180/270, pitch 90 (up) and 270 (down). Others
# (diagonal mounts) are said as "in view".
FACING_BY_ORIENTATION = {0: "ahead", 2: "right", 4: "behind", 6: "left", 24: "above",
                         25: "below"}
# A text that waited this long beyond its turn (the rate limit) is no longer news: the loop
# stood still that long (the ROV moved on meanwhile). Its hole is counted in the next text.
STALE_TEXT_S = 15.0


def damage_message(hole: ConfirmedHole, *, vehicle: str, frame: Frame, now_mono: float,
                   now_unix: float, crop_quality: int = 80,
                   run_started_unix: float | None = None) -> DamageMessage:
    """The telemetry message of a confirmed hole (the evidence crop as base64 JPEG)."""
    crop = ""
    if hole.crop is not None and hole.crop.size:
        try:
            crop = base64.b64encode(encode_jpeg(hole.crop, crop_quality)).decode("ascii")
        except NetposeError as exc:
            log.warning("cannot encode the evidence of hole %d: %s", hole.hole_id, exc)
    # The frame's own stamps, moved back to the first detection on the same clocks.
    first_mono = frame.t_monotonic - (hole.t_confirmed - hole.t_first)
    height, width = frame.image.shape[:2]
    return DamageMessage(
        vehicle=vehicle, time_unix=now_unix, time_mono=now_mono, hole_id=hole.hole_id,
        run_started_unix=run_started_unix,
        frame_time_unix=frame.t_wall, frame_time_mono=frame.t_monotonic,
        first_seen_mono=first_mono, width_m=hole.width_m, height_m=hole.height_m,
        cells=hole.cells, missing_bars=hole.missing_bars, image_x_px=hole.centre_px[0],
        image_y_px=hole.centre_px[1], image_box_px=list(hole.box_px),
        frame_width_px=int(width), frame_height_px=int(height),
        plane_x_m=hole.plane_xy_m[0], plane_y_m=hole.plane_xy_m[1], position_m=hole.point_m,
        range_m=hole.range_m, bearing=hole.bearing, confidence=hole.confidence,
        detections=hole.detections, looks=hole.looks, crop_jpeg=crop,
    )


class PilotNotices:
    """At most one STATUSTEXT per `interval_s`. Holes confirmed in between are not lost: the
    next text names the newest of them and says how many more there were ("(+2)")."""

    def __init__(self, link: AutopilotLink, interval_s: float, orientation: int = 0) -> None:
        self._link = link
        self.interval_s = interval_s
        self.facing = FACING_BY_ORIENTATION.get(orientation, "in view")
        self._last_sent = -float("inf")
        self._pending: tuple[ConfirmedHole, float] | None = None
        self._held_back = 0  # holes confirmed since the last text, besides the pending one
        # The last texts sent (tests and the status read them), and how many in all: a
        # daemon runs for months, so the texts themselves are not all kept.
        self.sent: collections.deque[str] = collections.deque(maxlen=RECENT_TEXTS)
        self.sent_total = 0

    def hole(self, hole: ConfirmedHole, now: float) -> None:
        if self._pending is not None:
            self._held_back += 1
        self._pending = (hole, now)
        self.tick(now)

    def tick(self, now: float) -> None:
        if self._pending is None or now - self._last_sent < self.interval_s:
            return
        _, at = self._pending
        due = max(at, self._last_sent + self.interval_s)
        if now - due > STALE_TEXT_S:
            self._pending = None
            self._held_back += 1
            return
        self._send(now)

    def flush(self, now: float) -> None:
        """The text still waiting, if any, now (the service is stopping: it would be lost),
        unless it is stale news already."""
        if self._pending is None:
            return
        _, at = self._pending
        if now - max(at, self._last_sent + self.interval_s) > STALE_TEXT_S:
            self._pending = None
            return
        self._send(now)

    def _send(self, now: float) -> None:
        assert self._pending is not None
        hole, _ = self._pending
        self._pending = None
        text = hole.pilot_text(self.facing, more=self._held_back)
        self._held_back = 0
        self._last_sent = now
        self.sent.append(text)
        self.sent_total += 1
        # NOTICE, not WARNING: a finding of the inspection, not a danger to the vehicle (ground
        # stations sound warnings).
        self._link.notify_pilot(text, MAV_SEVERITY_NOTICE)


class DamageOutputs:
    """Publishes each confirmed hole and tells the pilot (rate-limited)."""

    def __init__(self, link: AutopilotLink, telemetry: TelemetrySink, vehicle: str,
                 wall_clock: Callable[[], float], notify_interval_s: float,
                 observers: tuple[FrameObserver, ...] = (), orientation: int = 0) -> None:
        self._telemetry = telemetry
        self._observers = observers
        self._vehicle = vehicle
        self._wall_clock = wall_clock
        # Hole numbers start at 1 in each run: this tells a topside store one run from another.
        self.run_started_unix = wall_clock()
        self.notices = PilotNotices(link, notify_interval_s, orientation)
        self.reported = 0

    def confirmed(self, frame: Frame, holes: tuple[ConfirmedHole, ...], now: float) -> None:
        for hole in holes:
            self.reported += 1
            log.warning("net damage: hole %d confirmed, %.0f x %.0f cm (%d cells), %s at %.2f m "
                        "(confidence %.2f, found in %d of %d looks)", hole.hole_id,
                        hole.width_m * 100, hole.height_m * 100, hole.cells, hole.bearing,
                        hole.range_m, hole.confidence, hole.detections, hole.looks)
            message = damage_message(hole, vehicle=self._vehicle, frame=frame, now_mono=now,
                                     now_unix=self._wall_clock(),
                                     run_started_unix=self.run_started_unix)
            self._telemetry.publish_damage(message)
            for observer in self._observers:
                observer.observe_damage(message)
            self.notices.hole(hole, now)
        self.notices.tick(now)
