"""The `sim:` source: world geometry against first principles, and the source end to end against
the fake autopilot sending SIM_STATE (or the EKF's pose) over real loopback MAVLink, with the
real estimator measuring what it renders."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.sim_world import CameraMount, VehiclePose, WorldNet, camera_view
from drivers.sources import create_source
from drivers.sources.sim import SimSource, SimTruth
from service.core.errors import ConfigError
from service.core.estimator import EstimatorSettings, NetEstimator
from service.core.mesh import MeshGeometry
from tests.fake_autopilot import FakeAutopilot, UdpServerTransport, _Writer

pytestmark = pytest.mark.timeout(120)
MESH = MeshGeometry(0.025, 90.0)
LAT0, LON0 = 33.810313, -118.393867


# ---- geometry ----------------------------------------------------------------------------------
def random_pose(rng: np.random.Generator) -> VehiclePose:
    north, east = rng.uniform(-1, 1, 2)
    roll, pitch = np.radians(rng.uniform(-8, 8, 2))
    return VehiclePose(0.0, north, east, rng.uniform(0, 5), roll, pitch,
                       rng.uniform(-math.pi, math.pi))


@pytest.mark.parametrize("kind", ["plane", "cage-outside", "cage-inside"])
def test_rendered_pose_matches_the_world_geometry(kind: str) -> None:
    """For random vehicle poses and camera mounts, the renderer's NetPose places the net at the
    distance and with the normal that the world geometry says, and the truth agrees."""
    rng = np.random.default_rng(7)
    for _ in range(200):
        pose = random_pose(rng)
        forward, right, down = rng.uniform(-0.3, 0.3, 3)
        mount = CameraMount(forward, right, down, tilt_deg=rng.uniform(-30, 30))
        cam = pose.position + pose.body_to_world() @ mount.offset
        turn = rng.uniform(-0.5, 0.5)
        if kind == "plane":
            net = WorldNet.ahead_of((cam[0], cam[1]), pose.yaw, 1.5, turn)
            expected = 1.5
        else:
            net = WorldNet.ahead_of((cam[0], cam[1]), pose.yaw, 1.5, turn, kind="cage",
                                    radius_m=6.0, inside=kind.endswith("inside"))
            centre = np.array(net.point_ne)
            r = float(np.hypot(*(cam[:2] - centre)))
            expected = 6.0 - r if net.inside else r - 6.0
        view = camera_view(net, mount, pose, MESH)
        assert view.distance_m == pytest.approx(expected, abs=1e-9)
        assert view.heading_error_deg == pytest.approx(math.degrees(turn), abs=1e-6)
        if not view.in_view:
            continue
        assert view.net_pose is not None
        assert view.net_pose.distance_m() == pytest.approx(expected, abs=1e-9)
        assert tuple(view.net_pose.normal_towards_camera()) == pytest.approx(view.normal,
                                                                             abs=1e-9)
        # The range is where the optical axis meets the plane.
        assert view.range_m * abs(view.normal[2]) == pytest.approx(expected, abs=1e-9)


def test_the_mesh_is_fixed_to_the_net() -> None:
    """Sliding the camera one bar length along the net, or one down, moves the lattice by
    exactly one cell; half a bar moves it by half."""
    net = WorldNet.ahead_of((0.0, 0.0), 0.0, 1.2, 0.0)
    base = camera_view(net, CameraMount(), VehiclePose(0, 0, 0, 1.0, 0, 0, 0), MESH).net_pose
    one = camera_view(net, CameraMount(), VehiclePose(0, 0, 0.025, 1.025, 0, 0, 0),
                      MESH).net_pose
    half = camera_view(net, CameraMount(), VehiclePose(0, 0, 0.0125, 1.0, 0, 0, 0),
                       MESH).net_pose
    assert base is not None and one is not None and half is not None
    def cells(a: float, b: float) -> float:  # lattice shift, wrapped to -0.5..0.5
        return (a - b + 0.5) % 1.0 - 0.5

    assert [cells(a, b) for a, b in zip(one.phase, base.phase, strict=True)] == pytest.approx(
        [0.0, 0.0], abs=1e-6)
    assert abs(cells(half.phase[0], base.phase[0])) == pytest.approx(0.5, abs=1e-6)


def test_out_of_view_when_turned_away_or_behind() -> None:
    net = WorldNet.ahead_of((0.0, 0.0), 0.0, 1.0, 0.0)
    side = camera_view(net, CameraMount(), VehiclePose(0, 0, 0, 1, 0, 0, math.radians(80)), MESH)
    assert not side.in_view and side.net_pose is None and side.distance_m == pytest.approx(1.0)
    behind = camera_view(net, CameraMount(), VehiclePose(0, 1.5, 0, 1, 0, 0, 0), MESH)
    assert not behind.in_view and behind.distance_m == pytest.approx(-0.5)


# ---- URL ---------------------------------------------------------------------------------------
def test_sim_urls_are_checked_and_named() -> None:
    source = create_source("sim:udpin:127.0.0.1:14599?distance=1.5&turn=10&cam_tilt=15")
    assert isinstance(source, SimSource) and source.scene.turn_deg == 10.0
    assert source.camera.width == 640 and source.rendered
    assert not create_source("rtsp://host/x").rendered and create_source("synthetic:").rendered
    for bad, problem in (
        ("sim:?distance=2", "give the MAVLink URL"),
        ("sim:tcp:127.0.0.1:5764?distnce=2", "unknown option"),
        ("sim:tcp:127.0.0.1:5764?net=sphere", "net must be one of"),
        ("sim:ftp:somewhere", "is not udpout"),
        ("sim:tcp:127.0.0.1:5764?net=cage&side=inside&radius=2&distance=3", "less than radius"),
    ):
        with pytest.raises(ConfigError, match=problem) as info:
            create_source(bad)
        assert info.value.key == "camera.url"


# ---- the source against a (fake) autopilot ----------------------------------------------------
class Vehicle:
    """Plays an autopilot's pose messages at 20 Hz from its own thread-free calls."""

    def __init__(self, autopilot: FakeAutopilot) -> None:
        self.autopilot = autopilot
        self.mav = autopilot.mavlink.MAVLink(_Writer(autopilot.transport), srcSystem=1,
                                             srcComponent=1)

    def sim_state(self, north: float, east: float, alt: float, yaw: float,
                  vn: float = 0.0, ve: float = 0.0) -> float:
        lat = LAT0 + math.degrees(north / 6378137.0)
        lon = LON0 + math.degrees(east / (6378137.0 * math.cos(math.radians(LAT0))))
        sent = time.monotonic()
        self.mav.sim_state_send(1, 0, 0, 0, 0.0, 0.0, yaw, 0, 0, 0, 0, 0, 0, lat * 1e7,
                                lon * 1e7, alt, 0, 0, vn, ve, 0, int(round(lat * 1e7)),
                                int(round(lon * 1e7)))
        return sent

    def ekf(self, north: float, east: float, down: float, yaw: float) -> None:
        boot = self.autopilot.boot_ms()
        self.mav.attitude_send(boot, 0.0, 0.0, yaw, 0.0, 0.0, 0.0)
        self.mav.local_position_ned_send(boot, north, east, down, 0.0, 0.0, 0.0)


