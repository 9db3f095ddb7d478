"""`netpose bench damage`: holes found and measured, false alarms, cost - on rendered passes
along a net and on the real frames.

Each *pass* is a short run of frames of the ROV moving along a net (0.1-0.4 m/s, 10 inspected
frames per second: a 30 frames/s camera inspected every third frame), through the whole
pipeline (estimator, filter, inspection: detector and confirmation) as the daemon runs it:

- camera: 1280x720, 82 deg, barrel distortion (the accuracy benchmark's);
- net: square (70 %) or rhombic (60-80 deg) mesh with 1.5-3 cm bars, 0.4-2 m away, tilted up
  to 40 deg about any axis, any roll; the scene `SceneStyle.realistic` as the integrity
  benchmark draws it (fouling, seams, ropes, boards, billowing, turbidity, lamps, motion blur,
  JPEG, fish behind and in front), clutter drawn anew each frame, the net and its holes fixed;
- half the passes intact, half with one hole (`drivers/synthetic_damage.py`): a cut bar
  (2 cells), a missing knot (4 cells) or a torn hole of 2-10 cells, placed in view.

Reported: recall per frame and confirmed (per pass) by hole size and distance, the size error
of confirmed holes (width and height, knot to knot, against the truth), false alarms (confirmed
holes where there is none) per 1,000 intact frames, candidates per 1,000 intact frames, the
real frames (no hole in any: every candidate is a false alarm), the inspection's cost against
the estimator's, and what was missed and why (with pictures in `--out`).
"""

from __future__ import annotations

import copy
import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import numpy.typing as npt

from drivers.synthetic_damage import (
    Hole,
    HoleTruth,
    NetDamage,
    cell_at_pixel,
    hole_truth,
    random_hole,
)
from drivers.synthetic_net import NetPose, NetRenderer, SceneStyle
from service.benchmarks.scenes import bench_camera
from service.benchmarks.workers import run_chunks
from service.core.camera import CameraModel
from service.core.damage import DamageSettings
from service.core.damage_track import NetInspector
from service.core.estimator import NetEstimator
from service.core.mesh import MeshGeometry
from service.core.tracking import FilterSettings, NetTracker
from service.pipeline import Pipeline

Gray = npt.NDArray[np.uint8]

# Inspected frames per pass, 10 a second: 3.6 s along the net. A place of a real net stays in
# a forward camera's view for 4-17 s at 0.1-0.4 m/s (a view 1.7 m wide at 1 m), and a hole is
# confirmed by being found again where it was; passes of 12 frames (1.2 s, before 2026-11-26)
# left a candidate too few looks to be confirmed or rejected (docs/inspection.md).
FRAMES_PER_PASS = 36
FRAME_DT_S = 0.1
# Frames before the pass is scored: the ROV has been following the net already (the filter
# needs a few accepted measurements before its track is valid).
WARM_UP_FRAMES = 3
# A hole counts as in view only where the frame shows it: at least this share of the points
# along its missing bars change the image by at least VISIBLE_GREY grey levels against the
# same frame rendered intact (a board or a fish in front, a rope over it, fog: not a hole to
# find in that frame).
VISIBLE_SHARE = 0.7
VISIBLE_GREY = 3.0
# How clearly a shown hole stands out: the twine it removed (median change along its missing
# bars) over the frame's noise (sigma, grey levels). Recall targets are judged on holes of at
# least MIN_CNR; fainter ones are reported apart.
MIN_CNR = 1.5
# A hole is scored for confirmation when the pass showed it in at least this many frames
# (fixed, not the confirmation setting, so that runs with different settings score the same
# holes).
MIN_FRAMES_SHOWN = 3
CNR_BINS = ((0.0, 1.5), (1.5, 3.0), (3.0, 6.0), (6.0, math.inf))
SIZE_CLASSES = ((2, 2, "2 cells"), (3, 4, "3-4 cells"), (5, 10, "5-10 cells"))
DISTANCE_BINS = ((0.4, 0.8), (0.8, 1.2), (1.2, 1.5), (1.5, 2.01))
TARGET_RECALL = 0.95
TARGET_RECALL_RANGE_M = 1.5
TARGET_SIZE_ERROR = 0.20
TARGET_FALSE_PER_1000 = 1.0


