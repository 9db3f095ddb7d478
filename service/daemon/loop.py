"""The frame loop: read the newest frame, run the pipeline, hand the result to the outputs.

Per iteration: read (timeout <= 0.5 s, so a stop is honoured within a second) -> ping the
systemd watchdog (from the loop itself: a hung loop must stop the pings) -> pipeline -> the
reading to the link, the estimate to telemetry -> status when due. When the estimator is
slower than the camera the source hands over only its newest frame: older ones are skipped
(and counted), never queued.

Time comes from the frames (capture times) and from the injected `clock`, so tests drive
`iterate()` over a list of frames without sleeping, and a replay runs the same pipeline.
Signals: SIGTERM/SIGINT request a stop (exit 0); SIGHUP reloads the configuration (`reload`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from service import __version__
from service.config import Config, config_digest
from service.core.budget import BudgetController
from service.core.camera import CameraModel
from service.core.damage_track import NetInspector
from service.core.errors import CalibrationError, ConfigError, NetposeError
from service.core.estimator import NetEstimator
from service.core.readings import RangeReading
from service.core.redact import redact_text
from service.core.scale import scale_sigma_fraction
from service.core.state_log import StateLog
from service.core.tracking import NetTracker, TrackOutput
from service.daemon.damage_outputs import DamageOutputs
from service.daemon.events import OnceLogger, SourceWatch, TrackLog
from service.daemon.outputs import FrameOutputs, PreviewSettings
from service.daemon.ports import (
    AutopilotLink,
    FrameObserver,
    FrameSource,
    Notifier,
    TelemetrySink,
)
from service.daemon.search_pace import SearchPacer
from service.daemon.service_notices import ServiceNotices
from service.daemon.stats import LoopStats
from service.daemon.status import ReportContext, StatusReporter
from service.daemon.view_notices import ViewNotices
from service.pipeline import Pipeline, PipelineResult
from service.signals import SignalFlags

log = logging.getLogger("netpose.daemon")

# How often the loop looks whether the link dropped pilot texts (_note_link).
_LINK_CHECK_S = 0.25
# What a reload cannot change in the running parts: these need a restart (the page's Restart,
# or systemctl restart), and the reload says so.
RESTART_SECTIONS = frozenset({"camera", "mavlink", "telemetry", "web"})

Clock = Callable[[], float]


@dataclass(frozen=True)
class DaemonParts:
    """Everything the loop talks to, built (not yet started) by `service.daemon.wiring`."""

    source: FrameSource
    link: AutopilotLink
    telemetry: TelemetrySink
    notifier: Notifier
    camera: CameraModel
    vehicle: str = "rov"
    preview: PreviewSettings = field(default_factory=PreviewSettings)
    telemetry_enabled: bool = True
    observers: tuple[FrameObserver, ...] = ()


@dataclass(frozen=True)
class ReloadOutcome:
    """How a reload went, for whoever asked for it (the web page's settings)."""

    ok: bool
    changed: tuple[str, ...] = ()  # sections whose values changed
    restart_needed: tuple[str, ...] = ()  # of those, the ones the running parts keep
    error: str = ""  # why the new configuration was rejected
    digest: str = ""  # of the configuration in force afterwards
    # Set-up mode: the file was taken, but what it still lacks keeps the daemon from starting.
    pending: str = ""


def make_estimator(config: Config, camera: CameraModel) -> NetEstimator:
    estimator = NetEstimator(camera, config.mesh, config.estimator)
    # Per-size caches now, for the calibrated size, so the first frame costs what all do.
    estimator.prepare(camera.width, camera.height)
    return estimator


def _orientation(config: Config) -> int:
    """The camera's MAV_SENSOR_ORIENTATION (checked by the MAVLink driver when it was built)."""
    value = config.effective.get("mavlink", {}).get("orientation", 0)
    return value if isinstance(value, int) else 0


def make_inspector(config: Config, camera: CameraModel) -> NetInspector | None:
    """Net inspection (hole detection), or None when `damage.enabled` is false."""
    if not config.damage.enabled:
        return None
    return NetInspector(camera, config.mesh, config.damage)


class Daemon:
    """Owns the loop over its parts. Use `run()`; it always closes what it opened."""

    def __init__(
        self,
        config: Config,
        parts: DaemonParts,
        *,
        clock: Clock = time.monotonic,
        wall_clock: Clock = time.time,
        flags: SignalFlags | None = None,
        load_config: Callable[[], Config] | None = None,
        on_reload: Callable[[ReloadOutcome], None] | None = None,
    ) -> None:
        self.config = config
        self.parts = parts
        self.clock = clock
        self.flags = flags or SignalFlags()
        self._load_config = load_config
        self._on_reload = on_reload
        # The calibration's contents in force: a file recalibrated in place keeps its path, so
        # the configuration alone does not show the change.
        self._calibration_digest = _file_digest(config.calibration_path())
        self.pipeline = Pipeline(make_estimator(config, parts.camera), NetTracker(config.filter),
                                 config.service.autopilot_distance,
                                 make_inspector(config, parts.camera),
                                 scale_sigma_fraction=config.scale_sigma_fraction)
        self.stats = LoopStats()
        self.budget = BudgetController(config.budget)
        self.search = SearchPacer(config.budget.search_hz)
        self.problems = OnceLogger(log)
        states = StateLog()
        now = clock()
        self._url = redact_text(config.camera.url)
        self.track_log = TrackLog(states, config.filter.coast_timeout_s,
                                  config.filter.max_consecutive_rejects)
        self.source_watch = SourceWatch(self._url, config.camera.stale_after_s, now,
                                        parts.camera)
        self.outputs = FrameOutputs(
            parts.link, parts.telemetry, parts.vehicle, parts.preview, wall_clock, self.problems,
            parts.observers, DamageOutputs(parts.link, parts.telemetry, parts.vehicle,
                                           wall_clock, config.damage.notify_interval_s,
                                           parts.observers, _orientation(config)))
        self.reporter = StatusReporter(
            ReportContext(parts.source, parts.link, parts.telemetry, parts.notifier, self.stats,
                          self.pipeline.tracker, self.track_log, self.source_watch, self.outputs,
                          self.budget, self.search),
            vehicle=parts.vehicle, interval_s=config.service.status_interval_s,
            summary_interval_s=config.service.summary_interval_s, started_at=now,
            wall_clock=wall_clock, states=states,
        )
        self.view_notices = ViewNotices(parts.link, config.mesh.opening_angle_deg, states=states)
        self.service_notices = ServiceNotices(parts.link)
        self._texts_dropped = 0  # the link's count, as last looked at (_note_link)
        self._link_checked_at = -float("inf")
        self._apply_config_to_reporter()
        self.last: TrackOutput | None = None
        self.last_index: int | None = None  # the source's number of the last frame processed
        self._last_pass: float | None = None
        # (capture stamp, loop clock at arrival) of the newest frame.
        self._last_frame: tuple[float, float] | None = None
        self._closed = False
        self.stopped_for: str | None = None  # the stop reason the loop ended on (and said)

    # -- the loop ----------------------------------------------------------------------------
    def iterate(self) -> PipelineResult:
        """One pass of the frame loop."""
        frame = self.parts.source.read(self.config.camera.read_timeout_s)
        now = self.clock()
        self._note_stall(now)
        self.parts.notifier.watchdog(now)
        if frame is None:
            result = self.pipeline.tick(self._tick_time(now))
            self.source_watch.idle(now)
        else:
            self._last_frame = (frame.t_monotonic, now)
            h, w = frame.image.shape[:2]
            self.source_watch.frame(w, h, now, frame.t_monotonic)
            if self.search.due(frame.t_monotonic):
                result = self.pipeline.measure(frame.image, frame.t_monotonic, frame.index,
                                               budget=self.budget.level)
                self.search.measured(result)
            else:
                result = self.pipeline.skip(frame.t_monotonic, frame.index,
                                            self.search.why(frame.t_monotonic))
                self.budget.skipped(frame.t_monotonic, frame.index)
            self.last_index = frame.index
        self.service_notices.camera(self.source_watch.up, now)
        sent = self.outputs.to_autopilot(result)
        if frame is not None and not result.unmeasured:
            # After the distance has gone: an inspected frame's distance waited for the hole
            # search (about 10 ms here, more on a Pi).
            result = self.pipeline.inspect(frame.image, result)
        self.stats.record(result, self.clock())
        if frame is not None:
            self._note_errors(result)
            self.outputs.publish(frame, result, sent, self.clock())
            if not result.unmeasured:
                self._account(result, self.clock() - now)
        elif self.outputs.damage is not None:
            # A pilot text held back by its rate limit is due whether frames come or not.
            self.outputs.damage.notices.tick(now)
        self.track_log.update(result.track, now)
        self.view_notices.update(result, now)
        self._note_link(now, result)
        self.last = result.track
        self.reporter.tick(now, self.last)
        return result

    def _note_link(self, now: float, result: PipelineResult) -> None:
        """When the link dropped pilot texts that waited out an outage (as old news), what the
        pilot was told and still holds is said again, so the pilot hears the state of now (the
        camera still lost, the net still too close). Only then: a link that flaps without
        dropping anything repeats nothing. Looked at a few times a second."""
        if now - self._link_checked_at < _LINK_CHECK_S:
            return
        self._link_checked_at = now
        dropped = self.parts.link.status().texts_dropped
        if dropped > self._texts_dropped:
            self.service_notices.repeat()
            self.view_notices.repeat(result if result.has_frame else None)
        self._texts_dropped = dropped

    def _tick_time(self, now: float) -> float:
        """The time of a pass without a frame, in the frames' time base.

        Frame stamps and the loop's clock may run apart: a file read faster than real time is
        stamped with media time, a recording with its own clock. Between frames, time passes
        from the last frame by what the clock measures, so the filter's coasting ends
        `coast_timeout_s` of real time after the last frame whatever the stamps said (the
        clock itself when it is ahead: a live camera's frames arrive after their capture).
        """
        if self._last_frame is None:
            return now
        t_frame, arrived = self._last_frame
        return max(now, t_frame + (now - arrived))

    def _note_stall(self, now: float) -> None:
        """A pass of the loop that took as long as half the systemd watchdog's interval (at
        least a second) is a warning: the watchdog is pinged between passes only, so one more
        such pass and systemd kills the service; the line says how long, and which frame."""
        last, self._last_pass = self._last_pass, now
        interval = self.parts.notifier.watchdog_interval_s
        limit = max(1.0, interval / 2.0) if interval is not None else 5.0
        if last is not None and now - last >= limit:
            log.warning("frame loop stalled: %.1f s since the previous pass (watchdog %s); last"
                        " frame %s", now - last,
                        f"{interval:.0f} s" if interval is not None else "off",
                        self.last_index if self.last_index is not None else "none")

    def run(self, duration_s: float | None = None) -> int:
        """Start, loop until stopped (signal or `duration_s`), close. Returns the exit status."""
        try:
            self.start()
            deadline = None if duration_s is None else self.clock() + duration_s
            while not self.flags.stop.is_set():
                if deadline is not None and self.clock() >= deadline:
                    log.info("run duration of %.1f s reached", duration_s)
                    break
                if self.flags.reload.is_set():
                    self.flags.reload.clear()
                    self.reload()
                self.iterate()
            stopping_at = self.clock()
            self.stopped_for = self.flags.stop_signal
            if self.flags.stop_signal:
                log.info("%s received: stopping", self.flags.stop_signal)
            # The topside's last word from this run (the telemetry flushes it as it closes).
            self.reporter.report(stopping_at, self.last, stopping=True)
            self.parts.notifier.stopping()
            self.service_notices.stopping(self.flags.stop_signal)
            self.reporter.summary(stopping_at, final=True)
            self.close()
            log.info("stopped cleanly (outputs and source closed in %.2f s)",
                     self.clock() - stopping_at)
            return 0
        finally:
            self.close()  # idempotent; after an error too

    # -- start-up and shut-down ------------------------------------------------------------
    def start(self) -> None:
        """Open the source, start the outputs; everything was built (and checked) before."""
        cfg, parts = self.config, self.parts
        parts.source.open()
        parts.link.start()
        self.reporter.announce(self.clock())
        parts.telemetry.start()
        for observer in parts.observers:
            observer.start()
        log.info(
            "netpose %s started: source %s, MAVLink %s, telemetry %s, config %s (%s)",
            __version__, self._url, redact_text(str(cfg.effective["mavlink"]["url"])),
            "on" if parts.telemetry_enabled else "off", cfg.path or "defaults", cfg.digest,
        )
        parts.notifier.ready(status="started, waiting for frames")

    def close(self) -> None:
        """Withdraw the distance, then close outputs and source (reverse of opening)."""
        parts = self.parts
        if self._closed:
            return
        self._closed = True
        # Each step on its own: one that raises must not leave a recording unfinished or a
        # port open.
        closers = [("distance", lambda: parts.link.set_range(RangeReading.none(self.clock())))]
        damage = self.outputs.damage
        if damage is not None:  # a hole's text still waiting goes before the link closes
            closers.append(("pilot notices", lambda: damage.notices.flush(self.clock())))
        closers += [(type(o).__name__, o.close) for o in parts.observers]
        closers += [("telemetry", parts.telemetry.close), ("MAVLink link", parts.link.close),
                    ("frame source", parts.source.close)]
        for name, closer in closers:
            try:
                closer()
            except Exception:
                log.exception("closing the %s failed", name)

    def _account(self, result: PipelineResult, work_s: float) -> None:
        """The frame's loop time (and whether the net was seen) decides the next frame's budget
        level; a change is logged with its reason (changes are a second apart at least)."""
        before = self.budget.level
        after = self.budget.frame(result.t, result.index or 0, work_s, result.detected,
                                  tracked=result.tracked)
        if after != before:
            log.info("budget level %d -> %d: %s", before, after, self.budget.why)

    # -- problems ----------------------------------------------------------------------------
    def _note_errors(self, result: PipelineResult) -> None:
        if result.crashed:
            self.problems.problem("estimator-crash", "estimator failed on a frame: %s",
                                  result.error)
        elif isinstance(result.failure, CalibrationError):
            # The frames' size is the camera's (camera.url may ask for one); the calibration
            # is the file: the line says which keys to look at.
            self.problems.problem("estimator-input", "estimator cannot use frames: %s "
                                  "(camera.calibration, or the size camera.url asks for)",
                                  result.error)
        elif result.error:
            self.problems.problem("estimator-input", "estimator cannot use frames: %s",
                                  result.error)
        elif result.estimate is not None:
            self.problems.cleared("estimator-input", "estimator accepts frames again")
            self.problems.cleared("estimator-crash", "estimator works again")
        if result.damage is not None and result.damage.failed:
            # A bug in the hole detector: the distance goes on, but nobody would know that
            # inspection is dead for the dive (its traceback is at DEBUG level).
            self.problems.problem("inspection-crash", "net inspection failed on a frame: %s "
                                  "(the distance is not affected)", result.damage.reason)
        elif result.damage is not None and result.damage.inspected:
            self.problems.cleared("inspection-crash", "net inspection works again")

    # -- reload ----------------------------------------------------------------------------
    def reload(self) -> bool:
        """Re-read the configuration file (SIGHUP). Filter, estimator, mesh and log level take
        effect at once; camera (the calibration file's contents too), MAVLink, telemetry and web
        changes need a restart (logged). A bad new configuration is rejected and the running
        one kept."""
        if self._load_config is None:
            log.warning("reload requested, but this daemon has no configuration file to re-read")
            return False
        self.parts.notifier.reloading()
        try:
            new = self._load_config()
            changed = self.config.changed_sections(new)
            scale = _distance_scale(self.config, new)
            if scale != 1.0 and self.parts.link.status().armed:
                # A digit dropped in the file (0.25 for 0.025) passes every check and sent the
                # autopilot ten times the distance a second later, mid-dive. The page refuses
                # every change while armed (settings_editor.ARMED); so does a hand edit.
                self.parts.link.notify_pilot("netpose: mesh change refused: vehicle armed")
                raise ConfigError("mesh", f"not changed while the vehicle is armed (every "
                                  f"distance x{scale:.2f}): disarm, then reload")
            # A new tolerance says how well the scale is known, not what it is: the estimator,
            # the track and the holes being followed stay. A new angle rebuilds the estimator
            # (it says which lattice is the net) but scales no distance: the track stays too
            # (restarted, it withheld the distance mid-dive with no word to the pilot).
            geometry = new.mesh.geometry != self.config.mesh.geometry
            if geometry or "estimator" in changed:
                self.pipeline.replace_estimator(make_estimator(new, self.parts.camera),
                                                new_scale=scale != 1.0)
                if scale != 1.0:
                    log.warning("mesh changed: bar %.1f -> %.1f mm, opening %.0f -> %.0f deg: "
                                "every distance x%.2f; the net is tracked anew, no distance "
                                "until the new scale is confirmed",
                                1e3 * self.config.mesh.bar_length_m,
                                1e3 * new.mesh.bar_length_m, self.config.mesh.opening_angle_deg,
                                new.mesh.opening_angle_deg, scale)
                    self.parts.link.notify_pilot(
                        f"netpose: mesh {1e3 * self.config.mesh.bar_length_m:g}->"
                        f"{1e3 * new.mesh.bar_length_m:g} mm: dist x{scale:.2f}")
                self.view_notices.configured_opening_deg = new.mesh.opening_angle_deg
            if geometry or "damage" in changed:
                # Holes are placed on the net and counted in bars: only a new bar moves them.
                self.pipeline.replace_inspector(make_inspector(new, self.parts.camera),
                                                keep_holes=scale == 1.0)
                if self.outputs.damage is not None:
                    self.outputs.damage.notices.interval_s = new.damage.notify_interval_s
            if "filter" in changed:
                self.pipeline.tracker.reconfigure(new.filter)
            if "budget" in changed:
                self.budget.reset(new.budget)
                self.search.search_hz = new.budget.search_hz
            if "service" in changed:
                logging.getLogger().setLevel(new.service.log_level)
                self.pipeline.set_autopilot_distance(new.service.autopilot_distance)
                if new.service.autopilot_distance != self.config.service.autopilot_distance:
                    # The rangefinder's number changes meaning (by cos(tilt): 1.00 -> 0.82 m
                    # at 35 deg) on the pilot's screen and in net hold: said, like a mesh change.
                    along = ("along camera axis" if new.service.autopilot_distance
                             == "optical_axis" else "perpendicular to net")
                    log.warning("the autopilot's distance is now %s (service.autopilot_distance"
                                " = %s)", along, new.service.autopilot_distance)
                    self.parts.link.notify_pilot(f"netpose: rangefinder now {along}")
            if _file_digest(new.calibration_path()) != self._calibration_digest:
                changed.add("camera")
            needs_restart = sorted(changed & RESTART_SECTIONS)
            # (The focal tolerance is the camera section's, which a restart changes.)
            self.pipeline.set_scale_sigma_fraction(scale_sigma_fraction(
                new.mesh.bar_length_tolerance, self.config.camera.focal_tolerance))
        except NetposeError as exc:
            log.error("configuration reload rejected, keeping the running one: %s", exc)
            self.parts.notifier.ready(status="reload rejected: " + str(exc))
            self._reloaded(ReloadOutcome(ok=False, error=str(exc), digest=self.config.digest))
            return False
        # The running parts keep their old settings: record what is really in force.
        kept = {name: self.config.sections[name] for name in needs_restart}
        effective = dict(new.effective)
        for name in needs_restart:
            effective[name] = self.config.effective[name]
        self.config = dataclasses.replace(
            new, sections={**new.sections, **kept}, effective=effective,
            digest=config_digest(effective),
        )
        self._apply_config_to_reporter()
        for observer in self.parts.observers:
            observer.observe_reload(frozenset(changed))
        log.info(
            "configuration reloaded (%s), changed: %s%s", self.config.digest,
            ", ".join(sorted(changed)) or "nothing",
            f"; restart needed for: {', '.join(needs_restart)}" if needs_restart else "",
        )
        self.parts.notifier.ready(status="configuration reloaded")
        self._reloaded(ReloadOutcome(ok=True, changed=tuple(sorted(changed)),
                                     restart_needed=tuple(needs_restart),
                                     digest=self.config.digest))
        return True

    def _reloaded(self, outcome: ReloadOutcome) -> None:
        if self._on_reload is not None:
            self._on_reload(outcome)

    def _apply_config_to_reporter(self) -> None:
        self.reporter.set_config(self.config.digest, self.config.effective,
                                 self.parts.telemetry_enabled)
        self.reporter.set_intervals(self.config.service.status_interval_s,
                                    self.config.service.summary_interval_s)
        self.track_log.coast_timeout_s = self.config.filter.coast_timeout_s
        self.track_log.max_rejects = self.config.filter.max_consecutive_rejects


def _file_digest(path: Path | None) -> str | None:
    """sha256 of a file's contents; None without a file (or when it cannot be read: the
    reload's own check of the configuration says why)."""
    if path is None:
        return None
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError:
        return None


def _distance_scale(old: Config, new: Config) -> float:
    """What a change of mesh does to every distance: they scale with the bar's length (the
    cell's angle is the one measured, so the configured one changes only what passes as the
    net: estimator.py)."""
    return new.mesh.bar_length_m / old.mesh.bar_length_m
