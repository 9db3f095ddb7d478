"""`netpose bench speed`: frames per second and per-stage time on one core.

Frames are rendered first (not timed), then each estimator runs over them pinned to one CPU
with OpenCV's thread pool off. Three cases per resolution:
- cold: every frame on its own (scale search, seed, rectified pass) - a net just acquired;
- tracking: each frame with the previous estimate as prior (the daemon's steady state);
- paper: the paper's single-ROI PnP path.
The time reported is the median wall time per frame, and beside it the median CPU time of the
calling thread (what the frame costs on its core, much less disturbed when other processes share
the machine); fps is computed from the wall time.
"""

from __future__ import annotations

import os
import statistics
import time
from collections.abc import Callable

import cv2
import numpy as np
import numpy.typing as npt

from drivers.synthetic_net import NetPose, NetRenderer, SceneStyle
from service.benchmarks.scenes import PAPER_MESH, bench_camera
from service.core.estimator import NetEstimator
from service.core.paper import PaperEstimator
from service.core.results import NetEstimate
from service.core.tracking import FilterSettings, NetTracker
from service.pipeline import Pipeline

TARGET_FPS_720P = 60.0


def _pin_to_one_core() -> str:
    try:
        cpus = sorted(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpus[-1]})
        return f"pinned to CPU {cpus[-1]}"
    except (AttributeError, OSError):
        return "not pinned (no sched_setaffinity)"


def _frames(width: int, height: int, count: int, seed: int) -> list[npt.NDArray[np.uint8]]:
    """A slow approach along a tilted net: what the tracking case sees."""
    camera = bench_camera(width, height)
    renderer = NetRenderer(camera, PAPER_MESH, seed=seed)
    rng = np.random.default_rng(seed)
    style = SceneStyle.varied(rng)
    frames = []
    for i in range(count):
        s = i / max(1, count - 1)
        pose = NetPose(range_m=1.6 - 0.8 * s, tilt_deg=20.0 + 10.0 * s, tilt_axis_deg=30.0,
                       roll_deg=10.0)
        frames.append(renderer.render(pose, rng, style)[0])
    return frames


def _time(
    frames: list[npt.NDArray[np.uint8]], step: Callable[[npt.NDArray[np.uint8]], NetEstimate]
) -> tuple[list[float], list[float], dict[str, float], float]:
    step(frames[0])  # warm-up: per-size caches are built once at start-up, not per frame
    times: list[float] = []
    cpu: list[float] = []
    stages: dict[str, list[float]] = {}
    detected = 0
    for frame in frames:
        c0 = time.thread_time()
        t0 = time.perf_counter()
        est = step(frame)
        times.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.thread_time() - c0) * 1e3)
        detected += est.detected
        for name, ms in est.timings_ms.items():
            stages.setdefault(name, []).append(ms)
    medians = {name: statistics.median(v) for name, v in stages.items() if name != "total"}
    return times, cpu, medians, detected / len(frames)


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


def run(frames: int, seed: int) -> int:
    cv2.setNumThreads(1)
    pinning = _pin_to_one_core()
    print(f"netpose bench speed: {frames} frames per case, one core ({pinning}), "
          f"OpenCV {cv2.__version__}, numpy {np.__version__}")
    print(f"{'frame':>10} {'case':>9} | {'fps':>6} {'median ms':>9} {'p95 ms':>7} {'cpu ms':>7} "
          f"{'detected':>8} | stages (median ms)")
    ok = True
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
            times, cpu, stages, det = _time(images, step)
            median = statistics.median(times)
            fps = 1e3 / median
            p95 = float(np.percentile(times, 95))
            stage_txt = " ".join(f"{k}={v:.1f}" for k, v in stages.items())
            print(f"{width:>5}x{height:<4} {name:>9} | {fps:6.1f} {median:9.2f} {p95:7.2f} "
                  f"{statistics.median(cpu):7.2f} {det:8.0%} | {stage_txt}")
            if (width, height) == (1280, 720) and name in ("cold", "tracking"):
                ok &= fps >= TARGET_FPS_720P
    print(f"target: >= {TARGET_FPS_720P:.0f} frames/s at 1280x720 on one core: "
          f"{'met' if ok else 'NOT met'}")
    return 0 if ok else 1
