"""`netpose bench integrity`: never a confident wrong distance, over the whole working envelope.

Every frame draws its own case from a seed:
- camera: frame 384x180 .. 1920x1080 (16:9 mostly, also 4:3 and the 384x180 strip), horizontal
  field of view 60-110 deg, plumb-bob distortion (barrel, with the focal length chosen so the
  distorted frame spans that field of view);
- mesh: bar 1-4 cm, square or rhombic (opening 45-80 deg), the estimator configured with it;
- pose: range 0.3-3 m (log-uniform), tilt 0-60 deg about any axis, any roll and phase;
- scene: `SceneStyle.realistic` - fouling, seams, ropes, marker boards, billowing, turbidity,
  lamps, motion blur, JPEG, fish in front; a tenth of the frames have no net at all.
Frames are rendered in groups that share one camera and mesh (building a renderer costs more
than rendering), spread over worker processes; results do not depend on the number of workers.

Each frame whose net gave a distance is followed by a *tracked* frame: the same scene one
camera frame later (30 frames/s) after a plausible move (range +-3 %, tilt and roll +-2 deg,
the mesh shifted by up to a third of a cell, the clutter drawn anew), estimated with the first
frame's estimate as its prior, as the daemon tracks (`prior_age_s` one frame: no blind scale
check while the proof of scale holds). The daemon flies on such frames; they are reported
apart and count for the targets like the others.

A *gross error* is a valid distance off by more than 5 % in range or 10 deg in the normal. The
benchmark reports them (the target is none), the 3-sigma coverage of the reported range sigma,
the spread of error/sigma, detection per condition, and the worst cases with what reproduces
them (`build_case(seed, group, index)`). It also puts statistics of real frames (spectral SNR
per ROI, mesh contrast, noise) beside the rendered ones, to show how close the renderer is.
"""

from __future__ import annotations

import itertools
import math
import os
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import numpy.typing as npt

from drivers.synthetic_net import GroundTruth, NetPose, NetRenderer, SceneStyle
from service.benchmarks.workers import run_chunks
from service.core.camera import CameraModel
from service.core.estimator import NetEstimator
from service.core.mesh import MeshGeometry
from service.core.results import NetEstimate

Gray = npt.NDArray[np.uint8]

FRAME_SIZES = (
    (384, 216), (384, 180), (480, 270), (640, 360), (640, 480), (960, 540), (1280, 720),
    (1920, 1080),
)
GROUP_SIZE = 20
NET_FREE_FRACTION = 0.1
GROSS_RANGE = 0.05
GROSS_NORMAL_DEG = 10.0
# The tracked frame's move in one frame at 30 frames/s: the range by up to 3 % (a closing speed
# of up to 0.3 m/s at 0.3 m, 2.7 m/s at 3 m), tilt and roll by up to 2 deg (60 deg/s), and the
# mesh sideways by up to a third of a cell.
TRACK_FRAME_S = 1.0 / 30.0
TRACK_RANGE_STEP = 0.03
TRACK_ANGLE_STEP_DEG = 2.0
TRACK_PHASE_STEP = 0.33
TARGET_COVERAGE = 0.99
TARGET_Z_STD = (0.7, 1.5)


@dataclass(frozen=True)
class Case:
    """Everything that decides one frame; rebuilt exactly from (seed, group, index)."""

    seed: int
    group: int
    index: int
    camera: CameraModel
    hfov_deg: float
    mesh: MeshGeometry
    pose: NetPose
    style: SceneStyle

    @property
    def period_px(self) -> float:
        """Mesh period (sqrt of the cell area, pixels) where the optical axis meets the net."""
        f = math.sqrt(self.camera.fx * self.camera.fy)
        return f * math.sqrt(self.mesh.cell_area_m2) / self.pose.range_m


