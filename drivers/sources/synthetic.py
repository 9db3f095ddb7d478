"""`synthetic:` frames from the project's net renderer, along a scripted trajectory.

Every frame carries its ground truth (drivers.synthetic_net.GroundTruth: range, distance,
normal, whether the net is in view), so the whole chain can be checked without a vehicle:

    synthetic:                                       defaults below, paced like a camera
    synthetic:?trajectory=approach&near=0.6&far=2.0&period=20
    synthetic:?trajectory=sweep&range=1.5&tilt=30&gap=4-6&seed=3&realtime=0

Trajectories (t = media time in seconds; the mesh also drifts slowly sideways, as it does
past a moving ROV):
  static    range, tilt, tilt_axis and roll fixed.
  approach  range oscillates sinusoidally between far and near (starting far), period `period`;
            tilt fixed.
  sweep     range fixed; tilt swings between -tilt and +tilt about tilt_axis, period `period`.
Defaults: near 0.6, far 2.0, range 1.2 (m); tilt 10 (approach) or 20 (deg); tilt_axis 30, roll 0
(deg); period 20 (s).
Options: width, height (default 960x540: the estimator detects the whole default range at this
size; a frame takes ~0.1-0.2 s to render on one core of the 2-core CI machine), fps (default
5), seed, bar (mesh bar length, m, default 0.025), angle (mesh opening angle, deg, default 90),
style (plain: fixed look; varied: a random underwater look drawn once from the seed),
gap=START-END (no net in view during that interval, for drop-out tests), duration (end after
so many seconds; default endless), loop (with duration: start again), realtime (default 1:
frames become due at `fps`, as from a camera; 0: as fast as they are read), calibration (a
camera file to render with instead of the built-in camera). Rendering happens inside read(),
so one read can take a render time longer than its timeout.

Built-in camera: a 1280x720 reference of 82 deg horizontal field of view (fx = fy = 736 px),
principal point at the centre, mild barrel distortion k1 = -0.06, k2 = 0.012, scaled to the
requested size (the aspect ratio must be 16:9 unless a calibration file is given).
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace

import numpy as np

from drivers.errors import SourceError
from drivers.sources.base import SourceOptions
from drivers.sources.paced import EndOfMediaError, MediaFrame, PacedSource
from drivers.sources.url import SourceUrl, parse_source_url, url_error
from drivers.synthetic_net import NetPose, NetRenderer, SceneStyle
from service.core.camera import CameraModel, load_camera
from service.core.errors import CalibrationError, ConfigError
from service.core.mesh import MeshGeometry

log = logging.getLogger(__name__)

SYNTHETIC_OPTIONS = (
    "width", "height", "fps", "trajectory", "range", "near", "far", "tilt", "tilt_axis", "roll",
    "period", "gap", "seed", "bar", "angle", "style", "duration", "loop", "realtime",
    "calibration",
)  # fmt: skip
TRAJECTORIES = ("approach", "sweep", "static")

BUILTIN_CAMERA = CameraModel(
    width=1280,
    height=720,
    fx=736.0,
    fy=736.0,
    cx=639.5,
    cy=359.5,
    distortion=(-0.06, 0.012, 0.0, 0.0, 0.0),
    name="netpose_synthetic",
)
# Sideways drift of the mesh, in cells per second (x, y).
DRIFT_CELLS_PER_S = (0.11, 0.05)


def builtin_camera(width: int, height: int) -> CameraModel:
    return BUILTIN_CAMERA.scaled_to(width, height)


def rendered_camera(parsed: SourceUrl, default_size: tuple[int, int]) -> CameraModel:
    """The camera a rendering source's URL asks for: its calibration file (scaled to width and
    height when they are given), else the built-in camera at that size or `default_size`."""
    width = parsed.integer("width", None, 64, 8192)
    height = parsed.integer("height", None, 64, 8192)
    if (width is None) != (height is None):
        raise url_error(parsed.raw, "give both width and height, or neither")
    calibration = parsed.options.get("calibration")
    if calibration:
        camera = load_camera(calibration)  # CalibrationError names the file
        return camera if width is None or height is None else camera.scaled_to(width, height)
    try:
        return builtin_camera(width or default_size[0], height or default_size[1])
    except CalibrationError as exc:
        raise url_error(parsed.raw, f"the built-in camera is 16:9 ({exc})") from None


class Trajectory:
    """Pose of the net as a function of time, from the synthetic URL's options."""

    def __init__(self, parsed: SourceUrl) -> None:
        self.kind = parsed.choice("trajectory", "approach", TRAJECTORIES)
        self.near = parsed.number_or("near", 0.6, 0.05, 20.0)
        self.far = parsed.number_or("far", 2.0, 0.05, 20.0)
        self.range = parsed.number_or("range", 1.2, 0.05, 20.0)
        self.tilt = parsed.number_or("tilt", 20.0 if self.kind != "approach" else 10.0, 0.0, 70.0)
        self.axis = parsed.number_or("tilt_axis", 30.0, -360.0, 360.0)
        self.roll = parsed.number_or("roll", 0.0, -360.0, 360.0)
        self.period = parsed.number_or("period", 20.0, 0.5, 3600.0)
        if self.kind == "approach" and not self.near < self.far:
            raise url_error(parsed.raw, "option near must be less than far")

    def pose_at(self, t: float) -> NetPose:
        w = 2.0 * math.pi * t / self.period
        range_m, tilt = self.range, self.tilt
        if self.kind == "approach":
            mid, amp = 0.5 * (self.near + self.far), 0.5 * (self.far - self.near)
            range_m = mid + amp * math.cos(w)
        elif self.kind == "sweep":
            tilt = self.tilt * math.sin(w)
        return NetPose(
            range_m=range_m,
            tilt_deg=tilt,
            tilt_axis_deg=self.axis,
            roll_deg=self.roll,
            phase=(DRIFT_CELLS_PER_S[0] * t, DRIFT_CELLS_PER_S[1] * t),
        )


