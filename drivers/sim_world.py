"""The simulated world of the `sim:` source: a net fixed in the world, a vehicle, its camera.

Pure geometry, no I/O. Frames: the world is local NED (north, east, down; metres) and headings
are radians clockwise from north; the vehicle body is FRD (forward, right, down); the camera is
the optical frame (x right, y down, z forward). The net hangs vertically, infinitely deep:

  plane  a flat net through `point_ne` whose normal points along the heading `facing`
         (a vehicle looking along `facing` faces it squarely);
  cage   a cylinder of radius `radius_m` around `centre_ne`, seen from outside or inside.

For rendering, the net is replaced by its tangent plane at the point nearest to the camera.
For a flat net that is exact. For a cage it is exact at that point (the perpendicular distance
and the normal are those of the cylinder) and off by the sagitta elsewhere in the picture:
w^2 / (2 R) for a point w metres along the net from it, 1.4 cm at 0.85 m on a 25 m pen.
The mesh is fixed to the net (horizontal coordinate along the net, vertical coordinate depth),
so it moves across the picture as the vehicle moves, as a real one does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

from drivers.synthetic_net import NetPose
from service.core.mesh import MeshGeometry

FloatArray = npt.NDArray[np.float64]
# Beyond this angle between the optical axis and the net normal the net is out of view: the
# renderer needs the optical axis to meet the net, and the estimator measures up to ~70 deg.
MAX_VIEW_TILT_DEG = 75.0


@dataclass(frozen=True)
class VehiclePose:
    """Where the vehicle is: local NED position (m) and Euler attitude (rad), at `t`
    (time.monotonic of the pose's arrival). `source` says which autopilot message gave it."""

    t: float
    north: float
    east: float
    down: float
    roll: float
    pitch: float
    yaw: float
    source: str = "sim_state"

    @property
    def position(self) -> FloatArray:
        return np.array([self.north, self.east, self.down])

    def body_to_world(self) -> FloatArray:
        """Rotation taking body (FRD) vectors into NED: R = Rz(yaw) Ry(pitch) Rx(roll)."""
        return _rz(self.yaw) @ _ry(self.pitch) @ _rx(self.roll)


@dataclass(frozen=True)
class CameraMount:
    """The camera on the vehicle: offset of its centre in the body frame (m), and its tilt
    (deg, positive = looking down). The optical axis lies in the body's forward-down plane."""

    forward_m: float = 0.0
    right_m: float = 0.0
    down_m: float = 0.0
    tilt_deg: float = 0.0

    @property
    def offset(self) -> FloatArray:
        return np.array([self.forward_m, self.right_m, self.down_m])

    def camera_to_body(self) -> FloatArray:
        """Columns: the camera's x (right), y (down), z (optical axis) in body axes."""
        t = math.radians(self.tilt_deg)
        x = np.array([0.0, 1.0, 0.0])
        y = np.array([-math.sin(t), 0.0, math.cos(t)])
        z = np.array([math.cos(t), 0.0, math.sin(t)])
        return np.column_stack([x, y, z])


@dataclass(frozen=True)
class NetNearest:
    """The net's point nearest to a position: its distance, the horizontal unit normal pointing
    into the net, the unit tangent along the net (normal x down), and the mesh coordinate along
    the net (m) at that point."""

    distance_m: float
    into: FloatArray
    along: FloatArray
    foot: FloatArray
    u_m: float


@dataclass(frozen=True)
class WorldNet:
    kind: Literal["plane", "cage"]
    point_ne: tuple[float, float] = (0.0, 0.0)  # plane: a point on the net; cage: the centre
    facing: float = 0.0  # plane: heading of the normal into the net (rad)
    radius_m: float = 25.0  # cage
    inside: bool = False  # cage: the vehicle works inside the pen

    @staticmethod
    def ahead_of(
        camera_ne: tuple[float, float], heading: float, distance_m: float, turn_rad: float,
        kind: Literal["plane", "cage"] = "plane", radius_m: float = 25.0, inside: bool = False,
    ) -> WorldNet:
        """A net `distance_m` from the camera, its normal `turn_rad` to the right of `heading`."""
        facing = heading + turn_rad
        into = np.array([math.cos(facing), math.sin(facing)])
        cam = np.array(camera_ne)
        if kind == "plane":
            point = cam + distance_m * into
            return WorldNet("plane", (float(point[0]), float(point[1])), facing=facing)
        # The camera lies on the line through the centre along `into`.
        if inside:  # the wall ahead is at centre + radius * into
            centre = cam - (radius_m - distance_m) * into
        else:  # the wall ahead is at centre - radius * into
            centre = cam + (distance_m + radius_m) * into
        return WorldNet("cage", (float(centre[0]), float(centre[1])), radius_m=radius_m,
                        inside=inside)

    def nearest(self, position: FloatArray) -> NetNearest:
        p = np.array([position[0], position[1]])
        c = np.array(self.point_ne)
        if self.kind == "plane":
            into2 = np.array([math.cos(self.facing), math.sin(self.facing)])
            distance = float((c - p) @ into2)
            foot2 = p + distance * into2
            along2 = np.array([-into2[1], into2[0]])
            u = float((foot2 - c) @ along2)
        else:
            radial = p - c
            r = float(np.hypot(radial[0], radial[1]))
            if r < 1e-9:  # at the centre every direction is as near: pick north
                radial, r = np.array([1e-9, 0.0]), 1e-9
            out2 = radial / r
            into2 = out2 if self.inside else -out2
            distance = self.radius_m - r if self.inside else r - self.radius_m
            foot2 = c + self.radius_m * out2
            along2 = np.array([-into2[1], into2[0]])
            # Arc length along the pen, increasing in the direction of `along`.
            azimuth = math.atan2(out2[1], out2[0])
            u = self.radius_m * azimuth * (1.0 if self.inside else -1.0)
        into = np.array([into2[0], into2[1], 0.0])
        along = np.array([along2[0], along2[1], 0.0])
        foot = np.array([foot2[0], foot2[1], position[2]])
        return NetNearest(distance, into, along, foot, u)


@dataclass(frozen=True)
class CameraView:
    """What the camera sees of the net: the renderer's pose and the ground truth."""

    in_view: bool
    net_pose: NetPose | None  # None when out of view
    distance_m: float  # perpendicular, camera centre to the (tangent) net plane
    range_m: float  # along the optical axis (inf when the axis misses the net)
    normal: tuple[float, float, float]  # unit, from the net towards the camera, camera frame
    tilt_deg: float  # between the optical axis and the net normal
    heading_error_deg: float  # how far the vehicle must yaw (right +) to face the net squarely
    camera_position: tuple[float, float, float]  # NED


def camera_view(
    net: WorldNet, mount: CameraMount, vehicle: VehiclePose, mesh: MeshGeometry
) -> CameraView:
    """Where the net is in the camera's frame, as the renderer's NetPose."""
    r_b2w = vehicle.body_to_world()
    r_c2w = r_b2w @ mount.camera_to_body()
    cam = vehicle.position + r_b2w @ mount.offset
    near = net.nearest(cam)
    r_w2c = r_c2w.T
    away = r_w2c @ near.into  # net normal pointing away from the camera, camera frame
    u_axis = r_w2c @ near.along
    d = near.distance_m
    cos_tilt = float(np.clip(away[2], -1.0, 1.0))
    tilt_deg = math.degrees(math.acos(cos_tilt))
    facing = math.atan2(near.into[1], near.into[0])
    heading_error = math.degrees(_wrap(facing - vehicle.yaw))
    in_view = d > 0 and tilt_deg <= MAX_VIEW_TILT_DEG
    range_m = d / cos_tilt if in_view else math.inf
    normal = (-float(away[0]), -float(away[1]), -float(away[2]))
    cam_t = (float(cam[0]), float(cam[1]), float(cam[2]))
    if not in_view:
        return CameraView(False, None, d, range_m, normal, tilt_deg, heading_error, cam_t)
    # Renderer's parameters: away = (sin(phi) sin(t), -cos(phi) sin(t), cos(t)) for a tilt t
    # about the image-plane axis (cos(phi), sin(phi), 0); then the in-plane roll of the mesh.
    sin_t = math.hypot(float(away[0]), float(away[1]))
    phi = math.atan2(float(away[0]), -float(away[1])) if sin_t > 1e-12 else 0.0
    tilt_pose = NetPose(range_m=range_m, tilt_deg=tilt_deg, tilt_axis_deg=math.degrees(phi))
    in_plane = tilt_pose.rotation().T @ u_axis
    roll = math.degrees(math.atan2(float(in_plane[1]), float(in_plane[0])))
    # Mesh phase: the lattice coordinates of the point where the optical axis meets the net.
    hit = cam + range_m * r_c2w[:, 2]
    u_hit = near.u_m + float((hit - near.foot) @ near.along)
    v_hit = float(hit[2])
    alpha = math.radians(mesh.opening_angle_deg)
    s2 = v_hit / (mesh.bar_length_m * math.sin(alpha))
    s1 = u_hit / mesh.bar_length_m - s2 * math.cos(alpha)
    pose = NetPose(range_m=range_m, tilt_deg=tilt_deg, tilt_axis_deg=math.degrees(phi),
                   roll_deg=roll, phase=(s1 - math.floor(s1), s2 - math.floor(s2)))
    return CameraView(True, pose, d, range_m, normal, tilt_deg, heading_error, cam_t)


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def _rx(a: float) -> FloatArray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _ry(a: float) -> FloatArray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rz(a: float) -> FloatArray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