def draw_camera(rng: np.random.Generator) -> tuple[CameraModel, float]:
    """A random underwater camera: size, field of view and a monotonic barrel distortion."""
    w, h = FRAME_SIZES[int(rng.integers(len(FRAME_SIZES)))]
    hfov = float(rng.uniform(60.0, 110.0))
    r_edge = math.tan(math.radians(hfov / 2))
    aspect = h / w
    for _ in range(20):
        k1 = float(rng.uniform(-0.25, 0.02))
        k2 = float(rng.uniform(0.0, 0.05))
        p1, p2 = (float(v) for v in rng.uniform(-0.001, 0.001, 2))

        def radial(r: npt.NDArray[np.float64], k1: float = k1, k2: float = k2
                   ) -> npt.NDArray[np.float64]:
            return np.asarray(r * (1 + k1 * r * r + k2 * r**4), dtype=np.float64)

        f = 0.5 * w / float(radial(np.array([r_edge]))[0])
        corner = 0.5 * w * math.hypot(1.0, aspect) / f  # distorted radius of the corner
        r = np.linspace(0.0, 3.0 * r_edge + 1.0, 4000)
        rd = radial(r)
        rising = np.diff(rd) > 0
        # Monotonic (invertible) beyond the frame's corner: a lens, not a fold.
        if rising.all() or rd[int(np.argmin(rising))] > 1.05 * corner:
            break
    else:  # pragma: no cover - the draw above nearly always succeeds
        k1, k2, p1, p2 = 0.0, 0.0, 0.0, 0.0
        f = 0.5 * w / r_edge
    fy = f * float(rng.uniform(0.99, 1.01))
    camera = CameraModel(
        width=w, height=h, fx=f, fy=fy,
        cx=(w - 1) / 2 + float(rng.uniform(-0.02, 0.02)) * w,
        cy=(h - 1) / 2 + float(rng.uniform(-0.02, 0.02)) * h,
        distortion=(k1, k2, p1, p2, 0.0), name=f"integrity_{w}x{h}",
    )
    return camera, hfov


def draw_mesh(rng: np.random.Generator) -> MeshGeometry:
    bar = float(rng.uniform(0.01, 0.04))
    opening = 90.0 if rng.random() < 0.5 else float(rng.uniform(45.0, 80.0))
    return MeshGeometry(bar_length_m=bar, opening_angle_deg=opening)


def _group_draw(seed: int, group: int) -> tuple[CameraModel, float, MeshGeometry]:
    rng = np.random.default_rng([seed, group, 0xCA])
    camera, hfov = draw_camera(rng)
    return camera, hfov, draw_mesh(rng)


def _frame_draw(seed: int, group: int, index: int) -> tuple[NetPose, SceneStyle]:
    rng = np.random.default_rng([seed, group, index, 0xF0])
    z = float(math.exp(rng.uniform(math.log(0.3), math.log(3.0))))
    pose = NetPose(
        z, tilt_deg=float(rng.uniform(0.0, 60.0)), tilt_axis_deg=float(rng.uniform(0, 360)),
        roll_deg=float(rng.uniform(0, 180)),
        phase=(float(rng.uniform(0, 1)), float(rng.uniform(0, 1))),
    )
    net = rng.random() >= NET_FREE_FRACTION
    style = SceneStyle.realistic(rng, net_present=net)
    return pose, style


def moved_case(case: Case) -> Case:
    """The tracked frame's case: the same scene one frame later, after a plausible move."""
    rng = np.random.default_rng([case.seed, case.group, case.index, 0x7A])
    pose = case.pose
    moved = NetPose(
        pose.range_m * float(1.0 + rng.uniform(-TRACK_RANGE_STEP, TRACK_RANGE_STEP)),
        tilt_deg=float(np.clip(pose.tilt_deg + rng.uniform(-TRACK_ANGLE_STEP_DEG,
                                                           TRACK_ANGLE_STEP_DEG), 0.0, 60.0)),
        tilt_axis_deg=pose.tilt_axis_deg,
        roll_deg=pose.roll_deg + float(rng.uniform(-TRACK_ANGLE_STEP_DEG, TRACK_ANGLE_STEP_DEG)),
        phase=(pose.phase[0] + float(rng.uniform(-TRACK_PHASE_STEP, TRACK_PHASE_STEP)),
               pose.phase[1] + float(rng.uniform(-TRACK_PHASE_STEP, TRACK_PHASE_STEP))),
    )
    return replace(case, pose=moved)


