"""`netpose replay`: run the estimator over a recording and write what it saw.

    netpose replay dive.mp4 --calibration camera.yaml --mesh-size 0.025 --out dive-replay/

Writes to the output folder: estimates.csv (one row per processed frame), annotated.mp4 (each
frame with ROIs, mesh cells, the back-projected net axes and the distance), summary.json and
PNG plots. Frames come from drivers.sources, so INPUT is a video file, an image folder or any
frame-source URL. Ctrl-C (or SIGTERM) stops after the frame in hand and still writes a valid
video, summary and plots for what was processed (exit status 130).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import logging
import math
import os
import platform
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import cv2
import numpy as np
import numpy.typing as npt

from drivers.sources import FrameSource, SourceOptions, SourceState, open_source
from drivers.sources.files import ImageFolderSource
from drivers.sources.recording import RecordingSource, is_recording
from service import __version__
from service.core.camera import CameraModel, load_camera
from service.core.damage import DamageSettings
from service.core.damage_track import NetInspector
from service.core.errors import ConfigError, NetposeError
from service.core.estimator import EstimatorSettings, NetEstimator
from service.core.mesh import MeshGeometry
from service.core.redact import redact_text
from service.core.scale import (
    DEFAULT_BAR_LENGTH_TOLERANCE,
    DEFAULT_FOCAL_TOLERANCE,
    scale_sigma_fraction,
)
from service.core.state_io import to_plain
from service.core.tracking import FilterSettings, NetTracker
from service.daemon.wiring import load_daemon_config
from service.pipeline import AutopilotDistance, Pipeline
from service.signals import SignalFlags, handle_signals
from service.tools.annotate import FrameAnnotator
from service.tools.damage_report import (
    CONTACT_SHEET,
    CROPS_DIR,
    DAMAGE_CSV,
    DamageCsv,
    hole_label,
    write_contact_sheet,
)
from service.tools.replay import (
    PLOT_FILES,
    EstimatesCsv,
    FrameResult,
    ReplayFrame,
    ReplayRunner,
    ReplayStats,
    Truth,
    load_truth_csv,
    truth_from_object,
    write_json,
    write_plots,
)

log = logging.getLogger(__name__)

# What a replay that found no hole must say beside its count: "0 holes" went into a farm's
# report as "net inspected, no holes" for a fouled net whose four holes were all missed.
NO_PROOF = ("no hole found is no proof of an intact net: holes are missed, most on fouled "
            "twine (docs/inspection.md, Limits)")

EXIT_INTERRUPTED = 130
DEFAULT_VIDEO_WIDTH = 1280
DEFAULT_IMAGE_FPS = 10.0
# How long one read waits; a live source that stays silent longer is reported (once).
READ_TIMEOUT_S = 1.0
VIDEO_NAME = "annotated.mp4"
FALLBACK_VIDEO_NAME = "annotated.avi"


def add_parser(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "replay",
        help="evaluate a recording: estimates CSV, annotated video, summary and plots",
        description=(
            "Run the net estimator (and with --filter the tracking filter) over every frame of "
            "a recording and write estimates.csv, annotated.mp4, summary.json and PNG plots to "
            "the output folder, and the holes found in the net to damage.csv with a contact "
            "sheet of their evidence (damage.png). With ground truth (synthetic: source, or "
            "--truth CSV) the summary and plots include the error against it."
        ),
    )
    p.add_argument(
        "input", metavar="INPUT",
        help="video file, image folder, or frame-source URL (file:, images:, synthetic:, "
        "rtsp://, ...)",
    )
    p.add_argument("--calibration", type=Path, default=None, metavar="CAMERA.yaml",
                   help="camera calibration (ROS camera_info YAML or OpenCV FileStorage); "
                   "required unless INPUT is a netpose recording, which brings its own")
    p.add_argument("--mesh-size", type=float, default=None, metavar="M",
                   help="mesh bar length knot to knot in metres (side of a square mesh); "
                   "required unless INPUT is a netpose recording")
    p.add_argument("--opening-angle", type=float, default=None, metavar="DEG",
                   help="mesh opening angle in degrees (default 90: square mesh, or the "
                   "recording's)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="output folder (created; files of an earlier replay are replaced)")
    p.add_argument("--filter", action="store_true",
                   help="also run the tracking filter and write its output")
    p.add_argument("--every", type=int, default=1, metavar="N",
                   help="process every N-th frame only (default 1: all)")
    p.add_argument("--independent", action="store_true",
                   help="estimate every frame on its own, without the previous detection as "
                   "its prior (a folder of stills, per-frame evaluations: what `netpose "
                   "estimate` gives); by default frames are a sequence, tracked as the daemon "
                   "tracks them")
    p.add_argument("--truth", type=Path, default=None, metavar="CSV",
                   help="ground truth per frame number (columns frame, range_m, distance_m, "
                   "nx, ny, nz, net_present; see docs/replay.md)")
    p.add_argument("--max-frames", type=int, default=None, metavar="N",
                   help="stop after N processed frames (needed for endless sources)")
    p.add_argument("--fps", type=float, default=None,
                   help=f"frame rate of an image folder (default {DEFAULT_IMAGE_FPS:g}), or of a "
                   "video that does not state one")
    p.add_argument("--config", type=Path, default=None, metavar="FILE",
                   help="netpose configuration whose [estimator], [filter] and [damage] "
                   "tuning, autopilot distance and scale tolerances to use")
    p.add_argument("--video-width", type=int, default=DEFAULT_VIDEO_WIDTH, metavar="PX",
                   help=f"annotated video at most this wide (default {DEFAULT_VIDEO_WIDTH})")
    p.add_argument("--no-video", action="store_true", help="do not write the annotated video")
    p.add_argument("--no-timing", action="store_true",
                   help="leave out what is measured in time (process_ms, the summary's speed): "
                        "two replays of the same input then give byte-identical CSV and summary")
    p.add_argument("--no-damage", action="store_true",
                   help="do not inspect the net for holes (no damage.csv, damage.png, marks)")
    p.add_argument("--progress", choices=("auto", "on", "off"), default="auto",
                   help="progress bar on stderr (auto: when stderr is a terminal)")
    p.set_defaults(handler=run)


# -- input ----------------------------------------------------------------------------------
def source_url(text: str, fps: float | None) -> str:
    """The frame-source URL for INPUT: a folder -> images:, a file -> file:, URLs as given.

    A synthetic: URL is read as fast as the replay goes (realtime=0) unless it says otherwise.
    """
    path = Path(text).expanduser()
    if is_recording(path):
        return f"recording:{path}"  # its own capture times; --fps does not apply
    if path.is_dir():
        rate = fps if fps is not None else DEFAULT_IMAGE_FPS
        return f"images:{path}?fps={rate:g}"
    if path.is_file():
        return f"file:{path}" + (f"?fps={fps:g}" if fps is not None else "")
    scheme = text.partition(":")[0]
    if "://" in text or scheme in ("file", "images", "synthetic", "v4l2", "sdp", "recording"):
        if scheme == "synthetic" and "realtime=" not in text:
            return text + ("&" if "?" in text else "?") + "realtime=0"
        return text
    if text.startswith("/dev/"):
        return text
    raise NetposeError(f"{text}: no such file or folder, and not a frame-source URL")


def _open_source(url: str, keep_color: bool) -> FrameSource:
    try:
        return open_source(url, SourceOptions(keep_color=keep_color))
    except ConfigError as exc:
        # URL mistakes name the daemon's configuration key; here the URL is the INPUT argument.
        raise NetposeError(f"INPUT: {exc.problem}") from None


def _frame_count(source: FrameSource) -> int | None:
    """Frames in a recording, when it is cheap to know (image folder, video file)."""
    files = getattr(source, "files", None)
    if isinstance(files, list):
        return len(files)
    count, _ = _container_says(source)
    return None if count is None else int(count)


def _container_says(source: FrameSource) -> tuple[float | None, float | None]:
    """A video file's frame count and duration (s) as its container states them (Matroska
    and MPEG-TS: estimated from the duration and the rate); None where it does not say."""
    path = getattr(source, "path", None)
    if not (isinstance(path, Path) and path.is_file()):
        return None, None
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            return None, None
        count = float(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        fps = float(cap.get(cv2.CAP_PROP_FPS))
    finally:
        cap.release()
    if not (math.isfinite(count) and count > 0):
        return None, None
    return count, count / fps if math.isfinite(fps) and fps > 0 else None


def _ended_early(source: FrameSource, summary: dict[str, Any], every: int
                 ) -> tuple[float | None, bool]:
    """The duration the file states, and whether the frames read (every `every`-th) ended well
    before it (a file cut short: a card that filled, power lost, a copy interrupted): by more
    than two of the replay's steps and 5 % of it. A variable rate's stated count is an
    estimate; its duration is not."""
    _, stated = _container_says(source)
    duration = summary.get("duration_s")
    if stated is None or not isinstance(duration, float | int):
        return stated, False
    period = getattr(source, "frame_period_s", None)  # a file's (paced sources)
    if not isinstance(period, float) or period <= 0.0:
        return stated, False
    step = every * period
    return stated, duration + step < 0.95 * stated - 2.0 * step


def replay_frames(
    source: FrameSource, every: int, stop: threading.Event
) -> Iterator[ReplayFrame]:
    """ReplayFrames from an opened source until it ends or `stop` is set.

    Every `every`-th frame by the source's frame numbers (so frames the source could not
    decode do not shift the choice), of a netpose recording every `every`-th frame it holds;
    times are relative to the first frame read.
    """
    t0: float | None = None
    next_index = 0
    waiting_logged = False
    # An image folder's files, in the order it reads them (frame n is file n). Only a folder:
    # a recording's frame numbers are the vehicle's, with gaps, not positions in its list.
    files: list[Path] = source.files if isinstance(source, ImageFolderSource) else []
    # A recording holds the frames the vehicle processed, its numbers with gaps where it
    # skipped some: every N-th of them, not every N-th number (which kept 98 of 130 frames at
    # steps of 2-4 for --every 2: research review).
    by_row = isinstance(source, RecordingSource)
    rows = 0
    while not stop.is_set():
        frame = source.read(READ_TIMEOUT_S)
        if frame is None:
            if source.state in (SourceState.ENDED, SourceState.CLOSED):
                return
            if not waiting_logged:
                log.warning("no frame from the source for %.0f s (%s), still waiting",
                            READ_TIMEOUT_S, source.state.value)
                waiting_logged = True
            continue
        waiting_logged = False
        if by_row:
            rows += 1
            if (rows - 1) % every:
                continue
        elif frame.index < next_index:
            continue
        next_index = frame.index + every
        if t0 is None:
            t0 = frame.t_monotonic
        yield ReplayFrame(
            image=frame.image,
            index=frame.index,
            time_s=round(frame.t_monotonic - t0, 6),
            t_capture=frame.t_monotonic,
            color=frame.color,
            truth=truth_from_object(frame.truth),
            budget=frame.budget or 0,
            measured=frame.measured,
            inspected=frame.inspected,
            source_file=files[frame.index].name if frame.index < len(files) else "",
            # A recording's own wall-clock capture time (a video's or a folder's would be the
            # replay's own clock: not given).
            t_unix=frame.t_wall if getattr(source, "wall_clock_recorded", False) else None,
        )


# -- progress -------------------------------------------------------------------------------
class RateProgress:
    """`replay [#####.....] 12/30 40%  8.3 fps  ETA 0:02` redrawn in place on a stream.

    Without a known total: `replay 12 frames  8.3 fps`. Redraws at most 5 times a second.
    """

    def __init__(self, total: int | None, stream: TextIO, label: str = "replay",
                 width: int = 24) -> None:
        self._total = total
        self._stream = stream
        self._label = label
        self._width = width
        self._start = time.monotonic()
        self._last_draw = -math.inf
        self._drawn = False

    def update(self, done: int, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._last_draw < 0.2:
            return
        self._last_draw = now
        elapsed = max(now - self._start, 1e-9)
        rate = done / elapsed
        if self._total:
            fraction = min(1.0, done / self._total)
            filled = round(self._width * fraction)
            bar = "#" * filled + "." * (self._width - filled)
            eta = (self._total - done) / rate if rate > 0 else math.inf
            text = (f"{self._label} [{bar}] {done}/{self._total} {100 * fraction:3.0f}%  "
                    f"{rate:.1f} fps  ETA {_clock(eta)}")
        else:
            text = f"{self._label} {done} frames  {rate:.1f} fps  {_clock(elapsed)} elapsed"
        self._stream.write("\r" + text + "\x1b[K")
        self._stream.flush()
        self._drawn = True

    def close(self) -> None:
        if self._drawn:
            self._stream.write("\n")
            self._stream.flush()
            self._drawn = False


def _clock(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "?"
    s = round(seconds)
    if s >= 3600:
        return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"
    return f"{s // 60}:{s % 60:02d}"


# -- outputs ----------------------------------------------------------------------------------
class AnnotatedVideo:
    """annotated.mp4 (MPEG-4 Part 2, which every OpenCV build with FFmpeg writes), opened at
    the first frame; falls back to MJPG in annotated.avi if that writer is unavailable."""

    def __init__(self, out_dir: Path, fps: float) -> None:
        self._dir = out_dir
        self._fps = fps
        self._writer: Any = None
        self._size: tuple[int, int] | None = None
        self.path: Path | None = None
        self.frames = 0

    def write(self, image: npt.NDArray[np.uint8]) -> None:
        h, w = image.shape[:2]
        if self._writer is None:
            self._open(w, h)
        assert self._size is not None
        if (w, h) != self._size:
            image = np.asarray(cv2.resize(image, self._size, interpolation=cv2.INTER_AREA),
                               dtype=np.uint8)
        self._writer.write(image)
        self.frames += 1

    def _open(self, width: int, height: int) -> None:
        # Even sizes: some encoders refuse odd ones.
        size = (width - width % 2, height - height % 2)
        for name, fourcc in ((VIDEO_NAME, "mp4v"), (FALLBACK_VIDEO_NAME, "MJPG")):
            path = self._dir / name
            writer = cv2.VideoWriter(str(path), _fourcc(fourcc), self._fps, size)
            if writer.isOpened():
                if name != VIDEO_NAME:
                    log.warning("this OpenCV cannot write MPEG-4; annotated video is %s", name)
                self._writer, self._size, self.path = writer, size, path
                return
            writer.release()
            path.unlink(missing_ok=True)
        raise NetposeError("OpenCV can write neither MPEG-4 nor MJPG video here (use --no-video)")

    def close(self) -> None:
        if self._writer is not None:
            self._writer.release()  # writes the index: the file is playable from here on
            self._writer = None


def _fourcc(code: str) -> int:
    """cv2.VideoWriter_fourcc without depending on where each OpenCV version exposes it."""
    return sum(ord(c) << (8 * i) for i, c in enumerate(code))


@dataclass
class ReplayRun:
    """What one replay produced, for the summary."""

    frames_read: int = 0
    interrupted: bool = False
    stop_reason: str = ""
    outputs: list[str] = field(default_factory=list)
    holes: int | None = None  # confirmed holes in the net (None: inspection off)
    # How much of the net was looked at: frames searched for holes and the cells whose bars
    # were judged in them (with overlaps): no hole reported is no proof of an intact net.
    inspected_frames: int = 0
    judged_cells: int = 0
    # Bars sampled in the inspected frames, and those clear enough to show a missing one.
    bars_sampled: int = 0
    bars_judgeable: int = 0
    first_frame_unix: float | None = None  # the first frame's capture on the wall clock

    @property
    def judgeable_share(self) -> float | None:
        return self.bars_judgeable / self.bars_sampled if self.bars_sampled else None


def run(args: argparse.Namespace) -> int:
    if args.every < 1:
        raise ConfigError("--every", f"must be at least 1, got {args.every}")
    if args.max_frames is not None and args.max_frames < 1:
        raise ConfigError("--max-frames", f"must be at least 1, got {args.max_frames}")
    if args.fps is not None and not (math.isfinite(args.fps) and 0.01 <= args.fps <= 1000):
        raise ConfigError("--fps", f"must be 0.01..1000, got {args.fps}")
    if args.video_width < 16:
        raise ConfigError("--video-width", f"must be at least 16 px, got {args.video_width}")
    _recording_defaults(args)
    args.git_commit = _git_commit()  # the code that runs, before it runs
    camera = load_camera(args.calibration)
    try:
        mesh = MeshGeometry(args.mesh_size, args.opening_angle)
    except ConfigError as exc:
        option = "--mesh-size" if exc.key.endswith("bar_length_m") else "--opening-angle"
        raise ConfigError(option, exc.problem) from None
    _forget_state_at_another_scale(args, camera, mesh)
    tuning = _tuning(args.config, mesh.bar_length_m)
    truth = load_truth_csv(args.truth) if args.truth is not None else None
    url = source_url(args.input, args.fps)
    write_video = not args.no_video
    with _open_source(url, keep_color=write_video) as source:
        total = _frame_count(source)
        if total is not None:
            total = -(-total // args.every)
            if args.max_frames is not None:
                total = min(total, args.max_frames)
        try:
            return _replay(args, source, url, camera, mesh, tuning, truth, total)
        except OSError as exc:  # a full disk, an output name taken by a folder: one line
            raise NetposeError(f"{exc.filename or args.out}: {exc.strerror or exc}") from None


def _recording_defaults(args: argparse.Namespace) -> None:
    """A netpose recording (drivers/recorder.py) brings its calibration, mesh and tuning:
    options not given on the command line are taken from it, so the replay runs what the
    vehicle ran."""
    folder = Path(args.input).expanduser()
    recording = is_recording(folder)
    if recording:
        try:
            manifest = json.loads((folder / "recording.json").read_text(encoding="utf-8"))
            mesh = manifest["mesh"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise NetposeError(f"{folder}: recording.json is damaged ({exc})") from None
        args.recording = _recording_word(folder, manifest)
        args.recorded_scale = (folder / str(manifest.get("camera", "camera.yaml")),
                               float(mesh["bar_length_m"]), float(mesh["opening_angle_deg"]))
        if args.calibration is None:
            args.calibration = folder / str(manifest.get("camera", "camera.yaml"))
        if args.mesh_size is None:
            args.mesh_size = float(mesh["bar_length_m"])
        if args.opening_angle is None:
            args.opening_angle = float(mesh["opening_angle_deg"])
        tuning = folder / str(manifest.get("tuning", "netpose.toml"))
        if args.config is None and tuning.is_file():
            args.config = tuning
        state = folder / str(manifest.get("pipeline_state", "pipeline_state.json"))
        if state.is_file() and args.every == 1:
            try:
                args.pipeline_state = json.loads(state.read_text(encoding="utf-8"))["pipeline"]
                if not (isinstance(args.pipeline_state, dict)
                        and {"tracker", "prior"} <= args.pipeline_state.keys()):
                    raise ValueError("not a pipeline's state")
            except (OSError, ValueError, KeyError, TypeError) as exc:
                raise NetposeError(f"{state}: damaged ({exc})") from None
        elif args.every == 1:
            print(f"netpose replay: warning: {folder} has no {state.name}: the replay starts "
                  "without the vehicle's filter and prior, so its first frames may differ",
                  file=sys.stderr)
        args.recording["state_restored"] = getattr(args, "pipeline_state", None) is not None
    for option, value in (("--calibration", args.calibration), ("--mesh-size", args.mesh_size)):
        if value is None:
            raise ConfigError(option, "required (unless INPUT is a netpose recording)")
    if args.opening_angle is None:
        args.opening_angle = 90.0


def _forget_state_at_another_scale(args: argparse.Namespace, camera: CameraModel,
                                   mesh: MeshGeometry) -> None:
    """A recording's filter track and prior hold distances at the scale the vehicle ran with.
    Replayed with another mesh or calibration ("what if the mesh were 27.5 mm?"), restoring them
    rejected the first correct measurements at the new scale and kept the old scale's filtered
    distance valid beside them: one CSV of two scales. The replay then starts afresh, as the
    daemon resets its track when the mesh changes (`Pipeline.replace_estimator`)."""
    recorded = getattr(args, "recorded_scale", None)
    if recorded is None or getattr(args, "pipeline_state", None) is None:
        return
    camera_file, bar_m, angle_deg = recorded
    changed = []
    if not math.isclose(mesh.bar_length_m, bar_m, rel_tol=1e-9):
        changed.append(f"--mesh-size {mesh.bar_length_m:g} m (recorded {bar_m:g} m)")
    if not math.isclose(mesh.opening_angle_deg, angle_deg, rel_tol=1e-9):
        changed.append(f"--opening-angle {mesh.opening_angle_deg:g} (recorded {angle_deg:g})")
    try:
        same_lens = _same_lens(camera, load_camera(camera_file))
    except (OSError, NetposeError):  # no readable camera.yaml: the given one is all there is
        same_lens = True
    if not same_lens:
        changed.append(f"--calibration {args.calibration} (not the recording's {camera_file.name})")
    if not changed:
        return
    args.pipeline_state = None
    args.recording["state_restored"] = False
    print(f"netpose replay: {'; '.join(changed)}: the vehicle's filter track and prior are at "
          "the recording's scale, so the replay starts without them", file=sys.stderr)


def _same_lens(a: CameraModel, b: CameraModel) -> bool:
    numbers = (a.fx, a.fy, a.cx, a.cy, *a.distortion), (b.fx, b.fy, b.cx, b.cy, *b.distortion)
    return ((a.width, a.height) == (b.width, b.height) and len(a.distortion) == len(b.distortion)
            and all(math.isclose(x, y, rel_tol=1e-9, abs_tol=1e-12)
                    for x, y in zip(*numbers, strict=True)))


def _recording_word(folder: Path, manifest: dict[str, Any]) -> dict[str, Any]:
    """What the recording says of itself (frames its writer dropped, finished or not, why it
    stopped), said when a replay of it may differ from what the vehicle decided: the
    vehicle's filter ran over frames the recording does not hold."""
    dropped = manifest.get("dropped")
    started = manifest.get("started_unix")
    word = {"dropped": dropped if isinstance(dropped, int) else None,
            "started_unix": started if isinstance(started, int | float) else None,
            "finished": manifest.get("finished") is True,
            "stopped_because": str(manifest.get("stopped_because") or "") or None}
    problems = []
    if word["dropped"]:
        problems.append(f"its writer dropped {word['dropped']} frames")
    if not word["finished"]:
        problems.append("it was never finished (the daemon stopped, the power went or the "
                        "card filled before its manifest was written)")
    if word["stopped_because"]:
        problems.append(f"it stopped because {word['stopped_because']}")
    if problems:
        print(f"netpose replay: warning: {folder.name}: {'; '.join(problems)}: the vehicle's "
              "filter ran over frames this replay does not have, so it may differ from what "
              "the vehicle decided after them", file=sys.stderr)
    return word


