"""The tracker against scripted trajectories with known noise: smoothing, gating, dropouts."""

from __future__ import annotations

import math

import numpy as np
import pytest

from service.core.errors import ConfigError
from service.core.results import NetEstimate
from service.core.tracking import (
    FilterSettings,
    NetTracker,
    Outcome,
    TrackState,
    angles_from_normal,
    normal_from_angles,
)

FPS = 30.0


def estimate(d: float, yaw: float = 0.0, pitch: float = 0.0, sd: float = 0.02,
             sa: float = 1.0, confidence: float = 0.9) -> NetEstimate:
    n = normal_from_angles(yaw, pitch, -1.0)
    return NetEstimate(
        detected=True, confidence=confidence, normal=n, distance_m=d, range_m=d / abs(n[2]),
        sigma_distance_m=sd, sigma_normal_deg=sa,
    )


def test_normal_angles_round_trip() -> None:
    for yaw, pitch in ((0.0, 0.0), (25.0, -10.0), (-40.0, 30.0)):
        n = normal_from_angles(yaw, pitch, -1.0)
        assert math.isclose(sum(v * v for v in n), 1.0, rel_tol=1e-12)
        y2, p2, sign = angles_from_normal(n)
        assert sign == -1.0
        assert y2 == pytest.approx(yaw, abs=1e-9) and p2 == pytest.approx(pitch, abs=1e-9)


def test_new_track_needs_acquire_count_measurements_before_it_is_valid() -> None:
    tracker = NetTracker(FilterSettings(acquire_count=3))
    outs = [tracker.step(i / FPS, estimate(1.5)) for i in range(4)]
    assert [o.state for o in outs] == [TrackState.LOST, TrackState.LOST, TrackState.TRACKING,
                                       TrackState.TRACKING]
    assert [o.valid for o in outs] == [False, False, True, True]
    assert outs[-1].distance_m == pytest.approx(1.5, abs=1e-6)


def test_filter_reduces_noise_on_a_moving_net() -> None:
    """ROV approaching at 0.2 m/s with 3 cm measurement noise: the filter must beat the raw
    measurements clearly (a constant-velocity KF at 30 Hz over 300 frames should cut the RMS
    error by more than half), and the rate estimate must find the approach speed."""
    rng = np.random.default_rng(7)
    tracker = NetTracker(FilterSettings(accel_sigma_distance=0.2))
    raw_err, filt_err = [], []
    out = None
    for i in range(300):
        t = i / FPS
        truth = 2.5 - 0.2 * t
        meas = truth + rng.normal(0.0, 0.03)
        yaw_truth = 10.0 + 5.0 * t
        out = tracker.step(t, estimate(meas, yaw=yaw_truth + rng.normal(0, 1.0), sd=0.03))
        if i >= 60:  # after convergence
            assert out.state is TrackState.TRACKING
            assert out.distance_m is not None and out.yaw_deg is not None
            raw_err.append(meas - truth)
            filt_err.append(out.distance_m - truth)
    raw_rms = float(np.sqrt(np.mean(np.square(raw_err))))
    filt_rms = float(np.sqrt(np.mean(np.square(filt_err))))
    assert raw_rms == pytest.approx(0.03, rel=0.2)
    assert filt_rms < 0.5 * raw_rms
    assert out is not None and out.distance_rate_mps == pytest.approx(-0.2, abs=0.05)
    assert out.yaw_deg == pytest.approx(10.0 + 5.0 * 299 / FPS, abs=1.0)
    # range along the optical axis follows from distance and tilt.
    assert out.normal is not None and out.distance_m is not None
    assert out.range_m == pytest.approx(out.distance_m / abs(out.normal[2]), rel=1e-9)