@dataclass(frozen=True)
class PassCase:
    """Everything that decides one pass; rebuilt exactly from (seed, index)."""

    seed: int
    index: int
    camera: CameraModel
    mesh: MeshGeometry
    pose: NetPose  # at the first scored frame
    drift: tuple[float, float]  # lattice cells per second the net moves through the view
    style: SceneStyle
    holes: tuple[Hole, ...]
    frames: int = FRAMES_PER_PASS

    def pose_at(self, k: int) -> NetPose:
        t = k * FRAME_DT_S
        return replace(self.pose, phase=(self.pose.phase[0] + self.drift[0] * t,
                                         self.pose.phase[1] + self.drift[1] * t))

    def frame_rng(self, k: int) -> np.random.Generator:
        """The noise of frame k; the same for the damaged and the intact render of a frame."""
        return np.random.default_rng([self.seed, self.index, k + WARM_UP_FRAMES, 0x5E])


def draw_pass(seed: int, index: int, width: int = 1280, height: int = 720,
              damaged: bool | None = None, frames: int = FRAMES_PER_PASS) -> PassCase:
    rng = np.random.default_rng([seed, index, 0xDA])
    camera = bench_camera(width, height)
    bar = float(rng.uniform(0.015, 0.03))
    opening = 90.0 if rng.random() < 0.7 else float(rng.uniform(60.0, 80.0))
    mesh = MeshGeometry(bar, opening)
    pose = NetPose(float(rng.uniform(0.4, 2.0)), tilt_deg=float(rng.uniform(0.0, 40.0)),
                   tilt_axis_deg=float(rng.uniform(0, 360)), roll_deg=float(rng.uniform(0, 180)),
                   phase=(float(rng.uniform(0, 1)), float(rng.uniform(0, 1))))
    speed = float(rng.uniform(0.1, 0.4))
    heading = float(rng.uniform(0, 2 * math.pi))
    du, dv = speed * math.cos(heading), speed * math.sin(heading)
    alpha = math.radians(opening)
    s2 = dv / (bar * math.sin(alpha))
    drift = (du / bar - s2 * math.cos(alpha), s2)
    # One net per pass, its fouling and seams fixed on it (a real net keeps them while the ROV
    # passes), drawn from its own seed so the pass's other draws are those of before.
    net_seed = int(np.random.default_rng([seed, index, 0x4E]).integers(2**31))
    style = SceneStyle.realistic(rng, net_present=True, net_seed=net_seed)
    damaged = bool(index % 2) if damaged is None else damaged
    holes: tuple[Hole, ...] = ()
    if damaged:
        middle = replace(pose, phase=(pose.phase[0] + drift[0] * FRAME_DT_S * frames / 2,
                                      pose.phase[1] + drift[1] * FRAME_DT_S * frames / 2))
        for _ in range(20):
            pixel = (float(rng.uniform(0.2, 0.8) * width), float(rng.uniform(0.2, 0.8) * height))
            cell = cell_at_pixel(camera, middle, mesh, pixel)
            if cell is not None:
                kind = str(rng.choice(["cut_bar", "missing_knot", "torn"], p=[0.3, 0.2, 0.5]))
                holes = (random_hole(rng, cell, int(rng.integers(2, 11)), kind),)
                break
    return PassCase(seed, index, camera, mesh, pose, drift, style, holes, frames)


@dataclass
class FrameRow:
    """One frame of a pass, one truth hole (or none)."""

    index: int
    frame: int
    range_m: float
    tilt_deg: float
    period_px: float
    valid: bool  # the track was valid (inspection may run)
    inspected: bool
    estimate_ms: float
    inspect_ms: float
    candidates: int
    false_candidates: int
    hole_cells: int = 0  # 0: no hole in view in this frame
    hole_kind: str = ""
    hole_range_m: float = math.nan
    cnr: float = math.nan  # the hole's contrast over the noise in this frame
    detected: bool = False
    why: str = ""  # for a missed hole: what the detector made of it


