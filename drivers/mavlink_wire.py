"""Pure conversions from netpose values to MAVLink message fields (units, ranges, encodings).

Kept apart from the link so each mapping is a one-line rule that can be tested alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from drivers.mavlink_settings import MavlinkSettings
from service.core.readings import RangeReading, RangeStatus

# MAV_DISTANCE_SENSOR_UNKNOWN: a camera is none of laser/ultrasound/infrared/radar.
DISTANCE_SENSOR_TYPE_UNKNOWN = 4
# DISTANCE_SENSOR.covariance is a uint8 in cm^2; 255 means "unknown".
COVARIANCE_UNKNOWN = 255
UINT16_MAX = 65535
# DEBUG_VECT.name of the net plane read by the net-hold applet (scripts/net_hold.lua): at most
# 10 characters, and the same bytes in both places.
NET_PLANE_NAME = b"NET_PLANE"


def signal_quality(quality: float) -> int:
    """Map a 0..1 confidence to DISTANCE_SENSOR.signal_quality (percent).

    0 is reserved for "unknown" and sent only when the confidence is unknown (nan); 1 is
    MAVLink's "invalid signal" (common.xml), which a reading we send is not. A known confidence
    maps to round(100 * q) clamped to 2..100, so the weakest reading we still send is the worst
    valid one (ArduPilot keeps it, turns 1 into 0 % and 0 into "unknown").
    """
    if not math.isfinite(quality):
        return 0
    return max(2, min(100, round(100.0 * quality)))


def covariance_cm2(sigma_m: float) -> int:
    """DISTANCE_SENSOR.covariance: the variance in cm^2, or 255 (unknown).

    A variance that does not fit the uint8 (sigma > ~15.9 cm) is sent as unknown rather than
    saturated at 254, which would claim a precision we do not have.
    """
    if not math.isfinite(sigma_m) or sigma_m < 0.0:
        return COVARIANCE_UNKNOWN
    variance = (sigma_m * 100.0) ** 2
    # 0 would claim a perfect sensor: a sigma below 0.7 cm is still 1 cm^2.
    return max(1, round(variance)) if variance < 254.5 else COVARIANCE_UNKNOWN


def distance_cm(distance_m: float) -> int:
    return max(0, min(UINT16_MAX - 1, round(distance_m * 100.0)))


@dataclass(frozen=True)
class DistanceSensorFields:
    """Field values of one DISTANCE_SENSOR (without time_boot_ms)."""

    min_distance: int
    max_distance: int
    current_distance: int
    type: int
    id: int
    orientation: int
    covariance: int
    horizontal_fov: float
    vertical_fov: float
    signal_quality: int


def distance_sensor_fields(
    reading: RangeReading, settings: MavlinkSettings
) -> DistanceSensorFields:
    """The fields of a reading that is sent (GOOD or TOO_CLOSE; NONE is never sent).

    TOO_CLOSE goes out as a distance 1 cm below `min_distance`: ArduPilot compares a MAVLink
    rangefinder's distance with its minimum and reports OutOfRangeLow, which is the truth,
    where silence would read as NoData, the same as open water.
    """
    min_cm = distance_cm(settings.min_distance_m)
    if reading.status is RangeStatus.TOO_CLOSE:
        current = max(0, min_cm - 1)
    else:
        current = distance_cm(reading.distance_m)
    return DistanceSensorFields(
        min_distance=min_cm,
        max_distance=distance_cm(settings.max_distance_m),
        current_distance=current,
        type=DISTANCE_SENSOR_TYPE_UNKNOWN,
        id=settings.sensor_id,
        orientation=settings.orientation,
        covariance=covariance_cm2(reading.sigma_m),
        horizontal_fov=math.radians(settings.fov_horizontal_deg),
        vertical_fov=math.radians(settings.fov_vertical_deg),
        signal_quality=signal_quality(reading.quality),
    )