def estimate_tracked(case: Case, first: NetEstimate, renderer: NetRenderer,
                     estimator: NetEstimator) -> tuple[Case, Gray, GroundTruth, NetEstimate, float]:
    """The tracked frame after `case`, whose estimate was `first`: its case, frame, truth,
    estimate (with `first` as the prior, one frame later) and estimator CPU time in ms."""
    following = moved_case(case)
    image, truth = render_case(following, renderer, tracked=True)
    t0 = time.thread_time()
    est = estimator.estimate(image, prior=first, prior_age_s=TRACK_FRAME_S)
    return following, image, truth, est, (time.thread_time() - t0) * 1e3


def build_case(seed: int, group: int, index: int) -> Case:
    camera, hfov, mesh = _group_draw(seed, group)
    pose, style = _frame_draw(seed, group, index)
    return Case(seed, group, index, camera, hfov, mesh, pose, style)


def render_case(case: Case, renderer: NetRenderer | None = None, tracked: bool = False
                ) -> tuple[Gray, GroundTruth]:
    renderer = renderer or NetRenderer(case.camera, case.mesh)
    rng = np.random.default_rng([case.seed, case.group, case.index, 0x5C + int(tracked)])
    return renderer.render(case.pose, rng, case.style)


@dataclass(frozen=True)
class Row:
    group: int
    index: int
    width: int
    height: int
    hfov_deg: float
    k1: float
    bar_mm: float
    opening_deg: float
    range_m: float
    tilt_deg: float
    period_px: float
    net: bool
    fouling: float
    boards: int
    seams: int
    ropes: int
    billow: float
    turbidity: float
    spotlight: float
    motion_blur_px: float
    jpeg_quality: int
    fish_front: float
    detected: bool
    too_close: bool
    seen: bool  # recognised as a net, with or without a distance (NetEstimate.net_seen)
    confidence: float
    est_range_m: float
    sigma_range_m: float
    range_error: float  # relative
    normal_error_deg: float
    sigma_normal_deg: float
    reason: str
    ms: float
    approx_z: float = math.nan  # a net seen without a distance: refused range error / its sigma
    tracked: bool = False  # the frame after a valid one, estimated with it as the prior
    searched: bool = False  # the whole frame was searched (a tracked frame: the prior failed)

    @property
    def gross(self) -> bool:
        return self.detected and self.net and (
            abs(self.range_error) > GROSS_RANGE or self.normal_error_deg > GROSS_NORMAL_DEG
        )

    @property
    def z(self) -> float:
        """Range error over the reported sigma."""
        if not self.detected or not self.sigma_range_m > 0:
            return math.nan
        return self.range_error * self.range_m / self.sigma_range_m


def evaluate(case: Case, image: Gray, truth: GroundTruth, est: NetEstimate, ms: float,
             tracked: bool = False) -> Row:
    rel = math.nan
    nerr = math.nan
    if est.detected and est.range_m is not None and truth.net_present:
        rel = est.range_m / truth.range_m - 1.0
    if est.detected and est.normal is not None and truth.net_present:
        cos = float(np.clip(np.dot(est.normal, truth.normal), -1.0, 1.0))
        nerr = math.degrees(math.acos(cos))
    approx_z = math.nan
    if est.approx_range_m is not None and est.approx_sigma_range_m and truth.net_present:
        approx_z = (est.approx_range_m - truth.range_m) / est.approx_sigma_range_m
    st = case.style
    return Row(
        group=case.group, index=case.index, width=case.camera.width, height=case.camera.height,
        hfov_deg=case.hfov_deg, k1=case.camera.distortion[0],
        bar_mm=case.mesh.bar_length_m * 1e3, opening_deg=case.mesh.opening_angle_deg,
        range_m=truth.range_m, tilt_deg=truth.tilt_deg, period_px=case.period_px,
        net=truth.net_present, fouling=st.fouling, boards=st.boards, seams=st.seams,
        ropes=st.ropes, billow=st.billow, turbidity=st.turbidity, spotlight=st.spotlight,
        motion_blur_px=st.motion_blur_px, jpeg_quality=st.jpeg_quality,
        fish_front=truth.occluded_fraction, detected=est.detected, too_close=est.too_close,
        seen=est.net_seen, confidence=est.confidence, est_range_m=est.range_m or math.nan,
        sigma_range_m=est.sigma_range_m or math.nan, range_error=rel, normal_error_deg=nerr,
        sigma_normal_deg=est.sigma_normal_deg or math.nan, reason=est.reason, ms=ms,
        approx_z=approx_z, tracked=tracked, searched=est.searched,
    )