@dataclass(frozen=True)
class Tuning:
    """What a daemon configuration sets that changes the pipeline's output."""

    estimator: EstimatorSettings | None = None
    filter: FilterSettings | None = None
    autopilot_distance: AutopilotDistance = "optical_axis"
    damage: DamageSettings | None = None
    scale_sigma_fraction: float = scale_sigma_fraction(DEFAULT_BAR_LENGTH_TOLERANCE,
                                                       DEFAULT_FOCAL_TOLERANCE)


def _tuning(path: Path | None, mesh_size: float) -> Tuning:
    """[estimator], [filter], service.autopilot_distance and the scale's tolerances of a daemon
    configuration file (the rest is not used: the mesh and the calibration come from the
    command line, the source from INPUT)."""
    if path is None:
        return Tuning()
    # A configuration may leave the mesh or the camera to be set, or name a calibration file of
    # the vehicle that is not here: none of that matters to the replay (INPUT is the source).
    config = load_daemon_config(str(path), [f"mesh.bar_length_m={mesh_size!r}",
                                            "camera.url=replay-input"], check_files=False)
    return Tuning(config.estimator, config.filter, config.service.autopilot_distance,
                  config.damage, config.scale_sigma_fraction)


def _replay(
    args: argparse.Namespace,
    source: FrameSource,
    url: str,
    camera: CameraModel,
    mesh: MeshGeometry,
    tuning: Tuning,
    truth: dict[int, Truth] | None,
    total: int | None,
) -> int:
    if args.out.exists() and not args.out.is_dir():
        # Said before the first frame is estimated, not after.
        raise NetposeError(f"--out {args.out}: exists and is not a folder")
    _check_output_names(args.out)
    # The daemon's pipeline, as the daemon builds it: the filter always runs (its output is
    # written with --filter), so the estimates are the ones the vehicle would have made.
    pipeline = Pipeline(NetEstimator(camera, mesh, tuning.estimator),
                        NetTracker(tuning.filter or FilterSettings()),
                        tuning.autopilot_distance, _inspector(args, camera, mesh, tuning),
                        scale_sigma_fraction=tuning.scale_sigma_fraction,
                        independent=args.independent)
    state = getattr(args, "pipeline_state", None)
    if state is not None:
        # A recording started mid-dive: continue from the daemon's filter and prior.
        try:
            pipeline.restore(state)
        except (KeyError, TypeError, ValueError) as exc:
            raise NetposeError(f"{args.input}: pipeline_state.json is damaged ({exc!r})") from None
    runner = ReplayRunner(pipeline, keep_track=args.filter, truth=truth)
    show = args.progress == "on" or (args.progress == "auto" and sys.stderr.isatty())
    progress = RateProgress(total, sys.stderr) if show else None
    fps = _video_fps(source, args.every)
    annotator = None if args.no_video else FrameAnnotator(camera, width=args.video_width)
    stats = ReplayStats()
    replayed: list[int] = []
    outcome = ReplayRun()
    out_dir: Path = args.out
    csv_file: EstimatesCsv | None = None
    video: AnnotatedVideo | None = None
    damage_csv: DamageCsv | None = None

    with handle_signals(SignalFlags()) as stop:
        frames = replay_frames(source, args.every, stop.stop)
        try:
            for result in runner.run(frames):
                if csv_file is None:
                    # The first frame was accepted: only now is there something to write.
                    try:
                        out_dir.mkdir(parents=True, exist_ok=True)
                    except OSError as exc:
                        raise NetposeError(
                            f"--out {out_dir}: cannot create it ({exc.strerror or exc})") from None
                    _remove_stale_outputs(out_dir)
                    csv_file = EstimatesCsv(out_dir / "estimates.csv", timing=not args.no_timing)
                    video = None if annotator is None else AnnotatedVideo(out_dir, fps)
                    if pipeline.inspector is not None:
                        damage_csv = DamageCsv(out_dir, mesh.bar_length_m)
                report = result.result.damage
                if report is not None and report.inspected:
                    outcome.inspected_frames += 1
                    if report.scan is not None:
                        outcome.judged_cells += report.scan.inspected_cells
                        outcome.bars_sampled += report.scan.bars_sampled
                        outcome.bars_judgeable += report.scan.bars_judgeable
                if damage_csv is not None and report is not None:
                    for hole in report.confirmed:
                        # Said as it is found, as the daemon says it: a long replay's holes
                        # were known only from the files at its end.
                        log.info("replay: %s (%d cells), %s at %.2f m, frame %d (%.1f s), "
                                 "confidence %.2f", hole_label(hole), hole.cells, hole.bearing,
                                 hole.range_m, result.frame.index, result.frame.time_s,
                                 hole.confidence)
                        damage_csv.write(hole, result.frame.index, result.frame.time_s,
                                         result.frame.t_unix)
                if video is not None and annotator is not None:
                    video.write(_annotated(annotator, result))
                csv_file.write(result)
                if outcome.first_frame_unix is None:
                    outcome.first_frame_unix = result.frame.t_unix
                replayed.append(result.frame.index)
                stats.add(result)
                outcome.frames_read += 1
                if progress is not None:
                    progress.update(outcome.frames_read)
                if args.max_frames is not None and outcome.frames_read >= args.max_frames:
                    break
        except KeyboardInterrupt:
            stop.request_stop("SIGINT")
        finally:
            stats.finish()
            if progress is not None:
                progress.update(outcome.frames_read, force=True)
                progress.close()
            if video is not None:
                video.close()
            if csv_file is not None:
                csv_file.close()
            if damage_csv is not None:
                damage_csv.close()
        if stop.stop.is_set():
            outcome.interrupted = True
            outcome.stop_reason = stop.stop_signal or "stopped"

    if csv_file is None:
        if outcome.interrupted:
            print("netpose replay: interrupted before the first frame; nothing written",
                  file=sys.stderr)
            return EXIT_INTERRUPTED
        raise NetposeError(f"{args.input}: no frame could be read")
    outcome.outputs = ["estimates.csv"]
    if video is not None and video.path is not None:
        outcome.outputs.append(video.path.name)
    if damage_csv is not None:
        outcome.outputs.append(DAMAGE_CSV)
        outcome.holes = len(damage_csv.holes)
        if write_contact_sheet(damage_csv.holes, out_dir) is not None:
            outcome.outputs += [CONTACT_SHEET, f"{CROPS_DIR}/"]
    if truth:
        # With --every or --max-frames some rows have no frame by design: said only if none
        # matched at all.
        whole = args.every == 1 and args.max_frames is None and not outcome.interrupted
        _say_unmatched_truth(args.truth, truth, replayed, whole)
    doubt = stats.truth_scale_doubt()
    if doubt:
        print(f"netpose replay: warning: --truth {args.truth or ''}: {doubt}", file=sys.stderr)
    _finish(args, url, stats, outcome, out_dir, source, _provenance(args, camera, tuning))
    if outcome.interrupted:
        print(f"netpose replay: stopped by {outcome.stop_reason} after {outcome.frames_read} "
              f"frames; outputs in {out_dir} cover those frames", file=sys.stderr)
        return EXIT_INTERRUPTED
    return 0