def test_outlier_is_rejected_and_counted() -> None:
    tracker = NetTracker(FilterSettings(gate_sigma=4.0))
    for i in range(30):
        tracker.step(i / FPS, estimate(1.2, sd=0.02))
    out = tracker.step(30 / FPS, estimate(2.4, sd=0.02))  # a wrong lattice: double the period
    assert out.measurement.value == "rejected"
    assert out.mahalanobis is not None and out.mahalanobis > 4.0
    assert out.distance_m == pytest.approx(1.2, abs=0.01)
    assert out.state is TrackState.COASTING and out.valid  # within report_coasting_s
    assert tracker.rejected_total == 1
    out = tracker.step(31 / FPS, estimate(1.2, sd=0.02))
    assert out.measurement.value == "accepted" and out.state is TrackState.TRACKING


def test_the_gate_accepts_within_gate_sigma_and_rejects_beyond() -> None:
    """At the gate's boundary, not 60 sigma from it: on a converged track, a measurement
    3.5 innovation sigmas off is accepted and one 4.5 off rejected (gate_sigma 4). The
    innovation sigma is the measurement's and the track's own together: checked against
    sqrt(sd^2 + sigma_track^2) from the outputs (the prediction over one frame adds little)."""
    import copy

    sd = 0.02
    tracker = NetTracker(FilterSettings(gate_sigma=4.0))
    out = None
    for i in range(60):
        out = tracker.step(i / FPS, estimate(1.2, sd=sd))
    assert out is not None and out.sigma_distance_m is not None
    t = 60 / FPS
    probe = copy.deepcopy(tracker).step(t, estimate(1.2 + 0.01, sd=sd))
    assert probe.mahalanobis is not None
    per_metre = probe.mahalanobis / 0.01  # innovation sigmas per metre off
    assert 1.0 / per_metre == pytest.approx(math.hypot(sd, out.sigma_distance_m), rel=0.1)
    for sigmas, accepted in ((3.5, True), (4.5, False), (-3.5, True), (-4.5, False)):
        trial = copy.deepcopy(tracker).step(t, estimate(1.2 + sigmas / per_metre, sd=sd))
        assert (trial.measurement is Outcome.ACCEPTED) == accepted, sigmas


def test_consistent_rejects_restart_the_track_at_the_new_value() -> None:
    """The net really jumped (e.g. another net panel came into view): after
    max_consecutive_rejects the track restarts there and must be re-acquired."""
    s = FilterSettings(max_consecutive_rejects=4, acquire_count=3)
    tracker = NetTracker(s)
    for i in range(30):
        tracker.step(i / FPS, estimate(1.0, sd=0.01))
    outs = [tracker.step((30 + k) / FPS, estimate(2.0, sd=0.01)) for k in range(8)]
    assert [o.measurement.value for o in outs[:4]] == ["rejected"] * 3 + ["reset"]
    assert all(not o.valid for o in outs[3:5])  # re-acquiring: nothing for the autopilot
    assert outs[-1].state is TrackState.TRACKING and outs[-1].valid
    assert outs[-1].distance_m == pytest.approx(2.0, abs=0.005)
    assert tracker.resets_total == 1



@pytest.mark.parametrize("fps", [3.0, 4.0])
def test_a_slow_loop_coasts_through_one_missed_frame_and_not_two(fps: float) -> None:
    """A loaded CPU processes 3-4 frames a second (0.25-0.33 s apart): one frame without a net
    keeps the distance (the prediction, report_coasting_frames = 1.5 intervals), the second
    withdraws it. With report_coasting_s alone (0.3 s) the first miss at 3 frames/s did."""
    tracker = NetTracker(FilterSettings(report_coasting_s=0.3, coast_timeout_s=1.0))
    for i in range(10):
        assert tracker.step(i / fps, estimate(1.5, sd=0.01)).valid or i < 2
    miss = NetEstimate(detected=False, confidence=0.0, reason="no lattice")
    first = tracker.step(10 / fps, miss)
    second = tracker.step(11 / fps, miss)
    assert first.state is TrackState.COASTING and first.valid
    assert first.distance_m == pytest.approx(1.5, abs=0.01)
    assert second.state is TrackState.COASTING and not second.valid
    assert tracker.report_coasting_limit_s() == pytest.approx(1.5 / fps)


