"""A rendered pass along a net with two holes, through the real daemon loop: each hole is
confirmed once (not once per frame), measured within 20 %, published on Zenoh (a real session
on loopback) and told to the pilot as a STATUSTEXT (real MAVLink 2 to the fake autopilot).

Only the frame source is a stand-in (the rendered frames, played on a fake clock); estimator,
filter, inspection, publisher and MAVLink link are the production ones.
"""

from __future__ import annotations

import base64
import dataclasses
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import pytest

from drivers.mavlink_link import MavlinkLink
from drivers.mavlink_settings import MavlinkSettings
from drivers.sdnotify import RecordingNotifier
from drivers.sources import Frame
from drivers.synthetic_damage import (
    HoleTruth,
    NetDamage,
    cell_at_pixel,
    hole_truth,
    missing_knot,
    torn_hole,
)
from drivers.synthetic_net import NetPose, NetRenderer, SceneStyle
from drivers.telemetry import TelemetrySettings, ZenohPublisher
from drivers.telemetry_subscriber import TelemetrySubscriber
from service.benchmarks.scenes import bench_camera
from service.core.damage_track import ConfirmedHole
from service.core.mesh import MeshGeometry
from service.core.messages import schema_problems
from service.daemon.damage_outputs import PilotNotices
from service.daemon.loop import Daemon, DaemonParts
from tests.daemon_harness import WALL_OFFSET, FakeClock, ScriptedSource, Step, demo_config
from tests.fake_autopilot import FakeAutopilot, UdpServerTransport

CAMERA = bench_camera(960, 540)
MESH = MeshGeometry(bar_length_m=0.02)
FPS = 10.0
FRAMES = 36
SPEED_CELLS_PER_FRAME = 0.35  # the net moves ~0.07 m/s through the view (7 mm a frame)
SIZE_TOLERANCE = 0.20


@dataclass
class PassRun:
    truths: list[list[HoleTruth]]  # per frame, per hole
    damages: list[dict]
    texts: list[str]
    daemon_holes: int
    inspection: object = None  # the last status's InspectionHealth


def _pose(k: int) -> NetPose:
    return NetPose(1.0, 15.0, 20.0, 12.0, (0.2 + SPEED_CELLS_PER_FRAME * k, 0.4))