def _say_unmatched_truth(path: Path | None, truth: dict[int, Truth], replayed: list[int],
                         whole: bool) -> None:
    """Truth rows for frames the replay never had are said, not dropped without a word (a
    recording numbers its frames from the daemon's count, not from 0)."""
    unmatched = sorted(set(truth) - set(replayed))
    if not unmatched or not replayed or (len(unmatched) < len(truth) and not whole):
        return
    print(f"netpose replay: warning: {len(unmatched)} of {len(truth)} rows of {path} match no "
          f"replayed frame (they name frames {unmatched[0]}..{unmatched[-1]}; the replayed "
          f"frames are {min(replayed)}..{max(replayed)})", file=sys.stderr)


def _annotated(annotator: FrameAnnotator, result: FrameResult) -> npt.NDArray[np.uint8]:
    frame = result.frame
    return annotator.annotate(
        frame.color if frame.color is not None else frame.image,
        result.estimate,
        track=result.track,
        truth=result.truth,
        label=f"frame {frame.index}  t={frame.time_s:.2f} s",
        refused=result.error,
        damage=result.result.damage,
    )


def _inspector(args: argparse.Namespace, camera: CameraModel, mesh: MeshGeometry,
               tuning: Tuning) -> NetInspector | None:
    """Net inspection as the daemon does it, on every tracked frame (offline there is no time
    budget; a configuration's `every_n_frames` is kept), unless --no-damage or the
    configuration switches it off."""
    settings = tuning.damage or DamageSettings()
    if getattr(args, "no_damage", False) or not settings.enabled:
        return None
    if settings.every_n_frames == 0:
        settings = dataclasses.replace(settings, every_n_frames=1)
    return NetInspector(camera, mesh, settings)


