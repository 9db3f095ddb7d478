"""Kalman filter over the estimator's output, with outlier gating and an explicit validity state.

The state is the perpendicular distance to the net plane and the net's orientation as two angles,
each with its rate: x = [d, d', yaw, yaw', pitch, pitch'] (metres, degrees). `yaw` is the angle
of the net normal in the camera's x-z plane, `pitch` in the y-z plane (0, 0 = facing the net
squarely). Angles rather than normal components stay linear over the tilts the estimator can
measure; their noise follows from the estimator's `sigma_normal_deg` (`angle_covariance`).

Validity (what decides what the autopilot is told):
  TRACKING  this frame's measurement was accepted;
  COASTING  no accepted measurement this frame, the last one less than `coast_timeout_s` ago: the
            filter predicts through the gap (the autopilot still gets the prediction for
            `report_coasting_s`, or for `report_coasting_frames` of the measured intervals between
            frames when frames come slower than that allows, and through as many missed frames
            as that many intervals hold whatever their timing: one missed frame must not cut
            the distance of a loaded CPU that processes three frames a second, nor of one whose
            last frames were slow);
  LOST      no track, or nothing accepted for `coast_timeout_s` (a frame after that starts a
            new track rather than meeting a prediction wide enough to accept anything).
A new track starts tentative (state LOST) and becomes TRACKING after `acquire_count`
measurements that pass the gate, so a single false detection never reaches the autopilot; a
tentative track that meets a rejection restarts from it. A coasting prediction is not given
after two rejected frames in a row that put the net nearer than it (it may be too far, the
dangerous way).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from service.core.errors import ConfigError
from service.core.filterpy_kalman import load_kalman_filter
from service.core.frame_intervals import FrameIntervals
from service.core.results import NetEstimate

FloatArray = npt.NDArray[np.float64]

# Index of each tracked quantity in the state vector; its rate follows it.
_D, _YAW, _PITCH = 0, 2, 4
# Intervals between processed frames over which their typical value is taken (median), and how
# many are needed before it replaces `report_coasting_s` alone.
# The longest a prediction may be passed off as a reading: ArduPilot drops a rangefinder after
# 0.5 s of silence; a prediction held for seconds is a distance nobody measured.
MAX_REPORT_COASTING_S = 1.0
# The longest a track may go unconfirmed and still be a track.
MAX_COAST_TIMEOUT_S = 5.0
MAX_REPORT_COASTING_FRAMES = 5.0
# How far a frame may be stamped before the last one and still be the same clock (a driver's
# timestamp jitter): a quarter of a 60 frames/s interval.
STAMP_JITTER_S = 0.004
_INTERVAL_WINDOW = 15
_MIN_INTERVALS = 3


class TrackState(enum.Enum):
    TRACKING = "tracking"
    COASTING = "coasting"
    LOST = "lost"


class Outcome(enum.Enum):
    """What the filter did with one frame's measurement."""

    ACCEPTED = "accepted"  # inside the gate: fused
    REJECTED = "rejected"  # outside the gate: ignored
    NONE = "none"  # no usable measurement in this frame
    RESET = "reset"  # the track (re)started from this measurement