@dataclass
class PassResult:
    case_index: int
    rows: list[FrameRow]
    holes: list[HoleTruth]  # at the middle frame (sizes do not change along a pass)
    confirmed_true: list[tuple[int, float, float]] = field(default_factory=list)
    # (hole k, width error, height error) of confirmed detections of true holes
    confirmed_false: int = 0
    frames_in_view: list[int] = field(default_factory=list)  # per hole: frames it was in view
    frames_hidden: list[int] = field(default_factory=list)  # per hole: in the frame, not shown
    cnr: list[float] = field(default_factory=list)  # per hole: median over its shown frames
    miss_images: list[tuple[str, Gray]] = field(default_factory=list)


def _box_in_frame(truth: HoleTruth, w: int, h: int, margin: float = 0.02) -> bool:
    x0, y0, x1, y1 = truth.box_px
    mx, my = margin * w, margin * h
    return x0 >= mx and y0 >= my and x1 <= w - 1 - mx and y1 <= h - 1 - my


def _overlaps(centre: tuple[float, float], truth: HoleTruth, pad: float) -> bool:
    x0, y0, x1, y1 = truth.box_px
    return x0 - pad <= centre[0] <= x1 + pad and y0 - pad <= centre[1] <= y1 + pad


def run_pass(case: PassCase, renderer: NetRenderer, settings: DamageSettings,
             keep_misses: bool = False) -> PassResult:
    """Render and process one pass through the pipeline (estimator, filter, inspection)."""
    cam, mesh = case.camera, case.mesh
    estimator = NetEstimator(cam, mesh)
    estimator.prepare(cam.width, cam.height)
    inspector = NetInspector(cam, mesh, replace(settings, every_n_frames=1))
    pipeline = Pipeline(estimator, NetTracker(FilterSettings()), inspector=inspector)
    damage = NetDamage(list(case.holes))
    f = math.sqrt(cam.fx * cam.fy)
    rows: list[FrameRow] = []
    result = PassResult(case.index, rows, [])
    in_view = [0] * len(case.holes)
    invisible = [0] * len(case.holes)
    cnrs: list[list[float]] = [[] for _ in case.holes]
    for k in range(-WARM_UP_FRAMES, case.frames):
        pose = case.pose_at(k)
        image, truth = renderer.render(pose, case.frame_rng(k), case.style, damage=damage)
        res = pipeline.process(image, (k + WARM_UP_FRAMES) * FRAME_DT_S, k)
        if k < 0:
            continue
        intact = None
        if case.holes:
            intact, _ = renderer.render(pose, case.frame_rng(k), case.style)
        rep = res.damage
        inspect_ms = rep.inspect_ms if rep is not None else 0.0
        scan = rep.scan if rep is not None else None
        cands = list(scan.candidates) if scan is not None else []
        truths = [hole_truth(h, cam, pose, mesh, damage.masks[i] if damage.masks else None)
                  for i, h in enumerate(case.holes)]
        if k == case.frames // 2:
            result.holes = truths
        visible = [t for t in truths if _box_in_frame(t, cam.width, cam.height)]
        pad = 0.5 * f * mesh.bar_length_m / max(truth.range_m, 0.1)
        false = [c for c in cands if not any(_overlaps(c.centre_px, t, pad) for t in truths)]
        base = dict(index=case.index, frame=k, range_m=truth.range_m, tilt_deg=truth.tilt_deg,
                    period_px=f * math.sqrt(mesh.cell_area_m2) / truth.range_m,
                    valid=res.track.valid, inspected=rep is not None and rep.inspected,
                    estimate_ms=res.estimate_ms, inspect_ms=inspect_ms,
                    candidates=len(cands), false_candidates=len(false))
        cnr_now = [math.nan] * len(truths)
        for i, t in enumerate(truths):
            if t in visible and intact is not None:
                shown, cnr_now[i] = _shows(image, intact, case.holes[i], cam, pose, mesh)
                if not shown:
                    visible.remove(t)
                    invisible[i] += 1
                else:
                    cnrs[i].append(cnr_now[i])
        if not visible:
            rows.append(FrameRow(**base))  # type: ignore[arg-type]
        for i, t in enumerate(truths):
            if t not in visible:
                continue
            in_view[i] += 1
            hit = any(_overlaps(c.centre_px, t, pad) for c in cands)
            why = "" if hit else _why_missed(res, t, pad)
            rows.append(FrameRow(**base, hole_cells=t.cells,  # type: ignore[arg-type]
                                 hole_kind=t.hole.kind, hole_range_m=t.range_m,
                                 cnr=cnr_now[i], detected=hit, why=why))
            if keep_misses and not hit and base["inspected"] and len(result.miss_images) < 2:
                result.miss_images.append((f"pass {case.index} frame {k}: {why}",
                                           _crop(image, t)))
        for hole in (rep.confirmed if rep is not None else ()):
            match = [i for i, t in enumerate(truths) if _overlaps(hole.centre_px, t, pad)]
            if match:
                t = truths[match[0]]
                result.confirmed_true.append((match[0], hole.width_m / t.width_m - 1.0,
                                              hole.height_m / t.height_m - 1.0))
            else:
                result.confirmed_false += 1
    result.frames_in_view = in_view
    result.frames_hidden = invisible
    result.cnr = [float(np.median(c)) if c else math.nan for c in cnrs]
    return result