def _video_fps(source: FrameSource, every: int) -> float:
    period = getattr(source, "frame_period_s", None)
    fps = 1.0 / period if isinstance(period, float) and period > 0 else 10.0
    return max(0.5, min(120.0, fps / every))


def _check_output_names(out_dir: Path) -> None:
    """Each name the replay writes in `out_dir`, if taken, is taken by its own kind (a file,
    or the crops' folder): checked before the first frame, not found out at the first hole."""
    files = ("estimates.csv", "summary.json", VIDEO_NAME, FALLBACK_VIDEO_NAME, *PLOT_FILES,
             DAMAGE_CSV, CONTACT_SHEET)
    for name in files:
        if (out_dir / name).is_dir():
            raise NetposeError(f"{out_dir / name}: a folder where the replay writes a file")
    crops = out_dir / CROPS_DIR
    if crops.exists() and not crops.is_dir():
        raise NetposeError(f"{crops}: a file where the replay writes its folder of hole crops")


def _remove_stale_outputs(out_dir: Path) -> None:
    """Files an earlier replay left there would be mistaken for this one's."""
    for name in ("estimates.csv", "summary.json", VIDEO_NAME, FALLBACK_VIDEO_NAME, *PLOT_FILES,
                 DAMAGE_CSV, CONTACT_SHEET):
        (out_dir / name).unlink(missing_ok=True)
    crops = out_dir / CROPS_DIR
    if crops.is_dir():
        for png in crops.glob("hole_*.png"):
            png.unlink()


