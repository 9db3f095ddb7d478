"""Net inspection over time: a candidate hole becomes a hole when it stays put on the net.

`DamageDetector` judges one frame. Here candidates are followed from frame to frame on the net
plane (coordinates right and down of the camera's foot point on the plane, in metres, from the
estimated pose), so a hole is reported once, when confirmed, not once per frame:

- a candidate joins the track whose predicted place on the net (its last place moved by its
  own velocity) is nearest, within `gate_m` plus how far the net can have moved since;
- confirmation counts *looks*: inspections whose judged region (where a hole and the ring
  around it are inside what was inspected) held the track's predicted place. Not every frame
  inspects every place (a large view is inspected a window at a time), so a frame that did not
  look at the place says nothing about it. A track is confirmed when it was found in
  `confirm_hits` of its last `confirm_looks` looks (a caustic, a fish or a streak of light does
  not come back at the same place of the net), and dropped, unconfirmed, as soon as the looks
  since its last sighting leave it no way to get there;
- a track not seen for `track_timeout_s` ends; a confirmed one lives on while its predicted
  place is in the frame and the looks at it have not stopped finding it (a view is inspected
  a window at a time, and the detector misses some looks: the ROV holding a hole in view must
  not hear of it again every few seconds). Once it has ended it is forgotten: the net is
  periodic, so netpose cannot tell where on the net it is once the hole has left the view.

`NetInspector` puts detector and tracker together for the pipeline, and decides which frames
are inspected: only frames whose track is valid, at most `max_cost_fraction` of the
estimator's time on average (or every `every_n_frames`-th frame).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from service.core.camera import CameraModel
from service.core.damage import (
    DamageDetector,
    DamageScan,
    DamageSettings,
    HoleCandidate,
    NetFrame,
    net_frame_of,
)
from service.core.mesh import MeshGeometry
from service.core.results import NetEstimate

Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]

# How fast the net may move across the view between two inspected frames before its velocity
# is known (m/s): an ROV inspecting a net moves at a few tenths of a metre per second.
# MAVLink 1's STATUSTEXT: ground stations show at most this many characters.
STATUSTEXT_LENGTH = 50
MAX_SPEED_MPS = 0.6
# Once the velocity is known, how much it may change (m/s); of a confirmed hole's, measured
# over more sightings, less: a confirmed missing knot's gate grew to 0.26 m in a gap of 0.9 s
# and took the sightings of a tear 0.25 m away, which was never reported.
SPEED_UNCERTAINTY_MPS = 0.2
CONFIRMED_SPEED_UNCERTAINTY_MPS = 0.1
# Sightings of one hole differ in size (a bar at the edge of a fouled tear seen or not: 2 to 5
# cells for a 3-cell tear); holes of more than twice the track's usual size are other holes,
# however near the gate lets them be (a confirmed 3-cell tear took every sighting of a 10-cell
# one 0.25 m away, which was never reported). Sizes kept per track, for its median.
SAME_SIZE_RATIO = 2.0
SIZES_KEPT = 9
# Inspection time banked at most: this many frames' worth of earned share.
CREDIT_FRAMES = 30


@dataclass(frozen=True, eq=False)
class ConfirmedHole:
    """A hole seen at the same place of the net in several frames: what is reported."""

    hole_id: int
    t_first: float  # capture time of the first detection (frames' clock)
    t_confirmed: float  # capture time of the frame that confirmed it
    frame_index: int  # that frame's number
    detections: int  # inspections it was found in, up to confirmation
    looks: int  # inspections that judged its place, up to confirmation
    width_m: float  # median of the detections, knot to knot along the plane's horizontal
    height_m: float  # along the plane's vertical
    cells: int  # mesh openings merged (median of the detections)
    missing_bars: int
    centre_px: Vec2  # in the confirming frame
    box_px: tuple[float, float, float, float]
    plane_xy_m: Vec2  # on the net plane, right/down of the camera's foot point
    point_m: Vec3  # camera frame
    range_m: float  # camera to the hole
    confidence: float  # 0..1
    crop: npt.NDArray[np.uint8] | None = field(default=None, repr=False)  # best evidence
    crop_box_px: tuple[float, float, float, float] | None = None  # the hole in the crop
    # The crop's pixels per metre on the net at the hole, from the sighting the crop is of
    # (the reported size is the median of all sightings: another number of cells).
    crop_px_per_m: float | None = None

    @property
    def bearing(self) -> str:
        """Where it is seen from the camera, in a pilot's words for a camera looking ahead:
        ahead, ahead-left, ..., with "high"/"low" when well above or below the optical axis."""
        return self.bearing_as("ahead")

    def bearing_as(self, facing: str) -> str:
        """`bearing` for a camera whose axis points `facing` as the vehicle sees it ("ahead",
        "below", ...). Left and high are the vehicle's only for a camera looking ahead; for
        any other the place is said in the view's terms, as the pilot sees it on the video:
        "below, view top-left"."""
        x, y, z = self.point_m
        side = math.degrees(math.atan2(x, z))
        up = math.degrees(math.atan2(-y, z))
        horizontal = "" if abs(side) < 10.0 else ("right" if side > 0 else "left")
        vertical = "top" if up > 15.0 else "bottom" if up < -15.0 else ""
        if facing == "ahead":
            words = "ahead" + (f"-{horizontal}" if horizontal else "")
            return words + {"top": " high", "bottom": " low", "": ""}[vertical]
        part = "-".join(w for w in (vertical, horizontal) if w)
        return f"{facing}, view {part}" if part else facing

    def pilot_text(self, facing: str = "ahead", more: int = 0) -> str:
        """The STATUSTEXT (at most 50 characters): "net: hole ~6x4 cm ahead-left at 1.1 m"
        (`facing`: where the camera looks, as for `bearing_as`), with " (+2)" when `more`
        holes were held back by the rate limit. Built to fit, not cut: cut, a camera looking
        down lost the range and the count ("net: hole ~12x10 cm below, view bottom-right at
        1."). The place is said shorter ("below BR"), or not at all, before anything else."""
        w = max(1, round(self.width_m * 100))
        h = max(1, round(self.height_m * 100))
        head = f"net: hole ~{w}x{h} cm"
        tail = f"at {self.range_m:.1f} m" + (f" (+{more})" if more else "")
        text = ""
        for where in (self.bearing_as(facing), self._bearing_short(facing), ""):
            text = " ".join(part for part in (head, where, tail) if part)
            if len(text) <= STATUSTEXT_LENGTH:
                return text
        return text[:STATUSTEXT_LENGTH]

    def _bearing_short(self, facing: str) -> str:
        """`bearing_as` in two letters for the view's part: "below BR", "ahead-left high"."""
        words = self.bearing_as(facing)
        if ", view " not in words:
            return words
        where, part = words.split(", view ")
        return f"{where} " + "".join(w[0].upper() for w in part.split("-"))


@dataclass
class _Track:
    track_id: int
    t_first: float
    t_last: float
    position: npt.NDArray[np.float64]  # on the plane, metres
    velocity: npt.NDArray[np.float64] | None = None
    hits: list[HoleCandidate] = field(default_factory=list)
    # One entry per look (an inspection that judged its place): found there or not.
    record: list[bool] = field(default_factory=list)
    confirmed: bool = False
    # Once confirmed: its number and the size reported (what the video's label says too).
    hole_id: int | None = None
    reported_size_m: Vec2 | None = None
    cells_seen: list[int] = field(default_factory=list)  # of the last SIZES_KEPT sightings
    # Nothing was inspected for longer than a track lives since it was last seen: its speed
    # says nothing of where it went, so it is looked for only where it was, with the smallest
    # gate, until it is seen again.
    stale: bool = False

    @property
    def looks(self) -> int:
        return len(self.record)

    def same_size(self, cand: HoleCandidate) -> bool:
        """Could `cand` be this hole, by its size in mesh openings against the track's usual
        (the median of its last sightings)?"""
        usual = float(np.median(self.cells_seen)) if self.cells_seen else float(cand.cells)
        return max(cand.cells, usual) <= SAME_SIZE_RATIO * min(cand.cells, usual)

    def predicted(self, t: float, longest_s: float = math.inf) -> npt.NDArray[np.float64]:
        """Where the hole is now by its last place and speed, carried at most `longest_s`:
        a speed measured over a second or two says nothing of where it went over ten. A
        confirmed hole still in view is carried on as long as it lives: its speed is the
        net's across the view, measured over many sightings, and a place that stopped after
        2 s while the net moved on was looked at and not found, so the hole held in view was
        dropped and reported again under a new number."""
        if self.velocity is None or self.stale:
            return self.position
        dt = t - self.t_last if self.confirmed else min(t - self.t_last, longest_s)
        return np.asarray(self.position + self.velocity * dt, dtype=np.float64)

    def gate(self, t: float, base: float, longest_s: float) -> float:
        # A confirmed track can outlive its last sighting (while in view): how far it may
        # have moved since grows only up to what an unconfirmed one is given, `longest_s`.
        dt = min(max(t - self.t_last, 0.0), longest_s)
        speed = (MAX_SPEED_MPS if self.velocity is None else
                 CONFIRMED_SPEED_UNCERTAINTY_MPS if self.confirmed else SPEED_UNCERTAINTY_MPS)
        size = max((max(c.width_m, c.height_m) for c in self.hits[-1:]), default=0.0)
        return base + 0.5 * size + (0.0 if self.stale else speed * dt)


@dataclass(frozen=True)
class TrackView:
    """A track as drawn and listed: where it is in the frame and whether it is confirmed."""

    track_id: int
    confirmed: bool
    detections: int
    centre_px: Vec2
    box_px: tuple[float, float, float, float]
    width_m: float  # a confirmed hole's as reported; a candidate's last sighting's
    height_m: float
    hole_id: int | None = None  # a confirmed hole's number, as reported
    # Sighted in this frame; False: drawn where its place on the net is predicted now.
    seen: bool = True


class HoleTracker:
    """Follows candidate holes on the net plane across frames and confirms them once."""

    def __init__(self, camera: CameraModel, settings: DamageSettings | None = None) -> None:
        self.camera = camera
        self.settings = settings or DamageSettings()
        self._tracks: list[_Track] = []
        self._next_id = 1  # tracks' own numbers (candidates included)
        # Holes are numbered as they are confirmed, 1, 2, 3: numbered as tracks, a report
        # read "hole 4, hole 6" (candidates that came to nothing took the numbers between),
        # and a farm manager asked where hole 5 was.
        self._next_hole = 1
        self._last_update: float | None = None  # the time of the last inspection

    def reset(self) -> None:
        self._tracks = []
        self._last_update = None

    @property
    def next_id(self) -> int:
        """The number the next confirmed hole gets (hole ids are unique in a service run)."""
        return self._next_hole

    def continue_from(self, next_id: int, previous: HoleTracker | None = None) -> None:
        """Go on where another tracker of this run left off: hole numbers after its, and,
        given `previous`, its tracks (confirmed holes are not reported again)."""
        self._next_hole = max(self._next_hole, next_id)
        if previous is not None:
            self._tracks = list(previous._tracks)
            self._next_id = max(self._next_id, previous._next_id)
            self._last_update = previous._last_update

    @property
    def tracks(self) -> list[TrackView]:
        """Every track where it was last sighted."""
        out = []
        for tr in self._tracks:
            last = tr.hits[-1]
            width, height = tr.reported_size_m or (last.width_m, last.height_m)
            out.append(TrackView(tr.track_id, tr.confirmed, len(tr.hits), last.centre_px,
                                 last.box_px, width, height, tr.hole_id))
        return out

    def views(self, t: float, net: NetFrame | None) -> list[TrackView]:
        """The tracks as the frame at `t`, whose net plane is `net`, shows them: one sighted in
        it where it was seen; one not, where its place on the net is predicted now, and not at
        all once that place has left the frame or without a plane. The box of the last
        sighting stayed while the net slid across the view between inspection windows: 18-20
        px off the hole, up to 117 (a hole's width), on intact net half the time (inspection
        report review)."""
        out = []
        for view, tr in zip(self.tracks, self._tracks, strict=True):
            if tr.t_last == t:
                out.append(view)
                continue
            px = self._predicted_pixel(net, tr, t)
            if px is None or not (0.0 <= px[0] <= self.camera.width - 1.0
                                  and 0.0 <= px[1] <= self.camera.height - 1.0):
                continue
            dx, dy = float(px[0]) - view.centre_px[0], float(px[1]) - view.centre_px[1]
            x0, y0, x1, y1 = view.box_px
            out.append(replace(view, centre_px=(float(px[0]), float(px[1])),
                               box_px=(x0 + dx, y0 + dy, x1 + dx, y1 + dy), seen=False))
        return out

    def update(self, scan: DamageScan, t: float, frame_index: int) -> list[ConfirmedHole]:
        """One inspected frame's candidates; returns the holes confirmed by this frame."""
        st = self.settings
        hopeless = st.confirm_looks - st.confirm_hits + 1
        if self._last_update is not None and t - self._last_update > st.track_timeout_s:
            # Nothing was inspected for longer than a track lives (the net lost, a fish in
            # front, a loop behind its budget): a confirmed track carried on its old speed,
            # its gate grown to half a metre, took a new hole 0.35 m away for itself, which
            # was never reported. Each is looked for only where it was last seen, with the
            # smallest gate, until it is seen again (a hole held in view is still the same).
            for tr in self._tracks:
                tr.stale = True
        self._last_update = t
        self._tracks = [tr for tr in self._tracks if t - tr.t_last <= st.track_timeout_s
                        or (tr.confirmed
                            and self._still_in_view(scan, tr, t, st.confirm_looks))]
        candidates = list(scan.candidates)
        pairs = []
        for ci, cand in enumerate(candidates):
            p = np.array(cand.plane_xy_m)
            for ti, tr in enumerate(self._tracks):
                dist = float(np.linalg.norm(p - tr.predicted(t, st.track_timeout_s)))
                if dist <= tr.gate(t, st.gate_m, st.track_timeout_s) and tr.same_size(cand):
                    pairs.append((dist, ci, ti))
        used_c: set[int] = set()
        used_t: set[int] = set()
        for _, ci, ti in sorted(pairs):
            if ci in used_c or ti in used_t:
                continue
            used_c.add(ci)
            used_t.add(ti)
            self._extend(self._tracks[ti], candidates[ci], t)
        # A track whose place this inspection judged, and did not find there, gets a look
        # without a hit; a frame that did not judge its place leaves its record alone.
        for ti, tr in enumerate(self._tracks):
            if ti not in used_t and self.judged(scan, tr, t):
                tr.record.append(False)
                if tr.confirmed:
                    del tr.record[:-st.confirm_looks]
        for ci, cand in enumerate(candidates):
            if ci not in used_c:
                self._tracks.append(_Track(self._next_id, t, t, np.array(cand.plane_xy_m),
                                           hits=[cand], record=[True],
                                           cells_seen=[cand.cells]))
                self._next_id += 1
        # Unconfirmed tracks that can no longer be confirmed: their last looks without a hit
        # leave fewer than `confirm_hits` sightings possible in any window of `confirm_looks`.
        self._tracks = [tr for tr in self._tracks
                        if tr.confirmed or not (len(tr.record) >= hopeless
                                                and not any(tr.record[-hopeless:]))]
        confirmed = []
        for tr in self._tracks:
            if tr.confirmed or sum(tr.record[-st.confirm_looks:]) < st.confirm_hits:
                continue
            tr.confirmed = True
            confirmed.append(self._report(tr, t, frame_index))
        return confirmed

    def open_places(self, t: float) -> list[Vec2]:
        """Predicted places on the net (plane coordinates of this time) of the candidates not
        yet confirmed: where the next inspections should look first."""
        st = self.settings
        out = []
        for tr in self._tracks:
            if not tr.confirmed and t - tr.t_last <= st.track_timeout_s:
                p = tr.predicted(t)
                out.append((float(p[0]), float(p[1])))
        return out

    def _extend(self, tr: _Track, cand: HoleCandidate, t: float) -> None:
        p = np.array(cand.plane_xy_m)
        dt = t - tr.t_last
        if dt > 1e-6:
            v = (p - tr.position) / dt
            tr.velocity = v if tr.velocity is None else 0.5 * tr.velocity + 0.5 * v
        tr.position = p
        tr.t_last = t
        tr.stale = False
        tr.hits.append(cand)
        tr.cells_seen.append(cand.cells)
        del tr.cells_seen[:-SIZES_KEPT]
        tr.record.append(True)
        if tr.confirmed:
            # Reported: only the last sighting and looks are read again (its place, the gate,
            # whether the looks still find it). A hole held in view for an hour must not keep
            # every sighting and its evidence crop.
            del tr.hits[:-1]
            del tr.record[:-self.settings.confirm_looks]

    def _still_in_view(self, scan: DamageScan, tr: _Track, t: float, refuted_after: int
                       ) -> bool:
        """A confirmed hole not sighted for track_timeout_s is still the same hole while its
        predicted place is in the frame and the looks at that place have not stopped finding
        it (`refuted_after` looks in a row without it: it is not where the track says). A view
        is inspected a window at a time and the detector misses some looks: with its track
        ended 2 s after the last sighting, a hole the ROV held in view was confirmed and
        reported again, under a new number, every few seconds."""
        if len(tr.record) >= refuted_after and not any(tr.record[-refuted_after:]):
            return False
        px = self._predicted_pixel(scan.geometry, tr, t)
        if px is None:
            return False
        return bool(0.0 <= px[0] <= self.camera.width - 1.0
                    and 0.0 <= px[1] <= self.camera.height - 1.0)

    def _predicted_pixel(self, net: NetFrame | None, tr: _Track, t: float
                         ) -> npt.NDArray[np.float64] | None:
        """Where the track's predicted place on the net is in the frame whose net plane is
        `net` (None: no plane, or behind the camera)."""
        if net is None:
            return None
        plane_xy = tr.predicted(t, self.settings.track_timeout_s)
        foot = -net.normal * net.distance_m
        point = foot + plane_xy[0] * net.horizontal + plane_xy[1] * net.vertical
        if point[2] <= 1e-6:
            return None
        return np.asarray(self.camera.project_normalized(point[:2] / point[2]),
                          dtype=np.float64)

    def judged(self, scan: DamageScan, tr: _Track, t: float) -> bool:
        """Did this inspection judge the track's predicted place: is it inside the region
        where a hole and its ring were wholly inspected, by at least half the hole's size?"""
        import cv2

        outline = scan.judged_px or scan.outline_px
        px = self._predicted_pixel(scan.geometry, tr, t)
        if px is None or len(outline) < 3:
            return False
        x0, y0, x1, y1 = tr.hits[-1].box_px
        half = 0.5 * max(x1 - x0, y1 - y0)
        contour = np.array(outline, dtype=np.float32).reshape(-1, 1, 2)
        inside = cv2.pointPolygonTest(contour, (float(px[0]), float(px[1])), True)
        return bool(inside >= half)

    def _report(self, tr: _Track, t: float, frame_index: int) -> ConfirmedHole:
        last = tr.hits[-1]
        best = max(tr.hits, key=lambda c: c.significance)
        conf_frame = float(np.median([c.confidence for c in tr.hits]))
        # Repeated sightings add up: each further one halves what is left of the doubt.
        repeat = 1.0 - 0.5 ** max(len(tr.hits) - 1, 0)
        window = tr.record[-self.settings.confirm_looks:]
        confidence = conf_frame * (0.5 + 0.5 * repeat) * sum(window) / len(window)
        tr.hole_id = self._next_hole
        self._next_hole += 1
        tr.reported_size_m = (float(np.median([c.width_m for c in tr.hits])),
                              float(np.median([c.height_m for c in tr.hits])))
        return ConfirmedHole(
            hole_id=tr.hole_id, t_first=tr.t_first, t_confirmed=t, frame_index=frame_index,
            detections=len(tr.hits), looks=tr.looks,
            width_m=tr.reported_size_m[0], height_m=tr.reported_size_m[1],
            cells=int(round(float(np.median([c.cells for c in tr.hits])))),
            missing_bars=int(round(float(np.median([c.missing_bars for c in tr.hits])))),
            centre_px=last.centre_px, box_px=last.box_px, plane_xy_m=last.plane_xy_m,
            point_m=last.point_m, range_m=last.range_m, confidence=min(1.0, confidence),
            crop=best.crop, crop_box_px=best.crop_box_px,
            crop_px_per_m=_px_per_m(best.crop_box_px, best.width_m, best.height_m),
        )


def _px_per_m(box: tuple[float, float, float, float] | None, width_m: float,
              height_m: float) -> float | None:
    """Pixels per metre on the net of a hole's box whose size on the net is known."""
    if box is None:
        return None
    spans = [pixels / metres for pixels, metres in ((box[2] - box[0], width_m),
                                                    (box[3] - box[1], height_m))
             if metres > 0 and math.isfinite(pixels / metres) and pixels > 0]
    return sum(spans) / len(spans) if spans else None


@dataclass(frozen=True, eq=False)
class DamageReport:
    """What inspection did with one frame of the pipeline."""

    inspected: bool  # the detector ran on this frame
    reason: str = ""  # why not, or why it saw nothing ("" when it did)
    scan: DamageScan | None = None
    confirmed: tuple[ConfirmedHole, ...] = ()  # holes confirmed by this frame
    tracks: tuple[TrackView, ...] = ()  # candidates being followed (confirmed or not)
    inspect_ms: float = 0.0
    failed: bool = False  # the inspection raised (a bug): `reason` says what
    skipped: bool = False  # a frame it could have searched, left for the time budget

    @property
    def searched(self) -> bool | None:
        """What a recording keeps for a replay: True when the frame was searched (or the search
        was tried and failed: a replay must meet that frame too), False when the time budget
        skipped it, None when it was not a frame to search (no valid track, inspection off):
        a replay judges that itself."""
        if self.inspected or self.failed:
            return True
        return False if self.skipped else None


class NetInspector:
    """Detector + tracker + the decision which frames to inspect (pure; times come in)."""

    def __init__(self, camera: CameraModel, mesh: MeshGeometry,
                 settings: DamageSettings | None = None,
                 timer: Callable[[], float] = time.perf_counter) -> None:
        # `timer` measures what an inspection costs against the estimator's time (the budget);
        # only which frames are inspected depends on it, and a recording keeps those.
        self.settings = settings or DamageSettings()
        self._timer = timer
        self.detector = DamageDetector(camera, mesh, self.settings)
        self.tracker = HoleTracker(camera, self.settings)
        # Inspection time earned (max_cost_fraction of the estimator's time per tracked frame)
        # minus time spent: an inspection runs while it is not negative, so what is spent never
        # exceeds the share earned by more than one inspection. Capped, so a long stretch of
        # skipped frames does not bank a burst of inspections.
        self._credit_ms = 0.0
        self._tracked_frames = 0
        self.inspected_frames = 0
        self.skipped_frames = 0

    def step(self, image: npt.NDArray[Any], estimate: NetEstimate | None, t: float,
             frame_index: int, track_valid: bool, estimate_ms: float,
             due: bool | None = None) -> DamageReport:
        """One frame of the pipeline. Inspects it when the track is valid, the frame has a
        detection and the budget allows (or, with `due` given, as a recording says the vehicle
        decided: its CPU time chose, and a replay must search the same frames); follows
        candidates either way."""
        st = self.settings
        if not st.enabled:
            return DamageReport(False, "inspection is off (damage.enabled = false)")
        if not track_valid or estimate is None or not estimate.detected:
            # No plane the filter believes: nowhere to draw the holes followed.
            return DamageReport(False, "no valid net track")
        net = net_frame_of(estimate)
        earned = st.max_cost_fraction * max(estimate_ms, 0.0)
        self._credit_ms = min(self._credit_ms + earned, CREDIT_FRAMES * earned)
        self._tracked_frames += 1
        if due is None:
            if st.every_n_frames > 0:
                due = (self._tracked_frames - 1) % st.every_n_frames == 0
            else:
                due = self._credit_ms >= 0.0
        if not due:
            self.skipped_frames += 1
            return DamageReport(False, "skipped: inspection budget", skipped=True,
                                tracks=tuple(self.tracker.views(t, net)))
        t0 = self._timer()
        scan = self.detector.inspect(image, estimate, revisit=self.tracker.open_places(t))
        confirmed = self.tracker.update(scan, t, frame_index)
        ms = (self._timer() - t0) * 1e3
        if st.every_n_frames <= 0:
            self._credit_ms -= ms
        self.inspected_frames += 1
        return DamageReport(True, scan.reason, scan, tuple(confirmed),
                            tuple(self.tracker.views(t, scan.geometry or net)), ms)
