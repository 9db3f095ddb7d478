"""`netpose bench real`, stability: does a real view get the same distance when its pixels
change by less than a grey level?

Each real net frame is estimated as it is and as `copies` copies with Gaussian noise of
`noise_grey` grey levels (0.6 by default), rounded back to 8 bits: about what a codec, a
colour converter or another OpenCV version changes (Debian bookworm's OpenCV 4.6 and OpenCV 5
give frames of the SOLAQUA sequence that differ this much, and different verdicts). Nothing
about the net changes, so every valid output of one frame must agree with every other within
their sigmas: two valid distances of the same view that differ by more than 3 sigma (of their
difference) mean one of them is a confident wrong distance, which issue 11 rules out. The
figure per frame is the largest such z over its pairs of valid outputs, for the range along
the optical axis and for the normal.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from service.core.estimator import NetEstimator
from service.core.grey import decode_gray
from service.core.results import NetEstimate

if TYPE_CHECKING:  # real_frames runs this module: the type only, not a cycle at import
    from service.benchmarks.real_frames import RealFrame

Gray = npt.NDArray[np.uint8]

NOISE_GREY = 0.6
COPIES = 10
TARGET_Z = 3.0


@dataclass(frozen=True)
class FrameStability:
    name: str
    tries: int  # the frame and its noisy copies
    valid: int  # of those, how many gave a distance
    range_min_m: float
    range_max_m: float
    range_z: float  # largest |r_i - r_j| / hypot(sigma_i, sigma_j) over pairs of valid outputs
    normal_z: float  # the same for the angle between the normals

    @property
    def judged(self) -> bool:
        return self.valid >= 2

    @property
    def stable(self) -> bool:
        return self.range_z <= TARGET_Z and self.normal_z <= TARGET_Z


def noisy_copies(gray: Gray, copies: int, noise_grey: float, rng: np.random.Generator
                 ) -> Iterator[Gray]:
    """`copies` copies of `gray` with Gaussian noise of `noise_grey` levels, back in 8 bits."""
    for _ in range(copies):
        noisy = gray.astype(np.float32) + rng.normal(0.0, noise_grey, gray.shape).astype(
            np.float32)
        yield np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def disagreement(estimates: list[NetEstimate]) -> tuple[float, float]:
    """The largest range z and normal z over pairs of valid estimates (0 with fewer than two)."""
    valid = [e for e in estimates if e.detected and e.range_m is not None and e.normal is not None
             and e.sigma_range_m is not None and e.sigma_normal_deg is not None]
    range_z = normal_z = 0.0
    for a, b in itertools.combinations(valid, 2):
        assert a.range_m is not None and b.range_m is not None and a.normal is not None
        assert b.normal is not None and a.sigma_range_m is not None
        assert b.sigma_range_m is not None and a.sigma_normal_deg is not None
        assert b.sigma_normal_deg is not None
        range_z = max(range_z, abs(a.range_m - b.range_m) / math.hypot(a.sigma_range_m,
                                                                        b.sigma_range_m))
        cos = abs(float(np.dot(a.normal, b.normal)))
        angle = math.degrees(math.acos(min(1.0, cos)))
        normal_z = max(normal_z, angle / math.hypot(a.sigma_normal_deg, b.sigma_normal_deg))
    return range_z, normal_z


def frame_stability(frame: RealFrame, estimator: NetEstimator, copies: int, noise_grey: float,
                    rng: np.random.Generator) -> FrameStability:
    gray, _ = decode_gray(frame.image.read_bytes())
    estimates = [estimator.estimate(gray)]
    estimates += [estimator.estimate(g) for g in noisy_copies(gray, copies, noise_grey, rng)]
    ranges = [e.range_m for e in estimates if e.detected and e.range_m is not None]
    range_z, normal_z = disagreement(estimates)
    return FrameStability(frame.name, len(estimates), len(ranges),
                          min(ranges, default=math.nan), max(ranges, default=math.nan),
                          range_z, normal_z)


def run_stability(frames: list[RealFrame], estimator_for: Callable[[RealFrame], NetEstimator],
                  copies: int = COPIES, noise_grey: float = NOISE_GREY, seed: int = 1
                  ) -> list[FrameStability]:
    """Every real net frame (stills and sequence), each with its own seeded noise, measured by
    `estimator_for(frame)` (`real_frames.RealEstimators`)."""
    out = []
    for index, frame in enumerate(f for f in frames if f.kind in ("still", "sequence")):
        rng = np.random.default_rng([seed, index])
        out.append(frame_stability(frame, estimator_for(frame), copies, noise_grey, rng))
    return out


def format_stability(rows: list[FrameStability], copies: int, noise_grey: float) -> list[str]:
    judged = [r for r in rows if r.judged]
    lines = [f"stability: each net frame and {copies} copies with {noise_grey:g} grey levels "
             f"of noise; frames with two or more distances: {len(judged)} of {len(rows)}"]
    for r in judged:
        if not r.stable or r.range_max_m / r.range_min_m > 1.05:
            lines.append(f"  {r.name:30} {r.valid}/{r.tries} valid, ranges {r.range_min_m:.3f}-"
                         f"{r.range_max_m:.3f} m, largest pair z: range {r.range_z:.1f}, "
                         f"normal {r.normal_z:.1f}")
    unstable = [r for r in judged if not r.stable]
    lines.append(f"  target: valid outputs of one view agree within {TARGET_Z:g} sigma: "
                 f"{'met' if not unstable else 'MISSED'} ({len(unstable)} of {len(judged)} "
                 "frames beyond)")
    return lines