@dataclass(frozen=True)
class FilterSettings:
    """Tuning of the tracker; the `[filter]` section of the configuration."""

    # Process noise: standard deviation of the (white) acceleration of distance and angles, i.e.
    # how hard the ROV and the net can plausibly move between frames.
    accel_sigma_distance: float = 0.5  # m/s^2
    accel_sigma_angle: float = 30.0  # deg/s^2
    # Innovation gate: a measurement further than this many standard deviations (Mahalanobis
    # distance over the 3-dimensional measurement) from the prediction is rejected.
    gate_sigma: float = 4.0
    # After this many consecutive rejected measurements the track restarts from the newest one:
    # the net (or the ROV) really moved faster than the model allows.
    max_consecutive_rejects: int = 5
    # Gated measurements needed before a new track is believed (TRACKING).
    acquire_count: int = 3
    # Without an accepted measurement for this long the track is LOST.
    coast_timeout_s: float = 1.0
    # While COASTING, the autopilot still gets the predicted distance for this long (0 = only
    # while TRACKING). Must not exceed coast_timeout_s.
    report_coasting_s: float = 0.3
    # ... or for this many of the typical (median) intervals between processed frames, when that
    # is longer (never beyond coast_timeout_s). 1.5 lets one missed frame pass, with room for the
    # intervals' jitter, and not two. At 30 frames/s report_coasting_s decides; under a quarter
    # of a core (`netpose bench soak`: 3-7 frames/s with 0.2-0.3 s between frames) a fixed 0.3 s
    # made a single missed frame withdraw the distance, and the link's once-a-second limit on
    # starting again turned that into a 1.1 s gap for the autopilot. Its whole part is also a
    # number of missed frames coasted through whatever the time between them: the miss after
    # two slow frames (a 0.4 s whole-frame search under the quota) came after 3 typical
    # intervals, outlasted the window and cut the distance for a second. 0 = report_coasting_s
    # only.
    report_coasting_frames: float = 1.5
    # Estimates below this confidence are treated as no detection.
    min_confidence: float = 0.3
    # Floors on the estimator's own sigmas: its uncertainty never looks better than this. The
    # relative floor covers frame-to-frame scatter the estimator's sigma does not see (mesh
    # deformation, perspective inside a ROI), which grows with distance.
    min_sigma_distance_m: float = 0.005
    min_sigma_distance_frac: float = 0.01
    min_sigma_angle_deg: float = 0.5
    # Used when the estimator reports a detection without sigmas.
    fallback_sigma_distance_frac: float = 0.05
    fallback_sigma_angle_deg: float = 5.0
    # Initial uncertainty of the rates of a new track.
    initial_sigma_distance_rate: float = 0.5  # m/s
    initial_sigma_angle_rate: float = 20.0  # deg/s

    def __post_init__(self) -> None:
        positive = (
            "accel_sigma_distance",
            "accel_sigma_angle",
            "gate_sigma",
            "coast_timeout_s",
            "min_sigma_distance_m",
            "min_sigma_distance_frac",
            "min_sigma_angle_deg",
            "fallback_sigma_distance_frac",
            "fallback_sigma_angle_deg",
            "initial_sigma_distance_rate",
            "initial_sigma_angle_rate",
        )
        for name in positive:
            value = getattr(self, name)
            if not math.isfinite(value) or value <= 0:
                raise ConfigError(f"filter.{name}", f"must be a positive number, got {value}")
        if self.coast_timeout_s > MAX_COAST_TIMEOUT_S:
            raise ConfigError("filter.coast_timeout_s",
                              f"must be at most {MAX_COAST_TIMEOUT_S} s (a track unconfirmed "
                              f"longer is a guess), got {self.coast_timeout_s}")
        if not (math.isfinite(self.report_coasting_frames)
                and 0 <= self.report_coasting_frames <= MAX_REPORT_COASTING_FRAMES):
            raise ConfigError("filter.report_coasting_frames",
                              f"must be 0..{MAX_REPORT_COASTING_FRAMES:g}, "
                              f"got {self.report_coasting_frames}")
        if self.max_consecutive_rejects < 1:
            raise ConfigError("filter.max_consecutive_rejects", "must be at least 1")
        if self.acquire_count < 1:
            raise ConfigError("filter.acquire_count", "must be at least 1")
        if not 0.0 <= self.min_confidence <= 1.0:
            raise ConfigError("filter.min_confidence", f"must be 0..1, got {self.min_confidence}")
        if not 0.0 <= self.report_coasting_s <= min(self.coast_timeout_s,
                                                    MAX_REPORT_COASTING_S):
            raise ConfigError(
                "filter.report_coasting_s",
                f"must be 0..{MAX_REPORT_COASTING_S:g} s and at most coast_timeout_s "
                f"({self.coast_timeout_s}): a prediction is not a reading, got "
                f"{self.report_coasting_s}",
            )


@dataclass(frozen=True)
class Measurement:
    """What the filter takes from one NetEstimate: distance and two angles with 1-sigma noise."""

    distance_m: float
    yaw_deg: float
    pitch_deg: float
    sigma_distance_m: float
    sigma_angle_deg: float
    facing_sign: float  # sign of the normal's z component, kept to rebuild the normal


