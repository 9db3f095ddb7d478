"""Replay of a recording through the estimator (and optionally the filter): frames in, rows out.

`ReplayRunner` feeds any iterable of `ReplayFrame` (grey image, capture time, frame number,
optional ground truth) through the daemon's own `service.pipeline.Pipeline` and produces one
`FrameResult` per frame. Around it sit the pieces `netpose replay` writes to its output folder:

- `EstimatesCsv`: one CSV row per processed frame, flushed as it is written, so an interrupted
  replay leaves a valid file;
- `ReplayStats`: running statistics -> `summary.json` (detection rate, distance statistics,
  where the net was lost, processing speed, and the error against ground truth when known);
- `write_plots`: distance / confidence over time and the detection map over the frame (PNG).

Frames come from drivers.sources; the command (service/commands/replay.py) does that wiring, so
nothing here imports drivers.
"""

from __future__ import annotations

import csv
import difflib
import json
import logging
import math
import statistics
import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import numpy.typing as npt

from service.core.errors import NetposeError
from service.core.files import write_atomically
from service.core.messages import json_value
from service.core.results import NetEstimate, RoiResult
from service.core.scale import total_sigma
from service.core.tracking import TrackOutput
from service.pipeline import Pipeline, PipelineResult

log = logging.getLogger(__name__)

Gray = npt.NDArray[np.uint8]
Vec3 = tuple[float, float, float]

# Cell size (full-resolution pixels) of the detection map accumulated over the frame.
DETECTION_MAP_CELL_PX = 8
# Longest runs without detection listed in summary.json (all are counted).
MAX_LISTED_GAPS = 20


# -- ground truth ---------------------------------------------------------------------------
@dataclass(frozen=True)
class Truth:
    """What is known about one frame: from a synthetic source or a truth CSV.

    Any value may be unknown (None). `normal` points from the net towards the camera, like the
    estimator's.
    """

    net_present: bool = True
    range_m: float | None = None
    distance_m: float | None = None
    normal: Vec3 | None = None
    tilt_deg: float | None = None

    def tilt(self) -> float | None:
        if self.tilt_deg is not None:
            return self.tilt_deg
        if self.normal is None:
            return None
        return math.degrees(math.acos(min(1.0, abs(self.normal[2]))))


def truth_from_object(obj: object) -> Truth | None:
    """Truth from anything shaped like drivers.synthetic_net.GroundTruth (duck-typed)."""
    if obj is None:
        return None
    if isinstance(obj, Truth):
        return obj

    def number(name: str) -> float | None:
        value = getattr(obj, name, None)
        if isinstance(value, bool) or not isinstance(value, int | float):
            return None
        return float(value) if math.isfinite(value) else None

    normal = getattr(obj, "normal", None)
    vec: Vec3 | None = None
    if normal is not None and len(normal) == 3:
        vec = (float(normal[0]), float(normal[1]), float(normal[2]))
    return Truth(
        net_present=bool(getattr(obj, "net_present", True)),
        range_m=number("range_m"),
        distance_m=number("distance_m"),
        normal=vec,
        tilt_deg=number("tilt_deg"),
    )


TRUTH_COLUMNS = ("frame", "net_present", "range_m", "distance_m", "nx", "ny", "nz", "tilt_deg")