class SyntheticSource(PacedSource):
    """Rendered frames of a net moving along a scripted trajectory, with ground truth."""

    def __init__(self, url: str, options: SourceOptions | None = None) -> None:
        parsed = parse_source_url(url)
        if parsed.scheme != "synthetic":
            raise url_error(url, "not a synthetic: URL")
        parsed.check_options(SYNTHETIC_OPTIONS)
        super().__init__(
            url, options, loop=parsed.flag("loop", False), realtime=parsed.flag("realtime", True)
        )
        fps = parsed.number_or("fps", 5.0, 0.1, 240.0)
        seed = parsed.integer_or("seed", 0, 0, 2**31 - 1)
        bar = parsed.number_or("bar", 0.025, 0.001, 1.0)
        angle = parsed.number_or("angle", 90.0, 20.0, 160.0)
        self._fps, self.seed = fps, seed
        self.duration_s = parsed.number("duration", None, 0.01, 1e7)
        self.gap_s = parsed.interval("gap")
        self.trajectory = Trajectory(parsed)
        self.style_name = parsed.choice("style", "plain", ("plain", "varied"))
        try:
            self.mesh = MeshGeometry(bar, angle)
        except ConfigError as exc:
            raise url_error(url, exc.problem) from None
        self._camera = rendered_camera(parsed, (960, 540))
        self._renderer: NetRenderer | None = None
        self._style: SceneStyle | None = None
        self._number = 0

    @property
    def rendered(self) -> bool:
        return True

    @property
    def camera(self) -> CameraModel:
        return self._camera

    @property
    def frame_period_s(self) -> float:
        return 1.0 / self._fps

    def _start(self) -> None:
        try:
            self._renderer = NetRenderer(self._camera, self.mesh, seed=self.seed)
        except Exception as exc:  # the renderer is ours: say so rather than crash the caller
            raise SourceError(self.url, f"the renderer cannot start: {exc!r}") from exc
        if self.style_name == "varied":
            self._style = SceneStyle.varied(np.random.default_rng([self.seed, 1]))
        else:
            self._style = SceneStyle()
        self._number = 0

    def net_in_view(self, t: float) -> bool:
        return self.gap_s is None or not self.gap_s[0] <= t < self.gap_s[1]

    def _next_media(self) -> MediaFrame:
        renderer, style = self._renderer, self._style
        if renderer is None or style is None:
            raise EndOfMediaError
        number = self._number
        t = number / self._fps
        if self.duration_s is not None and t >= self.duration_s:
            raise EndOfMediaError
        self._number += 1
        # One generator per frame number: frame n is the same whatever was skipped before it.
        rng = np.random.default_rng([self.seed, 2, number])
        if not self.net_in_view(t):
            style = replace(style, net_present=False)
        image, truth = renderer.render(self.trajectory.pose_at(t), rng=rng, style=style)
        return MediaFrame(image=image, number=number, media_time_s=t, truth=truth)

    def _skip_to(self, number: int) -> int:
        if self.duration_s is not None:
            number = min(number, math.ceil(self.duration_s * self._fps))
        skipped = max(0, number - self._number)
        self._number += skipped
        return skipped

    def _rewind(self) -> None:
        self._number = 0

    def _stop(self) -> None:
        self._renderer = None
