"""The image's metric scale and how well it is known.

A distance from the lattice is the focal length times the bar length over the mesh's size in
pixels: a relative error in either goes 1:1 into every distance. The estimator's sigmas are the
image's precision (how its frames and ROIs disagree); they cannot see this error, which is the
same in every frame, so a filter averaging frames does not shrink it. It is added in quadrature
where a distance leaves the pipeline (telemetry's `sigma_*_total_m`, DISTANCE_SENSOR's
covariance), never fed to the filter as noise.
"""

from __future__ import annotations

import math

from service.core.errors import ConfigError

# What a user who has measured neither knows (`mesh.bar_length_tolerance`,
# `camera.focal_tolerance`).
DEFAULT_BAR_LENGTH_TOLERANCE = 0.02
DEFAULT_FOCAL_TOLERANCE = 0.01
# A tolerance beyond this is not a known scale: a quarter off is a different net or camera.
MAX_TOLERANCE = 0.25


def check_tolerance(key: str, value: float) -> None:
    """A relative one-sigma tolerance from the configuration, or a ConfigError naming `key`."""
    if not (math.isfinite(value) and 0.0 <= value <= MAX_TOLERANCE):
        raise ConfigError(key, f"must be a fraction 0..{MAX_TOLERANCE} (0.02 = 2 %), got {value}")


def scale_sigma_fraction(bar_length_tolerance: float, focal_tolerance: float) -> float:
    """The relative one-sigma error of every distance from the bar length's and the focal
    length's (independent errors, each 1:1 in the distance)."""
    return math.hypot(bar_length_tolerance, focal_tolerance)


def total_sigma(value_m: float | None, sigma_m: float | None, fraction: float) -> float | None:
    """One sigma of a distance as a measurement of the world: the image's `sigma_m` with the
    scale's `fraction` of the distance; None when either is unknown."""
    if value_m is None or sigma_m is None or not (math.isfinite(value_m)
                                                  and math.isfinite(sigma_m)):
        return None
    return math.hypot(sigma_m, fraction * value_m)