def test_a_miss_after_slow_frames_is_coasted_through_and_the_ticks_after_it_are_not() -> None:
    """Under a CPU quota two tracked frames took 0.45 s each (a whole-frame search), then one
    missed: 0.45 s after the last accepted measurement, beyond 1.5 typical intervals (0.375 s
    at 4 frames/s), which withdrew the distance and cost the autopilot a second. One missed
    frame is coasted through whatever its timing; ticks of a source that then stalls keep it
    only for the usual window after that frame; a second miss withdraws it."""
    fps = 4.0
    tracker = NetTracker(FilterSettings(report_coasting_s=0.3, coast_timeout_s=1.0))
    for i in range(10):
        tracker.step(i / fps, estimate(1.5, sd=0.01))
    t = 9 / fps
    for _ in range(2):  # two slow frames, both measured
        t += 0.45
        assert tracker.step(t, estimate(1.5, sd=0.01)).valid
    window = tracker.report_coasting_limit_s()
    assert window == pytest.approx(1.5 / fps)
    miss = NetEstimate(detected=False, confidence=0.0, reason="no lattice")
    first = tracker.step(t + 0.45, miss)
    assert first.state is TrackState.COASTING and first.valid
    assert first.since_accepted_s == pytest.approx(0.45)
    assert first.distance_m == pytest.approx(1.5, abs=0.01)
    after_miss = tracker.snapshot()
    assert tracker.step(t + 0.45 + 0.9 * window, None).valid
    assert not tracker.step(t + 0.45 + 1.1 * window, None).valid
    again = NetTracker(FilterSettings(report_coasting_s=0.3, coast_timeout_s=1.0))
    again.restore(after_miss)  # the count of missed frames is part of the saved state
    assert not again.step(t + 0.45 + 0.5 * window, miss).valid  # a second miss, soon after


def test_a_rejected_measurement_after_slow_frames_is_not_coasted_through() -> None:
    """A frame whose measurement the gate rejects is evidence against the prediction: unlike
    a frame without a net it gets the time window only, not the missed frame's pass."""
    fps = 4.0
    tracker = NetTracker(FilterSettings(report_coasting_s=0.3, coast_timeout_s=1.0))
    for i in range(10):
        tracker.step(i / fps, estimate(1.5, sd=0.01))
    t = 9 / fps + 0.45
    assert tracker.step(t, estimate(1.5, sd=0.01)).valid
    rejected = tracker.step(t + 0.45, estimate(2.5, sd=0.01))
    assert rejected.measurement is Outcome.REJECTED
    assert rejected.state is TrackState.COASTING and not rejected.valid


def test_missed_frames_are_not_coasted_through_when_the_window_is_fixed() -> None:
    tracker = NetTracker(FilterSettings(report_coasting_s=0.3, report_coasting_frames=0.0))
    for i in range(10):
        tracker.step(i / 4.0, estimate(1.5, sd=0.01))
    miss = NetEstimate(detected=False, confidence=0.0, reason="no lattice")
    assert not tracker.step(9 / 4.0 + 0.45, miss).valid


def test_the_coasting_window_follows_processed_frames_not_ticks() -> None:
    """At 30 frames/s the window is report_coasting_s (1.5 intervals are 50 ms); ticks of a
    stalled source (step without an estimate), here 0.25 s apart, are not frames and do not
    stretch it (as frames they would make it 0.375 s)."""
    tracker = NetTracker(FilterSettings(report_coasting_s=0.3, coast_timeout_s=5.0))
    for i in range(30):
        tracker.step(i / FPS, estimate(1.5, sd=0.01))
    assert tracker.report_coasting_limit_s() == pytest.approx(0.3)
    t0 = 29 / FPS
    valid = [(k * 0.25, tracker.step(t0 + k * 0.25, None).valid) for k in range(1, 17)]
    assert [v for _, v in valid] == [dt <= 0.3 + 1e-9 for dt, _ in valid]
    assert tracker.report_coasting_limit_s() == pytest.approx(0.3)