def _shows(image: Gray, intact: Gray, hole: Hole, cam: CameraModel, pose: NetPose,
           mesh: MeshGeometry) -> tuple[bool, float]:
    """Does the frame show the hole, and how clearly? Points along its missing bars (middle
    60 %) against the intact render of the same frame (same noise, same clutter): shown when
    most of them changed (nothing in front of them); the clarity is their median change over
    the frame's noise sigma."""
    import cv2

    from drivers.synthetic_damage import knot_points
    from service.benchmarks.integrity import noise_sigma

    pts = []
    for (fam, i, j), _, _ in hole.stubs:
        for f in np.linspace(0.2, 0.8, 7):
            pts.append((i, j + f) if fam == 1 else (i + f, j))
    xyz = knot_points(pose, mesh, np.array(pts))
    px = cam.project_normalized(xyz[:, :2] / xyz[:, 2:3])
    h, w = image.shape
    x = np.clip(np.round(px[:, 0]).astype(int), 0, w - 1)
    y = np.clip(np.round(px[:, 1]).astype(int), 0, h - 1)
    diff = np.abs(image.astype(np.float32) - intact.astype(np.float32))
    diff = cv2.dilate(diff, np.ones((3, 3), np.uint8))  # the twine's centre within a pixel
    change = diff[y, x]
    shown = float(np.mean(change >= VISIBLE_GREY)) >= VISIBLE_SHARE
    return shown, float(np.median(change)) / max(noise_sigma(image), 0.5)


def _why_missed(res: object, truth: HoleTruth, pad: float) -> str:
    rep = getattr(res, "damage", None)
    if rep is None or not rep.inspected:
        reason = rep.reason if rep is not None else "no inspector"
        est = getattr(res, "estimate", None)
        if est is not None and not est.detected:
            return "no net plane: " + (est.reason.split(":")[0] or "not detected")
        return "not inspected: " + reason
    scan = rep.scan
    if scan is None:
        return "not inspected"
    if scan.reason:
        return "nothing inspected: " + scan.reason
    import cv2

    if len(scan.outline_px) >= 3:
        contour = np.array(scan.outline_px, dtype=np.float32).reshape(-1, 1, 2)
        if cv2.pointPolygonTest(contour, truth.centre_px, False) < 0:
            if scan.windows > 1:
                # The view is inspected a window at a time and this frame looked elsewhere.
                return "outside this frame's window"
            return "outside the inspected region (mesh too fine or too oblique there)"
    for centre, _, why in scan.rejected:
        if _overlaps(centre, truth, pad):
            return "rejected: " + why
    return "no bar judged missing"


def _crop(image: Gray, truth: HoleTruth) -> Gray:
    import cv2

    x0, y0, x1, y1 = truth.box_px
    side = max(48.0, 3.0 * max(x1 - x0, y1 - y0))
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    h, w = image.shape
    a, b = int(max(0, cx - side / 2)), int(max(0, cy - side / 2))
    c, d = int(min(w, cx + side / 2)), int(min(h, cy + side / 2))
    crop = np.ascontiguousarray(image[b:d, a:c])
    return np.asarray(cv2.resize(crop, (160, 160), interpolation=cv2.INTER_AREA), dtype=np.uint8)


