"""A recording made by the daemon (drivers/recorder.py), read with its recorded capture times.

    recording:netpose-rov-20260101T120000Z/              as fast as the consumer reads
    recording:netpose-rov-20260101T120000Z/?realtime=1   paced like the camera was

Without `realtime` every frame carries the capture times written in frames.jsonl (monotonic
and wall clock), so `netpose replay` steps the filter exactly as the daemon did. With
`realtime` the recorded spacing is kept from the moment of open(), like any paced source.
`camera` is the recording's own calibration, so a daemon can run on a recording with
`camera.calibration = "builtin"`. A recording of a rendered source (`synthetic:`, `sim:`)
gives each frame its recorded ground truth again. Frame numbers are the daemon's source
numbers: the gaps are the frames the daemon skipped.
"""

from __future__ import annotations

import itertools
import json
import logging
import statistics
from pathlib import Path
from typing import Any

import cv2

from drivers.errors import SourceError
from drivers.sources.base import SourceOptions
from drivers.sources.paced import EndOfMediaError, MediaFrame, PacedSource
from drivers.sources.url import parse_source_url, url_error
from service.core.camera import CameraModel, load_camera
from service.core.errors import CalibrationError
from service.core.messages import TruthView

log = logging.getLogger(__name__)

RECORDING_OPTIONS = ("realtime",)
MANIFEST = "recording.json"  # the names drivers/recorder.py writes
FRAMES_LOG = "frames.jsonl"
CAMERA_FILE = "camera.yaml"


def is_recording(path: Path) -> bool:
    return path.is_dir() and (path / MANIFEST).is_file()