@pytest.fixture
def autopilot() -> Iterator[FakeAutopilot]:
    with FakeAutopilot(UdpServerTransport()) as fake:
        yield fake


def read_frame(source: SimSource, feed: Callable[[], None], timeout: float = 10.0) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        feed()
        frame = source.read(0.05)
        if frame is not None:
            return frame
    raise AssertionError("no frame")


def test_renders_what_the_vehicle_sees_and_the_estimator_measures_it(
    autopilot: FakeAutopilot, tmp_path: Path
) -> None:
    blind = tmp_path / "blind"
    url = (f"sim:udpout:{autopilot.url.split(':', 1)[1]}?distance=1.4&turn=12&fps=20"
           f"&width=640&height=360&cam_forward=0.2&blind={blind}")
    vehicle = Vehicle(autopilot)
    estimator = NetEstimator(SimSource(url).camera, MESH, EstimatorSettings())
    yaw = math.radians(30)
    position = {"north": 0.0}
    sent: list[float] = []

    def feed() -> None:
        sent.append(vehicle.sim_state(position["north"], 0.0, -2.0, yaw))
        time.sleep(0.05)

    with SimSource(url) as source:
        first = read_frame(source, feed)
        heartbeat = autopilot.wait_for("HEARTBEAT")[0]
        request = autopilot.wait_for("COMMAND_LONG", where=lambda r: r.msg.command == 511
                                     and int(r.msg.param1) == 108)[0]
        assert heartbeat.t <= request.t  # a heartbeat first, then the request
        assert int(request.msg.param2) == 50_000  # 20 Hz
        truth = first.truth
        assert isinstance(truth, SimTruth) and truth.net_present
        assert truth.distance_m == pytest.approx(1.4, abs=0.01)
        assert truth.heading_error_deg == pytest.approx(12.0, abs=0.01)
        # Stamped with the pose's arrival, not the end of rendering.
        assert min(abs(first.t_monotonic - s) for s in sent) < 0.02
        estimate = estimator.estimate(first.image)
        assert estimate.detected and estimate.distance_m is not None and estimate.normal
        assert estimate.distance_m == pytest.approx(truth.distance_m, rel=0.02)
        yaw_measured = math.degrees(math.atan2(-estimate.normal[0], -estimate.normal[2]))
        assert yaw_measured == pytest.approx(12.0, abs=2.0)

        # The vehicle moves 0.5 m north: the net, fixed in the world, comes nearer.
        position["north"] = 0.5
        time.sleep(0.1)
        frame = read_frame(source, feed)
        while frame.truth.vehicle.north < 0.49:
            frame = read_frame(source, feed)
        # The net's normal points along the heading 30 + 12 degrees.
        expected = 1.4 - 0.5 * math.cos(math.radians(42))
        assert frame.truth.distance_m == pytest.approx(expected, abs=0.015)
        estimate = estimator.estimate(frame.image)
        assert estimate.distance_m == pytest.approx(expected, rel=0.02)

        blind.touch()
        frame = read_frame(source, feed)
        assert not frame.truth.net_present
        assert not estimator.estimate(frame.image).detected

        # No pose: no frame (after pose_timeout), never an old pose rendered as new.
        time.sleep(0.6)
        assert source.read(0.2) is None


