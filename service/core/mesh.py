"""Geometry of the physical net mesh."""

from __future__ import annotations

import math
from dataclasses import dataclass

from service.core.errors import ConfigError


@dataclass(frozen=True)
class MeshGeometry:
    """A net of equal bars (knot to knot) `bar_length_m` long, opening angle in degrees.

    A square mesh has opening angle 90. A rhombic (diamond) mesh hung with an opening angle
    alpha has cells that are rhombi with side `bar_length_m` and interior angle alpha.
    """

    bar_length_m: float
    opening_angle_deg: float = 90.0

    def __post_init__(self) -> None:
        if not math.isfinite(self.bar_length_m) or not 0.001 <= self.bar_length_m <= 1.0:
            raise ConfigError("mesh.bar_length_m", f"must be 0.001..1.0 m, got {self.bar_length_m}")
        if not 20.0 <= self.opening_angle_deg <= 160.0:
            raise ConfigError(
                "mesh.opening_angle_deg", f"must be 20..160 degrees, got {self.opening_angle_deg}"
            )

    @property
    def cell_area_m2(self) -> float:
        return self.bar_length_m**2 * math.sin(math.radians(self.opening_angle_deg))