def run_group(args: tuple[int, int, int]) -> list[Row]:
    """Render and estimate one group of frames (one camera and mesh)."""
    import cv2

    cv2.setNumThreads(1)
    seed, group, count = args
    camera, _, mesh = _group_draw(seed, group)
    renderer = NetRenderer(camera, mesh)
    estimator = NetEstimator(camera, mesh)
    estimator.prepare(camera.width, camera.height)
    rows = []
    for index in range(count):
        case = build_case(seed, group, index)
        image, truth = render_case(case, renderer)
        t0 = time.thread_time()
        est = estimator.estimate(image)
        ms = (time.thread_time() - t0) * 1e3
        rows.append(evaluate(case, image, truth, est, ms))
        if est.detected and truth.net_present:
            following, image, truth, est, ms = estimate_tracked(case, est, renderer, estimator)
            rows.append(evaluate(following, image, truth, est, ms, tracked=True))
    return rows


def run_rows(frames: int, seed: int, jobs: int,
             progress: Callable[[int], None] | None = None) -> list[Row]:
    groups = [(seed, g, min(GROUP_SIZE, frames - g * GROUP_SIZE))
              for g in range(math.ceil(frames / GROUP_SIZE))]
    rows = run_chunks(run_group, groups, jobs, progress)
    rows.sort(key=lambda r: (r.group, r.index, r.tracked))
    return rows


# -- reporting ------------------------------------------------------------------------------


@dataclass(frozen=True)
class Summary:
    frames: int
    net_frames: int
    valid: int
    gross: int
    false_nets: int
    false_too_close: int
    coverage_3sigma: float
    z_std: float
    detection: float
    seen_only: int = 0  # frames with a net seen, but no distance (too uncertain)
    seen_only_coverage_3sigma: float = math.nan  # of their refused ranges

    @property
    def targets(self) -> dict[str, bool]:
        return {
            "no gross error among valid outputs": self.gross == 0,
            f"3-sigma coverage >= {TARGET_COVERAGE:.0%}": self.coverage_3sigma >= TARGET_COVERAGE,
            f"std(error/sigma) in {TARGET_Z_STD[0]}-{TARGET_Z_STD[1]}":
                TARGET_Z_STD[0] <= self.z_std <= TARGET_Z_STD[1],
            "no net-free frame taken for a net": self.false_nets == 0,
        }


def summarise(rows: list[Row]) -> Summary:
    net = [r for r in rows if r.net]
    valid = [r for r in net if r.detected]
    z = np.array([r.z for r in valid if math.isfinite(r.z)])
    seen_only = [r for r in net if r.seen and not r.detected]
    seen_z = np.array([r.approx_z for r in seen_only if math.isfinite(r.approx_z)])
    return Summary(
        frames=len(rows),
        net_frames=len(net),
        valid=len(valid),
        gross=sum(r.gross for r in valid),
        # A net-free frame recognised as a net is a false net, with or without a distance.
        false_nets=sum(r.seen for r in rows if not r.net),
        false_too_close=sum(r.too_close for r in rows if not r.net),
        coverage_3sigma=float(np.mean(np.abs(z) <= 3.0)) if z.size else math.nan,
        z_std=float(np.std(z)) if z.size > 1 else math.nan,
        detection=len(valid) / max(1, len(net)),
        seen_only=len(seen_only),
        seen_only_coverage_3sigma=float(np.mean(np.abs(seen_z) <= 3.0)) if seen_z.size
        else math.nan,
    )


