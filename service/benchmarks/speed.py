"""`netpose bench speed`: frames per second and per-stage time on one core.

Frames are rendered first (not timed), then each estimator runs over them pinned to one CPU
with OpenCV's thread pool off. Three cases per resolution:
- cold: every frame on its own (scale search, seed, rectified pass) - a net just acquired;
- tracking: each frame with the previous estimate as prior (the daemon's steady state);
- paper: the paper's single-ROI PnP path.
The time reported is the median wall time per frame, and beside it the median CPU time of the
calling thread (what the frame costs on its core, much less disturbed when other processes share
the machine); fps is computed from the wall time. Beside them:
- the stages (median ms each; `other` is the rest of the total);
- the FFT floor: the time of just the FFTs of the ROIs that frame computed (one stacked real
  FFT per ROI size, as `NetEstimate.fft_counts` says), the physical limit of this method;
- per budget level (`NetEstimator.estimate(budget=...)`) at 1280x720: cold and tracking time,
  detection, median |range error| and the largest |error| / sigma, so a controller that picks
  the level is backed by numbers.
"""

from __future__ import annotations

import functools
import math
import os
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from drivers.synthetic_net import GroundTruth, NetPose, NetRenderer, SceneStyle
from service.benchmarks.scenes import PAPER_MESH, bench_camera
from service.core.estimator import BUDGET_LEVELS, NetEstimator
from service.core.paper import PaperEstimator
from service.core.results import NetEstimate
from service.core.spectrum import half_plane_power
from service.core.tracking import FilterSettings, NetTracker
from service.pipeline import Pipeline

# Issue 13: one desktop core, 1280x720, median per frame.
TARGET_MS_720P = {"tracking": 4.0, "cold": 8.0}


def _pin_to_one_core() -> str:
    try:
        cpus = sorted(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpus[-1]})
        return f"pinned to CPU {cpus[-1]}"
    except (AttributeError, OSError):
        return "not pinned (no sched_setaffinity)"


def _frames(width: int, height: int, count: int, seed: int) -> list[npt.NDArray[np.uint8]]:
    """A slow approach along a tilted net: what the tracking case sees."""
    return [frame for frame, _ in _scenes(width, height, count, seed)]


def _scenes(
    width: int, height: int, count: int, seed: int
) -> list[tuple[npt.NDArray[np.uint8], GroundTruth]]:
    """The frames of `_frames` with their ground truth."""
    camera = bench_camera(width, height)
    renderer = NetRenderer(camera, PAPER_MESH, seed=seed)
    rng = np.random.default_rng(seed)
    style = SceneStyle.varied(rng)
    frames: list[tuple[npt.NDArray[np.uint8], GroundTruth]] = []
    for i in range(count):
        s = i / max(1, count - 1)
        pose = NetPose(range_m=1.6 - 0.8 * s, tilt_deg=20.0 + 10.0 * s, tilt_axis_deg=30.0,
                       roll_deg=10.0)
        frames.append(renderer.render(pose, rng, style))
    return frames


class _FftFloor:
    """Times just the FFTs a frame computed: one stacked real FFT per ROI size, with the
    estimator's own FFT (`spectrum.half_plane_power`)."""

    def __init__(self, seed: int) -> None:
        self._rng = np.random.default_rng(seed)
        self._stacks: dict[int, npt.NDArray[np.float32]] = {}

    def ms(self, counts: dict[int, int]) -> float:
        total = 0.0
        for size, count in counts.items():
            stack = self._stacks.get(size)
            if stack is None or stack.shape[0] < count:
                stack = self._rng.standard_normal((max(count, 64), size, size)).astype(
                    np.float32)
                self._stacks[size] = stack
            t0 = time.perf_counter()
            half_plane_power(stack[:count])
            total += (time.perf_counter() - t0) * 1e3
        return total


@dataclass
class _Timed:
    times: list[float]
    cpu: list[float]
    stages: dict[str, float]  # median ms per stage, `other` the rest of the total
    detected: float
    fft_floor: float  # median ms of just the frame's FFTs
    ffts: float  # median number of FFTs per frame
    estimates: list[NetEstimate]


def _time(
    frames: list[npt.NDArray[np.uint8]], step: Callable[[npt.NDArray[np.uint8]], NetEstimate],
    floor: _FftFloor,
) -> _Timed:
    step(frames[0])  # warm-up: per-size caches are built once at start-up, not per frame
    times: list[float] = []
    cpu: list[float] = []
    stages: dict[str, list[float]] = {}
    floors: list[float] = []
    ffts: list[int] = []
    estimates: list[NetEstimate] = []
    for frame in frames:
        c0 = time.thread_time()
        t0 = time.perf_counter()
        est = step(frame)
        times.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.thread_time() - c0) * 1e3)
        estimates.append(est)
        timings = dict(est.timings_ms)
        if "total" in timings:
            timings["other"] = max(0.0, timings["total"] - sum(
                v for k, v in timings.items() if k != "total"))
        for name, ms in timings.items():
            stages.setdefault(name, []).append(ms)
        floors.append(floor.ms(est.fft_counts))
        ffts.append(sum(est.fft_counts.values()))
    # A stage a frame did not run counts as 0 ms in that frame's median.
    medians = {name: statistics.median(v + [0.0] * (len(frames) - len(v)))
               for name, v in stages.items() if name != "total"}
    detected = sum(e.detected for e in estimates) / len(frames)
    return _Timed(times, cpu, medians, detected, statistics.median(floors),
                  statistics.median(ffts), estimates)