def write_truth_csv(path: str | Path, truths: Iterable[tuple[int, Truth]]) -> None:
    """Write (frame number, Truth) pairs in the layout `load_truth_csv` reads."""
    with Path(path).open("w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(TRUTH_COLUMNS)
        for index, t in truths:
            normal = t.normal if t.normal is not None else (None, None, None)
            writer.writerow(
                [index, int(t.net_present), _cell(t.range_m), _cell(t.distance_m),
                 *(_cell(v) for v in normal), _cell(t.tilt_deg)]
            )


def load_truth_csv(path: str | Path) -> dict[int, Truth]:
    """Ground truth per frame number (0-based, counted over the whole input) from a CSV.

    Required column: `frame`. Optional: `net_present` (0/1, default 1), `range_m`,
    `distance_m`, `nx` `ny` `nz` (all three or none), `tilt_deg`. Empty cells mean unknown.
    """
    p = Path(path)
    try:
        # utf-8-sig: Excel's "CSV UTF-8" starts with a byte-order mark, which would otherwise
        # become part of the first column's name.
        with p.open(newline="", encoding="utf-8-sig") as fh:
            reader = csv.DictReader(fh)
            rows = list(reader)
            # The header's names; an empty one (a trailing comma) is no column, and cells
            # beyond the header (DictReader's None key) are no column either.
            header = [c for c in (reader.fieldnames or []) if c and c.strip()]
    except FileNotFoundError:
        raise NetposeError(f"{p}: truth file not found") from None
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise NetposeError(f"{p}: cannot read truth CSV ({exc})") from None
    if not rows:
        raise NetposeError(f"{p}: truth CSV has no rows")
    if "frame" not in header:
        raise NetposeError(f"{p}: truth CSV needs a 'frame' column (has: {', '.join(header)})")
    # A column it does not know is refused, not passed over: a misspelt one ("distance")
    # would lose its truth without a word. `time_s` (estimates.csv's) may stand beside them.
    unknown = [c for c in header if c not in TRUTH_COLUMNS and c != "time_s"]
    if unknown:
        def named(column: str) -> str:
            near = difflib.get_close_matches(column, TRUTH_COLUMNS, n=1, cutoff=0.6)
            return f"'{column}'" + (f" (did you mean '{near[0]}'?)" if near else "")
        raise NetposeError(
            f"{p}: unknown column{'s' if len(unknown) > 1 else ''} "
            f"{', '.join(named(c) for c in unknown)}: a truth CSV has "
            f"{', '.join(TRUTH_COLUMNS)} (and time_s, not used)")
    if not set(header) & set(TRUTH_COLUMNS[1:]):
        raise NetposeError(
            f"{p}: truth CSV has no truth columns (expected some of {', '.join(TRUTH_COLUMNS[1:])})"
        )
    out: dict[int, Truth] = {}
    for line, row in enumerate(rows, start=2):

        def value(name: str, row: Mapping[str, str | None] = row, line: int = line,
                  low: float = -math.inf, high: float = math.inf) -> float | None:
            text = (row.get(name) or "").strip()
            if not text:
                return None
            try:
                number = float(text)
            except ValueError:
                raise NetposeError(f"{p}:{line}: {name}={text!r} is not a number") from None
            if not (math.isfinite(number) and low <= number <= high):
                raise NetposeError(f"{p}:{line}: {name}={text} is not a value it can have "
                                   f"({low:g}..{high:g}; leave the cell empty if unknown)")
            return number

        frame = value("frame")
        if frame is None or frame < 0 or frame != int(frame):
            raise NetposeError(f"{p}:{line}: 'frame' must be a frame number (0, 1, ...)")
        if int(frame) in out:
            raise NetposeError(f"{p}:{line}: frame {int(frame)} again (one row per frame)")
        nx, ny, nz = value("nx"), value("ny"), value("nz")
        normal: Vec3 | None = None
        if (nx, ny, nz).count(None) not in (0, 3):
            raise NetposeError(f"{p}:{line}: a normal needs nx, ny and nz (or none of them)")
        if nx is not None and ny is not None and nz is not None:
            norm = math.sqrt(nx * nx + ny * ny + nz * nz)
            if norm == 0:
                raise NetposeError(f"{p}:{line}: the normal (nx, ny, nz) is zero")
            normal = (nx / norm, ny / norm, nz / norm)
        present = value("net_present")
        if present not in (None, 0.0, 1.0):
            raise NetposeError(f"{p}:{line}: net_present={present:g} must be 0 or 1")
        out[int(frame)] = Truth(
            net_present=True if present is None else present != 0,
            range_m=value("range_m", low=0.0),
            distance_m=value("distance_m", low=0.0),
            normal=normal,
            tilt_deg=value("tilt_deg", low=0.0, high=90.0),
        )
    return out


# The reason given for a recorded frame the vehicle read but did not measure.
NOT_MEASURED_ON_VEHICLE = "not measured on the vehicle: no net in view, a paced search"


# -- frames -----------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class ReplayFrame:
    """One frame of a recording. `index` counts frames over the whole input (before --every);
    `time_s` is the time in the recording (seconds from its start); `t_capture` the capture
    time the pipeline is given (the source's clock, as the daemon gives it)."""

    image: Gray
    index: int
    time_s: float
    t_capture: float
    color: npt.NDArray[np.uint8] | None = None
    truth: Truth | None = None
    budget: int = 0  # the estimator's work level (a recording's, so a replay matches it)
    measured: bool = True  # False: the recording's vehicle did not measure it (paced search)
    inspected: bool | None = None  # a recording's: the vehicle searched it for holes
    source_file: str = ""  # the image file it came from (image folders)
    t_unix: float | None = None  # the capture's wall-clock time, where the input keeps it


# -- results ----------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class FrameResult:
    """One replayed frame: the pipeline's result, and the truth when known."""

    frame: ReplayFrame
    result: PipelineResult
    process_ms: float  # pipeline time for this frame (a measurement)
    keep_track: bool = True  # False without --filter: the filter's columns stay empty
    truth: Truth | None = None

    @property
    def estimate(self) -> NetEstimate | None:
        return self.result.estimate

    @property
    def track(self) -> TrackOutput | None:
        return self.result.track if self.keep_track else None

    @property
    def error(self) -> str:
        return self.result.error

    @property
    def detected(self) -> bool:
        return self.result.detected

    def range_error_m(self) -> float | None:
        e, t = self.estimate, self.truth
        if e is None or t is None or not e.detected or not t.net_present:
            return None
        return _difference(e.range_m, t.range_m)

    def distance_error_m(self) -> float | None:
        e, t = self.estimate, self.truth
        if e is None or t is None or not e.detected or not t.net_present:
            return None
        return _difference(e.distance_m, t.distance_m)

    def normal_error_deg(self) -> float | None:
        e, t = self.estimate, self.truth
        if e is None or t is None or not e.detected or not t.net_present:
            return None
        return angle_between_deg(e.normal, t.normal)

    def filtered_distance_error_m(self) -> float | None:
        k, t = self.track, self.truth
        if k is None or t is None or not k.valid or not t.net_present:
            return None
        return _difference(k.distance_m, t.distance_m)


def _difference(value: float | None, reference: float | None) -> float | None:
    if value is None or reference is None:
        return None
    return float(value) - float(reference)


def angle_between_deg(a: Sequence[float] | None, b: Sequence[float] | None) -> float | None:
    if a is None or b is None:
        return None
    va, vb = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    denom = float(np.linalg.norm(va) * np.linalg.norm(vb))
    if denom == 0 or not math.isfinite(denom):
        return None
    return math.degrees(math.acos(max(-1.0, min(1.0, float(va @ vb) / denom))))


class ReplayRunner:
    """Frames of a recording through the daemon's `Pipeline`, with their capture times.

    A frame the estimator cannot use gives a row without an estimate and one log line; if the
    very first frame is refused, the error is raised instead, since then no frame of the
    recording would be usable.
    """

    def __init__(
        self,
        pipeline: Pipeline,
        keep_track: bool = True,
        truth: Mapping[int, Truth] | None = None,
    ) -> None:
        self._pipeline = pipeline
        self._keep_track = keep_track
        self._truth = truth or {}
        self._processed = 0
        self._refusal_logged = False

    def process(self, frame: ReplayFrame) -> FrameResult:
        t0 = time.perf_counter()
        if frame.measured:
            result = self._pipeline.process(frame.image, frame.t_capture, frame.index,
                                            budget=frame.budget, inspect=frame.inspected)
        else:
            result = self._pipeline.skip(frame.t_capture, frame.index, NOT_MEASURED_ON_VEHICLE)
        if result.failure is not None and not result.crashed:
            if self._processed == 0:
                # Not even the first frame fits: the whole recording is unusable.
                raise result.failure
            if not self._refusal_logged:
                log.warning("frame %d: estimator refused the frame: %s (logged once)",
                            frame.index, result.error)
                self._refusal_logged = True
        self._processed += 1
        # A truth file given for the run is what the user asked to be scored against; a
        # rendered frame's own truth (a synthetic source, a recording of one) otherwise.
        truth = self._truth.get(frame.index, frame.truth)
        return FrameResult(frame=frame, result=result,
                           process_ms=(time.perf_counter() - t0) * 1e3,
                           keep_track=self._keep_track, truth=truth)

    def run(self, frames: Iterable[ReplayFrame]) -> Iterator[FrameResult]:
        for frame in frames:
            yield self.process(frame)


# -- estimates.csv ----------------------------------------------------------------------------
CSV_COLUMNS = (
    "frame", "time_s",
    # raw estimate
    "detected", "confidence", "range_m", "distance_m", "nx", "ny", "nz", "tilt_deg",
    "sigma_range_m", "sigma_distance_m", "sigma_normal_deg", "rois", "rois_used", "level",
    "reason", "process_ms",
    # a net seen but too uncertain for a distance (no distance above): its refused range
    "net_seen", "approx_range_m", "approx_sigma_range_m",
    # filter (--filter)
    "filter_state", "filter_valid", "filter_measurement", "filtered_range_m",
    "filtered_distance_m", "filtered_nx", "filtered_ny", "filtered_nz", "filtered_tilt_deg",
    "filtered_sigma_distance_m",
    # ground truth (synthetic source or --truth)
    "true_net_present", "true_range_m", "true_distance_m", "true_tilt_deg",
    "range_error_m", "distance_error_m", "normal_error_deg", "filtered_distance_error_m",
    # the frame's image file (image folders), last so that earlier columns keep their places
    "source_file",
    # net inspection searched the frame for holes (empty: inspection off)
    "inspected",
    # the sigmas with the scale's error (mesh.bar_length_tolerance, camera.focal_tolerance)
    "sigma_distance_total_m", "filtered_sigma_distance_total_m",
    # the capture's wall-clock time (a recording's), to line up with a DVL or a vehicle log;
    # whether the estimator searched the whole frame (1) or tried the last detection's plane
    # first (0: a frame's result depends on the one before it)
    "time_unix", "searched",
)


def _cell(value: object) -> str:
    """A CSV cell: empty for unknown, 0/1 for booleans, 12 significant digits (a replay can be
    compared with the daemon's own output to the nanometre)."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return f"{value:.12g}" if math.isfinite(value) else ""
    return str(value)


def csv_row(result: FrameResult, timing: bool = True) -> list[str]:
    """The CSV_COLUMNS cells of one frame (`timing` False: `process_ms` left empty, the one
    cell that differs from run to run)."""
    e, k, t = result.estimate, result.track, result.truth
    scale = result.result.scale_sigma_fraction
    normal = e.normal if e is not None and e.normal is not None else (None, None, None)
    # The filter's values only where it gives them (filter_valid): a tentative track's are
    # not out yet, a lost track's are its last ones, frozen.
    kv = k if k is not None and k.valid else None
    fnormal = kv.normal if kv is not None and kv.normal is not None else (None, None, None)
    ftilt = None
    if kv is not None and kv.normal is not None:
        ftilt = math.degrees(math.acos(min(1.0, abs(kv.normal[2]))))
    values: list[object] = [
        result.frame.index, round(result.frame.time_s, 6),
        e is not None and e.detected,
        None if e is None else e.confidence,
        None if e is None else e.range_m,
        None if e is None else e.distance_m,
        *normal,
        None if e is None else e.tilt_deg,
        None if e is None else e.sigma_range_m,
        None if e is None else e.sigma_distance_m,
        None if e is None else e.sigma_normal_deg,
        None if e is None else len(e.rois),
        None if e is None else e.rois_used,
        None if e is None else e.level,
        result.result.why_no_estimate if e is None else e.reason,
        round(result.process_ms, 3) if timing else None,
        e is not None and e.net_seen,
        None if e is None else e.approx_range_m,
        None if e is None else e.approx_sigma_range_m,
        None if k is None else k.state.value,
        None if k is None else k.valid,
        None if k is None else k.measurement.value,
        None if kv is None else kv.range_m,
        None if kv is None else kv.distance_m,
        *fnormal,
        ftilt,
        None if kv is None else kv.sigma_distance_m,
        None if t is None else t.net_present,
        None if t is None else t.range_m,
        None if t is None else t.distance_m,
        None if t is None else t.tilt(),
        result.range_error_m(),
        result.distance_error_m(),
        result.normal_error_deg(),
        result.filtered_distance_error_m(),
        result.frame.source_file,
        None if result.result.damage is None else result.result.damage.searched,
        None if e is None else total_sigma(e.distance_m, e.sigma_distance_m, scale),
        None if kv is None else total_sigma(kv.distance_m, kv.sigma_distance_m, scale),
        None if result.frame.t_unix is None else round(result.frame.t_unix, 6),
        None if e is None else e.searched,
    ]
    return [_cell(v) for v in values]


class EstimatesCsv:
    """estimates.csv, written and flushed row by row: valid after an interruption."""

    def __init__(self, path: str | Path, timing: bool = True) -> None:
        self.path = Path(path)
        self._timing = timing
        self._fh: TextIO | None = self.path.open("w", newline="", encoding="utf-8")
        self._writer = csv.writer(self._fh)
        self._writer.writerow(CSV_COLUMNS)
        self._fh.flush()
        self.rows = 0

    def write(self, result: FrameResult) -> None:
        if self._fh is None:
            raise NetposeError(f"{self.path}: already closed")
        self._writer.writerow(csv_row(result, self._timing))
        self._fh.flush()
        self.rows += 1

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None


# -- statistics, summary.json -------------------------------------------------------------
def _stats(values: Sequence[float]) -> dict[str, float | int | None]:
    data = np.asarray([v for v in values if v is not None and math.isfinite(v)], dtype=float)
    if data.size == 0:
        return {"count": 0}
    return {
        "count": int(data.size),
        "mean": float(data.mean()),
        "median": float(np.median(data)),
        # The sample's (n - 1): over a few detections the population one understates the
        # scatter a researcher reads from it.
        "std": float(data.std(ddof=1)) if data.size > 1 else None,
        "min": float(data.min()),
        "max": float(data.max()),
        "p5": float(np.percentile(data, 5)),
        "p95": float(np.percentile(data, 95)),
    }


def _error_stats(errors: Sequence[float]) -> dict[str, float | int | None]:
    data = np.asarray([v for v in errors if v is not None and math.isfinite(v)], dtype=float)
    if data.size == 0:
        return {"count": 0}
    return {
        "count": int(data.size),
        "mean": float(data.mean()),
        "rms": float(np.sqrt(np.mean(data**2))),
        "median_abs": float(np.median(np.abs(data))),
        "p95_abs": float(np.percentile(np.abs(data), 95)),
        "max_abs": float(np.abs(data).max()),
    }


@dataclass
class _Series:
    """Per-frame values kept for the plots and the summary (a few floats per frame)."""

    time_s: list[float] = field(default_factory=list)
    index: list[int] = field(default_factory=list)
    detected: list[bool] = field(default_factory=list)
    seen: list[bool] = field(default_factory=list)  # a net seen, with a distance or not
    confidence: list[float] = field(default_factory=list)
    distance: list[float] = field(default_factory=list)
    range: list[float] = field(default_factory=list)
    process_ms: list[float] = field(default_factory=list)
    filtered: list[float] = field(default_factory=list)  # nan where the filter is not valid
    filter_state: list[str] = field(default_factory=list)
    true_distance: list[float] = field(default_factory=list)
    true_range: list[float] = field(default_factory=list)
    true_present: list[float] = field(default_factory=list)  # 1, 0 or nan (unknown)
    range_error: list[float] = field(default_factory=list)
    distance_error: list[float] = field(default_factory=list)
    normal_error: list[float] = field(default_factory=list)
    filtered_error: list[float] = field(default_factory=list)


def _nan(value: float | None) -> float:
    return math.nan if value is None else float(value)


class DetectionMap:
    """Per cell of the frame: in how many processed frames an ROI covering it saw the lattice."""

    def __init__(self, cell_px: int = DETECTION_MAP_CELL_PX) -> None:
        self.cell_px = cell_px
        self.size: tuple[int, int] | None = None  # (width, height) of the frames counted
        self.detected: npt.NDArray[np.int32] | None = None
        self.used: npt.NDArray[np.int32] | None = None
        self.frames = 0
        self.background: Gray | None = None  # a small copy of one frame, for the plot

    def add(self, image: Gray, rois: Sequence[RoiResult]) -> None:
        h, w = image.shape[:2]
        if self.size is None:
            self.size = (w, h)
            shape = (-(-h // self.cell_px), -(-w // self.cell_px))
            self.detected = np.zeros(shape, np.int32)
            self.used = np.zeros(shape, np.int32)
            self.background = np.ascontiguousarray(image[:: self.cell_px, :: self.cell_px])
        if (w, h) != self.size or self.detected is None or self.used is None:
            return  # frames of another size are not on this map
        seen = np.zeros(self.detected.shape, bool)
        used = np.zeros(self.detected.shape, bool)
        c = self.cell_px
        for roi in rois:
            if not roi.detected:
                continue
            half = roi.size_px / 2.0
            x0 = max(0, int((roi.center_px[0] - half) // c))
            x1 = max(0, int(-(-(roi.center_px[0] + half) // c)))
            y0 = max(0, int((roi.center_px[1] - half) // c))
            y1 = max(0, int(-(-(roi.center_px[1] + half) // c)))
            seen[y0:y1, x0:x1] = True
            if roi.used_in_fit:
                used[y0:y1, x0:x1] = True
        self.detected += seen
        self.used += used
        self.frames += 1


class ReplayStats:
    """Accumulates FrameResults; `summary()` is the content of summary.json."""

    def truth_scale_doubt(self) -> str:
        """A truth table in another unit (a DVL's export in centimetres) or of another quantity
        gave a -59 m mean error and exit status 0 (research review): where the median ratio of
        the measured to the true distances over at least 3 frames is off by more than a factor
        of 2 (no calibration or mesh error is that large), what it looks like; else ""."""
        s = self.series
        ratios = [d / t for d, t in zip(s.distance, s.true_distance, strict=True)
                  if math.isfinite(d) and math.isfinite(t) and t > 0]
        if len(ratios) < 3:
            return ""
        ratio = statistics.median(ratios)
        if 0.5 <= ratio <= 2.0:
            return ""
        units = {100.0: "centimetres", 1000.0: "millimetres", 1 / 0.3048: "feet",
                 1 / 0.0254: "inches"}
        guess = next((f" (in {name}?)" for factor, name in units.items()
                      if abs(math.log(ratio * factor)) < 0.3), "")
        return (f"the measured distances are {ratio:.3g} times the truth's (median of "
                f"{len(ratios)} frames){guess}: is the truth file in metres, and of the "
                "perpendicular distance?")

    def __init__(self) -> None:
        self.series = _Series()
        self.detection_map = DetectionMap()
        self.has_filter = False
        self.has_truth = False
        self.refused = 0
        self._t_start = time.perf_counter()
        self._t_end: float | None = None

    def add(self, result: FrameResult) -> None:
        s = self.series
        e, k, t = result.estimate, result.track, result.truth
        s.time_s.append(result.frame.time_s)
        s.index.append(result.frame.index)
        s.detected.append(result.detected)
        s.seen.append(e is not None and e.net_seen)
        s.confidence.append(_nan(None if e is None else e.confidence))
        s.distance.append(_nan(e.distance_m) if e is not None and e.detected else math.nan)
        s.range.append(_nan(e.range_m) if e is not None and e.detected else math.nan)
        s.process_ms.append(result.process_ms)
        if e is None:
            self.refused += 1
        else:
            self.detection_map.add(result.frame.image, e.rois)
        if k is not None:
            self.has_filter = True
        s.filtered.append(_nan(k.distance_m) if k is not None and k.valid else math.nan)
        s.filter_state.append("" if k is None else k.state.value)
        if t is not None:
            self.has_truth = True
        s.true_distance.append(_nan(None if t is None else t.distance_m))
        s.true_range.append(_nan(None if t is None else t.range_m))
        s.true_present.append(math.nan if t is None else float(t.net_present))
        s.range_error.append(_nan(result.range_error_m()))
        s.distance_error.append(_nan(result.distance_error_m()))
        s.normal_error.append(_nan(result.normal_error_deg()))
        s.filtered_error.append(_nan(result.filtered_distance_error_m()))

    def finish(self) -> None:
        """Stop the wall clock (processing speed counts up to here)."""
        if self._t_end is None:
            self._t_end = time.perf_counter()

    @property
    def frames(self) -> int:
        return len(self.series.index)

    def gaps(self) -> list[dict[str, float | int]]:
        """Runs of consecutive processed frames without detection, longest first."""
        s = self.series
        runs: list[tuple[int, int]] = []
        start: int | None = None
        for i, detected in enumerate([*s.detected, True]):
            if not detected and start is None:
                start = i
            elif detected and start is not None:
                runs.append((start, i - 1))
                start = None
        runs.sort(key=lambda r: (-(r[1] - r[0]), r[0]))
        return [
            {
                "first_frame": s.index[a],
                "last_frame": s.index[b],
                "frames": b - a + 1,
                "start_s": round(s.time_s[a], 3),
                "end_s": round(s.time_s[b], 3),
            }
            for a, b in runs
        ]

    def summary(self) -> dict[str, Any]:
        s = self.series
        n = self.frames
        detected = sum(s.detected)
        end = self._t_end if self._t_end is not None else time.perf_counter()
        wall = max(end - self._t_start, 1e-9)
        process = _stats(s.process_ms)
        mean_ms = process.get("mean")
        gaps = self.gaps()
        out: dict[str, Any] = {
            "frames": n,
            "first_frame": s.index[0] if n else None,
            "last_frame": s.index[-1] if n else None,
            "duration_s": (s.time_s[-1] - s.time_s[0]) if n else 0.0,
            "detected_frames": detected,
            "detection_rate": detected / n if n else None,
            # With a distance or not: also the frames whose plane was too uncertain for one.
            "net_seen_frames": sum(s.seen),
            "refused_frames": self.refused,
            "confidence": _stats([c for c, d in zip(s.confidence, s.detected, strict=True)
                                  if d]),
            "distance_m": _stats(s.distance),
            "range_m": _stats(s.range),
            "lost": {
                "runs": len(gaps),
                "longest": gaps[:MAX_LISTED_GAPS],
            },
            "speed": {
                "wall_s": wall,
                "frames_per_s": n / wall,
                "estimator_ms": process,
                "estimator_frames_per_s": 1e3 / mean_ms if mean_ms else None,
            },
        }
        if self.has_filter:
            valid = [not math.isnan(v) for v in s.filtered]
            out["filter"] = {
                "valid_frames": sum(valid),
                "valid_rate": sum(valid) / n if n else None,
                "distance_m": _stats(s.filtered),
                "states": {st: s.filter_state.count(st) for st in sorted(set(s.filter_state))},
            }
        if self.has_truth:
            out["truth"] = self._truth_summary()
        return dict(json_value(out))

    def _truth_summary(self) -> dict[str, Any]:
        s = self.series
        present = [p == 1.0 for p in s.true_present]
        absent = [p == 0.0 for p in s.true_present]
        hits = sum(1 for p, d in zip(present, s.detected, strict=True) if p and d)
        false_alarms = sum(1 for a, d in zip(absent, s.detected, strict=True) if a and d)
        rel = [
            100.0 * err / ref
            for err, ref in zip(s.range_error, s.true_range, strict=True)
            if math.isfinite(err) and math.isfinite(ref) and ref > 0
        ]
        out: dict[str, Any] = {
            "frames_with_truth": sum(1 for p in s.true_present if not math.isnan(p)),
            "net_present_frames": sum(present),
            "detected_when_present": hits,
            "detection_rate_when_present": hits / sum(present) if any(present) else None,
            "net_absent_frames": sum(absent),
            "false_detections": false_alarms,
            "range_error_m": _error_stats(s.range_error),
            "range_error_pct": _error_stats(rel),
            "distance_error_m": _error_stats(s.distance_error),
            "normal_error_deg": _error_stats(s.normal_error),
        }
        if self.has_filter:
            out["filtered_distance_error_m"] = _error_stats(s.filtered_error)
        return out


def write_json(path: str | Path, document: Mapping[str, Any]) -> None:
    """Write JSON atomically (temporary file, then rename): never half a file."""
    write_atomically(path, (json.dumps(document, indent=2, allow_nan=False) + "\n").encode())


# -- plots ------------------------------------------------------------------------------------
PLOT_FILES = ("distance.png", "confidence.png", "detection_map.png")


def write_plots(stats: ReplayStats, out_dir: str | Path) -> list[Path]:
    """distance.png, confidence.png (over time) and detection_map.png (over the frame).

    matplotlib's object API with the Agg canvas: no pyplot, no global figure state.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    out = Path(out_dir)
    s = stats.series
    t = np.asarray(s.time_s, dtype=float)
    written: list[Path] = []

    def save(fig: Figure, name: str) -> None:
        FigureCanvasAgg(fig)
        path = out / name
        tmp = out / f".{name}.tmp.png"
        fig.savefig(tmp, dpi=100)
        tmp.replace(path)
        written.append(path)

    # Distance over time (and the error against the truth below it).
    rows = 2 if stats.has_truth else 1
    fig = Figure(figsize=(10, 3.2 * rows + 0.6), layout="constrained")
    axes = fig.subplots(rows, 1, sharex=True, squeeze=False)[:, 0]
    ax = axes[0]
    ax.plot(t, s.distance, ".", ms=3, color="tab:blue", label="estimate (perpendicular)")
    if stats.has_filter:
        ax.plot(t, s.filtered, "-", lw=1.5, color="tab:orange", label="filtered")
    if stats.has_truth:
        ax.plot(t, s.true_distance, "--", lw=1, color="black", label="truth")
    ax.set_ylabel("distance to net [m]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    ax.set_title("Distance to the net")
    if stats.has_truth:
        ax = axes[1]
        err_cm = 100.0 * np.asarray(s.distance_error, dtype=float)
        ax.plot(t, err_cm, ".", ms=3, color="tab:blue", label="estimate - truth")
        if stats.has_filter:
            ax.plot(t, 100.0 * np.asarray(s.filtered_error, dtype=float), "-", lw=1,
                    color="tab:orange", label="filtered - truth")
        ax.axhline(0.0, color="black", lw=0.8)
        ax.set_ylabel("distance error [cm]")
        ax.grid(True, alpha=0.3)
        ax.legend(loc="best", fontsize="small")
    axes[-1].set_xlabel("time in recording [s]")
    save(fig, "distance.png")

    # Confidence and detection over time.
    fig = Figure(figsize=(10, 3.8), layout="constrained")
    ax = fig.subplots()
    conf = np.asarray(s.confidence, dtype=float)
    det = np.asarray(s.detected, dtype=bool)
    ax.plot(t, conf, "-", lw=1, color="tab:gray", label="confidence")
    if det.size:
        ax.plot(t[det], conf[det], ".", ms=4, color="tab:green", label="detected")
        ax.plot(t[~det], conf[~det], "x", ms=4, color="tab:red", label="not detected")
    if stats.has_truth:
        absent = np.asarray(s.true_present, dtype=float) == 0.0
        if absent.any():
            ax.fill_between(t, 0, 1, where=absent, color="tab:red", alpha=0.1, step="mid",
                            label="no net (truth)")
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel("time in recording [s]")
    ax.set_ylabel("confidence")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    ax.set_title("Detection confidence")
    save(fig, "confidence.png")

    # Where in the frame the lattice was seen.
    dm = stats.detection_map
    fig = Figure(figsize=(8, 5), layout="constrained")
    ax = fig.subplots()
    if dm.detected is not None and dm.frames > 0 and dm.size is not None:
        w, h = dm.size
        extent = (0.0, float(w), float(h), 0.0)
        if dm.background is not None:
            ax.imshow(dm.background, cmap="gray", extent=extent, vmin=0, vmax=255)
        image = ax.imshow(dm.detected / dm.frames, cmap="viridis", vmin=0.0, vmax=1.0,
                          alpha=0.6, extent=extent)
        fig.colorbar(image, ax=ax, label="fraction of frames with a lattice found")
        ax.set_title(f"Net lattice found, over {dm.frames} frames")
    else:
        ax.text(0.5, 0.5, "no frame processed", ha="center", va="center")
    ax.set_xlabel("x [px]")
    ax.set_ylabel("y [px]")
    save(fig, "detection_map.png")
    return written
