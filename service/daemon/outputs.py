"""Per-frame outputs: the reading to the autopilot link, the estimate to telemetry, a preview.

Every call here returns at once: the link and the publisher take the newest value and do their
I/O on their own threads, so a slow or dead output never stalls the frame loop.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

from service.core.errors import NetposeError
from service.core.messages import (
    EstimateLatency,
    EstimateMessage,
    FilteredView,
    PreviewMeta,
    StatusMessage,
    TruthView,
)
from service.core.readings import NetPlane, RangeReading, RangeStatus
from service.core.scale import total_sigma
from service.core.tracking import TrackOutput
from service.daemon.damage_outputs import DamageOutputs
from service.daemon.events import OnceLogger
from service.daemon.ports import AutopilotLink, Frame, FrameObserver, TelemetrySink
from service.pipeline import PipelineResult, sigma_range_of
from service.tools.preview import encode_jpeg, estimate_caption, render_preview
from service.tools.replay import truth_from_object


@dataclass(frozen=True)
class PreviewSettings:
    width: int = 320
    quality: int = 70


def filtered_view(track: TrackOutput, sent: RangeReading,
                  scale_sigma_fraction: float = 0.0) -> FilteredView:
    """The filter's view with what the autopilot was given (`sent`): a reader shows that
    distance as the autopilot's, never re-derives it from the setting. `scale_sigma_fraction`:
    the scale's share of the total sigmas (service.core.scale)."""
    rate = track.distance_rate_mps
    good = sent.status is RangeStatus.GOOD
    sigma_range = sigma_range_of(track)
    return FilteredView(
        valid=track.valid,
        autopilot=sent.status.value,
        autopilot_distance_m=sent.distance_m if good else None,
        autopilot_along=sent.along,
        state=track.state.value,
        measurement=track.measurement.value,
        distance_m=track.distance_m,
        sigma_distance_m=track.sigma_distance_m,
        sigma_distance_total_m=total_sigma(track.distance_m, track.sigma_distance_m,
                                           scale_sigma_fraction),
        range_m=track.range_m,
        sigma_range_m=sigma_range,
        sigma_range_total_m=total_sigma(track.range_m, sigma_range, scale_sigma_fraction),
        normal=track.normal,
        closing_speed_mps=None if rate is None else -rate,
        age_s=track.since_accepted_s,
    )


def truth_view(truth: object | None) -> TruthView | None:
    """Ground truth of a rendered frame as the estimate message carries it."""
    known = truth_from_object(truth)
    if known is None:
        return None
    return TruthView(net_present=known.net_present, range_m=known.range_m,
                     distance_m=known.distance_m, tilt_deg=known.tilt_deg, normal=known.normal)


def estimate_message(
    *, vehicle: str, seq: int, frame: Frame, result: PipelineResult, now_mono: float,
    now_unix: float, sent: RangeReading | None = None,
) -> EstimateMessage:
    """The telemetry message of one processed frame; `sent` is what the autopilot was given
    (the pipeline's reading unless the outputs withheld it)."""
    est = result.estimate
    scale = result.scale_sigma_fraction
    stages = dict(est.timings_ms) if est is not None else {}
    total = stages.pop("total", None)
    latency = EstimateLatency(
        stages=stages,
        estimator_total=total if total is not None else result.estimate_ms,
        frame_to_publish=(now_mono - frame.t_monotonic) * 1e3,
    )
    return EstimateMessage(
        vehicle=vehicle, time_unix=now_unix, time_mono=now_mono, seq=seq,
        frame_time_unix=frame.t_wall, frame_time_mono=frame.t_monotonic,
        detected=est is not None and est.detected,
        confidence=est.confidence if est is not None else 0.0,
        range_m=est.range_m if est is not None else None,
        sigma_range_m=est.sigma_range_m if est is not None else None,
        sigma_range_total_m=None if est is None else total_sigma(est.range_m,
                                                                 est.sigma_range_m, scale),
        distance_m=est.distance_m if est is not None else None,
        sigma_distance_m=est.sigma_distance_m if est is not None else None,
        sigma_distance_total_m=None if est is None else total_sigma(est.distance_m,
                                                                    est.sigma_distance_m, scale),
        normal=est.normal if est is not None else None,
        tilt_deg=est.tilt_deg if est is not None else None,
        sigma_normal_deg=est.sigma_normal_deg if est is not None else None,
        rois=len(est.rois) if est is not None else 0,
        rois_used=est.rois_used if est is not None else 0,
        reason=est.reason if est is not None else (result.why_no_estimate or "estimator error"),
        net_seen=est is not None and est.net_seen,
        approx_range_m=est.approx_range_m if est is not None else None,
        approx_sigma_range_m=est.approx_sigma_range_m if est is not None else None,
        filtered=filtered_view(result.track, sent or result.reading, scale),
        latency_ms=latency,
        truth=truth_view(frame.truth), budget_level=result.budget,
        measured=not result.unmeasured,
        inspected=None if result.damage is None else result.damage.searched,
    )