def _bins(rows: list[Row]) -> Iterable[tuple[str, list[tuple[str, list[Row]]]]]:
    net = [r for r in rows if r.net]

    def split(edges: list[float], fmt: str,
              key: Callable[[Row], float]) -> list[tuple[str, list[Row]]]:
        return [(fmt.format(lo, hi), [r for r in net if lo <= key(r) < hi])
                for lo, hi in itertools.pairwise(edges)]

    yield "mesh period px", split([0, 3, 6, 12, 25, 50, 100, 1e9], "{:.0f}-{:.0f}",
                                  lambda r: r.period_px)
    yield "range m", split([0.3, 0.5, 1.0, 2.0, 3.01], "{:.1f}-{:.1f}", lambda r: r.range_m)
    yield "tilt deg", split([0, 20, 40, 50, 61], "{:.0f}-{:.0f}", lambda r: r.tilt_deg)
    yield "frame width", [(f"{w}", [r for r in net if r.width == w])
                          for w in sorted({r.width for r in net})]
    yield "hfov deg", split([60, 75, 90, 110.1], "{:.0f}-{:.0f}", lambda r: r.hfov_deg)
    yield "mesh", [("square", [r for r in net if r.opening_deg == 90.0]),
                   ("rhombic", [r for r in net if r.opening_deg != 90.0])]
    flags: list[tuple[str, Callable[[Row], bool]]] = [
        ("fouling", lambda r: r.fouling > 0), ("boards", lambda r: r.boards > 0),
        ("seams", lambda r: r.seams > 0), ("ropes", lambda r: r.ropes > 0),
        ("billow", lambda r: r.billow > 0), ("turbidity", lambda r: r.turbidity > 0),
        ("lamps", lambda r: r.spotlight > 0), ("motion blur", lambda r: r.motion_blur_px >= 1),
        ("jpeg", lambda r: r.jpeg_quality > 0), ("fish in front", lambda r: r.fish_front > 0),
    ]
    yield "condition", [(name, [r for r in net if test(r)]) for name, test in flags]


def format_report(rows: list[Row], worst: int = 8) -> list[str]:
    """The cold frames' report (each frame on its own), then the tracked frames' in brief."""
    following = [r for r in rows if r.tracked]
    rows = [r for r in rows if not r.tracked]
    s = summarise(rows)
    lines = [
        f"frames {s.frames} ({s.net_frames} with a net), valid outputs {s.valid} "
        f"({s.detection:.1%} of frames with a net)",
        f"gross errors (|range| > {GROSS_RANGE:.0%} or normal > {GROSS_NORMAL_DEG:.0f} deg): "
        f"{s.gross}",
        f"3-sigma coverage of the range: {s.coverage_3sigma:.2%}; std(error/sigma) "
        f"{s.z_std:.2f}",
        f"net seen without a distance (plane too uncertain): {s.seen_only} frames, their "
        f"refused range within 3 sigma of the truth in {s.seen_only_coverage_3sigma:.1%}",
        f"net-free frames: {s.false_nets} taken for a net, {s.false_too_close} 'too close' "
        f"(of {s.frames - s.net_frames})",
        "detection rate | gross | coverage by condition:",
    ]
    for title, groups in _bins(rows):
        cells = []
        for label, part in groups:
            if not part:
                continue
            det = [r for r in part if r.detected]
            z = np.array([r.z for r in det if math.isfinite(r.z)])
            cov = f"{np.mean(np.abs(z) <= 3):.0%}" if z.size else "-"
            gross = sum(r.gross for r in det)
            cells.append(f"{label} {len(det) / len(part):.0%} ({len(part)}) g{gross} c{cov}")
        lines.append(f"  {title:14}: " + "; ".join(cells))
    refusals: dict[str, int] = {}
    for r in rows:
        if r.net and not r.detected:
            key = r.reason.split(":")[0].split("(")[0].strip()
            key = "".join("N" if ch.isdigit() else ch for ch in key)
            refusals[key] = refusals.get(key, 0) + 1
    lines.append("why frames with a net gave no distance (count):")
    for key, count in sorted(refusals.items(), key=lambda kv: -kv[1])[:10]:
        lines.append(f"  {count:6d}  {key}")
    valid = [r for r in rows if r.net and r.detected]
    if valid:
        lines.append("worst cases by |range error| (reproduce: build_case(seed, group, index)):")
        for r in sorted(valid, key=lambda r: -abs(r.range_error))[:worst]:
            lines.append("  " + describe_row(r))
        lines.append("worst cases by |error/sigma|:")
        for r in sorted(valid, key=lambda r: -abs(r.z) if math.isfinite(r.z) else 0)[:worst]:
            lines.append("  " + describe_row(r))
    if following:
        t = summarise(following)
        kept = summarise([r for r in following if not r.searched])
        lines += [
            f"tracked frames (the frame after each valid one, that one as the prior): "
            f"{t.frames}, valid {t.valid} ({t.detection:.1%}), gross errors {t.gross}, "
            f"3-sigma coverage {t.coverage_3sigma:.2%}, std(error/sigma) {t.z_std:.2f}, "
            f"net seen without a distance {t.seen_only}",
            f"  of them the prior held (no search): {kept.frames}, valid {kept.valid}, gross "
            f"errors {kept.gross}, 3-sigma coverage {kept.coverage_3sigma:.2%}; searched whole "
            f"(the prior failed): {t.frames - kept.frames}, valid {t.valid - kept.valid}, gross "
            f"errors {t.gross - kept.gross}",
        ]
        wrong = [r for r in following if r.gross]
        for r in sorted(wrong, key=lambda r: -abs(r.range_error))[:worst]:
            lines.append("  gross, tracked: " + describe_row(r))
    return lines


