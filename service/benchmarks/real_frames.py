"""`netpose bench real`: the estimator on real fish-farm frames and real net-free scenes.

The data set is `shared/data/real-field/` (see its README): three SOLAQUA stills with a net, a
44-frame SOLAQUA sequence (384x180 strip) whose vehicle kept a DVL stand-off of 0.57-0.63 m to
the net, and 18 real underwater scenes without a net; each image has its calibration. The net is
a 27.5 mm mesh. `shared/data/real-net-frame/` adds one more real net frame.

What can be checked exactly: detection (net or no net), tilt direction and frame-to-frame
stability. Distances only to the DVL's ~0.1 m. The targets (issue 11):
- every still with a net detected, >= 40 of the 44 sequence frames detected;
- none of the 18 net-free scenes taken for a net (and never "too close" there);
- the sequence's distance within 0.1 m of the 0.57-0.63 m stand-off;
- the reported sigma at least the frame-to-frame spread of the sequence.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.benchmarks.real_stability import (
    COPIES,
    NOISE_GREY,
    format_stability,
    run_stability,
)
from service.core.camera import CameraModel, load_camera
from service.core.estimator import NetEstimator
from service.core.grey import decode_gray
from service.core.mesh import MeshGeometry
from service.core.results import NetEstimate

SOLAQUA_MESH = MeshGeometry(bar_length_m=0.0275)
SEQUENCE_STANDOFF_M = (0.57, 0.63)
STANDOFF_TOLERANCE_M = 0.10
TARGET_SEQUENCE_DETECTED = 40


@dataclass(frozen=True)
class RealFrame:
    """One real image, its calibration and what is known about it."""

    name: str
    image: Path
    calibration: Path
    kind: str  # "still" (a net), "sequence" (a net, frames in order) or "no-net"
    mesh: MeshGeometry = SOLAQUA_MESH


def default_data_dir() -> Path:
    """`shared/data` beside the checkout (NETPOSE_SHARED_DATA overrides it)."""
    import os

    override = os.environ.get("NETPOSE_SHARED_DATA")
    if override:
        return Path(override)
    return Path(__file__).resolve().parents[3] / "shared" / "data"


def real_field_frames(data_dir: Path) -> list[RealFrame]:
    """Every frame of real-field/ (and real-net-frame/ when present), stills first."""
    root = data_dir / "real-field"
    frames: list[RealFrame] = []
    for image in sorted((root / "frames").glob("*.png")):
        frames.append(RealFrame(image.stem, image, root / "calibration" / f"{image.stem}.yaml",
                                "still"))
    other = data_dir / "real-net-frame" / "net_1280x720.jpg"
    if other.is_file():
        # Its README: a 2 cm mesh in the public implementation's run; the 2024 trials' nets
        # were 27.5 mm. Only detection and tilt direction are checked on it.
        frames.append(RealFrame("real-net-frame", other,
                                other.parent / "camera_solaqua_1280x720.yaml", "still"))
    for seq in sorted(root.glob("sequence_*")):
        for image in sorted(seq.glob("*.png")):
            frames.append(RealFrame(f"{seq.name[9:]}/{image.stem}", image, seq / "camera.yaml",
                                    "sequence"))
    for image in sorted((root / "no-net").glob("*.png")):
        frames.append(RealFrame(image.stem, image, root / "calibration" / f"{image.stem}.yaml",
                                "no-net"))
    return frames


@dataclass(frozen=True)
class RealResult:
    frame: RealFrame
    estimate: NetEstimate
    cpu_ms: float


class RealEstimators:
    """The estimator of a real frame: one per calibration file and mesh, each calibration
    loaded once."""

    def __init__(self) -> None:
        self._cameras: dict[Path, CameraModel] = {}
        self._estimators: dict[tuple[Path, MeshGeometry], NetEstimator] = {}

    def __call__(self, frame: RealFrame) -> NetEstimator:
        key = (frame.calibration, frame.mesh)
        if key not in self._estimators:
            if frame.calibration not in self._cameras:
                self._cameras[frame.calibration] = load_camera(frame.calibration)
            self._estimators[key] = NetEstimator(self._cameras[frame.calibration], frame.mesh)
        return self._estimators[key]


def run_frames(frames: list[RealFrame], tracking: bool = False) -> Iterator[RealResult]:
    """Estimate every frame on its own (cold); with `tracking`, sequence frames get the previous
    frame's detection as prior: the estimator's tracked path alone, without the daemon's
    filter, search pacing or frame times (`netpose replay` runs the daemon's pipeline, and may
    say "no net" on a frame after a miss that this searches whole)."""
    estimator_for = RealEstimators()
    prior: NetEstimate | None = None
    previous_folder: Path | None = None
    for frame in frames:
        gray, _ = decode_gray(frame.image.read_bytes())
        # Only the sequence's own previous frame is its past: a still, or another sequence's
        # last frame, is another camera and another place.
        same_sequence = frame.kind == "sequence" and frame.image.parent == previous_folder
        use_prior = prior if tracking and same_sequence else None
        t0 = time.thread_time()
        est = estimator_for(frame).estimate(gray, prior=use_prior)
        cpu = (time.thread_time() - t0) * 1e3
        prior = est if est.detected else None
        previous_folder = frame.image.parent if frame.kind == "sequence" else None
        yield RealResult(frame, est, cpu)


def describe(result: RealResult) -> str:
    e = result.estimate
    head = f"{result.frame.kind:8} {result.frame.name:18}"
    if e.detected and e.range_m is not None and e.distance_m is not None:
        return (f"{head} net   range {e.range_m:.3f} +- {e.sigma_range_m or 0:.3f} m, distance "
                f"{e.distance_m:.3f} m, tilt {e.tilt_deg or 0:4.1f} +- "
                f"{e.sigma_normal_deg or 0:.1f} deg, {e.rois_used}/{len(e.rois)} ROIs, "
                f"conf {e.confidence:.2f}, {result.cpu_ms:.0f} ms")
    if e.approx_range_m is not None and e.approx_sigma_range_m is not None:
        return (f"{head} seen  ~{e.approx_range_m:.2f} +- {e.approx_sigma_range_m:.2f} m, no "
                f"distance: {e.reason.split(':')[0]} ({e.rois_used}/{len(e.rois)} ROIs, "
                f"{result.cpu_ms:.0f} ms)")
    state = "CLOSE" if e.too_close else "none "
    return f"{head} {state} {e.reason} (conf {e.confidence:.2f}, {result.cpu_ms:.0f} ms)"


@dataclass(frozen=True)
class RealSummary:
    stills: int
    stills_detected: int
    sequence: int
    sequence_detected: int
    sequence_seen: int  # recognised as the net, measured or not (`NetEstimate.net_seen`)
    no_net: int
    false_nets: int
    false_too_close: int
    sequence_distance_median_m: float
    sequence_range_median_m: float
    sequence_frame_to_frame_m: float
    sequence_sigma_median_m: float
    # The same over every frame with a range along the axis, measured or only seen (the refused
    # range a pilot reads as "net seen, ~0.8 m"): defined on far more consecutive frames.
    sequence_seen_frame_to_frame_m: float = math.nan
    sequence_seen_sigma_median_m: float = math.nan

    @property
    def targets(self) -> dict[str, bool | None]:
        """Each target and whether it is met; None when this run cannot tell (the spread
        needs two steps between consecutive measured frames of the sequence)."""
        lo, hi = SEQUENCE_STANDOFF_M
        d = self.sequence_distance_median_m
        return {
            "all stills detected": self.stills_detected == self.stills,
            f">= {TARGET_SEQUENCE_DETECTED} of {self.sequence} sequence frames detected":
                self.sequence_detected >= TARGET_SEQUENCE_DETECTED,
            "no net-free scene taken for a net": self.false_nets == 0,
            "never 'too close' on a net-free scene": self.false_too_close == 0,
            f"sequence distance within {STANDOFF_TOLERANCE_M} m of {lo}-{hi} m":
                math.isfinite(d) and lo - STANDOFF_TOLERANCE_M <= d <= hi + STANDOFF_TOLERANCE_M,
            "sequence sigma >= frame-to-frame spread":
                self.sequence_sigma_median_m >= self.sequence_frame_to_frame_m
                if math.isfinite(self.sequence_frame_to_frame_m) else None,
            f">= {TARGET_SEQUENCE_DETECTED} of {self.sequence} sequence frames seen as a net "
            "(measured or not)": self.sequence_seen >= TARGET_SEQUENCE_DETECTED,
            "sequence sigma >= frame-to-frame spread, ranges measured or seen":
                self.sequence_seen_sigma_median_m >= self.sequence_seen_frame_to_frame_m
                if math.isfinite(self.sequence_seen_frame_to_frame_m) else None,
        }


def summarise(results: list[RealResult]) -> RealSummary:
    def of(kind: str) -> list[RealResult]:
        return [r for r in results if r.frame.kind == kind]

    stills, seq, free = of("still"), of("sequence"), of("no-net")
    found = [r.estimate for r in seq if r.estimate.detected]
    dist = np.array([e.distance_m for e in found if e.distance_m is not None])
    rng = np.array([e.range_m for e in found if e.range_m is not None])
    sig = np.array([e.sigma_distance_m for e in found if e.sigma_distance_m is not None])
    # Frame-to-frame spread: consecutive detected frames, differences / sqrt(2) (slow motion of
    # the vehicle cancels; what remains is the per-frame scatter).
    diffs = []
    for a, b in itertools.pairwise(seq):
        da, db = a.estimate.distance_m, b.estimate.distance_m
        if a.estimate.detected and b.estimate.detected and da is not None and db is not None:
            diffs.append(db - da)
    spread = float(np.std(diffs) / math.sqrt(2.0)) if len(diffs) > 1 else math.nan
    ranged = [_range_and_sigma(r.estimate) for r in seq]
    seen_diffs = [b[0] - a[0] for a, b in itertools.pairwise(ranged)
                  if a is not None and b is not None]
    seen_sig = [v[1] for v in ranged if v is not None]
    return RealSummary(
        stills=len(stills),
        stills_detected=sum(r.estimate.detected for r in stills),
        sequence=len(seq),
        sequence_detected=len(found),
        sequence_seen=sum(r.estimate.net_seen for r in seq),
        no_net=len(free),
        # A net-free scene recognised as a net is a false net, with or without a distance.
        false_nets=sum(r.estimate.net_seen for r in free),
        false_too_close=sum(r.estimate.too_close for r in free),
        sequence_distance_median_m=float(np.median(dist)) if dist.size else math.nan,
        sequence_range_median_m=float(np.median(rng)) if rng.size else math.nan,
        sequence_frame_to_frame_m=spread,
        sequence_sigma_median_m=float(np.median(sig)) if sig.size else math.nan,
        sequence_seen_frame_to_frame_m=(float(np.std(seen_diffs) / math.sqrt(2.0))
                                        if len(seen_diffs) > 1 else math.nan),
        sequence_seen_sigma_median_m=float(np.median(seen_sig)) if seen_sig else math.nan,
    )


def _range_and_sigma(e: NetEstimate) -> tuple[float, float] | None:
    """The range along the optical axis and its sigma, measured or (a net seen) refused."""
    if e.detected and e.range_m is not None and e.sigma_range_m is not None:
        return e.range_m, e.sigma_range_m
    if e.approx_range_m is not None and e.approx_sigma_range_m is not None:
        return e.approx_range_m, e.approx_sigma_range_m
    return None


def format_summary(s: RealSummary, label: str) -> list[str]:
    lines = [
        f"{label}: stills {s.stills_detected}/{s.stills} detected; sequence "
        f"{s.sequence_detected}/{s.sequence} detected (a distance), {s.sequence_seen}/"
        f"{s.sequence} seen as a net (with or without one); net-free {s.false_nets}/{s.no_net} "
        f"taken for a net, {s.false_too_close} 'too close'",
        f"{label}: sequence distance median {s.sequence_distance_median_m:.3f} m (range "
        f"{s.sequence_range_median_m:.3f} m), frame-to-frame spread "
        f"{s.sequence_frame_to_frame_m * 100:.1f} cm, reported sigma median "
        f"{s.sequence_sigma_median_m * 100:.1f} cm",
        f"{label}: sequence ranges measured or seen: frame-to-frame spread "
        f"{s.sequence_seen_frame_to_frame_m * 100:.1f} cm, reported sigma median "
        f"{s.sequence_seen_sigma_median_m * 100:.1f} cm",
    ]
    return lines


def run(data_dir: Path | None, verbose: bool = True, copies: int = COPIES) -> int:
    import cv2

    cv2.setNumThreads(1)
    data = data_dir or default_data_dir()
    frames = real_field_frames(data)
    if not frames:
        print(f"netpose bench real: no real frames under {data} (real-field/ not found)")
        return 2
    print(f"netpose bench real: {len(frames)} real frames from {data}, mesh "
          f"{SOLAQUA_MESH.bar_length_m * 1e3:.1f} mm")
    ok = True
    for tracking in (False, True):
        label = "tracked" if tracking else "cold"
        results = list(run_frames(frames, tracking=tracking))
        if verbose and not tracking:
            for r in results:
                print("  " + describe(r))
        summary = summarise(results)
        for line in format_summary(summary, label):
            print(line)
        if not tracking:
            for name, met in summary.targets.items():
                verdict = ("not measurable in this run" if met is None
                           else "met" if met else "MISSED")
                print(f"  target: {name}: {verdict}")
                ok &= met is True
    if copies > 0:
        rows = run_stability(frames, RealEstimators(), copies, NOISE_GREY)
        for line in format_stability(rows, copies, NOISE_GREY):
            print(line)
        ok &= all(r.stable for r in rows if r.judged)
    print("RESULT:", "all targets met" if ok else "some targets missed")
    return 0 if ok else 1