class FrameOutputs:
    """Hands each result to the link and to telemetry (and, when someone watches, a preview)."""

    def __init__(
        self,
        link: AutopilotLink,
        telemetry: TelemetrySink,
        vehicle: str,
        preview: PreviewSettings,
        wall_clock: Callable[[], float],
        problems: OnceLogger,
        observers: Sequence[FrameObserver] = (),
        damage: DamageOutputs | None = None,
    ) -> None:
        self._link = link
        self._telemetry = telemetry
        self._vehicle = vehicle
        self._preview = preview
        self._wall_clock = wall_clock
        self._problems = problems
        self._observers = tuple(observers)
        self.damage = damage
        self._seq = 0
        self.last_estimate: EstimateMessage | None = None

    def to_autopilot(self, result: PipelineResult) -> RangeReading:
        """Hand the reading (and, for a frame, the net plane) to the link; returns the reading
        it was given."""
        self._link.set_range(result.reading)
        if result.has_frame:  # each frame confirms the net plane, or says it did not
            self._link.set_net_plane(
                result.plane if result.plane is not None else NetPlane.none(result.t))
        return result.reading

    def publish(self, frame: Frame, result: PipelineResult, sent: RangeReading,
                now: float) -> None:
        self._seq += 1
        message = estimate_message(vehicle=self._vehicle, seq=self._seq, frame=frame,
                                   result=result, now_mono=now, now_unix=self._wall_clock(),
                                   sent=sent)
        self.last_estimate = message
        self._telemetry.publish_estimate(message)
        if self.damage is not None:
            report = result.damage
            self.damage.confirmed(frame, report.confirmed if report is not None else (), now)
        for observer in self._observers:
            observer.observe(frame, result, message)
        if self._telemetry.wants_preview(now):
            self._publish_preview(frame, result, message)

    def publish_status(self, message: StatusMessage) -> None:
        for observer in self._observers:
            observer.observe_status(message)

    def _publish_preview(self, frame: Frame, result: PipelineResult,
                         message: EstimateMessage) -> None:
        est = result.estimate
        try:
            image = render_preview(frame.color if frame.color is not None else frame.image,
                                   est.rois if est is not None else (),
                                   estimate_caption(est, result.scale_sigma_fraction),
                                   width=self._preview.width)
            jpeg = encode_jpeg(image, self._preview.quality)
        except NetposeError as exc:
            self._problems.problem("preview", "cannot draw the preview: %s", exc)
            return
        h, w = image.shape[:2]
        frame_h, frame_w = frame.image.shape[:2]
        self._telemetry.publish_preview(
            jpeg, PreviewMeta(vehicle=self._vehicle, seq=self._seq, time_unix=message.time_unix,
                              width=w, height=h, time_mono=message.time_mono,
                              frame_time_mono=frame.t_monotonic, frame_width=int(frame_w),
                              frame_height=int(frame_h)))