def describe_row(r: Row) -> str:
    extras = [name for name, on in (
        ("fouling", r.fouling > 0), ("boards", r.boards > 0), ("seams", r.seams > 0),
        ("ropes", r.ropes > 0), ("billow", r.billow > 0), ("turbid", r.turbidity > 0),
        ("lamps", r.spotlight > 0), ("blur", r.motion_blur_px >= 1),
        (f"jpeg{r.jpeg_quality}", r.jpeg_quality > 0), ("fish", r.fish_front > 0)) if on]
    return (f"group {r.group} index {r.index}: {r.width}x{r.height} hfov {r.hfov_deg:.0f} "
            f"bar {r.bar_mm:.1f} mm {r.opening_deg:.0f} deg, range {r.range_m:.2f} m tilt "
            f"{r.tilt_deg:.0f}, period {r.period_px:.1f} px [{' '.join(extras)}] -> "
            f"{r.est_range_m:.3f} m ({r.range_error:+.2%}, sigma {r.sigma_range_m * 1e3:.1f} mm,"
            f" z {r.z:+.1f}), normal {r.normal_error_deg:.1f} deg")


def write_csv(path: Path, rows: list[Row]) -> None:
    import csv

    with path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=[*asdict(rows[0]).keys(), "gross", "z"])
        writer.writeheader()
        for r in rows:
            writer.writerow({**asdict(r), "gross": r.gross, "z": r.z})


def run(frames: int, seed: int, jobs: int, out: Path | None, realism: bool = True) -> int:
    jobs = jobs or min(2, os.cpu_count() or 1)
    print(f"netpose bench integrity: {frames} frames, seed {seed}, {jobs} worker processes")
    start = time.monotonic()
    done = [0]

    def progress(n: int) -> None:
        done[0] += n
        if sys.stderr.isatty():
            rate = done[0] / max(1e-6, time.monotonic() - start)
            print(f"\r  {done[0]}/{frames} frames, {rate:.1f}/s ", end="", file=sys.stderr,
                  flush=True)

    rows = run_rows(frames, seed, jobs, progress)
    elapsed = time.monotonic() - start
    if sys.stderr.isatty():
        print(file=sys.stderr)
    for line in format_report(rows):
        print(line)
    ms = np.array([r.ms for r in rows])
    print(f"estimator CPU per frame: median {np.median(ms):.1f} ms, p95 "
          f"{np.percentile(ms, 95):.1f} ms; wall {elapsed:.0f} s "
          f"({frames / max(elapsed, 1e-9):.1f} frames/s with rendering)")
    if realism:
        for line in realism_report(seed):
            print(line)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        write_csv(out / "integrity.csv", rows)
        print(f"wrote {out / 'integrity.csv'}")
    ok = True
    for label, part in (("", [r for r in rows if not r.tracked]),
                        ("tracked frames: ", [r for r in rows if r.tracked])):
        if not part:
            continue
        for name, met in summarise(part).targets.items():
            print(f"target: {label}{name}: {'met' if met else 'MISSED'}")
            ok &= met
    print("RESULT:", "all targets met" if ok else "some targets missed")
    return 0 if ok else 1


# -- realism: real frames against rendered ones -------------------------------------------------


