"""The 1 Hz health report: one systemd STATUS line, one telemetry status, one queryable state.

Also the periodic summary line in the log. Reporting only reads: it takes a snapshot of the
loop's counters and subtracts the previous one, so reporting never changes what it reports on.
"""

from __future__ import annotations

import logging
import os
import resource
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from service import __version__
from service.core.budget import BudgetController
from service.core.messages import (
    AutopilotHealth,
    CpuHealth,
    EstimatorHealth,
    FilterHealth,
    FrameSourceHealth,
    InspectionHealth,
    StateMessage,
    StatusLatency,
    StatusMessage,
    TelemetryHealth,
)
from service.core.redact import redact_config
from service.core.state_log import StateLog
from service.core.tracking import NetTracker, TrackOutput
from service.daemon.events import SourceWatch, TrackLog
from service.daemon.outputs import FrameOutputs
from service.daemon.ports import AutopilotLink, FrameSource, Notifier, TelemetrySink
from service.daemon.search_pace import SearchPacer
from service.daemon.stats import LoopStats, StatsSnapshot

log = logging.getLogger("netpose.daemon")


@dataclass(frozen=True)
class ProcessUsage:
    cpu_s: float
    rss_mb: float | None


def process_usage() -> ProcessUsage:
    """CPU time and resident memory of this process."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    rss = None
    try:
        with open("/proc/self/statm", encoding="ascii") as fh:
            rss = int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6
    except (OSError, ValueError, IndexError):
        pass
    return ProcessUsage(cpu_s=usage.ru_utime + usage.ru_stime, rss_mb=rss)


@dataclass(frozen=True)
class ReportContext:
    """What the reporter reads; all of it owned by the daemon."""

    source: FrameSource
    link: AutopilotLink
    telemetry: TelemetrySink
    notifier: Notifier
    stats: LoopStats
    tracker: NetTracker
    track_log: TrackLog
    source_watch: SourceWatch
    outputs: FrameOutputs
    budget: BudgetController
    search: SearchPacer


class StatusReporter:
    """Status every `interval_s`, summary every `summary_interval_s`, on the injected clock."""

    def __init__(
        self,
        ctx: ReportContext,
        *,
        vehicle: str,
        interval_s: float,
        summary_interval_s: float,
        started_at: float,
        wall_clock: Callable[[], float],
        usage: Callable[[], ProcessUsage] = process_usage,
        states: StateLog | None = None,
    ) -> None:
        self._ctx = ctx
        self._vehicle = vehicle
        self.interval_s = interval_s
        self.summary_interval_s = summary_interval_s
        self._started_at = started_at
        self._wall_clock = wall_clock
        self._usage = usage
        self._states = states or StateLog()
        self._next_status = started_at
        self._next_summary = started_at + summary_interval_s
        self._mark = ctx.stats.snapshot()
        self._mark_at = started_at
        self._mark_cpu = usage().cpu_s
        self._link_announced = False
        self.config_digest = ""
        self._config_redacted: dict[str, Any] = {}
        self.telemetry_enabled = True
        self.inspecting = False  # net inspection on (damage.enabled)
        self.last_status: StatusMessage | None = None

    def set_config(
        self, digest: str, effective: Mapping[str, Any], telemetry_enabled: bool
    ) -> None:
        """The configuration in force: its digest, and what the queryable shows of it."""
        self.config_digest = digest
        self._config_redacted = redact_config(effective)  # once here, not per report
        self.telemetry_enabled = telemetry_enabled
        self.inspecting = bool(effective.get("damage", {}).get("enabled", False))

    def announce(self, now: float) -> None:
        """What the `state` queryable answers before the first status: the configuration,
        status and estimate null (it did not answer at all, and a topside took the vehicle
        for absent)."""
        self._ctx.telemetry.set_state(StateMessage(
            vehicle=self._vehicle, time_unix=self._wall_clock(), time_mono=now, status=None,
            config=self._config_redacted, estimate=None))

    def set_intervals(self, interval_s: float, summary_interval_s: float) -> None:
        """New periods (a reload): the next report comes the new period after the last one."""
        self._next_status += interval_s - self.interval_s
        self._next_summary += summary_interval_s - self.summary_interval_s
        self.interval_s = interval_s
        self.summary_interval_s = summary_interval_s

    def tick(self, now: float, last: TrackOutput | None) -> None:
        if now >= self._next_status:
            self._next_status = now + self.interval_s
            self.report(now, last)
        if now >= self._next_summary:
            self._next_summary = now + self.summary_interval_s
            self.summary(now)

    def report(self, now: float, last: TrackOutput | None, stopping: bool = False
               ) -> StatusMessage:
        """Build and publish a status. `stopping`: the last one, sent as the daemon stops, so a
        topside can tell a clean stop from a crash or a cut tether (those end the liveliness
        token without it)."""
        ctx = self._ctx
        link = ctx.link.status()
        self._log_link(link.state, link.url, now)
        telemetry = ctx.telemetry.status() if self.telemetry_enabled else None
        self._log_telemetry(telemetry, now)
        snapshot = ctx.stats.snapshot()
        period = snapshot.minus(self._mark)
        seconds = now - self._mark_at
        usage = self._usage()
        message = self._status_message(now, link, telemetry, period, seconds, usage, stopping)
        if not stopping:  # systemd has been told STOPPING; its status line stays the last one
            ctx.notifier.status(self.status_line(last, period, seconds, link.state))
        ctx.telemetry.publish_status(message)
        ctx.outputs.publish_status(message)
        ctx.telemetry.set_state(StateMessage(
            vehicle=self._vehicle, time_unix=message.time_unix, time_mono=now, status=message,
            config=self._config_redacted, estimate=ctx.outputs.last_estimate))
        self._mark, self._mark_at, self._mark_cpu = snapshot, now, usage.cpu_s
        self.last_status = message
        return message

    def _status_message(
        self, now: float, link: AutopilotHealth, telemetry: TelemetryHealth | None,
        period: StatsSnapshot, seconds: float, usage: ProcessUsage, stopping: bool = False,
    ) -> StatusMessage:
        ctx = self._ctx
        counters = ctx.source.stats()
        watch = ctx.source_watch
        latency = ctx.stats.latency_since(self._mark_at)
        fps = period.frames / seconds if seconds > 0 else None
        taken = period.frames + period.paced
        said = counters.state.value
        if said == "ended":  # a file at its end: nothing more will come
            source_state = "ended"
        elif said == "closed":
            source_state = "stopped"
        elif said == "down":
            # The source knows it lost the camera at once; the frame watchdog would say so
            # only after its timeout, and "streaming" beside the source's error meanwhile.
            source_state = "reconnecting"
        elif watch.up:
            source_state = "streaming"
        else:
            source_state = "starting" if watch.last_frame_at is None else "reconnecting"
        refusing = period.frames > 0 and period.errors == period.frames
        # Degraded: a part that should work does not (no frames, every frame refused, an
        # autopilot that answered and stopped). An autopilot that never answered is shown in
        # `autopilot.state` ("waiting") without degrading: a demo has none.
        degraded = source_state != "streaming" or refusing or link.state == "lost"
        if stopping:
            state = "stopping"
        elif source_state == "starting" and not counters.error:
            state = "starting"  # no frame yet, and nothing wrong with the source so far
        else:
            state = "degraded" if degraded else "running"
        return StatusMessage(
            vehicle=self._vehicle,
            time_unix=self._wall_clock(),
            time_mono=now,
            version=__version__,
            state=state,
            uptime_s=now - self._started_at,
            config_digest=self.config_digest,
            frame_source=FrameSourceHealth(
                state=source_state, fps=taken / seconds if seconds > 0 else None,
                frames=ctx.stats.frames + ctx.stats.paced,
                # The source's own count: the gaps in the frame numbers the loop sees are
                # these same frames (and, from a live camera, the corrupt ones too).
                dropped=counters.drops, corrupt=counters.corrupt,
                last_frame_age_s=None if watch.last_frame_at is None
                else now - watch.last_frame_at,
                up_since_mono=watch.up_since,
                error=counters.error,
            ),
            autopilot=link,
            estimator=EstimatorHealth(
                fps=fps, frames=period.frames,
                detected_fraction=period.detected / period.frames if period.frames else None,
                latency_ms_mean=latency.mean_ms, latency_ms_max=latency.max_ms,
                errors=ctx.stats.errors, last_error=ctx.stats.last_error,
                budget_level=ctx.budget.level,
                frame_interval_ms=_ms(ctx.budget.frame_interval_s),
                frame_work_ms=_ms(ctx.budget.cost_s(ctx.budget.level)),
                searching_hz=ctx.search.search_hz if ctx.search.pacing else None,
            ),
            cpu=CpuHealth(
                cores=os.cpu_count(), load_1m=_load_1m(),
                process_percent=(usage.cpu_s - self._mark_cpu) / seconds * 100
                if seconds > 0 else None,
                rss_mb=usage.rss_mb,
            ),
            telemetry=telemetry,
            filter=FilterHealth(
                state=ctx.track_log.state.value, accepted=ctx.tracker.accepted_total,
                rejected=ctx.tracker.rejected_total, resets=ctx.tracker.resets_total,
            ),
            latency_ms=StatusLatency(capture_to_link_p50=latency.p50_ms,
                                     capture_to_link_p99=latency.p99_ms),
            inspection=None if ctx.outputs.damage is None or not self.inspecting
            else InspectionHealth(inspected_frames=ctx.stats.inspected,
                                  judged_cells=ctx.stats.judged_cells,
                                  holes=ctx.outputs.damage.reported),
        )

    def status_line(
        self, out: TrackOutput | None, period: StatsSnapshot, seconds: float, link_state: str
    ) -> str:
        """One line for `systemctl status`: state, distance, rate, detection share."""
        fps = period.frames / seconds if seconds > 0 else 0.0
        det = 100.0 * period.detected / period.frames if period.frames else 0.0
        if not self._ctx.source_watch.up:
            error = self._ctx.source.stats().error
            head = "no frames" + (f" ({error})" if error else "")
        elif period.frames and period.errors == period.frames:
            head = f"estimator cannot use the frames: {self._ctx.stats.last_error}"
        elif out is None or out.distance_m is None:
            head = "searching"
            if self._ctx.search.pacing:
                head += f" at {self._ctx.search.search_hz:g} frames/s"
        else:
            head = f"{out.state.value} {out.distance_m:.2f} m"
            if not out.valid:
                head += " (not sent)"
        return f"{head} | {fps:.1f} fps, {det:.0f}% detected | MAVLink {link_state}"

    def summary(self, now: float, final: bool = False) -> None:
        stats = self._ctx.stats
        tracker = self._ctx.tracker
        uptime = now - self._started_at
        latency = stats.latency_since(-float("inf"))
        log.info(
            "%s: %.0f s up, %d frames (%.1f fps), %d skipped, %d not measured (no net in "
            "view), %.0f%% detected, track %s, filter accepted %d rejected %d resets %d, "
            "latency mean %s p99 %s ms",
            "final summary" if final else "summary", uptime, stats.frames,
            stats.frames / uptime if uptime > 0 else 0.0, stats.skipped, stats.paced,
            100.0 * stats.detected / stats.frames if stats.frames else 0.0,
            self._ctx.track_log.state.value, tracker.accepted_total, tracker.rejected_total,
            tracker.resets_total,
            "-" if latency.mean_ms is None else f"{latency.mean_ms:.1f}",
            "-" if latency.p99_ms is None else f"{latency.p99_ms:.1f}",
        )

    def _log_link(self, state: str, url: str, now: float) -> None:
        due, _, between = self._states.update("link", state, now)
        first = not self._link_announced
        if first or due:
            self._link_announced = True
            level = logging.INFO if state == "connected" or first else logging.WARNING
            log.log(level, "MAVLink link %s (%s)%s", state, url,
                    f" (after {between} more change(s))" if between else "")

    def _log_telemetry(self, health: TelemetryHealth | None, now: float) -> None:
        """Online means someone can receive: a session with no router or peer linked is said
        as such, and so is the last peer leaving."""
        if health is None:
            return
        if health.state != "online":
            state = "offline"
        elif health.linked is False:
            state = "online, nobody connected"
        else:
            state = "online, linked"
        due, _, between = self._states.update("telemetry", state, now)
        if due:
            log.info("telemetry %s%s", state,
                     f" (after {between} more change(s))" if between else "")


def _load_1m() -> float | None:
    """The system's 1-minute load, or None where /proc hides it (systemd's ProcSubset=pid)."""
    try:
        return os.getloadavg()[0]
    except OSError:
        return None


def _ms(seconds: float | None) -> float | None:
    return None if seconds is None else seconds * 1e3