def _provenance(args: argparse.Namespace, camera: CameraModel, tuning: Tuning
                ) -> dict[str, Any]:
    """What made this replay's numbers, so that two runs can be told apart and one repeated: a
    default, a tuned and a recalibrated run of one recording had the same description (the
    calibration by its path only, a file saved over it undetectable), and the version has been
    0.1.0 for hundreds of commits (research review)."""
    effective = {
        "estimator": to_plain(tuning.estimator or EstimatorSettings()),
        "filter": to_plain(tuning.filter or FilterSettings()),
        "damage": to_plain(tuning.damage or DamageSettings()),
        "autopilot_distance": tuning.autopilot_distance,
        "scale_sigma_fraction": tuning.scale_sigma_fraction,
    }
    canonical = json.dumps(effective, sort_keys=True, separators=(",", ":"))
    try:
        calibration_sha = hashlib.sha256(Path(args.calibration).read_bytes()).hexdigest()
    except OSError:
        calibration_sha = None
    return {
        "tuning": {"config": None if args.config is None else str(args.config),
                   "digest": "sha256:" + hashlib.sha256(canonical.encode()).hexdigest()[:16],
                   **effective},
        "camera": {"sha256": calibration_sha, "width": camera.width, "height": camera.height,
                   "fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy,
                   "distortion": list(camera.distortion)},
        "fps_option": args.fps,
        "software": {"netpose": __version__, "git": args.git_commit,
                     "python": platform.python_version(), "numpy": np.__version__,
                     "opencv": cv2.__version__},
    }