def test_a_new_track_does_not_coast_on_the_search_rate_of_open_water() -> None:
    """With no net in view the loop measures a frame every second or two (budget.search_hz);
    once the net is found and frames come at 30 a second, a stall must not be coasted through
    for 1.5 of those search intervals: the window is the new track's."""
    tracker = NetTracker(FilterSettings(report_coasting_s=0.3, coast_timeout_s=1.0))
    miss = NetEstimate(detected=False, confidence=0.0, reason="no lattice")
    for i in range(10):  # open water, one frame a second
        tracker.step(float(i), miss)
    for k in range(8):  # the net, at 30 frames/s
        tracker.step(10.0 + k / FPS, estimate(1.5, sd=0.01))
    assert tracker.report_coasting_limit_s() == pytest.approx(0.3)
    t_last = 10.0 + 7 / FPS
    assert not tracker.step(t_last + 0.35, None).valid


def test_the_coasting_window_never_outlasts_the_track_and_can_be_fixed() -> None:
    slow = NetTracker(FilterSettings(report_coasting_s=0.3, coast_timeout_s=1.0))
    fixed = NetTracker(FilterSettings(report_coasting_s=0.3, report_coasting_frames=0.0))
    for i in range(6):  # a frame every 0.9 s (one every coast_timeout_s ends the track)
        slow.step(0.9 * i, estimate(1.5, sd=0.01))
        fixed.step(0.9 * i, estimate(1.5, sd=0.01))
    assert slow.report_coasting_limit_s() == pytest.approx(1.0)  # coast_timeout_s
    assert fixed.report_coasting_limit_s() == pytest.approx(0.3)
    with pytest.raises(ConfigError, match=r"filter\.report_coasting_frames"):
        FilterSettings(report_coasting_frames=-1.0)


def test_the_frame_intervals_survive_a_snapshot() -> None:
    """A replay that starts from a saved state coasts as the run it continues would have."""
    tracker = NetTracker(FilterSettings())
    for i in range(8):
        tracker.step(i / 3.0, estimate(1.5, sd=0.01))
    copy = NetTracker(FilterSettings())
    copy.restore(tracker.snapshot())
    assert copy.snapshot() == tracker.snapshot()
    assert copy.report_coasting_limit_s() == pytest.approx(tracker.report_coasting_limit_s())
    miss = NetEstimate(detected=False, confidence=0.0, reason="no lattice")
    assert copy.step(8 / 3.0, miss).valid == tracker.step(8 / 3.0, miss).valid

def test_dropout_coasts_on_the_prediction_then_is_lost() -> None:
    s = FilterSettings(coast_timeout_s=1.0, report_coasting_s=0.3, accel_sigma_distance=0.1)
    tracker = NetTracker(s)
    for i in range(90):  # 3 s of approach at 0.1 m/s, noise-free
        t = i / FPS
        tracker.step(t, estimate(2.0 - 0.1 * t, sd=0.01))
    t0 = 89 / FPS
    seen = []
    for k in range(1, 40):  # the net vanishes (turbidity): frames keep coming, no detection
        t = t0 + k / FPS
        out = tracker.step(t, NetEstimate(detected=False, confidence=0.0, reason="no lattice"))
        seen.append((t - t0, out))
    for dt, out in seen:
        if dt < 1.0 - 1e-9:
            assert out.state is TrackState.COASTING
            # The prediction carries the approach on: 2 - 0.1 t.
            assert out.distance_m == pytest.approx(2.0 - 0.1 * (t0 + dt), abs=0.01)
            assert out.valid == (dt <= 0.3 + 1e-9)
        else:
            assert out.state is TrackState.LOST and not out.valid and out.distance_m is None


def test_low_confidence_and_nonsense_estimates_are_not_measurements() -> None:
    tracker = NetTracker(FilterSettings(min_confidence=0.5, acquire_count=1))
    assert tracker.step(0.0, estimate(1.0, confidence=0.4)).measurement.value == "none"
    assert tracker.step(0.1, estimate(float("nan"))).measurement.value == "none"
    assert tracker.step(0.2, estimate(-1.0)).measurement.value == "none"
    out = tracker.step(0.3, estimate(1.0, confidence=0.6))
    assert out.measurement.value == "reset" and out.valid  # acquire_count=1: believed at once


