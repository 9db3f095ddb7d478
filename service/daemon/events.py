"""Log lines about the daemon's state changes, never one per frame, and never more than one a
second per topic (`service.core.state_log.StateLog` decides when).
"""

from __future__ import annotations

import logging
import math

from service.core.camera import CameraModel
from service.core.errors import CalibrationError
from service.core.state_log import StateLog, not_logged_note
from service.core.tracking import Outcome, TrackOutput, TrackState

log = logging.getLogger("netpose.daemon")


class OnceLogger:
    """A recurring problem is logged once when it starts and once when it clears."""

    def __init__(self, logger: logging.Logger = log) -> None:
        self._logger = logger
        self._active: set[str] = set()

    def problem(self, key: str, message: str, *args: object, exc_info: bool = False) -> None:
        if key not in self._active:
            self._active.add(key)
            self._logger.warning(message, *args, exc_info=exc_info)

    def cleared(self, key: str, message: str, *args: object) -> None:
        if key in self._active:
            self._active.discard(key)
            self._logger.info(message, *args)


class TrackLog:
    """Net acquired / lost / track restarted, from the filter's state (TRACKING and COASTING
    both count as "net"; the flip between them is not news)."""

    def __init__(self, states: StateLog, coast_timeout_s: float, max_rejects: int) -> None:
        self._states = states
        self._state = TrackState.LOST
        self.coast_timeout_s = coast_timeout_s
        self.max_rejects = max_rejects

    @property
    def state(self) -> TrackState:
        return self._state

    def update(self, out: TrackOutput, now: float) -> None:
        self._state = out.state
        has_net = out.state is not TrackState.LOST
        due, _, between = self._states.update("track", has_net, now)
        if not due:
            if out.state is TrackState.LOST and out.measurement is Outcome.RESET:
                log.debug("net track restarted: measurements left the gate %d times in a row",
                          self.max_rejects)
            return
        if has_net:
            log.info("net acquired at %.2f m (tilt %.1f deg)%s",
                     out.distance_m if out.distance_m is not None else math.nan,
                     tilt_deg(out), not_logged_note(between))
        elif out.measurement is Outcome.RESET:
            log.info("net track restarted at %.2f m: measurements left the gate %d times in a "
                     "row%s", out.distance_m if out.distance_m is not None else math.nan,
                     self.max_rejects, not_logged_note(between))
        else:
            log.info("net lost (no accepted measurement for %.1f s)%s", self.coast_timeout_s,
                     not_logged_note(between))


class SourceWatch:
    """Frame source up / down, judged by the time since the last frame."""

    def __init__(self, url_for_logs: str, stale_after_s: float, started_at: float,
                 camera: CameraModel | None = None) -> None:
        self._url = url_for_logs
        self.stale_after_s = stale_after_s
        self._started_at = started_at
        self._camera = camera
        self._sizes_seen: set[tuple[int, int]] = set()
        self.up: bool | None = None  # None: no frame yet
        self.last_frame_at: float | None = None
        # Capture time of the first frame since the source (last) came up; None while down.
        self.up_since: float | None = None

    def frame(self, width: int, height: int, now: float, captured_at: float) -> None:
        if not self.up:
            log.info("frame source up: %dx%d from %s", width, height, self._url)
            self.up_since = captured_at
            self._check_size(width, height)
        self.up = True
        self.last_frame_at = now

    def _check_size(self, width: int, height: int) -> None:
        """Once per frame size: a calibration scaled to another resolution is right only if
        that mode shows the whole sensor; a crop or a binned window has another field of view,
        and every distance would be off by its ratio."""
        size = (width, height)
        camera = self._camera
        if camera is None or size == (camera.width, camera.height) or size in self._sizes_seen:
            return
        self._sizes_seen.add(size)
        try:
            camera.scaled_to(width, height)
        except CalibrationError:
            return  # not the calibrated view resized at all: the estimator refuses it, and says so
        cw, ch = camera.width, camera.height
        log.warning("frames are %dx%d, the calibration is for %dx%d: scaled to them, which is "
                    "right only if this camera mode shows the whole sensor (not a crop or a "
                    "binned window); calibrate at %dx%d to be sure", width, height, cw, ch,
                    width, height)

    def idle(self, now: float) -> None:
        last = self.last_frame_at if self.last_frame_at is not None else self._started_at
        if now - last >= self.stale_after_s and self.up is not False:
            self.up = False
            self.up_since = None
            log.warning("frame source down: no frame for %.1f s (%s)", now - last, self._url)


def tilt_deg(out: TrackOutput) -> float:
    if out.normal is None:
        return math.nan
    return math.degrees(math.acos(min(1.0, abs(out.normal[2]))))
