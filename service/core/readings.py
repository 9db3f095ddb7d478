"""What the autopilot is told: one reading type with one validity field.

The filter decides whether it believes its distance (`TrackOutput.valid`); the pipeline turns
that into a `RangeReading`, and the MAVLink link sends exactly what `RangeReading.status` says.
No other flag anywhere decides what reaches the autopilot.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import Literal

# Which distance a reading gives (`service.autopilot_distance`): along the camera's optical axis
# (what a forward rangefinder would measure), or perpendicular to the net plane.
DistanceAlong = Literal["optical_axis", "perpendicular"]


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
    `along` says which distance `distance_m` is (the pipeline's setting when it made the
    reading, also on a reading without a distance; None when nobody said), so whoever shows
    the reading shows what the autopilot got, not another distance beside it.
    """

    status: RangeStatus
    t_capture: float
    distance_m: float = math.nan
    sigma_m: float = math.nan
    quality: float = math.nan
    along: DistanceAlong | None = None

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
class NetPlane:
    """The net plane as one frame saw it, for the autopilot's net-hold applet.

    `foot_m` is the vector from the camera to the nearest point of the net plane, in the camera
    frame (x right, y down, z forward; metres): its length is the perpendicular distance and its
    direction is the net normal pointing away from the camera. It is made only from a frame whose
    measurement the filter accepted, and `t_capture` is that frame's capture time (monotonic
    seconds), so its age on the autopilot is the age of the evidence: a coasting filter never
    produces one. Every other frame gives `NetPlane.none` (a zero vector): "no net in this
    frame". (Why no VISION_POSITION_ESTIMATE: docs/net-hold.md.)
    """

    t_capture: float
    foot_m: tuple[float, float, float]

    @classmethod
    def none(cls, t_capture: float) -> NetPlane:
        """The frame at `t_capture` did not confirm the net: sent as a zero vector, so the
        applet stops at once instead of waiting for its timeout."""
        return cls(t_capture, (0.0, 0.0, 0.0))

    @classmethod
    def from_distance_normal(
        cls, t_capture: float, distance_m: float, normal_towards_camera: tuple[float, float, float]
    ) -> NetPlane:
        nx, ny, nz = normal_towards_camera
        return cls(t_capture, (-distance_m * nx, -distance_m * ny, -distance_m * nz))

    @property
    def distance_m(self) -> float:
        return math.sqrt(sum(v * v for v in self.foot_m))

    @property
    def usable(self) -> bool:
        """Finite, and the net in front of the camera (positive forward component)."""
        return all(math.isfinite(v) for v in self.foot_m) and self.foot_m[2] > 0.0