@dataclass(frozen=True)
class FrameStats:
    """What the estimator sees of a net in one frame: spectral SNR of its ROIs' lattices (dB),
    mesh contrast (amplitude of the fundamental over the local mean) and sensor noise (grey
    levels, Immerkaer's estimator)."""

    snr_db: float
    contrast: float
    noise: float


def noise_sigma(gray: Gray) -> float:
    """Immerkaer (1996): noise sigma from the Laplacian-difference operator, in grey levels."""
    import cv2

    kernel = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    resp = cv2.filter2D(gray.astype(np.float32), -1, kernel)[1:-1, 1:-1]
    h, w = gray.shape
    return float(math.sqrt(math.pi / 2) * np.abs(resp).sum() / (6.0 * (w - 2) * (h - 2)))


def frame_stats(gray: Gray, est: NetEstimate) -> FrameStats | None:
    """Statistics over the ROIs whose lattice was used in the fit; None without such ROIs."""
    used = [r for r in est.rois if r.used_in_fit and r.reciprocal is not None]
    if not used:
        return None
    img = gray.astype(np.float64)
    contrasts = []
    for roi in used:
        if roi.reciprocal is None:
            continue
        n = min(roi.size_px, 256)
        x0 = int(round(roi.center_px[0] - n / 2))
        y0 = int(round(roi.center_px[1] - n / 2))
        x0 = min(max(x0, 0), gray.shape[1] - n)
        y0 = min(max(y0, 0), gray.shape[0] - n)
        if x0 < 0 or y0 < 0:
            continue
        patch = img[y0:y0 + n, x0:x0 + n]
        win = np.outer(np.hanning(n), np.hanning(n))
        yy, xx = np.mgrid[0:n, 0:n]
        k = np.asarray(roi.reciprocal[0])  # cycles per pixel, the first reduced basis vector
        phase = np.exp(-2j * math.pi * (k[0] * xx + k[1] * yy))
        mean = float((patch * win).sum() / win.sum())
        amp = 2.0 * abs(complex(((patch - mean) * win * phase).sum())) / float(win.sum())
        contrasts.append(amp / max(mean, 1.0))
    return FrameStats(
        snr_db=float(np.median([r.snr_db for r in used])),
        contrast=float(np.median(contrasts)) if contrasts else math.nan,
        noise=noise_sigma(gray),
    )


def realism_report(seed: int, rendered: int = 60) -> list[str]:
    """Real and rendered frames side by side: median [quartiles] of each statistic."""
    from service.benchmarks.real_frames import default_data_dir, real_field_frames, run_frames

    frames = [f for f in real_field_frames(default_data_dir()) if f.kind != "no-net"]
    lines = ["realism: real frames vs rendered (median [25-75 %] over frames with a net found)"]
    if not frames:
        return [*lines, "  real-field data not found: no comparison"]
    real: list[FrameStats] = []
    from service.core.grey import decode_gray

    for result in run_frames(frames):
        gray, _ = decode_gray(result.frame.image.read_bytes())
        st = frame_stats(gray, result.estimate)
        if st is not None:
            real.append(st)
    synth: list[FrameStats] = []
    group = 10_000
    while len(synth) < rendered and group < 10_400:
        camera, _, mesh = _group_draw(seed, group)
        renderer = NetRenderer(camera, mesh)
        estimator = NetEstimator(camera, mesh)
        for index in range(5):
            case = build_case(seed, group, index)
            if not case.style.net_present:
                continue
            image, _ = render_case(case, renderer)
            st = frame_stats(image, estimator.estimate(image))
            if st is not None:
                synth.append(st)
        group += 1

    def q(values: list[float]) -> str:
        v = np.array([x for x in values if math.isfinite(x)])
        if not v.size:
            return "-"
        a, b, c = np.percentile(v, [25, 50, 75])
        return f"{b:6.3g} [{a:.3g}-{c:.3g}]"

    for name in ("snr_db", "contrast", "noise"):
        lines.append(f"  {name:9}: real {q([getattr(s, name) for s in real]):26} "
                     f"rendered {q([getattr(s, name) for s in synth])}")
    lines.append(f"  ({len(real)} real frames, {len(synth)} rendered frames with a net found)")
    return lines
