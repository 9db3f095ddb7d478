"""`sim:` frames of a world-fixed net, seen by a camera on a vehicle the autopilot moves.

This closes the loop in simulation: the autopilot (ArduSub SITL) moves the vehicle, this source
renders what the vehicle's camera then sees, netpose measures it, and what the autopilot does
with that moves the vehicle again. The URL is `sim:` + the MAVLink URL of a connection of its
own (not the daemon's autopilot link):

    sim:tcp:127.0.0.1:5764?distance=2&turn=20&cam_forward=0.25
    sim:udpin:0.0.0.0:14570?net=cage&radius=12&side=inside&fps=10

The net is placed when the first pose arrives, relative to the camera then: `distance` metres
away (perpendicular), its normal turned `turn` degrees to the right of the vehicle's heading
(so the vehicle must yaw right by `turn` to face it squarely). Or it is fixed in the world with
`facing` (deg, heading of its normal into the net) and `net_north`, `net_east` (m: a point on a
flat net, the centre of a cage), in local coordinates from `origin=LAT,LON` (SIM_STATE; default:
the first pose) or the EKF origin. drivers/sim_world.py has the
geometry. Each frame is rendered from the newest pose and stamped with that pose's time, and
carries its ground truth (`SimTruth`).

Options (defaults): fps (10; frames are rendered at most this often, each from a newer pose),
width, height (640x360; the built-in 82 deg camera of the synthetic source, or `calibration`),
net (plane | cage), distance (2.0 m), turn (0 deg), radius (25 m, cage), side (outside |
inside, cage), bar (0.025 m), angle (90 deg): the mesh; cam_forward, cam_right, cam_down (0 m):
camera offset on the vehicle; cam_tilt (0 deg, + = down); style (plain | varied), seed (0);
pose (auto | sim | ekf: SIM_STATE, or the EKF's LOCAL_POSITION_NED + ATTITUDE; auto prefers
SIM_STATE); sysid (1), compid (25): this connection's MAVLink identity; pose_timeout (0.5 s:
no frame from a pose older than this); blind (a file path: while that file exists the camera
sees no net, as when it is blocked or the net is out of view; for tests).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal, cast

import numpy as np

from drivers.errors import SourceError
from drivers.mavlink_settings import MavlinkSettings
from drivers.sim_world import (
    CameraMount,
    CameraView,
    VehiclePose,
    WorldNet,
    camera_view,
)
from drivers.sources.base import (
    Frame,
    FrameSource,
    RateMeter,
    SourceOptions,
    SourceState,
    SourceStats,
    wall_time_of,
)
from drivers.sources.synthetic import rendered_camera
from drivers.sources.url import SourceUrl, parse_source_url, url_error
from drivers.synthetic_net import NetPose, NetRenderer, SceneStyle
from drivers.vehicle_pose import PoseFeedSettings, PoseSource, VehiclePoseFeed
from service.core.camera import CameraModel
from service.core.errors import ConfigError
from service.core.mesh import MeshGeometry

log = logging.getLogger(__name__)

SIM_OPTIONS = (
    "fps", "width", "height", "calibration", "net", "distance", "turn", "radius", "side", "bar",
    "angle", "cam_forward", "cam_right", "cam_down", "cam_tilt", "style", "seed", "pose",
    "sysid", "compid", "pose_timeout", "blind", "facing", "net_north", "net_east", "origin",
)  # fmt: skip
# A stand-in pose for the renderer when the net is out of view (the net is not drawn).
_NO_NET = NetPose(range_m=1.0)


@dataclass(frozen=True)
class SimTruth:
    """Ground truth of one `sim:` frame (the fields `truth_view` reads, and the vehicle's)."""

    net_present: bool  # the net is drawn (in view and the camera not blind)
    range_m: float  # along the optical axis (inf when the axis misses the net)
    distance_m: float  # perpendicular, camera centre to the net
    normal: tuple[float, float, float]  # from the net towards the camera, camera frame
    tilt_deg: float
    heading_error_deg: float  # yaw (right +) that would square the vehicle to the net
    vehicle: VehiclePose
    camera_position: tuple[float, float, float]


@dataclass(frozen=True)
class SimScene:
    """The URL's options, checked."""

    fps: float
    net_kind: str
    distance_m: float
    turn_deg: float
    radius_m: float
    inside: bool
    mount: CameraMount
    mesh: MeshGeometry
    style: str
    seed: int
    pose_source: PoseSource
    pose_timeout_s: float
    blind: Path | None
    facing_deg: float | None = None  # fixed in the world (with net_ne) instead of `distance`
    net_ne: tuple[float, float] = (0.0, 0.0)

    def place_net(self, first: VehiclePose) -> WorldNet:
        kind: Literal["plane", "cage"] = "cage" if self.net_kind == "cage" else "plane"
        if self.facing_deg is not None:
            return WorldNet(kind, self.net_ne, facing=math.radians(self.facing_deg),
                            radius_m=self.radius_m, inside=self.inside)
        cam = first.position + first.body_to_world() @ self.mount.offset
        return WorldNet.ahead_of(
            (float(cam[0]), float(cam[1])), first.yaw, self.distance_m,
            math.radians(self.turn_deg), kind=kind, radius_m=self.radius_m, inside=self.inside,
        )


def parse_sim_url(url: str) -> tuple[SourceUrl, SimScene, PoseFeedSettings]:
    parsed = parse_source_url(url)
    if parsed.scheme != "sim":
        raise url_error(url, "not a sim: URL")
    parsed.check_options(SIM_OPTIONS)
    if not parsed.path:
        raise url_error(url, "give the MAVLink URL to read the vehicle's pose from, e.g. "
                        "sim:tcp:127.0.0.1:5764")
    net_kind = parsed.choice("net", "plane", ("plane", "cage"))
    radius = parsed.number_or("radius", 25.0, 1.0, 1000.0)
    distance = parsed.number_or("distance", 2.0, 0.1, 50.0)
    inside = parsed.choice("side", "outside", ("outside", "inside")) == "inside"
    if net_kind == "cage" and inside and distance >= radius:
        raise url_error(url, "inside a cage, distance must be less than radius")
    try:
        mesh = MeshGeometry(parsed.number_or("bar", 0.025, 0.001, 1.0),
                            parsed.number_or("angle", 90.0, 20.0, 160.0))
    except ConfigError as exc:
        raise url_error(url, exc.problem) from None
    blind = parsed.options.get("blind")
    facing = parsed.number("facing", None, -360.0, 360.0)
    net_ne = (parsed.number_or("net_north", 0.0, -1e4, 1e4), parsed.number_or("net_east", 0.0,
                                                                              -1e4, 1e4))
    origin = None
    if "origin" in parsed.options:
        try:
            lat, lon = (float(v) for v in parsed.options["origin"].split(","))
        except ValueError:
            raise url_error(url, "option origin must be LAT,LON in degrees") from None
        if not (-90 <= lat <= 90 and -180 <= lon <= 180):
            raise url_error(url, "option origin must be LAT,LON in degrees")
        origin = (lat, lon)
    scene = SimScene(
        fps=parsed.number_or("fps", 10.0, 0.5, 60.0),
        net_kind=net_kind,
        distance_m=distance,
        turn_deg=parsed.number_or("turn", 0.0, -80.0, 80.0),
        radius_m=radius,
        inside=inside,
        mount=CameraMount(
            forward_m=parsed.number_or("cam_forward", 0.0, -5.0, 5.0),
            right_m=parsed.number_or("cam_right", 0.0, -5.0, 5.0),
            down_m=parsed.number_or("cam_down", 0.0, -5.0, 5.0),
            tilt_deg=parsed.number_or("cam_tilt", 0.0, -60.0, 60.0),
        ),
        mesh=mesh,
        style=parsed.choice("style", "plain", ("plain", "varied")),
        seed=parsed.integer_or("seed", 0, 0, 2**31 - 1),
        pose_source=cast(PoseSource, parsed.choice("pose", "auto", ("auto", "sim", "ekf"))),
        pose_timeout_s=parsed.number_or("pose_timeout", 0.5, 0.05, 10.0),
        blind=Path(blind) if blind else None,
        facing_deg=facing,
        net_ne=net_ne,
    )
    try:
        feed = PoseFeedSettings(
            url=parsed.path, source_system=parsed.integer_or("sysid", 1, 1, 254),
            source_component=parsed.integer_or("compid", 25, 1, 254),
            rate_hz=max(20.0, scene.fps), source=scene.pose_source, origin=origin,
        )
        MavlinkSettings(url=feed.url, source_system=feed.source_system,
                        source_component=feed.source_component)
    except ConfigError as exc:
        raise url_error(url, exc.problem) from None
    return parsed, scene, feed


class SimSource(FrameSource):
    """Rendered frames of a world-fixed net from the vehicle's pose; see the module docstring."""

    def __init__(self, url: str, options: SourceOptions | None = None) -> None:
        super().__init__(url)
        parsed, self.scene, self._feed_settings = parse_sim_url(url)
        self._options = options or SourceOptions()
        self._camera = rendered_camera(parsed, (640, 360))
        self._feed: VehiclePoseFeed | None = None
        self._renderer: NetRenderer | None = None
        self._style = SceneStyle()
        self.net: WorldNet | None = None
        self._state = SourceState.OPENING
        self._last_pose_t = -math.inf
        self._next_due = 0.0
        self._frames = 0
        self._drops = 0
        self._rate = RateMeter()
        self._stale_since: float | None = None

    @property
    def rendered(self) -> bool:
        return True

    @property
    def camera(self) -> CameraModel:
        return self._camera

    @property
    def state(self) -> SourceState:
        return self._state

    def open(self) -> None:
        if self._state is not SourceState.OPENING or self._feed is not None:
            return
        try:
            self._renderer = NetRenderer(self._camera, self.scene.mesh, seed=self.scene.seed)
        except Exception as exc:
            raise SourceError(self.url, f"the renderer cannot start: {exc!r}") from exc
        if self.scene.style == "varied":
            self._style = SceneStyle.varied(np.random.default_rng([self.scene.seed, 1]))
        self._feed = VehiclePoseFeed(self._feed_settings)
        self._feed.start()
        log.info("frame source %s: waiting for the vehicle's pose", self.url)

    def read(self, timeout_s: float) -> Frame | None:
        feed = self._feed
        if feed is None or self._state is SourceState.CLOSED:
            time.sleep(max(0.0, timeout_s))
            return None
        deadline = time.monotonic() + max(0.0, timeout_s)
        wait_due = self._next_due - time.monotonic()
        if wait_due > 0:
            if wait_due > timeout_s:
                time.sleep(max(0.0, timeout_s))
                return None
            time.sleep(wait_due)
        pose = feed.wait_newer(self._last_pose_t, deadline - time.monotonic())
        now = time.monotonic()
        if pose is None or now - pose.t > self.scene.pose_timeout_s:
            self._note_stale(now)
            return None
        self._note_fresh(now)
        if self.net is None:
            self.net = self.scene.place_net(pose)
            log.info("frame source %s: %s net at %.2f m from the camera, normal %.1f deg from "
                     "the heading", self.url, self.net.kind, self.view_of(pose).distance_m,
                     self.view_of(pose).heading_error_deg)
        frame = self._render(pose)
        self._last_pose_t = pose.t
        # Frames are due at `fps`; a render slower than that makes the next one due at once.
        self._next_due = max(self._next_due + 1.0 / self.scene.fps, now)
        self._frames += 1
        self._rate.tick(now)
        return frame

    def view_of(self, pose: VehiclePose) -> CameraView:
        if self.net is None:
            raise RuntimeError("the net is placed when the first pose arrives")
        return camera_view(self.net, self.scene.mount, pose, self.scene.mesh)

    def _render(self, pose: VehiclePose) -> Frame:
        renderer = self._renderer
        assert renderer is not None
        view = self.view_of(pose)
        blind = self.scene.blind is not None and self.scene.blind.exists()
        present = view.in_view and not blind and view.net_pose is not None
        style = self._style if present else replace(self._style, net_present=False)
        rng = np.random.default_rng([self.scene.seed, 2, self._frames])
        image, _ = renderer.render(view.net_pose if present and view.net_pose else _NO_NET,
                                   rng=rng, style=style)
        truth = SimTruth(
            net_present=present, range_m=view.range_m, distance_m=view.distance_m,
            normal=view.normal, tilt_deg=view.tilt_deg,
            heading_error_deg=view.heading_error_deg, vehicle=pose,
            camera_position=view.camera_position,
        )
        return Frame(image=image, index=self._frames, t_monotonic=pose.t,
                     t_wall=wall_time_of(pose.t), truth=truth)

    def _note_stale(self, now: float) -> None:
        if self._state is SourceState.UP and self._stale_since is None:
            self._stale_since = now
        if (self._state is SourceState.UP and self._stale_since is not None
                and now - self._stale_since > self._options.stall_timeout_s):
            self._state = SourceState.DOWN
            log.warning("frame source %s: no vehicle pose for %.1f s", self.url,
                        now - self._stale_since)

    def _note_fresh(self, now: float) -> None:
        self._stale_since = None
        if self._state is not SourceState.UP:
            if self._state is SourceState.DOWN:
                log.info("frame source %s: vehicle pose back", self.url)
            self._state = SourceState.UP

    def stats(self) -> SourceStats:
        feed = self._feed
        return SourceStats(
            state=self._state, frames=self._frames, captured=self._frames + self._drops,
            drops=self._drops, corrupt=0, reconnects=0 if feed is None else feed.errors,
            fps=self._rate.rate(time.monotonic()),
        )

    def close(self) -> None:
        if self._state is SourceState.CLOSED:
            return
        self._state = SourceState.CLOSED
        feed, self._feed = self._feed, None
        if feed is not None:
            feed.close()
        self._renderer = None