# -- running ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class BenchSpec:
    passes: int
    seed: int
    width: int = 1280
    height: int = 720
    keep_misses: bool = False
    frames: int = FRAMES_PER_PASS


def _run_chunk(args: tuple[BenchSpec, list[int]]) -> list[PassResult]:
    import cv2

    cv2.setNumThreads(1)
    spec, indices = args
    settings = DamageSettings()
    base = NetRenderer(bench_camera(spec.width, spec.height), MeshGeometry(0.02))
    out = []
    for index in indices:
        case = draw_pass(spec.seed, index, spec.width, spec.height, frames=spec.frames)
        renderer = copy.copy(base)
        renderer.mesh = case.mesh
        out.append(run_pass(case, renderer, settings, spec.keep_misses))
    return out


def run_passes(spec: BenchSpec, jobs: int,
               progress: Callable[[int], None] | None = None) -> list[PassResult]:
    chunks = [(spec, list(range(i, min(i + 4, spec.passes)))) for i in range(0, spec.passes, 4)]
    results = run_chunks(_run_chunk, chunks, jobs, progress)
    results.sort(key=lambda r: r.case_index)
    return results


# -- real frames --------------------------------------------------------------------------------
@dataclass(frozen=True)
class RealDamage:
    name: str
    kind: str
    detected: bool
    inspected_cells: int
    candidates: int
    confirmed: int
    reason: str


# A still is shown to the pipeline this many times (a hovering ROV: the filter needs a few
# frames before its track is valid, and every look is inspected; the same image each time is
# the hardest case for confirmation, since a false candidate would repeat exactly).
STILL_REPEATS = 8


def run_real(data_dir: Path | None = None) -> list[RealDamage]:
    """The real frames through the pipeline with inspection on every tracked frame: each still
    on its own, shown STILL_REPEATS times; the sequence in order, as the daemon would see it.
    None of them shows a hole: every candidate is a false one."""
    from service.benchmarks.real_frames import default_data_dir, real_field_frames
    from service.core.camera import load_camera
    from service.core.grey import decode_gray

    frames = [f for f in real_field_frames(data_dir or default_data_dir()) if f.kind != "no-net"]
    out = []
    pipeline: Pipeline | None = None
    key: object = None
    t = 0.0
    for frame in frames:
        if frame.kind == "still" or key != (frame.calibration, frame.kind):
            cam = load_camera(frame.calibration)
            pipeline = Pipeline(NetEstimator(cam, frame.mesh), NetTracker(FilterSettings()),
                                inspector=NetInspector(cam, frame.mesh,
                                                       DamageSettings(every_n_frames=1)))
            key = (frame.calibration, frame.kind)
        assert pipeline is not None
        gray, _ = decode_gray(frame.image.read_bytes())
        looks = STILL_REPEATS if frame.kind == "still" else 1
        detected = False
        cells = candidates = confirmed = 0
        reason = ""
        for _ in range(looks):
            t += 1.0 / 30.0  # frames of a 30 frames/s camera
            res = pipeline.process(gray, t, round(t * 30))
            detected |= res.detected
            rep = res.damage
            if rep is None:
                continue
            confirmed += len(rep.confirmed)
            reason = rep.reason or reason
            if rep.scan is not None:
                cells = max(cells, rep.scan.inspected_cells)
                candidates += len(rep.scan.candidates)
        out.append(RealDamage(frame.name, frame.kind, detected, cells, candidates, confirmed,
                              reason))
    return out