def _git_commit() -> str | None:
    """The commit of a netpose run from its checkout, "-dirty" when its tracked files differ;
    None for an installed copy. Read before the first frame (a checkout switched during a long
    replay was recorded instead of the code that ran), and without writing the checkout's
    index (`git describe --dirty` refreshes it: a read-only tool took index.lock)."""
    checkout = Path(__file__).resolve().parents[2]
    if not (checkout / ".git").exists():
        return None
    env = dict(os.environ, GIT_OPTIONAL_LOCKS="0")

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(["git", "-C", str(checkout), *args], capture_output=True,
                                  text=True, timeout=10, check=False, env=env)
        except (OSError, subprocess.SubprocessError):
            return None
        return done.stdout if done.returncode == 0 else None

    commit = (git("rev-parse", "--short", "HEAD") or "").strip()
    if not commit:
        return None
    changes = git("status", "--porcelain", "--untracked-files=no")
    return commit + ("-dirty" if changes else "") if changes is not None else commit


def _finish(
    args: argparse.Namespace,
    url: str,
    stats: ReplayStats,
    outcome: ReplayRun,
    out_dir: Path,
    source: FrameSource,
    provenance: dict[str, Any],
) -> None:
    try:
        plots = write_plots(stats, out_dir)
        outcome.outputs += [p.name for p in plots]
    except Exception as exc:  # a plotting problem must not cost the CSV, video and summary
        log.warning("plots not written: %s", exc)
    source_stats = source.stats()
    summary: dict[str, Any] = {
        "netpose_version": __version__,
        "input": redact_text(url),
        "calibration": str(args.calibration),
        "mesh": {"bar_length_m": args.mesh_size, "opening_angle_deg": args.opening_angle},
        "every": args.every,
        "independent": bool(args.independent),
        "filter_enabled": bool(args.filter),
        "truth_file": None if args.truth is None else str(args.truth),
        **provenance,
        "first_frame_unix": outcome.first_frame_unix,
        "interrupted": outcome.interrupted,
        "stop_reason": outcome.stop_reason or None,
        "source": {"corrupt_frames": source_stats.corrupt, "dropped_frames": source_stats.drops},
        "damage_holes": outcome.holes,
        "damage_inspection": None if outcome.holes is None else {
            "inspected_frames": outcome.inspected_frames, "judged_cells": outcome.judged_cells,
            "judgeable_bar_share": outcome.judgeable_share,
            "caveat": NO_PROOF},
        **stats.summary(),
    }
    if args.no_timing:
        summary.pop("speed", None)
    recording = getattr(args, "recording", None)
    if recording is not None:
        summary["recording"] = recording
    stated, early = _ended_early(source, summary, args.every)
    # Only a replay that read to the end can tell (not one stopped, nor one of --max-frames).
    early = early and not outcome.interrupted and (
        args.max_frames is None or outcome.frames_read < args.max_frames)
    summary["source"].update(stated_duration_s=stated, ended_early=early)
    if early:
        print(f"netpose replay: warning: {redact_text(url)} ended early: its frames stop at "
              f"{summary.get('duration_s', 0.0):.1f} s of the {stated:.1f} s its container "
              "states (cut short?); the outputs cover the frames read", file=sys.stderr)
    summary["outputs"] = [*outcome.outputs, "summary.json"]
    write_json(out_dir / "summary.json", summary)
    detection = summary.get("detection_rate")
    log.info("replay: %d frames, %s detected (a distance), %d with the net seen, written to %s",
             summary["frames"], "-" if detection is None else f"{100 * detection:.0f} %",
             summary.get("net_seen_frames", 0), out_dir)
    if outcome.holes is not None:
        # "No rows" must not read as "no holes": say how much of the net was looked at.
        share = outcome.judgeable_share
        clear = "" if share is None else (f"; {100 * share:.0f} % of their bars clear enough "
                                          "for a missing one to show")
        log.info("replay: net inspection: %d holes in %d inspected frames (%d cells judged%s)%s",
                 outcome.holes, outcome.inspected_frames, outcome.judged_cells, clear,
                 ": nothing was inspected, so no hole found says nothing of the net"
                 if not outcome.inspected_frames else f": {NO_PROOF}" if not outcome.holes
                 else "")