def angles_from_normal(normal: tuple[float, float, float]) -> tuple[float, float, float]:
    """(yaw_deg, pitch_deg, sign of n_z) of a unit normal; inverse of `normal_from_angles`."""
    nx, ny, nz = normal
    sign = -1.0 if nz < 0 else 1.0
    az = max(abs(nz), 1e-9)
    return math.degrees(math.atan2(nx, az)), math.degrees(math.atan2(ny, az)), sign


def normal_from_angles(yaw_deg: float, pitch_deg: float, sign: float) -> tuple[float, float, float]:
    tx, ty = math.tan(math.radians(yaw_deg)), math.tan(math.radians(pitch_deg))
    norm = math.sqrt(tx * tx + ty * ty + 1.0)
    return tx / norm, ty / norm, sign / norm


def angle_covariance(yaw_deg: float, pitch_deg: float, sigma_deg: float) -> FloatArray:
    """Covariance (deg^2) of (yaw, pitch) for a normal known to `sigma_deg` in every
    direction across it. Each angle is the normal's tilt in one plane of the camera (tan(yaw) =
    n_x / n_z, tan(pitch) = n_y / n_z): in the plane of the net's tilt its error is the
    normal's, across it the error grows as 1 / cos(tilt), and the two correlate when the tilt
    is oblique. J J^T of the angles' gradients over the unit normal, which lie across it."""
    nx, ny, nz = normal_from_angles(yaw_deg, pitch_deg, 1.0)
    xz = nx * nx + nz * nz
    yz = ny * ny + nz * nz
    return float(sigma_deg) ** 2 * np.array([[1.0 / xz, nx * ny / (xz * yz)],
                                             [nx * ny / (xz * yz), 1.0 / yz]])


def measurement_from_estimate(
    estimate: NetEstimate, settings: FilterSettings
) -> Measurement | None:
    """The filter's view of an estimate, or None when it carries no usable detection."""
    if not estimate.detected or estimate.confidence < settings.min_confidence:
        return None
    if estimate.distance_m is None or estimate.normal is None:
        return None
    d = float(estimate.distance_m)
    if not math.isfinite(d) or d <= 0 or not all(math.isfinite(v) for v in estimate.normal):
        return None
    yaw, pitch, sign = angles_from_normal(estimate.normal)
    sd = estimate.sigma_distance_m
    sa = estimate.sigma_normal_deg
    sd = settings.fallback_sigma_distance_frac * d if sd is None or not math.isfinite(sd) else sd
    sa = settings.fallback_sigma_angle_deg if sa is None or not math.isfinite(sa) else sa
    return Measurement(
        distance_m=d,
        yaw_deg=yaw,
        pitch_deg=pitch,
        sigma_distance_m=max(
            float(sd), settings.min_sigma_distance_m, settings.min_sigma_distance_frac * d
        ),
        sigma_angle_deg=max(float(sa), settings.min_sigma_angle_deg),
        facing_sign=sign,
    )


@dataclass(frozen=True)
class TrackOutput:
    """The filter's answer for one frame."""

    state: TrackState
    # Filtered values (None when there is no track at all).
    distance_m: float | None
    distance_rate_mps: float | None
    range_m: float | None  # along the optical axis: distance / cos(tilt)
    yaw_deg: float | None
    pitch_deg: float | None
    normal: tuple[float, float, float] | None
    sigma_distance_m: float | None
    measurement: Outcome
    mahalanobis: float | None
    consecutive_rejects: int
    since_accepted_s: float | None
    # True when the autopilot may be given `distance_m`.
    valid: bool