def test_missing_sigmas_use_the_fallback_noise() -> None:
    tracker = NetTracker(FilterSettings(fallback_sigma_distance_frac=0.05, acquire_count=1))
    est = NetEstimate(detected=True, confidence=0.9, normal=(0.0, 0.0, -1.0), distance_m=2.0)
    out = tracker.step(0.0, est)
    assert out.sigma_distance_m == pytest.approx(0.1, rel=1e-6)


@pytest.mark.parametrize(
    ("kwargs", "key"),
    [
        ({"gate_sigma": 0.0}, "filter.gate_sigma"),
        ({"coast_timeout_s": -1.0}, "filter.coast_timeout_s"),
        ({"report_coasting_s": 2.0, "coast_timeout_s": 1.0}, "filter.report_coasting_s"),
        ({"min_confidence": 1.5}, "filter.min_confidence"),
        ({"acquire_count": 0}, "filter.acquire_count"),
        # A prediction sent for minutes with the last frame's quality: 1000 s of coasting and
        # 300 s of it reported sent 7.5 s of extrapolation, down to 1 cm, at quality 97.
        ({"coast_timeout_s": 1000.0}, "filter.coast_timeout_s"),
        ({"report_coasting_s": 4.0, "coast_timeout_s": 5.0}, "filter.report_coasting_s"),
        ({"report_coasting_frames": 100.0}, "filter.report_coasting_frames"),
    ],
)
def test_bad_settings_name_the_key(kwargs: dict[str, float], key: str) -> None:
    with pytest.raises(ConfigError) as info:
        FilterSettings(**kwargs)  # type: ignore[arg-type]
    assert info.value.key == key


def test_the_filter_is_filterpys_own_class_loaded_without_scipy_stats() -> None:
    """service.core.filterpy_kalman loads filterpy's KalmanFilter source alone (no scipy.stats,
    70 MB and a second of start-up less); it must compute exactly what filterpy's package
    export computes, and its logpdf what scipy's does."""
    import subprocess
    import sys

    from filterpy.kalman import KalmanFilter as PackageKalmanFilter
    from scipy.stats import multivariate_normal

    from service.core.filterpy_kalman import load_kalman_filter, logpdf

    rng = np.random.default_rng(4)
    mine, theirs = load_kalman_filter()(dim_x=4, dim_z=2), PackageKalmanFilter(dim_x=4, dim_z=2)
    assert type(mine).__name__ == "KalmanFilter" and type(mine) is not PackageKalmanFilter
    F = np.eye(4) + np.diag([0.1, 0.0, 0.1], k=1)
    H = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    for kf in (mine, theirs):
        kf.x = np.array([[1.0], [0.0], [2.0], [0.0]])
        kf.P = np.eye(4)
        kf.F, kf.H, kf.R, kf.Q = F, H, np.eye(2) * 0.01, np.eye(4) * 1e-3
    for _ in range(20):
        z = rng.normal(size=(2, 1))
        for kf in (mine, theirs):
            kf.predict()
            kf.update(z)
        np.testing.assert_array_equal(mine.x, theirs.x)
        np.testing.assert_array_equal(mine.P, theirs.P)
    cov = np.array([[2.0, 0.3], [0.3, 0.5]])
    for x in ([0.0, 0.0], [1.0, -2.0]):
        assert logpdf(x, [0.5, 0.1], cov) == pytest.approx(
            multivariate_normal.logpdf(x, [0.5, 0.1], cov), rel=1e-12)
    singular = np.array([[1.0, 1.0], [1.0, 1.0]])
    assert logpdf([1.0, 1.0], [0.0, 0.0], singular) == pytest.approx(
        multivariate_normal.logpdf([1.0, 1.0], [0.0, 0.0], singular, allow_singular=True),
        rel=1e-9)
    probe = subprocess.run(
        [sys.executable, "-c", "import sys; from service.core.tracking import NetTracker, "
         "FilterSettings; NetTracker(FilterSettings()); "
         "print('scipy.stats' in sys.modules, 'filterpy' in sys.modules)"],
        capture_output=True, text=True, timeout=60, check=True)
    assert probe.stdout.split() == ["False", "False"]