class _Tracking:
    """The daemon's own pipeline (prior feedback, filter) at the camera's frame spacing."""

    def __init__(self, estimator: NetEstimator, fps: float = 30.0) -> None:
        self.pipeline = Pipeline(estimator, NetTracker(FilterSettings()))
        self.period = 1.0 / fps
        self.index = 0

    def step(self, image: npt.NDArray[np.uint8]) -> NetEstimate:
        result = self.pipeline.process(image, self.index * self.period, self.index)
        self.index += 1
        assert result.estimate is not None, result.error
        return result.estimate


class _TrackingAt:
    """Tracking at one budget level: each frame with the last detection as prior (as
    `Pipeline` feeds it back), without the filter."""

    def __init__(self, estimator: NetEstimator, budget: int) -> None:
        self.estimator = estimator
        self.budget = budget
        self.prior: NetEstimate | None = None

    def step(self, image: npt.NDArray[np.uint8]) -> NetEstimate:
        est = self.estimator.estimate(image, prior=self.prior, budget=self.budget,
                                      prior_age_s=1.0 / 30.0)
        self.prior = est if est.detected else None
        return est


def _cold_at(estimator: NetEstimator, budget: int, image: npt.NDArray[np.uint8]) -> NetEstimate:
    return estimator.estimate(image, budget=budget)


def _accuracy(estimates: list[NetEstimate], truths: list[GroundTruth]) -> tuple[float, float]:
    """Median |range error| (%) and the largest |error| / sigma of the detections."""
    errors: list[float] = []
    z: list[float] = []
    for est, truth in zip(estimates, truths, strict=True):
        if est.detected and est.range_m is not None and est.sigma_range_m:
            err = est.range_m - truth.range_m
            errors.append(abs(err) / truth.range_m * 100.0)
            z.append(abs(err) / est.sigma_range_m)
    if not errors:
        return math.nan, math.nan
    return statistics.median(errors), max(z)


def _budget_table(frames: int, seed: int, floor: _FftFloor) -> None:
    width, height = 1280, 720
    scenes = _scenes(width, height, frames, seed + 1)
    images = [f for f, _ in scenes]
    truths = [t for _, t in scenes]
    print(f"budget levels at {width}x{height} (tracking: the last detection as prior):")
    print(f"{'level':>5} {'case':>9} | {'median ms':>9} {'cpu ms':>7} {'fft floor':>9} "
          f"{'ffts':>5} {'detected':>8} {'|err| med':>9} {'max |err|/sigma':>15}")
    camera = bench_camera(width, height)
    for level in range(BUDGET_LEVELS):
        estimator = NetEstimator(camera, PAPER_MESH)
        tracking = _TrackingAt(estimator, level)
        cases: list[tuple[str, Callable[[npt.NDArray[np.uint8]], NetEstimate]]] = [
            ("cold", functools.partial(_cold_at, estimator, level)),
            ("tracking", tracking.step),
        ]
        for name, step in cases:
            timed = _time(images, step, floor)
            err, z = _accuracy(timed.estimates, truths)
            print(f"{level:>5} {name:>9} | {statistics.median(timed.times):9.2f} "
                  f"{statistics.median(timed.cpu):7.2f} {timed.fft_floor:9.2f} "
                  f"{timed.ffts:5.0f} {timed.detected:8.0%} {err:8.3f}% {z:15.2f}")


def run(frames: int, seed: int) -> int:
    cv2.setNumThreads(1)
    pinning = _pin_to_one_core()
    print(f"netpose bench speed: {frames} frames per case, one core ({pinning}), "
          f"OpenCV {cv2.__version__}, numpy {np.__version__}")
    print(f"{'frame':>10} {'case':>9} | {'fps':>6} {'median ms':>9} {'p95 ms':>7} {'cpu ms':>7} "
          f"{'fft floor':>9} {'ffts':>5} {'detected':>8} | stages (median ms)")
    floor = _FftFloor(seed)
    ok = True
    verdicts: list[str] = []
    for width, height in ((1280, 720), (1920, 1080)):
        camera = bench_camera(width, height)
        images = _frames(width, height, frames, seed)
        estimator = NetEstimator(camera, PAPER_MESH)
        paper = PaperEstimator(camera, PAPER_MESH)
        tracking = _Tracking(estimator)
        cases: list[tuple[str, Callable[[npt.NDArray[np.uint8]], NetEstimate]]] = [
            ("cold", estimator.estimate),
            ("tracking", tracking.step),
            ("paper", paper.estimate),
        ]
        for name, step in cases:
            timed = _time(images, step, floor)
            median = statistics.median(timed.times)
            fps = 1e3 / median
            p95 = float(np.percentile(timed.times, 95))
            stage_txt = " ".join(f"{k}={v:.1f}" for k, v in timed.stages.items() if v >= 0.05)
            print(f"{width:>5}x{height:<4} {name:>9} | {fps:6.1f} {median:9.2f} {p95:7.2f} "
                  f"{statistics.median(timed.cpu):7.2f} {timed.fft_floor:9.2f} "
                  f"{timed.ffts:5.0f} {timed.detected:8.0%} | {stage_txt}")
            if (width, height) == (1280, 720) and name in TARGET_MS_720P:
                target = TARGET_MS_720P[name]
                met = median <= target
                ok &= met
                verdicts.append(f"{name} <= {target:.0f} ms median at 1280x720: "
                                f"{median:.2f} ms, {'met' if met else 'NOT met'}")
    for verdict in verdicts:
        print(f"target: {verdict}")
    _budget_table(frames, seed, floor)
    return 0 if ok else 1
