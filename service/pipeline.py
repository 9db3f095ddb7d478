"""The one frame pipeline: image -> estimator -> filter -> what the autopilot is told.

The daemon, `netpose replay`, the benchmarks and the tests all run frames through `Pipeline`,
so a replay of a recording runs exactly the code the ROV runs (openpilot's process-replay idea).
Time comes from the data: `process` takes the frame's capture time, `tick` the time at which no
frame came; nothing here reads a clock that affects the estimate, the filter or the distance.
The estimator's time does decide one thing: which frames net inspection searches for holes
(a share of that time, on the vehicle's CPU). The daemon's estimate message says which it
searched, a recording keeps that, and a replay searches the same frames (`process(inspect=)`).

The last detection is fed back to the estimator as its prior (tracking skips the scale
search); after one frame that misses it, the next tries it again before the frame is searched.
A frame the estimator cannot use gives a result with `error` set and no estimate; the filter
still steps, so a track that stops being fed coasts and ends in LOST.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy.typing as npt

from service.core.damage_track import DamageReport, NetInspector
from service.core.errors import NetposeError
from service.core.estimator import NetEstimator
from service.core.readings import DistanceAlong, NetPlane, RangeReading, RangeStatus
from service.core.results import NetEstimate
from service.core.scale import total_sigma
from service.core.state_io import from_plain, to_plain
from service.core.tracking import NetTracker, Outcome, TrackOutput, TrackState

log = logging.getLogger(__name__)

AutopilotDistance = DistanceAlong

# Net inspection runs only at budget levels up to this: when the loop is behind the camera,
# a fresh distance comes first.
INSPECT_MAX_BUDGET = 1

# Frames the estimator must call "too close", with no frame between them that measures the net
# or shows no lattice at all, before the autopilot is told so: one frame of a blur filling the
# view (a fish passing the lens) must not replace a distance. Frames between them that still
# show the net's lattice but cannot measure it ("only 2 ROIs share one lattice") neither count
# nor end the count: at 0.12 m the renderer's approach alternates between the two, so "too
# close" was never said, nor held, and the autopilot got nothing for 2.9 s at the closest
# point, the same as open water (pilot review).
TOO_CLOSE_FRAMES = 2
# ... and such frames hold "too close" for at most this long after the last frame that was.
TOO_CLOSE_HOLD_S = 1.5


@dataclass(frozen=True, eq=False)
class PipelineResult:
    """Everything the pipeline knows after one frame (or one tick without a frame)."""

    t: float  # capture time of the frame, or the time of the tick (seconds, the frames' clock)
    index: int | None  # the source's frame number; None for a tick without a frame
    estimate: NetEstimate | None  # None without a frame, or when the estimator refused it
    track: TrackOutput
    reading: RangeReading  # what the autopilot is told
    failure: Exception | None = None  # why a frame gave no estimate
    estimate_ms: float = 0.0  # estimator wall time (a measurement, never an input)
    # The net plane for the autopilot's net hold: only from a frame whose measurement the filter
    # accepted (never from a coasting prediction), stamped with that frame's capture time.
    plane: NetPlane | None = None
    # Net inspection of this frame (None when the pipeline has no inspector).
    damage: DamageReport | None = None
    budget: int = 0  # the estimator's work level asked for (service.core.budget)
    # Why a frame that came was not given to the estimator ("" when it was, or without a
    # frame): the daemon paces its search in open water (service/daemon/search_pace.py).
    unmeasured: str = ""
    # The estimator tracked the last detected net (no scale search ran on this frame).
    tracked: bool = False
    # The relative one-sigma error of every distance from the mesh's and the calibration's
    # scale (service.core.scale): in the reading's sigma, not in the estimate's or the track's.
    scale_sigma_fraction: float = 0.0

    @property
    def error(self) -> str:
        """Why a frame gave no estimate ("" when it gave one, or without a frame)."""
        if self.failure is None:
            return ""
        if self.crashed:
            return f"{type(self.failure).__name__}: {self.failure}"
        return str(self.failure)

    @property
    def why_no_estimate(self) -> str:
        """Why a frame has no estimate: it was not measured, or the estimator refused it ("" when
        it has one, or without a frame)."""
        return self.unmeasured or self.error

    @property
    def crashed(self) -> bool:
        """The estimator raised something unexpected: a bug, not a frame it refused."""
        return self.failure is not None and not isinstance(self.failure, NetposeError)

    @property
    def has_frame(self) -> bool:
        return self.index is not None

    @property
    def detected(self) -> bool:
        return self.estimate is not None and self.estimate.detected


class Pipeline:
    """Estimator with prior feedback, then the filter, then the autopilot reading."""

    def __init__(
        self,
        estimator: NetEstimator,
        tracker: NetTracker,
        autopilot_distance: AutopilotDistance = "optical_axis",
        inspector: NetInspector | None = None,
        scale_sigma_fraction: float = 0.0,
        independent: bool = False,
    ) -> None:
        """`scale_sigma_fraction`: how well the image's metric scale is known (the mesh's bar
        and the focal length, `Config.scale_sigma_fraction`); 0 counts only the image's
        precision. `independent`: every frame is searched whole, without the last detection
        as its prior (stills, per-frame evaluations: `netpose replay --independent`); the
        daemon's frames are a sequence, and tracked."""
        self._independent = independent
        self._estimator = estimator
        self._scale_sigma_fraction = scale_sigma_fraction
        self._tracker = tracker
        self._inspector = inspector
        self._autopilot_distance: AutopilotDistance = autopilot_distance
        self._prior: NetEstimate | None = None
        self._prior_t = math.nan  # capture time of the prior's frame
        # The last frame missed the prior and was not searched: this one searches if it
        # misses too.
        self._search_deferred = False
        # Confidence of the last accepted measurement: what a coasting reading is worth.
        self._last_quality = math.nan
        self._too_close_frames = 0
        self._too_close_t = math.nan  # capture time of the last frame that was too close
        self._next_hole_id = 1  # across inspectors (reloads): a hole's number in this run

    @property
    def estimator(self) -> NetEstimator:
        return self._estimator

    @property
    def tracker(self) -> NetTracker:
        return self._tracker

    @property
    def inspector(self) -> NetInspector | None:
        return self._inspector

    def replace_inspector(self, inspector: NetInspector | None, *, keep_holes: bool) -> None:
        """Net inspection on, off or retuned. Hole numbers go on from the last one of this
        run; with `keep_holes` (the mesh unchanged) the holes being followed carry over too,
        so one confirmed before is not reported again."""
        old = self._inspector
        if old is not None:
            self._next_hole_id = max(self._next_hole_id, old.tracker.next_id)
        if inspector is not None:
            inspector.tracker.continue_from(
                self._next_hole_id, old.tracker if keep_holes and old is not None else None)
        self._inspector = inspector

    def replace_estimator(self, estimator: NetEstimator, *, new_scale: bool) -> None:
        """A new estimator (mesh or tuning changed); the old prior does not carry over. With
        `new_scale` (the mesh changed) neither does the filter's track: a distance scales with
        the mesh, and a track on the old scale went on predicting the old distance (sent to
        the autopilot) until the new measurements, outside its gate, restarted it."""
        self._estimator = estimator
        self._prior = None
        self._prior_t = math.nan
        self._search_deferred = False
        if new_scale:
            self._tracker.reset()
            self._too_close_frames = 0

    def set_autopilot_distance(self, which: AutopilotDistance) -> None:
        self._autopilot_distance = which

    def set_scale_sigma_fraction(self, fraction: float) -> None:
        self._scale_sigma_fraction = fraction

    def snapshot(self) -> dict[str, Any]:
        """What the next frame's result depends on besides the frame: the filter's state, the
        prior (the last detection), whether the last frame deferred a search, and the last
        accepted quality, as exact JSON values."""
        return {"tracker": self._tracker.snapshot(), "prior": to_plain(self._prior),
                "prior_t": to_plain(self._prior_t),
                "last_quality": to_plain(self._last_quality),
                "too_close_frames": self._too_close_frames,
                "too_close_t": to_plain(self._too_close_t),
                "search_deferred": self._search_deferred}

    def restore(self, state: dict[str, Any]) -> None:
        """Continue from a `snapshot`, as if the frames before it had been processed here."""
        self._tracker.restore(state["tracker"])
        prior = state.get("prior")
        self._prior = None if prior is None else from_plain(NetEstimate, prior)
        # A snapshot from before prior times were kept: the prior's age is unknown.
        self._prior_t = from_plain(float, state.get("prior_t", to_plain(math.nan)))
        self._last_quality = from_plain(float, state["last_quality"])
        self._too_close_frames = int(state.get("too_close_frames", 0))
        self._too_close_t = from_plain(float, state.get("too_close_t", to_plain(math.nan)))
        self._search_deferred = bool(state.get("search_deferred", False))

    def process(self, image: npt.NDArray[Any], t: float, index: int,
                budget: int = 0, inspect: bool | None = None) -> PipelineResult:
        """One frame captured at `t`, at the estimator's work level `budget` (0 = full):
        `measure`, then `inspect` (`inspect`: a recording's decision whether to search this
        frame for holes; None: the inspector's own)."""
        return self.inspect(image, self.measure(image, t, index, budget), due=inspect)

    def measure(self, image: npt.NDArray[Any], t: float, index: int,
                budget: int = 0) -> PipelineResult:
        """The estimator and the filter on one frame: everything the autopilot is told (no net
        inspection yet: `inspect`)."""
        estimate: NetEstimate | None = None
        failure: Exception | None = None
        t0 = time.perf_counter()
        try:
            age = t - self._prior_t if math.isfinite(self._prior_t) else None
            # A tracked net missed in one frame (blur, a fish, a codec glitch) is usually
            # there in the next: the whole-frame search a miss would start costs three to ten
            # tracked frames (a latency spike the autopilot sees as a gap), so it waits one
            # frame, which tries the last plane again.
            prior = None if self._independent else self._prior
            estimate = self._estimator.estimate(image, prior=prior, budget=budget,
                                                prior_age_s=age,
                                                search=self._search_deferred)
        except NetposeError as exc:
            failure = exc
        except Exception as exc:  # a bug must cost one frame, not the service
            log.debug("estimator crashed on frame %d", index, exc_info=True)
            failure = exc
        estimate_ms = (time.perf_counter() - t0) * 1e3
        deferred = (estimate is not None and not estimate.detected and not estimate.searched
                    and self._prior is not None and not self._search_deferred)
        self._search_deferred = deferred
        if not deferred:
            self._prior = estimate if estimate is not None and estimate.detected else None
            self._prior_t = t if self._prior is not None else math.nan
        if estimate is not None and estimate.too_close:
            # Only too-close frames within TOO_CLOSE_HOLD_S of each other count together: two
            # spurious ones minutes apart, with partial lattices between (20 frames in a row
            # of the real sequence at 0.6-0.8 m), must not make "too close" (diff review).
            recent = t - self._too_close_t <= TOO_CLOSE_HOLD_S
            self._too_close_frames = self._too_close_frames + 1 if recent else 1
            self._too_close_t = t
        elif estimate is not None and (estimate.net_seen
                                       or not any(r.detected for r in estimate.rois)):
            self._too_close_frames = 0  # the net measured (or its range seen), or no lattice
        if self._too_close_frames == TOO_CLOSE_FRAMES:
            # The net came nearer than the filter's track can follow: its prediction is from
            # before, and must not be coasted on once the net is out of "too close" again
            # (a frame with no net, a stall). A new track earns trust from new detections.
            self._tracker.reset()
        track = self._tracker.step(t, estimate)
        return PipelineResult(
            t=t, index=index, estimate=estimate, track=track,
            reading=self._reading(track, estimate, t), failure=failure, estimate_ms=estimate_ms,
            plane=net_plane_of(track, t), budget=budget,
            tracked=estimate is not None and not estimate.searched,
            scale_sigma_fraction=self._scale_sigma_fraction,
        )

    def inspect(self, image: npt.NDArray[Any], measured: PipelineResult,
                due: bool | None = None) -> PipelineResult:
        """Net inspection of the frame `measured` came from. A separate step so that the daemon
        sends the distance first: a hole search never delays what the autopilot is told. `due`:
        whether to search this frame (a recording's decision, made by the vehicle's CPU time);
        None: the inspector decides."""
        if self._inspector is None or measured.index is None:
            return measured
        if measured.budget > INSPECT_MAX_BUDGET:
            damage = DamageReport(False, f"skipped: budget level {measured.budget}", skipped=True)
        else:
            # Only while the track is valid: holes are measured on a plane the filter believes.
            try:
                damage = self._inspector.step(image, measured.estimate, measured.t,
                                              measured.index, measured.track.valid,
                                              measured.estimate_ms, due=due)
            except Exception as exc:  # inspection must never cost the distance
                log.debug("net inspection crashed on frame %d", measured.index, exc_info=True)
                damage = DamageReport(False, f"{type(exc).__name__}: {exc}", failed=True)
        return replace(measured, damage=damage)

    def skip(self, t: float, index: int, why: str) -> PipelineResult:
        """A frame captured at `t` that is not measured (`why`): for the filter, time without a
        measurement, as for `tick`."""
        track = self._tracker.step(t, None)
        return PipelineResult(t=t, index=index, estimate=None, track=track,
                              reading=self._reading(track, None, t), unmeasured=why,
                              scale_sigma_fraction=self._scale_sigma_fraction)

    def tick(self, t: float) -> PipelineResult:
        """No frame by `t`: time passes for the filter, so coasting ends in LOST."""
        track = self._tracker.step(t, None)
        return PipelineResult(t=t, index=None, estimate=None, track=track,
                              reading=self._reading(track, None, t),
                              scale_sigma_fraction=self._scale_sigma_fraction)

    def _reading(
        self, track: TrackOutput, estimate: NetEstimate | None, t: float
    ) -> RangeReading:
        """What the autopilot is told, saying which distance it is (`along`)."""
        return replace(self._untagged_reading(track, estimate, t),
                       along=self._autopilot_distance)

    def _untagged_reading(
        self, track: TrackOutput, estimate: NetEstimate | None, t: float
    ) -> RangeReading:
        if track.measurement in (Outcome.ACCEPTED, Outcome.RESET) and estimate is not None:
            self._last_quality = estimate.confidence
        if (self._too_close_frames >= TOO_CLOSE_FRAMES
                and t - self._too_close_t <= TOO_CLOSE_HOLD_S):
            # Nearer than the mesh can be resolved: the autopilot must see "below minimum"
            # (OutOfRangeLow), not the silence of open water, and not a coasting prediction
            # from before the net came this close. A frame that still shows the lattice says
            # so too. Without a new frame (a tick, a skipped frame) that is still the last
            # word, stamped with the frame that said it, so the link stops repeating it once
            # it is stale rather than falling back to the filter.
            return RangeReading(RangeStatus.TOO_CLOSE,
                                t_capture=t if estimate is not None else self._too_close_t)
        if not track.valid or track.distance_m is None:
            return RangeReading.none(t)
        distance = track.distance_m
        sigma = track.sigma_distance_m if track.sigma_distance_m is not None else math.nan
        if self._autopilot_distance == "optical_axis":
            if track.range_m is None or track.normal is None:
                return RangeReading.none(t)
            cos_tilt = abs(track.normal[2])
            distance, sigma = track.range_m, sigma / cos_tilt
        if not (math.isfinite(distance) and distance >= 0.0):
            return RangeReading.none(t)
        # The autopilot's covariance is the distance's whole uncertainty: the filter's sigma
        # shrinks as frames agree, the scale's error is in all of them.
        total = total_sigma(distance, sigma, self._scale_sigma_fraction)
        sigma = total if total is not None else math.nan
        # A coasting prediction is not a measurement: half the last one's quality, so the
        # autopilot (RNGFND_SQ_MIN) and a reader of its log can tell them apart.
        quality = self._last_quality * (1.0 if track.state is TrackState.TRACKING else 0.5)
        return RangeReading(RangeStatus.GOOD, t_capture=t, distance_m=distance, sigma_m=sigma,
                            quality=quality)


def net_plane_of(track: TrackOutput, t: float) -> NetPlane | None:
    """The filtered plane of a frame whose measurement was accepted; None otherwise."""
    if not (track.valid and track.state is TrackState.TRACKING):
        return None
    if track.distance_m is None or track.normal is None:
        return None
    plane = NetPlane.from_distance_normal(t, track.distance_m, track.normal)
    return plane if plane.usable else None


def sigma_range_of(track: TrackOutput) -> float | None:
    """The filtered range's sigma: the distance's, through the tilt."""
    if track.sigma_distance_m is None or track.normal is None or abs(track.normal[2]) <= 0:
        return None
    return track.sigma_distance_m / abs(track.normal[2])

