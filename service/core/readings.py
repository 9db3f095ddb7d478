"""What the autopilot is told: one reading type with one validity field.

The filter decides whether it believes its distance (`TrackOutput.valid`); the pipeline turns
that into a `RangeReading`, and the MAVLink link sends exactly what `RangeReading.status` says.
No other flag anywhere decides what reaches the autopilot.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass


class RangeStatus(enum.Enum):
    """What the autopilot's rangefinder gets from this reading."""

    # A distance the filter believes: sent as DISTANCE_SENSOR.
    GOOD = "good"
    # The net fills the view, nearer than the mesh can be resolved: sent as a reading below the
    # rangefinder's minimum, which ArduPilot reports as OutOfRangeLow (not NoData).
    TOO_CLOSE = "too_close"
    # Nothing believable: nothing is sent, and ArduPilot reports NoData after 500 ms.
    NONE = "none"


@dataclass(frozen=True)
class RangeReading:
    """One distance to the net along the sensor orientation, from one frame.

    `t_capture` is the capture time of the frame it came from (monotonic seconds, the frames'
    clock), so the link can refuse stale readings and stamp what it sends with the frame's time.
    `sigma_m` is one standard deviation (nan = unknown); `quality` 0..1 (nan = unknown).
    """

    status: RangeStatus
    t_capture: float
    distance_m: float = math.nan
    sigma_m: float = math.nan
    quality: float = math.nan

    def __post_init__(self) -> None:
        if self.status is RangeStatus.GOOD and not (
            math.isfinite(self.distance_m) and self.distance_m >= 0.0
        ):
            raise ValueError(f"a GOOD reading needs a distance >= 0, got {self.distance_m}")

    @classmethod
    def none(cls, t_capture: float) -> RangeReading:
        return cls(RangeStatus.NONE, t_capture)

    @property
    def sendable(self) -> bool:
        return self.status is not RangeStatus.NONE


@dataclass(frozen=True)
class VisionPose:
    """The vehicle's pose in the net frame (metres, radians), for VISION_POSITION_ESTIMATE.

    Frame: ArduPilot expects a right-handed, z-down frame (x forward, y right, z down at
    acquisition). `covariance` is the upper triangle (21 values, row-major) of the 6x6
    covariance of (x, y, z, roll, pitch, yaw), or None if unknown. `frame_id` identifies one
    acquisition of the net frame: change it whenever the net is re-acquired so the link bumps
    reset_counter and the EKF does not fuse a jump as motion. `t_capture` is the frame's
    capture time (monotonic seconds): ArduPilot aligns vision data by its timestamp.
    """

    x: float
    y: float
    z: float
    roll: float
    pitch: float
    yaw: float
    t_capture: float
    covariance: tuple[float, ...] | None = None
    frame_id: int = 0

    def __post_init__(self) -> None:
        if self.covariance is not None and len(self.covariance) != 21:
            raise ValueError(f"covariance needs 21 values, got {len(self.covariance)}")

    @property
    def usable(self) -> bool:
        values = (self.x, self.y, self.z, self.roll, self.pitch, self.yaw)
        return all(math.isfinite(v) for v in values)