# -- reporting ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Summary:
    recall_confirmed: dict[tuple[str, str], tuple[int, int]]  # (size, distance) -> (hit, all)
    recall_frames: dict[tuple[str, str], tuple[int, int]]
    size_errors: list[float]  # |relative error| of width and height, confirmed holes
    intact_frames: int
    intact_false_confirmed: int
    intact_false_candidates: int
    damaged_false_confirmed: int
    real_candidates: int
    real_frames: int
    cost_ratio: float  # inspection CPU / estimator CPU over inspected frames
    inspect_ms_median: float
    estimate_ms_median: float
    hidden_frames: int = 0  # frames where a hole in the frame was not shown (not scored)
    recall_cnr_frames: dict[str, tuple[int, int]] = field(default_factory=dict)
    recall_cnr_confirmed: dict[str, tuple[int, int]] = field(default_factory=dict)

    def target_recall(self) -> tuple[int, int]:
        hit = total = 0
        near = {f"{lo:.1f}-{min(hi, 2.0):.1f}" for lo, hi in DISTANCE_BINS
                if hi <= TARGET_RECALL_RANGE_M + 1e-9}
        for (_, dist), (h, n) in self.recall_confirmed.items():
            if dist in near:
                hit += h
                total += n
        return hit, total

    @property
    def targets(self) -> dict[str, bool | None]:
        """Each target: met, missed, or None where this run measured nothing to judge it by
        (no hole that counts, none confirmed, no real frame)."""
        hit, total = self.target_recall()
        sizes = np.array(self.size_errors)
        per_1000 = 1000.0 * self.intact_false_confirmed / max(self.intact_frames, 1)
        return {
            f"recall of holes >= 2 cells at <= {TARGET_RECALL_RANGE_M} m >= "
            f"{TARGET_RECALL:.0%} ({hit}/{total})":
                hit >= TARGET_RECALL * total if total else None,
            f"size within {TARGET_SIZE_ERROR:.0%} (95 % of widths and heights)":
                float(np.percentile(sizes, 95)) <= TARGET_SIZE_ERROR if sizes.size else None,
            f"<= {TARGET_FALSE_PER_1000:g} false alarm per 1,000 intact frames "
            f"({per_1000:.2f})": per_1000 <= TARGET_FALSE_PER_1000,
            f"no false alarm on the real frames ({self.real_candidates})":
                self.real_candidates == 0 if self.real_frames else None,
            "inspection <= 30 % of the estimator's time": self.cost_ratio <= 0.30,
        }


def _size_label(cells: int) -> str:
    for lo, hi, label in SIZE_CLASSES:
        if lo <= cells <= hi:
            return label
    return f"{cells} cells"


def _cnr_label(cnr: float) -> str:
    for lo, hi in CNR_BINS:
        if lo <= cnr < hi:
            return f"{lo:g}-{hi:g}" if math.isfinite(hi) else f">={lo:g}"
    return "?"


def _dist_label(r: float) -> str:
    for lo, hi in DISTANCE_BINS:
        if lo <= r < hi:
            return f"{lo:.1f}-{min(hi, 2.0):.1f}"
    return "other"