class RecordingSource(PacedSource):
    def __init__(self, url: str, options: SourceOptions | None = None) -> None:
        parsed = parse_source_url(url)
        if parsed.scheme != "recording":
            raise url_error(url, "not a recording: URL")
        parsed.check_options(RECORDING_OPTIONS)
        if not parsed.path:
            raise url_error(url, "recording: needs a folder")
        super().__init__(url, options, realtime=parsed.flag(
            "realtime", (options or SourceOptions()).realtime_default))
        self.path = Path(parsed.path).expanduser()
        self._entries: list[tuple[str, int, float, float, int | None, bool, bool | None,
                                  TruthView | None]] = []
        self._position = 0
        self._camera: CameraModel | None = None
        self._period = 0.1

    @property
    def recorded(self) -> bool:
        return True

    @property
    def wall_clock_recorded(self) -> bool:
        """Frames carry the vehicle's own capture time (`Frame.t_wall`), not the replay's."""
        return True

    @property
    def camera(self) -> CameraModel | None:
        """The recording's own calibration (camera.yaml), readable before open(): the
        service resolves its camera before it opens the source. None without one; a damaged
        one raises CalibrationError saying what is wrong with it."""
        if self._camera is None and (self.path / CAMERA_FILE).is_file():
            self._camera = load_camera(self.path / CAMERA_FILE)
        return self._camera

    @property
    def frame_period_s(self) -> float:
        return self._period

    @property
    def files(self) -> list[Path]:
        return [self.path / name for name, *_ in self._entries]

    def open(self) -> None:
        super().open()
        if not self.realtime and self._entries:
            # The recorded clock, not the clock of this open(): media time is measured from
            # the first frame, so frame i gets t0 + (t_i - t_first) = its recorded time (and
            # its recorded wall time, which each frame carries).
            self._t0_mono = self._entries[0][2]

    def _start(self) -> None:
        if not is_recording(self.path):
            raise SourceError(self.url, f"{self.path}: not a netpose recording (no {MANIFEST})")
        try:
            # A recording cut short by a power loss may end in a torn character as well as a
            # torn line: decoded leniently, the tail is judged line by line below.
            lines = (self.path / FRAMES_LOG).read_text(encoding="utf-8",
                                                       errors="replace").splitlines()
        except OSError as exc:
            raise SourceError(self.url, f"cannot read {FRAMES_LOG}: {exc.strerror}") from None
        entries = []
        damaged: list[int] = []
        for number, line in enumerate(lines, 1):
            if not line.strip("\0 \t\r"):
                continue
            try:
                row: dict[str, Any] = json.loads(line)
                estimate = row.get("estimate") or {}
                budget = estimate.get("budget_level") if isinstance(estimate, dict) else None
                measured = estimate.get("measured") if isinstance(estimate, dict) else None
                inspected = estimate.get("inspected") if isinstance(estimate, dict) else None
                truth = estimate.get("truth") if isinstance(estimate, dict) else None
                entry = (str(row["frame"]), int(row["index"]), float(row["t_mono"]),
                         float(row["t_unix"]), int(budget) if isinstance(budget, int) else None,
                         measured is not False,
                         inspected if isinstance(inspected, bool) else None,
                         _truth(truth))
            except (ValueError, KeyError, TypeError, AttributeError):
                damaged.append(number)
                continue
            if damaged:
                # Good lines after a damaged one: not a recording cut short, and a frame
                # missing there would make every later one differ from the vehicle's.
                raise SourceError(self.url, f"{FRAMES_LOG} line {damaged[0]} is damaged")
            entries.append(entry)
        if damaged:
            log.warning("%s: %s ends in %d damaged line(s) (the recording was cut short): "
                        "%d frames before them are replayed", self.path, FRAMES_LOG,
                        len(damaged), len(entries))
        if not entries:
            raise SourceError(self.url, "the recording holds no frame")
        if any(b[1] <= a[1] for a, b in itertools.pairwise(entries)):
            raise SourceError(self.url, f"{FRAMES_LOG}: frame numbers do not increase")
        self._entries = entries
        gaps = [b[2] - a[2] for a, b in itertools.pairwise(entries)]
        gaps = [g for g in gaps if g > 0]
        if gaps:
            self._period = statistics.median(gaps)
        if (self.path / CAMERA_FILE).is_file():
            try:
                self._camera = load_camera(self.path / CAMERA_FILE)
            except CalibrationError as exc:
                raise SourceError(self.url, str(exc)) from None

    def _next_media(self) -> MediaFrame:
        if self._position >= len(self._entries):
            raise EndOfMediaError
        name, index, t_mono, t_unix, budget, measured, inspected, truth = (
            self._entries[self._position])
        self._position += 1
        flags = cv2.IMREAD_COLOR if self._options.keep_color else cv2.IMREAD_GRAYSCALE
        image: Any = cv2.imread(str(self.path / name), flags)
        return MediaFrame(image=image, number=index, media_time_s=t_mono - self._entries[0][2],
                          budget=budget, measured=measured, inspected=inspected,
                          wall_s=t_unix, truth=truth)

    def _skip_to(self, number: int) -> int:
        """Skip the frames recorded before `number` frame periods of media time. By time, not
        by the recorded numbers: those are the vehicle's, which start wherever the recording
        started, so a paced reader compared with them never skipped and fell behind."""
        if not self._entries:
            return 0
        due_s = number * self._period
        t_first = self._entries[0][2]
        skipped = 0
        while (self._position < len(self._entries)
               and self._entries[self._position][2] - t_first < due_s):
            self._position += 1
            skipped += 1
        return skipped

    def _rewind(self) -> None:
        self._position = 0

    def _stop(self) -> None:
        self._entries = []
        self._position = 0


def _truth(recorded: object) -> TruthView | None:
    """A frame's recorded ground truth (the estimate message's `truth`); None where there is
    none, or where it is not of the schema's shape (it is data to score against, never a
    reason to refuse the frame)."""
    if not isinstance(recorded, dict):
        return None
    try:
        normal = recorded.get("normal")
        return TruthView(
            net_present=bool(recorded.get("net_present", True)),
            range_m=_number(recorded.get("range_m")),
            distance_m=_number(recorded.get("distance_m")),
            tilt_deg=_number(recorded.get("tilt_deg")),
            normal=(float(normal[0]), float(normal[1]), float(normal[2]))
            if isinstance(normal, list) and len(normal) == 3 else None)
    except (TypeError, ValueError):
        return None


def _number(value: object) -> float | None:
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else None