@pytest.fixture(scope="module")
def ran() -> Iterator[PassRun]:
    renderer = NetRenderer(CAMERA, MESH)
    middle = _pose(FRAMES // 2)
    rng = np.random.default_rng(8)
    first = cell_at_pixel(CAMERA, middle, MESH, (330.0, 230.0))
    second = cell_at_pixel(CAMERA, middle, MESH, (640.0, 330.0))
    assert first is not None and second is not None
    holes = [torn_hole(first, 6, rng), missing_knot(second, rng)]
    damage = NetDamage(holes)
    clock = FakeClock(100.0)
    script = []
    truths = []
    for k in range(FRAMES):
        pose = _pose(k)
        image, _ = renderer.render(pose, np.random.default_rng([8, k]), SceneStyle(),
                                   damage=damage)
        t = 100.0 + k / FPS
        script.append(Step(Frame(image, k, t, t + WALL_OFFSET), processing_s=0.05))
        truths.append([hole_truth(h, CAMERA, pose, MESH) for h in holes])
    tel = TelemetrySubscriber(vehicle="pass")
    autopilot = FakeAutopilot(UdpServerTransport()).start()
    config = demo_config("mesh.bar_length_m=0.02", "damage.every_n_frames=1",
                         "damage.notify_interval_s=4", "telemetry.vehicle=pass")
    publisher = ZenohPublisher(TelemetrySettings(
        vehicle="pass", mode="peer", connect=(tel.endpoint,), listen=(), scouting=False))
    link = MavlinkLink(MavlinkSettings(url=autopilot.url, allow_simulated=True))
    parts = DaemonParts(source=ScriptedSource(script, clock), link=link, telemetry=publisher,
                        notifier=RecordingNotifier(), camera=CAMERA, vehicle="pass")
    daemon = Daemon(config, parts, clock=clock, wall_clock=clock.wall)
    try:
        daemon.start()
        deadline = time.monotonic() + 10.0
        while not publisher.online:  # the session opens in the background
            assert time.monotonic() < deadline, "the Zenoh session did not open"
            time.sleep(0.05)
        for _ in range(FRAMES):
            daemon.iterate()
        # The frames stop before the second hole's text is due (one text per 4 s): it goes
        # out all the same (it waited for the next frame, which never came).
        while clock.now < 100.0 + 8.0:
            daemon.iterate()
        outputs = daemon.outputs.damage
        assert outputs is not None
        daemon_holes = outputs.reported
        last_status = daemon.reporter.last_status
        inspection = last_status.inspection if last_status is not None else None
        expected = outputs.notices.sent_total
        autopilot.wait_for("STATUSTEXT", count=expected, timeout=10.0,
                           where=lambda r: "hole" in r.msg.text)
        deadline = time.monotonic() + 10.0
        while len(tel.damages) < daemon_holes and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        daemon.close()
        autopilot.close()
        damages = list(tel.damages)
        tel.close()
    texts = [r.msg.text for r in autopilot.received("STATUSTEXT") if "hole" in r.msg.text]
    yield PassRun(truths, damages, texts, daemon_holes, inspection)


def _matching(message: dict, truths: list[HoleTruth]) -> list[int]:
    x, y = message["image_x_px"], message["image_y_px"]
    return [k for k, t in enumerate(truths)
            if t.box_px[0] - 5 <= x <= t.box_px[2] + 5 and t.box_px[1] - 5 <= y <= t.box_px[3] + 5]


def test_both_holes_are_confirmed_once(ran: PassRun) -> None:
    assert ran.daemon_holes == 2
    assert len(ran.damages) == 2
    assert len({m["hole_id"] for m in ran.damages}) == 2
    # One run: the same start on both, which with hole_id keys a hole across runs (ids start
    # at 1 again after a restart).
    assert len({m["run_started_unix"] for m in ran.damages}) == 1
    assert all(isinstance(m["run_started_unix"], float) for m in ran.damages)
    found = set()
    for message in ran.damages:
        assert schema_problems(message) == []
        # The pixels' frame: a dashboard scales them onto its (smaller) preview with these.
        assert (message["frame_width_px"], message["frame_height_px"]) == (
            CAMERA.width, CAMERA.height)
        frame = round((message["frame_time_mono"] - 100.0) * FPS)
        match = _matching(message, ran.truths[frame])
        assert len(match) == 1, (message["image_x_px"], message["image_y_px"])
        found.add(match[0])
    assert found == {0, 1}


def test_the_status_says_how_much_of_the_net_was_looked_at(ran: PassRun) -> None:
    """No hole reported is no proof of an intact net: the status carries the inspection's
    coverage (frames searched, cells judged) beside the holes found."""
    from service.core.messages import InspectionHealth

    assert isinstance(ran.inspection, InspectionHealth)
    assert ran.inspection.holes == ran.daemon_holes == 2
    assert 3 <= ran.inspection.inspected_frames <= FRAMES
    assert ran.inspection.judged_cells > 100 * ran.inspection.inspected_frames


def test_their_sizes_are_within_20_percent(ran: PassRun) -> None:
    for message in ran.damages:
        frame = round((message["frame_time_mono"] - 100.0) * FPS)
        truth = ran.truths[frame][_matching(message, ran.truths[frame])[0]]
        assert message["width_m"] == pytest.approx(truth.width_m, rel=SIZE_TOLERANCE)
        assert message["height_m"] == pytest.approx(truth.height_m, rel=SIZE_TOLERANCE)
        assert message["cells"] == truth.cells
        assert message["range_m"] == pytest.approx(truth.range_m, rel=0.05)
        assert 0.0 < message["confidence"] <= 1.0
        jpeg = base64.b64decode(message["crop_jpeg"])
        assert jpeg[:2] == b"\xff\xd8"  # the evidence is a JPEG


def test_the_pilot_is_told_about_each_hole(ran: PassRun) -> None:
    """One STATUSTEXT per hole ("net: hole ~6x4 cm ahead-left at 1.1 m"), or one naming the
    newest and counting the other when both came within damage.notify_interval_s; a text held
    back by that limit goes out when due, with or without frames."""
    assert ran.texts
    told = sum(1 + (1 if text.endswith("(+1)") else 0) for text in ran.texts)
    assert told == 2
    sizes = {f"~{max(1, round(m['width_m'] * 100))}x{max(1, round(m['height_m'] * 100))} cm"
             for m in ran.damages}
    for text in ran.texts:
        assert text.startswith("net: hole ~") and len(text) <= 50
        assert any(size in text for size in sizes), text
        assert math.isfinite(float(text.split(" at ")[1].split(" m")[0]))


class _TextLink:
    def __init__(self) -> None:
        self.texts: list[str] = []

    def notify_pilot(self, text: str, severity: int = 4) -> None:
        self.texts.append(text)


def _hole(hole_id: int) -> ConfirmedHole:
    return ConfirmedHole(
        hole_id=hole_id, t_first=0.0, t_confirmed=0.0, frame_index=0, detections=3, looks=3,
        width_m=0.05, height_m=0.04, cells=4, missing_bars=4, centre_px=(0.0, 0.0),
        box_px=(0.0, 0.0, 1.0, 1.0), plane_xy_m=(0.0, 0.0), point_m=(0.3, 0.0, 1.0),
        range_m=1.04, confidence=0.9)


@pytest.mark.parametrize("interval_s", [5.0, 30.0, 120.0])
def test_a_text_held_back_by_the_rate_limit_is_sent_when_its_turn_comes(
        interval_s: float) -> None:
    """Two holes 10 s apart: with one text per 30 s (a setting --check accepts) the second
    waited 20 s, was taken for stale news (over 15 s) and dropped, with no later text to
    count it in."""
    link = _TextLink()
    notices = PilotNotices(link, interval_s)  # type: ignore[arg-type]
    for k in range(int(10 * (interval_s + 20.0))):
        now = k / 10.0
        if k in (0, 100):
            notices.hole(_hole(1 if k == 0 else 2), now)
        else:
            notices.tick(now)
    assert len(link.texts) == 2 and "(+" not in link.texts[1]


def test_a_text_still_waiting_goes_out_when_the_service_stops() -> None:
    link = _TextLink()
    notices = PilotNotices(link, 5.0)  # type: ignore[arg-type]
    notices.hole(_hole(1), 0.0)
    notices.hole(_hole(2), 1.0)
    notices.flush(1.5)
    assert link.texts == [_hole(1).pilot_text(), _hole(2).pilot_text()]


def test_the_pilots_text_says_where_the_hole_is_for_the_cameras_mounting() -> None:
    """A camera looking down (mavlink.orientation 25, as --check accepts) had its holes said
    "ahead" and "high": below the vehicle, and "high" was forward. Where the camera does not
    look ahead, the place is said in the view's terms, as the pilot sees it on the video."""
    left_high = dataclasses.replace(_hole(1), point_m=(-0.3, -0.4, 1.0))
    centre = dataclasses.replace(_hole(2), point_m=(0.0, 0.0, 1.0))
    for orientation, expected_left_high, expected_centre in (
            (0, "ahead-left high", "ahead"), (25, "below, view top-left", "below"),
            (2, "right, view top-left", "right"), (7, "in view, view top-left", "in view")):
        link = _TextLink()
        notices = PilotNotices(link, 0.0, orientation)  # type: ignore[arg-type]
        notices.hole(left_high, 0.0)
        notices.hole(centre, 1.0)
        assert link.texts == [f"net: hole ~5x4 cm {expected_left_high} at 1.0 m",
                              f"net: hole ~5x4 cm {expected_centre} at 1.0 m"], orientation
        assert all(len(t) <= 50 for t in link.texts)


@pytest.mark.parametrize("facing", ["ahead", "below", "in view", "behind"])
def test_a_pilots_hole_text_fits_without_losing_its_range_or_its_count(facing: str) -> None:
    """Cut at 50 characters, a camera looking down lost the range and the count of holes held
    back: "net: hole ~12x10 cm below, view bottom-right at 1." The text is built to fit: the
    place is said shorter, or not at all, before the size, the range or the count go. Worst
    cases: three-digit sizes, a corner of the view, ten held back."""
    hole = dataclasses.replace(_hole(1), width_m=1.23, height_m=1.17, range_m=12.34,
                               point_m=(0.5, 0.5, 1.0))  # bottom-right of the view
    for more in (0, 2, 10):
        text = hole.pilot_text(facing, more=more)
        assert len(text) <= 50, text
        assert text.startswith("net: hole ~123x117 cm") and "at 12.3 m" in text, text
        assert text.endswith(f" (+{more})" if more else " m"), text
    assert hole.pilot_text("below") == "net: hole ~123x117 cm below BR at 12.3 m"
    assert _hole(1).pilot_text("below") == "net: hole ~5x4 cm below, view right at 1.0 m"


def test_the_daemon_tells_the_pilot_in_the_configured_cameras_terms() -> None:
    clock = FakeClock(100.0)
    config = demo_config("mavlink.orientation=25")
    parts = DaemonParts(source=ScriptedSource([], clock), link=MavlinkLink(MavlinkSettings(
        url="udpout:127.0.0.1:9", allow_simulated=True)), telemetry=ZenohPublisher(
        TelemetrySettings(enabled=False)), notifier=RecordingNotifier(), camera=CAMERA,
        vehicle="pass")
    daemon = Daemon(config, parts, clock=clock, wall_clock=clock.wall)
    try:
        assert daemon.outputs.damage is not None
        assert daemon.outputs.damage.notices.facing == "below"
    finally:
        daemon.close()