def test_a_slow_camera_does_not_stretch_the_reported_coasting_past_a_second() -> None:
    """1.5 intervals of a camera at 1 frame/s would report a prediction for 1.5 s: ArduPilot
    drops a rangefinder after 0.5 s of silence, so a second is the most a prediction is
    passed off as a reading."""
    tracker = NetTracker(FilterSettings(report_coasting_s=0.3, coast_timeout_s=5.0))
    for i in range(8):
        tracker.step(float(i), estimate(1.0))
    assert tracker.report_coasting_limit_s() == pytest.approx(1.0)


@pytest.mark.parametrize("ticks", [False, True])
def test_a_measurement_after_the_coast_timeout_starts_a_new_tentative_track(ticks: bool) -> None:
    """A frame that comes more than coast_timeout_s after the last accepted one (a stalled
    camera, a slow whole-frame search) meets a prediction whose uncertainty has grown to let
    anything through: a mesh harmonic at 1.5 times the distance joined the old confirmed
    track as TRACKING, and its velocity then rejected the true frames after it. The track is
    over by then: the frame starts a new one, tentative until acquire_count frames confirm it.
    Ticks through the gap (the daemon's, while its reader waits) must not change what follows:
    a recording keeps no ticks, and its replay meets the same frames."""
    s = FilterSettings(coast_timeout_s=1.0, acquire_count=3)
    tracker = NetTracker(s)
    for i in range(30):
        tracker.step(i / 10.0, estimate(2.0, sd=0.02))
    t = 2.9 + 1.5
    if ticks:
        for k in range(1, 6):
            tracker.step(2.9 + 0.25 * k, None)
    outs = [tracker.step(t, estimate(3.0, sd=0.02))]
    outs += [tracker.step(t + k / 10.0, estimate(2.0, sd=0.02)) for k in range(1, 4)]
    assert outs[0].measurement is Outcome.RESET
    assert outs[0].state is TrackState.LOST and not outs[0].valid
    # The harmonic was a track of one frame: the first true frame replaces it (a track not
    # yet confirmed is not defended by the gate), and they earn trust again.
    assert outs[1].measurement is Outcome.RESET
    assert not outs[1].valid and not outs[2].valid
    assert outs[3].valid and outs[3].distance_m == pytest.approx(2.0, abs=0.01)
    replayed = NetTracker(s)
    for i in range(30):
        replayed.step(i / 10.0, estimate(2.0, sd=0.02))
    replayed.step(t, estimate(3.0, sd=0.02))
    for k in range(1, 4):
        replayed.step(t + k / 10.0, estimate(2.0, sd=0.02))
    assert replayed.snapshot() == tracker.snapshot()


@pytest.mark.parametrize(("measured", "valid"), [(1.4, False), (2.6, True)])
def test_a_nearer_measurement_the_gate_rejects_withdraws_the_prediction(measured: float,
                                                                        valid: bool) -> None:
    """The net stepped nearer (a billow, the vehicle pushed in): the gate rejects the first
    frames that say so, and the prediction coasting on the old, farther distance was still
    sent for the reporting window. Farther than the net really is, the dangerous way: a second
    rejected frame in a row that puts the net nearer withdraws the distance. Frames that put
    it farther (a sub-lattice, twice the period) leave the window as it was: the prediction
    then errs on the side of a nearer net."""
    tracker = NetTracker(FilterSettings())
    for i in range(30):
        tracker.step(i / FPS, estimate(2.0, sd=0.02))
    first = tracker.step(30 / FPS, estimate(measured, sd=0.02))
    assert first.measurement is Outcome.REJECTED and first.valid  # one frame may be wild
    out = tracker.step(30.5 / FPS, estimate(measured, sd=0.02))
    assert out.measurement is Outcome.REJECTED and out.state is TrackState.COASTING
    assert out.valid is valid
    if not valid:
        assert not tracker.step(31 / FPS, None).valid  # nor a tick after it
    back = tracker.step(32 / FPS, estimate(2.0, sd=0.02))
    assert back.measurement is Outcome.ACCEPTED and back.valid


