"""Geometry of the physical net mesh."""

from __future__ import annotations

import math
from dataclasses import dataclass

from service.core.errors import ConfigError
from service.core.scale import DEFAULT_BAR_LENGTH_TOLERANCE, check_tolerance


@dataclass(frozen=True)
class MeshGeometry:
    """A net of equal bars (knot to knot) `bar_length_m` long, opening angle in degrees.

    A square mesh has opening angle 90. A rhombic (diamond) mesh hung with an opening angle
    alpha has cells that are rhombi with side `bar_length_m` and interior angle alpha.
    """

    bar_length_m: float
    opening_angle_deg: float = 90.0
    # How well `bar_length_m` is known, one sigma as a fraction of it: a used net's bars stretch,
    # shrink and thicken with fouling by 2-3 %. Every distance scales 1:1 with the bar, in every
    # frame alike, so this is reported beside the image's own sigma (`service.core.scale`),
    # never averaged away by the filter. 0: measured on this net, in water.
    bar_length_tolerance: float = DEFAULT_BAR_LENGTH_TOLERANCE

    def __post_init__(self) -> None:
        if not math.isfinite(self.bar_length_m) or not 0.001 <= self.bar_length_m <= 1.0:
            raise ConfigError("mesh.bar_length_m", f"must be 0.001..1.0 m, got {self.bar_length_m}")
        if not 20.0 <= self.opening_angle_deg <= 160.0:
            raise ConfigError(
                "mesh.opening_angle_deg", f"must be 20..160 degrees, got {self.opening_angle_deg}"
            )
        check_tolerance("mesh.bar_length_tolerance", self.bar_length_tolerance)

    @property
    def geometry(self) -> tuple[float, float]:
        """What the image is measured against: the bar scales every distance, the angle says
        which lattice is the net (the distance uses the one measured); a change of the
        tolerance only says how well the scale is known."""
        return (self.bar_length_m, self.opening_angle_deg)

    @property
    def cell_area_m2(self) -> float:
        return self.bar_length_m**2 * math.sin(math.radians(self.opening_angle_deg))