def test_sim_state_position_steps_are_smoothed_with_its_velocity(
    autopilot: FakeAutopilot
) -> None:
    """SIM_STATE's lat_int/lon_int come in ~1.1 cm steps; following its velocity, the source's
    positions stay within a few millimetres of the true, moving position."""
    url = f"sim:udpout:{autopilot.url.split(':', 1)[1]}?distance=2&fps=20"
    vehicle = Vehicle(autopilot)
    t0 = time.monotonic()
    speed = 0.1  # m/s north

    def feed() -> None:
        vehicle.sim_state(speed * (time.monotonic() - t0), 0.0, -1.0, 0.0, vn=speed)
        time.sleep(0.05)

    samples = []
    with SimSource(url) as source:
        while time.monotonic() - t0 < 4.0:
            frame = read_frame(source, feed)
            if time.monotonic() - t0 > 2.0:  # after the smoothing's time constant
                samples.append((frame.truth.vehicle.t, frame.truth.vehicle.north))
    t, north = np.array(samples).T
    slope, offset = np.polyfit(t - t0, north, 1)
    residual = north - (slope * (t - t0) + offset)
    assert slope == pytest.approx(speed, rel=0.05)
    assert np.max(np.abs(residual)) < 0.003  # raw fixes step by 11 mm


def test_ekf_pose_when_asked(autopilot: FakeAutopilot) -> None:
    url = f"sim:udpout:{autopilot.url.split(':', 1)[1]}?pose=ekf&distance=2&fps=20"
    vehicle = Vehicle(autopilot)

    def feed() -> None:
        vehicle.ekf(3.0, -1.0, 1.5, 0.2)
        time.sleep(0.05)

    with SimSource(url) as source:
        frame = read_frame(source, feed)
        assert frame.truth.vehicle.source == "ekf"
        assert frame.truth.distance_m == pytest.approx(2.0, abs=1e-6)
        request = autopilot.wait_for("COMMAND_LONG", where=lambda r: r.msg.command == 511)
        assert {int(r.msg.param1) for r in autopilot.received("COMMAND_LONG")} >= {30, 32}
        assert request


def test_a_rendered_distance_reaches_an_autopilot_only_when_allowed() -> None:
    from service.daemon.wiring import check_config

    demo = str(Path(__file__).resolve().parents[1] / "config" / "demo.toml")
    sim = "camera.url=sim:tcp:127.0.0.1:5764"
    with pytest.raises(ConfigError) as info:
        check_config(demo, [sim, "mavlink.allow_simulated=false"])
    assert info.value.key == "mavlink.allow_simulated"
    assert check_config(demo, [sim]).startswith("configuration OK")