@pytest.mark.parametrize(("yaw", "pitch"), [(0.0, 0.0), (45.0, 0.0), (70.0, 0.0),
                                            (0.0, 65.0), (50.0, 40.0)])
def test_the_angle_noise_follows_the_tilt(yaw: float, pitch: float) -> None:
    """The estimator's sigma_normal_deg is the normal's error in any direction. As the two
    angles of the state, it is that in the plane of the tilt, but across it the angle's error
    grows as 1 / cos(tilt) (tan(pitch) = n_y / n_z, and n_z shrinks): a net 70 deg off square
    with 2 deg of normal noise rejected 17 % of its good frames (and with them their
    distance), where the gate (4 sigma in 3 dimensions) should reject about 0.1 %."""
    rng = np.random.default_rng(11)
    tracker = NetTracker(FilterSettings())
    true = np.array(normal_from_angles(yaw, pitch, -1.0))
    sigma = 2.0
    basis = np.linalg.svd(true[None, :])[2][1:]  # two unit vectors across the normal
    rejected = 0
    for i in range(600):
        tip = np.radians(sigma) * rng.standard_normal(2) @ basis
        n = true + tip
        n /= np.linalg.norm(n)
        est = NetEstimate(detected=True, confidence=0.9, normal=(float(n[0]), float(n[1]),
                                                                 float(n[2])),
                          distance_m=1.5 + rng.normal(0.0, 0.02), range_m=1.5,
                          sigma_distance_m=0.02, sigma_normal_deg=sigma)
        out = tracker.step(i / FPS, est)
        rejected += out.measurement is Outcome.REJECTED
    assert tracker.resets_total == 0
    assert rejected <= 6, rejected  # 1 % of the frames


def test_a_frame_stamped_a_moment_before_the_last_does_not_end_the_track() -> None:
    """Time that goes back means the frames' clock changed (a source re-opened with older
    stamps): the track starts afresh. A frame stamped a millisecond before the last one (a
    driver's timestamp jitter) restarted it too, and the distance was withdrawn for the frames
    a new track needs to be confirmed. Within a frame's jitter it is the same instant."""
    tracker = NetTracker(FilterSettings())
    for i in range(30):
        tracker.step(i / FPS, estimate(1.5, sd=0.01))
    out = tracker.step(29 / FPS - 0.001, estimate(1.5, sd=0.01))
    assert out.valid and tracker.resets_total == 0 and out.measurement is Outcome.ACCEPTED
    assert tracker.step(30 / FPS, estimate(1.5, sd=0.01)).valid
    jumped = tracker.step(30 / FPS - 2.0, estimate(1.5, sd=0.01))  # a new clock
    assert not jumped.valid and jumped.measurement is Outcome.RESET


def test_noise_does_not_withdraw_the_prediction_of_a_still_net() -> None:
    """The nearer-rejection rule withdrew the prediction on any rejected frame more than one
    sigma nearer: with heavy-tailed noise on a still net (Student-t, 4 degrees of freedom, at
    the reported sigma) that was 66 withdrawals in ten minutes at 30 frames/s, each costing the
    autopilot a second (the link's restart limit). A second nearer frame in a row withdraws it:
    a net that really came nearer does that from the frame after."""
    rng = np.random.default_rng(1)
    tracker = NetTracker(FilterSettings())
    drops = 0
    previous = True
    for i in range(30 * 120):
        d = 1.5 + 0.02 * float(rng.standard_t(4)) * math.sqrt(2 / 4)
        out = tracker.step(i / FPS, estimate(d, sd=0.02))
        if i > 10:
            drops += previous and not out.valid
            previous = out.valid
    assert drops <= 1, drops
