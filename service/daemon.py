"""The netpose daemon: frame source -> estimator -> filter -> autopilot link and telemetry.

This is the one module that constructs drivers. The frame loop runs on the main thread and
owns the order of things; every output is non-blocking (the MAVLink link and the Zenoh
publisher each run their own thread and take the newest value), so a slow output never stalls
the loop. When the estimator is slower than the camera the source hands over only its newest
frame: older ones are skipped (and counted), never queued.

Per iteration: read the newest frame (timeout <= 0.5 s, so a stop is honoured within a second)
-> ping the systemd watchdog (from the loop itself: a hung loop must stop the pings) -> estimate
-> filter -> hand the filtered distance to the link (or withdraw it) -> publish the estimate.
Once per `service.status_interval_s`: STATUS to systemd, status to telemetry, link-state log
lines. Once per `service.summary_interval_s`: one summary log line.

Signals: SIGTERM/SIGINT request a stop (exit 0); SIGHUP reloads the configuration file (see
`Daemon.reload` for what can change without a restart).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import resource
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from types import FrameType
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import numpy.typing as npt

from drivers.mavlink_settings import RangeReading
from service import __version__
from service import telemetry_schema as ts
from service.config import Config, config_digest, load_config
from service.core.camera import CameraModel, load_camera
from service.core.errors import ConfigError, NetposeError
from service.core.results import NetEstimate
from service.core.tracking import NetTracker, TrackOutput, TrackState

if TYPE_CHECKING:
    from drivers.mavlink_link import AutopilotLink
    from drivers.sdnotify import Notifier
    from drivers.telemetry import TelemetryPublisher

log = logging.getLogger("netpose.daemon")


def driver_sections() -> dict[str, type]:
    """Configuration sections of the drivers this daemon wires (added to the core ones)."""
    from drivers.mavlink_settings import MavlinkSettings
    from drivers.telemetry import TelemetrySettings

    return {"mavlink": MavlinkSettings, "telemetry": TelemetrySettings}


def load_daemon_config(path: str | None, overrides: Iterable[str] = ()) -> Config:
    return load_config(path, overrides, extra_sections=driver_sections())


# -- the frame source, as the daemon sees it ----------------------------------------------------
class Frame(Protocol):
    """What the loop uses of drivers.sources.Frame."""

    @property
    def image(self) -> npt.NDArray[Any]: ...  # uint8 grey
    @property
    def index(self) -> int: ...  # frame number from the source: gaps are skipped frames
    @property
    def t_monotonic(self) -> float: ...  # capture time, time.monotonic()
    @property
    def t_wall(self) -> float: ...  # capture time, time.time()


class FrameSource(Protocol):
    """What the loop uses of drivers.sources.FrameSource."""

    def open(self) -> None: ...
    def read(self, timeout_s: float) -> Frame | None: ...
    def close(self) -> None: ...


# -- stop / reload requests from signals -------------------------------------------------------
class SignalFlags:
    """Set by signal handlers, polled by the frame loop (handlers do nothing else)."""

    def __init__(self) -> None:
        self.stop = threading.Event()
        self.reload = threading.Event()
        self.stop_signal: str | None = None
        self._previous: dict[int, Any] = {}

    def install(self) -> None:
        def on_stop(signum: int, _frame: FrameType | None) -> None:
            self.stop_signal = signal.Signals(signum).name
            self.stop.set()

        def on_hup(_signum: int, _frame: FrameType | None) -> None:
            self.reload.set()

        for sig, handler in ((signal.SIGTERM, on_stop), (signal.SIGINT, on_stop),
                             (signal.SIGHUP, on_hup)):
            self._previous[sig] = signal.signal(sig, handler)

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()


# -- bookkeeping -------------------------------------------------------------------------------
@dataclass
class Counters:
    """Per-period and total counts for the status and summary lines."""

    frames: int = 0
    skipped: int = 0
    detected: int = 0
    accepted: int = 0
    rejected: int = 0
    errors: int = 0
    latencies_ms: list[float] = field(default_factory=list)  # capture -> hand-off to the link
    cpu_s: float = 0.0

    def latency_stats(self) -> tuple[float | None, float | None, float | None]:
        if not self.latencies_ms:
            return None, None, None
        arr = np.asarray(self.latencies_ms)
        return float(arr.mean()), float(np.percentile(arr, 99)), float(arr.max())


class OnceLogger:
    """Logs a recurring problem once (until it clears), not once per frame."""

    def __init__(self, logger: logging.Logger) -> None:
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


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


# -- the daemon --------------------------------------------------------------------------------
SourceFactory = Callable[[Config], FrameSource]


class Daemon:
    """Owns every driver and the frame loop. Use `run()`; it always closes what it opened."""

    def __init__(
        self,
        config: Config,
        notifier: Notifier,
        flags: SignalFlags | None = None,
        *,
        source_factory: SourceFactory | None = None,
        link: AutopilotLink | None = None,
        telemetry: TelemetryPublisher | None = None,
    ) -> None:
        self.config = config
        self.notifier = notifier
        self.flags = flags or SignalFlags()
        self._source_factory = source_factory or open_source
        self._link_override = link
        self._telemetry_override = telemetry
        self._source: FrameSource | None = None
        self._link: AutopilotLink | None = None
        self._telemetry: TelemetryPublisher | None = None
        self._estimator: Any = None
        self._camera: CameraModel | None = None
        self.tracker = NetTracker(config.filter)
        self._once = OnceLogger(log)
        self._period = Counters()
        self._total = Counters()
        self._seq = 0
        self._last_seq: int | None = None
        # The previous detection lets the estimator skip its scale search while tracking.
        self._prior: NetEstimate | None = None
        self._last_frame_at: float | None = None
        self._source_up: bool | None = None  # None: no frame yet
        self._track_state = TrackState.LOST
        self._link_state: str | None = None
        self._telemetry_online: bool | None = None
        self._started_at = time.monotonic()
        self._next_status = 0.0
        self._next_summary = 0.0
        self._last_output: TrackOutput | None = None
        self._period_started = time.monotonic()
        self._cpu_mark = _cpu_seconds()

    # -- start-up and shut-down ------------------------------------------------------------
    def start(self) -> None:
        """Open everything; configuration problems raise before anything is sent."""
        cfg = self.config
        self._source = self._source_factory(cfg)
        self._camera = self._resolve_camera(self._source)
        self._estimator = self._make_estimator(cfg, self._camera)
        self._link = self._link_override or self._make_link(cfg)
        self._telemetry = self._telemetry_override or self._make_telemetry(cfg)
        # Everything is built (and every setting checked); now touch the outside world.
        self._source.open()
        self._link.start()
        self._telemetry.start()
        self._telemetry.set_query_state(None, cfg.effective)
        now = time.monotonic()
        self._started_at = self._period_started = now
        self._next_status = now
        self._next_summary = now + cfg.service.summary_interval_s
        self._cpu_mark = _cpu_seconds()
        log.info(
            "netpose %s started: source %s, MAVLink %s, telemetry %s, config %s (%s)",
            __version__, _redact_url(cfg.camera.url), cfg.effective["mavlink"]["url"],
            "on" if cfg.effective["telemetry"]["enabled"] else "off",
            cfg.path or "defaults", cfg.digest,
        )
        if cfg.effective["mavlink"].get("vision_enabled"):
            # A net plane gives distance and two angles; the position along the net is not
            # observable, so there is no honest VISION_POSITION_ESTIMATE to send.
            log.warning("mavlink.vision_enabled is set, but the daemon sends no vision pose: "
                        "only the distance (DISTANCE_SENSOR) is sent")
        self.notifier.ready(status="started, waiting for frames")

    def close(self) -> None:
        """Withdraw the distance, then close outputs and source (reverse of opening)."""
        if self._link is not None:
            self._link.set_range(None, time.monotonic())
        for name, closer in (
            ("telemetry", None if self._telemetry is None else self._telemetry.close),
            ("MAVLink link", None if self._link is None else self._link.close),
            ("frame source", None if self._source is None else self._source.close),
        ):
            if closer is None:
                continue
            try:
                closer()
            except Exception:
                log.exception("closing the %s failed", name)
        self._telemetry = self._link = None
        self._source = None

    def _resolve_camera(self, source: FrameSource) -> CameraModel:
        path = self.config.calibration_path()
        if path is not None:
            return load_camera(path)
        camera = getattr(source, "camera", None)
        if camera is None:
            raise ConfigError(
                "camera.calibration",
                "this source does not describe its camera: give a calibration file",
            )
        return camera

    @staticmethod
    def _make_estimator(cfg: Config, camera: CameraModel) -> Any:
        from service.core.estimator import NetEstimator

        settings = cfg.sections.get("estimator")
        estimator = NetEstimator(camera, cfg.mesh, settings)
        # Per-size caches now, for the calibrated size (frames of another size of the same
        # aspect ratio build theirs on the first frame).
        estimator.prepare(camera.width, camera.height)
        return estimator

    @staticmethod
    def _make_link(cfg: Config) -> AutopilotLink:
        from drivers.mavlink_link import MavlinkLink
        from drivers.mavlink_settings import MavlinkSettings

        return MavlinkLink(cfg.section("mavlink", MavlinkSettings))

    @staticmethod
    def _make_telemetry(cfg: Config) -> TelemetryPublisher:
        from drivers.telemetry import TelemetrySettings, make_publisher

        return make_publisher(cfg.section("telemetry", TelemetrySettings))

    # -- the loop --------------------------------------------------------------------------
    def run(self, duration_s: float | None = None) -> int:
        """Start, loop until stopped (signal or `duration_s`), close. Returns the exit status."""
        try:
            self.start()
            deadline = None if duration_s is None else time.monotonic() + duration_s
            while not self.flags.stop.is_set():
                if deadline is not None and time.monotonic() >= deadline:
                    log.info("run duration of %.1f s reached", duration_s)
                    break
                if self.flags.reload.is_set():
                    self.flags.reload.clear()
                    self.reload()
                self.iterate()
            stopping_at = time.monotonic()
            if self.flags.stop_signal:
                log.info("%s received: stopping", self.flags.stop_signal)
            self.notifier.stopping()
            self._log_summary(stopping_at, final=True)
            self.close()
            log.info("stopped cleanly (outputs and source closed in %.2f s)",
                     time.monotonic() - stopping_at)
            return 0
        finally:
            self.close()  # idempotent; after an error too

    def iterate(self) -> None:
        """One pass of the frame loop."""
        assert self._source is not None and self._link is not None
        cfg = self.config
        frame = self._source.read(cfg.camera.read_timeout_s)
        now = time.monotonic()
        self.notifier.watchdog(now)
        if frame is None:
            self._no_frame(now)
        else:
            self._process(frame, now)
        if now >= self._next_status:
            self._next_status = now + cfg.service.status_interval_s
            self._status(now)
        if now >= self._next_summary:
            self._next_summary = now + cfg.service.summary_interval_s
            self._log_summary(now)

    def _no_frame(self, now: float) -> None:
        # Time passes for the filter even without frames: coasting must end in LOST.
        out = self.tracker.step(now, None)
        self._publish_track(out, now)
        stale = self.config.camera.stale_after_s
        last = self._last_frame_at if self._last_frame_at is not None else self._started_at
        if now - last >= stale and self._source_up is not False:  # up, or never came up
            self._source_up = False
            log.warning("frame source down: no frame for %.1f s (%s)", now - last,
                        _redact_url(self.config.camera.url))

    def _process(self, frame: Frame, now: float) -> None:
        assert self._link is not None
        if not self._source_up:
            self._source_up = True
            h, w = frame.image.shape[:2]
            log.info("frame source up: %dx%d from %s", w, h, _redact_url(self.config.camera.url))
        self._last_frame_at = now
        if self._last_seq is not None and frame.index > self._last_seq + 1:
            skipped = frame.index - self._last_seq - 1
            self._period.skipped += skipped
            self._total.skipped += skipped
        self._last_seq = frame.index
        self._period.frames += 1
        self._total.frames += 1

        estimate = self._estimate(frame)
        out = self.tracker.step(frame.t_monotonic, estimate)
        if estimate is not None and estimate.detected:
            self._period.detected += 1
            self._total.detected += 1
        self._prior = estimate if estimate is not None and estimate.detected else None
        if out.measurement == "accepted":
            self._period.accepted += 1
        elif out.measurement == "rejected":
            self._period.rejected += 1
        self._publish_track(out, frame.t_monotonic, estimate)
        handed_over = time.monotonic()
        latency_ms = (handed_over - frame.t_monotonic) * 1e3
        self._period.latencies_ms.append(latency_ms)
        self._total.latencies_ms.append(latency_ms)
        self._publish_estimate(frame, estimate, out, handed_over)

    def _estimate(self, frame: Frame) -> NetEstimate | None:
        try:
            estimate: NetEstimate = self._estimator.estimate(frame.image, prior=self._prior)
        except NetposeError as exc:
            # A frame the estimator cannot use (size, calibration mismatch): keep running,
            # say it once, report nothing for this frame.
            self._period.errors += 1
            self._once.problem("estimator-input", "estimator cannot use frames: %s", exc)
            return None
        except Exception:
            self._period.errors += 1
            self._once.problem("estimator-crash", "estimator failed on a frame", exc_info=True)
            return None
        self._once.cleared("estimator-input", "estimator accepts frames again")
        self._once.cleared("estimator-crash", "estimator works again")
        return estimate

    def _publish_track(
        self, out: TrackOutput, t: float, estimate: NetEstimate | None = None
    ) -> None:
        """Hand the filtered distance to the link, or withdraw it; log state changes."""
        assert self._link is not None
        self._log_track_change(out)
        self._last_output = out
        distance = self._autopilot_distance(out)
        if out.valid and distance is not None:
            sigma = out.sigma_distance_m if out.sigma_distance_m is not None else math.nan
            # Coasting frames have no estimate of their own: quality unknown (nan).
            quality = estimate.confidence if estimate is not None else math.nan
            self._link.set_range(RangeReading(distance, sigma_m=sigma, quality=quality), t)
        else:
            self._link.set_range(None, t)

    def _autopilot_distance(self, out: TrackOutput) -> float | None:
        if self.config.service.autopilot_distance == "optical_axis":
            return out.range_m
        return out.distance_m

    def _log_track_change(self, out: TrackOutput) -> None:
        previous, self._track_state = self._track_state, out.state
        if out.state is previous:
            return
        if out.state is TrackState.TRACKING and previous is TrackState.LOST:
            log.info("net acquired at %.2f m (tilt %.1f deg)", out.distance_m or math.nan,
                     _tilt(out))
        elif out.state is TrackState.LOST and out.measurement == "reset":
            log.info("net track restarted at %.2f m: measurements left the gate %d times in a "
                     "row", out.distance_m or math.nan, self.config.filter.max_consecutive_rejects)
        elif out.state is TrackState.LOST:
            log.info("net lost (no accepted measurement for %.1f s)",
                     self.config.filter.coast_timeout_s)
        else:
            log.debug("track %s -> %s", previous.value, out.state.value)

    def _publish_estimate(
        self, frame: Frame, estimate: NetEstimate | None, out: TrackOutput, now: float
    ) -> None:
        assert self._telemetry is not None
        tel = self._telemetry
        self._seq += 1
        est = (estimate or NetEstimate(detected=False, confidence=0.0,
                                       reason="estimator error")).to_json_dict()
        sigma_range = None
        if out.sigma_distance_m is not None and out.normal is not None and abs(out.normal[2]) > 0:
            sigma_range = out.sigma_distance_m / abs(out.normal[2])
        filtered = ts.filtered_payload(
            valid=out.valid,
            distance_m=out.distance_m,
            sigma_distance_m=out.sigma_distance_m,
            range_m=out.range_m,
            sigma_range_m=sigma_range,
            normal=out.normal,
            closing_speed_mps=None if out.distance_rate_mps is None else -out.distance_rate_mps,
            age_s=out.since_accepted_s,
        )
        filtered["state"] = out.state.value
        filtered["measurement"] = out.measurement
        wall = time.time()
        payload = ts.estimate_payload(
            vehicle=tel.settings.vehicle,
            seq=self._seq,
            estimate=est,
            now_unix=wall,
            now_mono=now,
            frame_time_unix=frame.t_wall,
            frame_time_mono=frame.t_monotonic,
            filtered=filtered,
        )
        truth = _truth_dict(getattr(frame, "truth", None))
        if truth is not None:
            # Synthetic frames know the answer: publish it so a topside (or a test) can score
            # the estimate and the filter live. Extra keys are allowed by the schema.
            payload["truth"] = truth
        tel.publish_estimate(payload)
        if tel.wants_preview(now):
            self._publish_preview(frame, estimate, wall)

    def _publish_preview(self, frame: Frame, estimate: NetEstimate | None, wall: float) -> None:
        """Downscaled frame with ROIs and mesh drawn (tools.preview), a few times a minute."""
        assert self._telemetry is not None
        from service.tools.preview import encode_jpeg, estimate_caption, render_preview

        settings = self._telemetry.settings
        try:
            caption = estimate_caption(estimate.to_json_dict()) if estimate is not None else []
            rois = estimate.rois if estimate is not None else ()
            image = render_preview(frame.image, rois, caption, width=settings.preview_width)
            jpeg = encode_jpeg(image, settings.preview_quality)
        except NetposeError as exc:
            self._once.problem("preview", "cannot draw the preview: %s", exc)
            return
        h, w = image.shape[:2]
        meta = ts.preview_meta(vehicle=settings.vehicle, seq=self._seq, now_unix=wall, width=w,
                            height=h)
        self._telemetry.publish_preview(jpeg, meta)

    # -- status, summaries -----------------------------------------------------------------
    def _status(self, now: float) -> None:
        assert self._link is not None and self._telemetry is not None
        link_status = self._link.status()
        link_state = str(link_status.get("state", "unknown"))
        if link_state != self._link_state:
            level = logging.INFO if link_state == "connected" or self._link_state is None \
                else logging.WARNING
            log.log(level, "MAVLink link %s (%s)", link_state, link_status.get("url", ""))
            self._link_state = link_state
        online = self._telemetry.online
        if online != self._telemetry_online and self.config.effective["telemetry"]["enabled"]:
            if self._telemetry_online is not None or online:
                log.info("telemetry %s", "online" if online else "offline")
            self._telemetry_online = online

        period = now - self._period_started
        out = self._last_output
        line = self.status_line(out, period)
        self.notifier.status(line)

        self._publish_status(now, period, link_status, link_state)

    def _publish_status(
        self, now: float, period: float, link_status: dict[str, Any], link_state: str
    ) -> None:
        assert self._telemetry is not None
        mean, p99, worst = self._period.latency_stats()
        frames = self._period.frames
        cpu = _cpu_seconds()
        cpu_share = (cpu - self._cpu_mark) / period * 100 if period > 0 else None
        last_age = None if self._last_frame_at is None else now - self._last_frame_at
        sent = link_status.get("sent")
        payload = ts.status_payload(
            vehicle=self._telemetry.settings.vehicle,
            version=__version__,
            state="running" if self._source_up and link_state == "connected" else "degraded",
            uptime_s=now - self._started_at,
            config_digest=self.config.digest,
            now_unix=time.time(),
            now_mono=now,
            frame_source=ts.frame_source_status(
                state="streaming" if self._source_up
                else ("starting" if self._last_frame_at is None else "reconnecting"),
                fps=frames / period if period > 0 else None,
                frames=self._total.frames,
                dropped=self._total.skipped,
                last_frame_age_s=last_age,
            ),
            autopilot=ts.autopilot_status(
                state={"connecting": "waiting"}.get(link_state, link_state),
                heartbeat_age_s=link_status.get("last_heartbeat_age_s"),
                messages_sent=sum(sent.values()) if isinstance(sent, dict) else None,
            ),
            estimator=ts.estimator_status(
                fps=frames / period if period > 0 else None,
                frames=frames,
                detected_fraction=self._period.detected / frames if frames else None,
                latency_ms_mean=mean,
                latency_ms_max=worst,
            ),
            cpu=ts.cpu_status(
                cores=os.cpu_count(),
                load_1m=os.getloadavg()[0],
                process_percent=cpu_share,
            ),
            telemetry=self._telemetry.status(),
        )
        payload["filter"] = {
            "state": self._track_state.value,
            "accepted": self.tracker.accepted_total,
            "rejected": self.tracker.rejected_total,
            "resets": self.tracker.resets_total,
        }
        payload["latency_ms"] = {"capture_to_link_p99": p99}
        self._telemetry.publish_status(payload)
        self._telemetry.set_query_state(payload, self.config.effective)
        self._reset_period(now, cpu)

    def status_line(self, out: TrackOutput | None, period_s: float) -> str:
        """One line for `systemctl status`: state, distance, rate, detection share."""
        frames = self._period.frames
        fps = frames / period_s if period_s > 0 else 0.0
        det = 100.0 * self._period.detected / frames if frames else 0.0
        if not self._source_up:
            head = "no frames"
        elif out is None or out.distance_m is None:
            head = "searching"
        else:
            head = f"{out.state.value} {out.distance_m:.2f} m"
            if not out.valid:
                head += " (not sent)"
        return f"{head} | {fps:.1f} fps, {det:.0f}% detected | MAVLink {self._link_state}"

    def _reset_period(self, now: float, cpu: float) -> None:
        # Memory must not grow with the run time: the summary's latency statistics cover the
        # newest 20000 frames at most.
        del self._total.latencies_ms[:-20000]
        self._period = Counters()
        self._period_started = now
        self._cpu_mark = cpu

    def _log_summary(self, now: float, final: bool = False) -> None:
        total = self._total
        frames, detected = total.frames, total.detected
        mean, p99, _ = total.latency_stats()
        uptime = now - self._started_at
        log.info(
            "%s: %.0f s up, %d frames (%.1f fps), %d skipped, %.0f%% detected, track %s, "
            "filter accepted %d rejected %d resets %d, latency mean %s p99 %s ms",
            "final summary" if final else "summary", uptime, frames,
            frames / uptime if uptime > 0 else 0.0, total.skipped,
            100.0 * detected / frames if frames else 0.0, self._track_state.value,
            self.tracker.accepted_total, self.tracker.rejected_total, self.tracker.resets_total,
            "-" if mean is None else f"{mean:.1f}", "-" if p99 is None else f"{p99:.1f}",
        )

    # -- reload ----------------------------------------------------------------------------
    def reload(self) -> bool:
        """Re-read the configuration file (SIGHUP). Filter, estimator, mesh and log level take
        effect at once; camera, MAVLink and telemetry changes need a restart (logged). A bad
        new configuration is rejected and the running one kept."""
        self.notifier.reloading()
        try:
            new = load_config(self.config.path, self.config.overrides,
                              extra_sections=driver_sections())
            changed = self.config.changed_sections(new)
            if ("mesh" in changed or "estimator" in changed) and self._camera is not None:
                self._estimator = self._make_estimator(new, self._camera)
            if "filter" in changed:
                self.tracker.reconfigure(new.filter)
            if "service" in changed:
                logging.getLogger().setLevel(new.service.log_level)
            needs_restart = sorted(changed & {"camera", "mavlink", "telemetry"})
        except NetposeError as exc:
            log.error("configuration reload rejected, keeping the running one: %s", exc)
            self.notifier.ready(status="reload rejected: " + str(exc))
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
        log.info(
            "configuration reloaded (%s), changed: %s%s", self.config.digest,
            ", ".join(sorted(changed)) or "nothing",
            f"; restart needed for: {', '.join(needs_restart)}" if needs_restart else "",
        )
        self.notifier.ready(status="configuration reloaded")
        return True


def _truth_dict(truth: Any) -> dict[str, Any] | None:
    """Ground truth of a synthetic frame (drivers.synthetic_net.GroundTruth) as JSON values."""
    if truth is None:
        return None
    out: dict[str, Any] = {}
    for name in ("net_present", "range_m", "distance_m", "tilt_deg"):
        value = getattr(truth, name, None)
        if isinstance(value, bool | int | float):
            out[name] = value if isinstance(value, bool) or math.isfinite(value) else None
    normal = getattr(truth, "normal", None)
    if normal is not None:
        out["normal"] = [round(float(v), 6) for v in normal]
    return out or None


def _tilt(out: TrackOutput) -> float:
    if out.normal is None:
        return math.nan
    return math.degrees(math.acos(min(1.0, abs(out.normal[2]))))


def _redact_url(url: str) -> str:
    return str(ts.redact_secrets({"url": url})["url"])


def open_source(config: Config) -> FrameSource:
    """The frame source for `camera.url` (drivers.sources), built but not yet opened."""
    from drivers.sources import SourceOptions, create_source

    # A live source that delivers nothing for stale_after_s is re-opened by the source itself.
    options = SourceOptions(stall_timeout_s=config.camera.stale_after_s)
    source: FrameSource = create_source(config.camera.url, options)
    return source


def check_config(config_path: str | None, overrides: Iterable[str] = ()) -> str:
    """`netpose run --check`: validate everything that can be checked without opening a device
    (settings, calibration file, source URL); raises ConfigError/CalibrationError."""
    config = load_daemon_config(config_path, overrides)
    path = config.calibration_path()
    if path is not None:
        load_camera(path)
    open_source(config)  # built, not opened: parses and checks the URL and its options
    return f"configuration OK: {config.path or 'defaults'} ({config.digest})"


def main(
    config_path: str | None,
    overrides: Iterable[str] = (),
    duration_s: float | None = None,
    notifier: Notifier | None = None,
) -> int:
    """`netpose run`: load and validate the configuration, run until stopped."""
    from drivers.sdnotify import notifier_from_environment

    config = load_daemon_config(config_path, overrides)
    logging.getLogger().setLevel(config.service.log_level)
    flags = SignalFlags()
    flags.install()
    notify = notifier or notifier_from_environment(console=sys.stdout)
    try:
        return Daemon(config, notify, flags).run(duration_s)
    finally:
        flags.restore()
        notify.close()