def summarise(results: list[PassResult], real: list[RealDamage]) -> Summary:
    conf: dict[tuple[str, str], list[int]] = {}
    per_frame: dict[tuple[str, str], list[int]] = {}
    sizes: list[float] = []
    intact_frames = intact_fc = intact_cand = damaged_fc = hidden = 0
    cnr_frames: dict[str, list[int]] = {}
    cnr_conf: dict[str, list[int]] = {}
    inspected_est: list[float] = []
    inspected_ins: list[float] = []
    for res in results:
        damaged = bool(res.holes)
        if damaged:
            damaged_fc += res.confirmed_false
        else:
            intact_frames += len({r.frame for r in res.rows})
            intact_fc += res.confirmed_false
            intact_cand += sum(r.false_candidates for r in res.rows)
        for r in res.rows:
            if r.inspected:
                inspected_est.append(r.estimate_ms)
                inspected_ins.append(r.inspect_ms)
            if r.hole_cells:
                cnr_cell = cnr_frames.setdefault(_cnr_label(r.cnr), [0, 0])
                cnr_cell[0] += r.detected
                cnr_cell[1] += 1
            if r.hole_cells and r.cnr >= MIN_CNR:
                key = (_size_label(r.hole_cells), _dist_label(r.hole_range_m))
                cell = per_frame.setdefault(key, [0, 0])
                cell[0] += r.detected
                cell[1] += 1
        hidden += sum(res.frames_hidden)
        for k, truth in enumerate(res.holes):
            # A hole counts when it was shown in at least MIN_FRAMES_SHOWN frames.
            if res.frames_in_view[k] < MIN_FRAMES_SHOWN:
                continue
            found_any = any(e[0] == k for e in res.confirmed_true)
            cnr_cell = cnr_conf.setdefault(_cnr_label(res.cnr[k]), [0, 0])
            cnr_cell[0] += found_any
            cnr_cell[1] += 1
            if not res.cnr[k] >= MIN_CNR:
                continue
            key = (_size_label(truth.cells), _dist_label(truth.range_m))
            cell = conf.setdefault(key, [0, 0])
            found = [e for e in res.confirmed_true if e[0] == k]
            cell[0] += bool(found)
            cell[1] += 1
            for _, ew, eh in found[:1]:
                sizes += [abs(ew), abs(eh)]
    est = np.array(inspected_est)
    ins = np.array(inspected_ins)
    return Summary(
        recall_confirmed={k: (v[0], v[1]) for k, v in conf.items()},
        recall_frames={k: (v[0], v[1]) for k, v in per_frame.items()},
        size_errors=sizes, intact_frames=intact_frames, intact_false_confirmed=intact_fc,
        intact_false_candidates=intact_cand, damaged_false_confirmed=damaged_fc,
        real_candidates=sum(r.candidates for r in real), real_frames=len(real),
        cost_ratio=float(ins.sum() / est.sum()) if est.size and est.sum() > 0 else math.nan,
        inspect_ms_median=float(np.median(ins)) if ins.size else math.nan,
        estimate_ms_median=float(np.median(est)) if est.size else math.nan,
        hidden_frames=hidden,
        recall_cnr_frames={k: (v[0], v[1]) for k, v in cnr_frames.items()},
        recall_cnr_confirmed={k: (v[0], v[1]) for k, v in cnr_conf.items()},
    )


def _table(title: str, cells: dict[tuple[str, str], tuple[int, int]]) -> list[str]:
    dists = [f"{lo:.1f}-{min(hi, 2.0):.1f}" for lo, hi in DISTANCE_BINS]
    lines = [f"{title} (found/all):", "  " + " " * 11 + "".join(f"{d + ' m':>16}" for d in dists)]
    for _, _, size in SIZE_CLASSES:
        row = []
        for d in dists:
            h, n = cells.get((size, d), (0, 0))
            row.append(f"{h:>5}/{n:<4} {h / n:4.0%}" if n else f"{'-':>16}")
        lines.append(f"  {size:11}" + "".join(f"{c:>16}" for c in row))
    return lines


def format_report(results: list[PassResult], real: list[RealDamage]) -> list[str]:
    s = summarise(results, real)
    lines = _table(f"confirmed holes by size and distance (contrast/noise >= {MIN_CNR:g})",
                   s.recall_confirmed)
    lines += _table(f"per frame, the detector alone (contrast/noise >= {MIN_CNR:g})",
                    s.recall_frames)
    for title, cells in (("confirmed", s.recall_cnr_confirmed), ("per frame", s.recall_cnr_frames)):
        parts = [f"{label} {h}/{n} {h / n:.0%}" for label, (h, n) in sorted(cells.items()) if n]
        lines.append(f"recall by the hole's contrast/noise ({title}, all sizes and distances): "
                     + "; ".join(parts))
    sizes = np.array(s.size_errors)
    if sizes.size:
        lines.append(f"size error of confirmed holes (|relative|, width and height): median "
                     f"{np.median(sizes):.1%}, 95 % {np.percentile(sizes, 95):.1%}, max "
                     f"{sizes.max():.1%} ({sizes.size // 2} holes)")
    lines.append(f"intact passes: {s.intact_frames} frames, {s.intact_false_confirmed} false "
                 f"holes confirmed ({1000 * s.intact_false_confirmed / max(s.intact_frames, 1):.2f}"
                 f" per 1,000 frames), {s.intact_false_candidates} single-frame candidates "
                 f"({1000 * s.intact_false_candidates / max(s.intact_frames, 1):.1f} per 1,000)")
    lines.append(f"passes with a hole: {s.damaged_false_confirmed} false holes confirmed besides "
                 f"the true ones; {s.hidden_frames} frames where the hole was in the frame but "
                 "not shown (hidden by a board, a fish, a rope; not scored)")
    lines.append(f"real frames: {s.real_frames} frames with a net, {s.real_candidates} "
                 f"candidates, {sum(r.confirmed for r in real)} confirmed; inspected cells per "
                 f"frame median {np.median([r.inspected_cells for r in real]) if real else 0:.0f}")
    for r in real:
        if r.candidates or r.kind == "still":
            lines.append(f"  {r.kind:8} {r.name:18} net {'yes' if r.detected else 'no '} "
                         f"cells {r.inspected_cells:5d} candidates {r.candidates} "
                         f"{r.reason}")
    lines.append(f"cost: inspection {s.inspect_ms_median:.1f} ms median per inspected frame, "
                 f"estimator {s.estimate_ms_median:.1f} ms; inspection / estimator time "
                 f"{s.cost_ratio:.0%} when every tracked frame is inspected (the daemon holds "
                 "it to damage.max_cost_fraction by skipping frames)")
    why: dict[str, int] = {}
    for res in results:
        for row in res.rows:
            if row.hole_cells and not row.detected and row.hole_range_m <= 2.0:
                key = "".join("N" if ch.isdigit() else ch
                              for ch in row.why.split("(")[0].strip())
                why[key] = why.get(key, 0) + 1
    if why:
        lines.append("why holes in view were not detected in a frame (count):")
        for key, count in sorted(why.items(), key=lambda kv: -kv[1])[:10]:
            lines.append(f"  {count:6d}  {key}")
    return lines