class NetTracker:
    """Constant-velocity Kalman filter (filterpy) with gating and TRACKING/COASTING/LOST state.

    Call `step(t, estimate)` once per processed frame with the frame's capture time (monotonic
    seconds); `estimate` may be None for a frame that produced nothing.
    """

    def __init__(self, settings: FilterSettings) -> None:
        self._settings = settings
        self._kf = load_kalman_filter()(dim_x=6, dim_z=3)
        self._kf.F = np.eye(6)
        self._kf.H = np.zeros((3, 6))
        self._kf.H[0, _D] = self._kf.H[1, _YAW] = self._kf.H[2, _PITCH] = 1.0
        self._H = self._kf.H.copy()
        self._has_track = False
        self._confirmed = False
        self._hits = 0
        self._rejects = 0
        self._t_last: float | None = None
        self._t_accepted: float | None = None
        self._facing_sign = -1.0
        # Intervals between processed frames (steps with an estimate) while there is a track,
        # for the coasting window.
        self._frames = FrameIntervals(_INTERVAL_WINDOW, _MIN_INTERVALS)
        # Processed frames since the last accepted measurement.
        self._misses = 0
        # Two rejected frames in a row put the net nearer than the prediction: no coasting is
        # reported until a frame is accepted.
        self._withdrawn = False
        self._nearer = False  # the last rejected frame put the net nearer than the prediction
        self.accepted_total = 0
        self.rejected_total = 0
        self.resets_total = 0

    @property
    def settings(self) -> FilterSettings:
        return self._settings

    def reconfigure(self, settings: FilterSettings) -> None:
        """New tuning (configuration reload); the current track and its state are kept."""
        self._settings = settings

    def reset(self) -> None:
        self._has_track = False
        self._confirmed = False
        self._hits = 0
        self._rejects = 0
        self._t_accepted = None
        # The coasting window follows the frame rate of a track: the search rate of open water
        # (`budget.search_hz`, as slow as one frame in two seconds) must not stretch a new one.
        self._frames.clear()
        self._misses = 0
        self._withdrawn = self._nearer = False

    # -- state, for recordings that start mid-dive ------------------------------------------
    def snapshot(self) -> dict[str, Any]:
        """The filter's state as plain JSON values (floats exact), for `restore`."""
        return {
            "x": self._kf.x.tolist(), "P": self._kf.P.tolist(),
            "has_track": self._has_track, "confirmed": self._confirmed, "hits": self._hits,
            "rejects": self._rejects, "t_last": self._t_last, "t_accepted": self._t_accepted,
            "facing_sign": self._facing_sign, "intervals": self._frames.values(),
            "t_frame": self._frames.last, "misses": self._misses, "withdrawn": self._withdrawn,
            "nearer": self._nearer,
        }

    def restore(self, state: dict[str, Any]) -> None:
        """Continue from a `snapshot` (the totals are not part of the state)."""
        self._kf.x = np.array(state["x"], dtype=float).reshape(6, 1)
        self._kf.P = np.array(state["P"], dtype=float).reshape(6, 6)
        self._has_track = bool(state["has_track"])
        self._confirmed = bool(state["confirmed"])
        self._hits = int(state["hits"])
        self._rejects = int(state["rejects"])
        self._t_last = None if state["t_last"] is None else float(state["t_last"])
        self._t_accepted = None if state["t_accepted"] is None else float(state["t_accepted"])
        self._facing_sign = float(state["facing_sign"])
        # Absent from states saved before the coasting window followed the frame rate.
        self._frames.restore(state.get("intervals", ()), state.get("t_frame"))
        self._misses = int(state.get("misses", 0))
        self._withdrawn = bool(state.get("withdrawn", False))
        self._nearer = bool(state.get("nearer", False))

    # -- the filter ------------------------------------------------------------------------
    def _start(self, m: Measurement, t: float) -> None:
        s = self._settings
        self._kf.x = np.array([[m.distance_m], [0.0], [m.yaw_deg], [0.0], [m.pitch_deg], [0.0]])
        P = np.diag(
            [
                m.sigma_distance_m**2,
                s.initial_sigma_distance_rate**2,
                0.0,
                s.initial_sigma_angle_rate**2,
                0.0,
                s.initial_sigma_angle_rate**2,
            ]
        )
        P[np.ix_([_YAW, _PITCH], [_YAW, _PITCH])] = angle_covariance(
            m.yaw_deg, m.pitch_deg, m.sigma_angle_deg)
        self._kf.P = P
        self._has_track = True
        self._confirmed = s.acquire_count <= 1
        self._hits = 1
        self._rejects = 0
        self._misses = 0
        self._withdrawn = self._nearer = False
        self._t_accepted = t
        self._facing_sign = m.facing_sign

    def _predict(self, dt: float) -> None:
        s = self._settings
        F = np.eye(6)
        Q = np.zeros((6, 6))
        # Discrete white-noise acceleration: accel variance q gives this per-axis block.
        block = np.array([[dt**4 / 4.0, dt**3 / 2.0], [dt**3 / 2.0, dt**2]])
        for i, sigma in ((_D, s.accel_sigma_distance), (_YAW, s.accel_sigma_angle),
                         (_PITCH, s.accel_sigma_angle)):
            F[i, i + 1] = dt
            Q[i : i + 2, i : i + 2] = block * sigma**2
        self._kf.predict(F=F, Q=Q)

    def _gate(self, m: Measurement) -> tuple[FloatArray, FloatArray, float]:
        z = np.array([[m.distance_m], [m.yaw_deg], [m.pitch_deg]])
        R = np.zeros((3, 3))
        R[0, 0] = m.sigma_distance_m**2
        R[1:, 1:] = angle_covariance(m.yaw_deg, m.pitch_deg, m.sigma_angle_deg)
        y = z - self._H @ self._kf.x
        S = self._H @ self._kf.P @ self._H.T + R
        d2 = float((y.T @ np.linalg.solve(S, y))[0, 0])
        return z, R, math.sqrt(max(d2, 0.0))

    def report_coasting_limit_s(self) -> float:
        """How long after the last accepted measurement a coasting prediction is still given
        (`report_coasting_s`, or `report_coasting_frames` typical frame intervals)."""
        s = self._settings
        limit = s.report_coasting_s
        typical = self._frames.median()
        if s.report_coasting_frames > 0 and typical is not None:
            limit = max(limit, s.report_coasting_frames * typical)
        return min(limit, s.coast_timeout_s, MAX_REPORT_COASTING_S)

    def _coasting_reported(self, t: float, since: float) -> bool:
        """Whether a coasting prediction still goes to the autopilot: within the window of the
        last accepted measurement, or after no more missed frames than the window holds and
        within the window of the newest of them (a stalled source's ticks do not stretch it).
        A rejected measurement is no missed frame: it is evidence against the prediction, which
        then gets the time window only."""
        limit = self.report_coasting_limit_s()
        if since <= limit:
            return True
        allowed = math.floor(self._settings.report_coasting_frames)
        newest = self._frames.last
        return (0 < self._misses <= allowed and self._rejects == 0
                and newest is not None and t - newest <= limit)

    def step(self, t: float, estimate: NetEstimate | None) -> TrackOutput:
        s = self._settings
        if self._t_last is not None and t < self._t_last - STAMP_JITTER_S:
            # Time went back: the frames' clock changed under the track (a source that
            # re-opened with stamps behind those it gave before). The filter cannot predict
            # backwards, and "since the last accepted measurement" would stay negative, so the
            # track would read as TRACKING on a blank view for as long as the old stamps led.
            self.reset()
            self._t_last = None
        elif self._t_last is not None and t < self._t_last:
            t = self._t_last  # a driver's stamp a moment early: the same instant, not a clock
        if (self._has_track and self._t_accepted is not None
                and t - self._t_accepted >= s.coast_timeout_s):
            # The track is over before this frame is judged: its prediction has grown wide
            # enough to let anything through the gate (a mesh harmonic after a stalled camera
            # joined it as TRACKING), and a frame must find the track ended whether or not
            # ticks came through the gap (a recording keeps no ticks).
            self.reset()
        if estimate is not None:  # a processed frame (ticks and unmeasured frames are not)
            if self._has_track:
                self._frames.add(t)
            else:  # intervals are the track's only; the next one counts from this frame
                self._frames.last = t
        m = None if estimate is None else measurement_from_estimate(estimate, s)
        # Time without a frame (a tick, a frame not measured) is predicted for the output only:
        # the filter commits one prediction over the whole interval at the next measured
        # frame. Discrete process noise does not add up over split intervals, and a recording
        # keeps frames, not ticks: a replay must meet the same filter state.
        held = None if estimate is not None else self._held_state()
        if self._has_track and self._t_last is not None:
            dt = t - self._t_last
            if dt > 0:
                self._predict(dt)
        if held is None:
            self._t_last = t

        outcome = Outcome.NONE
        maha: float | None = None
        if m is not None:
            if not self._has_track:
                self._start(m, t)
                outcome = Outcome.RESET
            else:
                z, R, maha = self._gate(m)
                if maha <= s.gate_sigma:
                    # filterpy 2.0: with H given, z must already be a (dim_z, 1) column.
                    self._kf.update(z, R=R, H=self._H)
                    self._t_accepted = t
                    self._rejects = 0
                    self._hits += 1
                    self._facing_sign = m.facing_sign
                    self._misses = 0
                    self._withdrawn = self._nearer = False
                    if self._hits >= s.acquire_count:
                        self._confirmed = True
                    outcome = Outcome.ACCEPTED
                    self.accepted_total += 1
                else:
                    self._rejects += 1
                    self.rejected_total += 1
                    outcome = Outcome.REJECTED
                    # Frames that put the net nearer than the prediction say the prediction may
                    # be too far, the way that drives a vehicle into the net: after two in a row
                    # it is not given again until a frame confirms it (farther errs safe). A net
                    # that came nearer does that from the frame after; one wild frame of a still
                    # net does not (a single one, even far beyond the gate, cut the distance
                    # for a second every twenty seconds with heavy-tailed noise).
                    innovation = float(z[0, 0] - self._kf.x[_D, 0])
                    nearer = innovation < -math.sqrt(float(self._kf.P[_D, _D]) + R[0, 0])
                    if nearer and self._nearer:
                        self._withdrawn = True
                    self._nearer = nearer
                    if not self._confirmed or self._rejects >= s.max_consecutive_rejects:
                        # The world moved beyond the model: start again from what is seen now,
                        # and earn trust again before telling the autopilot anything. A track
                        # not yet confirmed has no trust to keep: one false detection (a mesh
                        # harmonic) must not hold off the net's own frames for several more.
                        self._start(m, t)
                        self._confirmed = s.acquire_count <= 1
                        self.resets_total += 1
                        outcome = Outcome.RESET

        if estimate is not None and outcome not in (Outcome.ACCEPTED, Outcome.RESET):
            self._misses += 1
        since = None if self._t_accepted is None else t - self._t_accepted

        if not self._has_track or not self._confirmed:
            state = TrackState.LOST
        elif since is not None and since <= 0.0:
            state = TrackState.TRACKING
        else:
            state = TrackState.COASTING
        output = self._output(t, state, outcome, maha, since)
        if held is not None:
            self._kf.x, self._kf.P, self._kf.x_prior, self._kf.P_prior = held
        return output

    def _held_state(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        kf = self._kf
        return kf.x.copy(), kf.P.copy(), kf.x_prior.copy(), kf.P_prior.copy()

    def _output(
        self, t: float, state: TrackState, outcome: Outcome, maha: float | None,
        since: float | None,
    ) -> TrackOutput:
        if not self._has_track:
            return TrackOutput(
                state=state, distance_m=None, distance_rate_mps=None, range_m=None, yaw_deg=None,
                pitch_deg=None, normal=None, sigma_distance_m=None, measurement=outcome,
                mahalanobis=maha, consecutive_rejects=self._rejects, since_accepted_s=since,
                valid=False,
            )
        x = self._kf.x[:, 0]
        d, yaw, pitch = float(x[_D]), float(x[_YAW]), float(x[_PITCH])
        normal = normal_from_angles(yaw, pitch, self._facing_sign)
        cos_tilt = abs(normal[2])
        valid = d > 0 and (
            state is TrackState.TRACKING
            or (
                state is TrackState.COASTING
                and since is not None
                and not self._withdrawn
                and self._coasting_reported(t, since)
            )
        )
        return TrackOutput(
            state=state,
            distance_m=d,
            distance_rate_mps=float(x[_D + 1]),
            range_m=d / cos_tilt if cos_tilt > 1e-6 else None,
            yaw_deg=yaw,
            pitch_deg=pitch,
            normal=normal,
            sigma_distance_m=math.sqrt(max(float(self._kf.P[_D, _D]), 0.0)),
            measurement=outcome,
            mahalanobis=maha,
            consecutive_rejects=self._rejects,
            since_accepted_s=since,
            valid=valid,
        )
