"""The benchmark's camera, mesh and scene draws, shared by the accuracy and speed benchmarks."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from service.core.camera import CameraModel
from service.core.mesh import MeshGeometry

# The paper's protocol: a 1.5 cm mesh at 40-200 cm, tilted 0/20/40 degrees. Its camera is not
# published; this one is a typical wide underwater camera (82 deg HFOV) with barrel distortion.
PAPER_MESH = MeshGeometry(bar_length_m=0.015)
DISTANCES_CM = (40, 80, 120, 160, 200)
TILTS_DEG = (0, 20, 40)

# Table 1 of the paper: mean measured distance (cm), its std (cm) and mean normal error (deg).
PAPER_TABLE1: dict[tuple[int, int], tuple[float, float, float] | None] = {
    (40, 0): (39.97, 0.25, 9.0), (40, 20): (39.73, 1.2, 15.0), (40, 40): None,
    (80, 0): (78.56, 0.18, 4.9), (80, 20): (80.06, 0.50, 16.0), (80, 40): (79.13, 9.81, 5.3),
    (120, 0): (118.22, 0.61, 4.7), (120, 20): (119.21, 1.15, 11.6),
    (120, 40): (119.05, 0.85, 2.8),
    (160, 0): (156.15, 1.94, 6.6), (160, 20): (158.75, 12.10, 1.6),
    (160, 40): (153.38, 13.72, 5.9),
    (200, 0): (198.50, 0.88, 5.2), (200, 20): (200.76, 0.61, 4.2), (200, 40): (197.51, 0.88, 6.2),
}


def bench_camera(width: int = 1280, height: int = 720) -> CameraModel:
    f = 0.5 * width / math.tan(math.radians(41.0))
    return CameraModel(
        width=width,
        height=height,
        fx=f,
        fy=f,
        cx=(width - 1) / 2 + 3.0,
        cy=(height - 1) / 2 - 2.0,
        distortion=(-0.08, 0.05, 0.0005, -0.0003, 0.0),
        name=f"bench_{width}x{height}",
    )


@dataclass(frozen=True)
class PoseDraw:
    tilt_axis_deg: float
    roll_deg: float
    phase: tuple[float, float]


def draw_pose(rng: np.random.Generator) -> PoseDraw:
    return PoseDraw(
        tilt_axis_deg=float(rng.uniform(0, 360)),
        roll_deg=float(rng.uniform(0, 90)),
        phase=(float(rng.uniform(0, 1)), float(rng.uniform(0, 1))),
    )