def write_misses(results: list[PassResult], path: Path, limit: int = 24) -> int:
    """A contact sheet of missed holes (crops around the truth), captioned with why."""
    import cv2

    tiles = []
    for res in results:
        for caption, crop in res.miss_images:
            tile = cv2.cvtColor(crop, cv2.COLOR_GRAY2BGR)
            tile = cv2.copyMakeBorder(tile, 0, 34, 0, 0, cv2.BORDER_CONSTANT, value=(0, 0, 0))
            for line, text in enumerate((caption[:26], caption[26:52])):
                cv2.putText(tile, text, (3, 174 + 14 * line), cv2.FONT_HERSHEY_SIMPLEX, 0.36,
                            (255, 255, 255), 1, cv2.LINE_AA)
            tiles.append(tile)
    tiles = tiles[:limit]
    if not tiles:
        return 0
    cols = 6
    while len(tiles) % cols:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.hstack(tiles[i:i + cols]) for i in range(0, len(tiles), cols)]
    cv2.imwrite(str(path), np.vstack(rows))
    return len(tiles)


def run(passes: int, seed: int, jobs: int, out: Path | None, width: int = 1280,
        height: int = 720, real: bool = True, frames: int = FRAMES_PER_PASS) -> int:
    jobs = jobs or min(2, os.cpu_count() or 1)
    spec = BenchSpec(passes, seed, width, height, keep_misses=out is not None, frames=frames)
    print(f"netpose bench damage: {passes} passes of {frames} frames ({width}x{height}),"
          f" seed {seed}, {jobs} worker processes")
    start = time.monotonic()
    done = [0]

    def progress(n: int) -> None:
        done[0] += n
        if sys.stderr.isatty():
            print(f"\r  {done[0]}/{passes} passes ", end="", file=sys.stderr, flush=True)

    results = run_passes(spec, jobs, progress)
    if sys.stderr.isatty():
        print(file=sys.stderr)
    real_rows = run_real() if real else []
    for line in format_report(results, real_rows):
        print(line)
    print(f"wall {time.monotonic() - start:.0f} s")
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        n = write_misses(results, out / "damage-misses.png")
        if n:
            print(f"wrote {out / 'damage-misses.png'} ({n} missed holes)")
    s = summarise(results, real_rows)
    ok = True
    for name, met in s.targets.items():
        verdict = "not measurable in this run" if met is None else "met" if met else "MISSED"
        print(f"target: {name}: {verdict}")
        ok &= met is True
    print("RESULT:", "all targets met" if ok else "some targets missed")
    return 0 if ok else 1
