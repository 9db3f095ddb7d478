"""The replay's record of net damage: damage.csv (one row per confirmed hole), the evidence
crops and a contact sheet of them (damage.png), and the marks drawn on annotated frames."""

from __future__ import annotations

import csv
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import IO

import cv2
import numpy as np
import numpy.typing as npt

from service.core.damage_track import ConfirmedHole, DamageReport

BGR = npt.NDArray[np.uint8]

CONFIRMED = (0, 0, 255)  # red: a confirmed hole
CANDIDATE = (0, 220, 255)  # yellow: a candidate being followed
INSPECTED = (200, 160, 0)  # teal: the part of the frame inspected in this frame

DAMAGE_CSV = "damage.csv"
CONTACT_SHEET = "damage.png"
CROPS_DIR = "damage"
DAMAGE_COLUMNS = (
    "hole_id", "frame", "time_s", "width_cm", "height_cm", "cells", "missing_bars",
    "image_x_px", "image_y_px", "plane_x_m", "plane_y_m", "range_m", "bearing", "confidence",
    "detections", "looks", "first_seen_s", "crop",
    # the frame's capture time as the vehicle's clock said it (a recording's), to join a hole
    # with the dive's log; empty where the input does not keep it (a video, a folder)
    "time_unix",
    # the bar length the sizes are counted in (--mesh-size): a CSV handed on keeps its scale
    "bar_length_m",
    # the crop for a report: enlarged, the hole marked, captioned, with a scale bar of one bar
    "evidence",
)
# An evidence image is at least this wide: a 71-148 px crop does not go into a report.
EVIDENCE_MIN_PX = 480
EVIDENCE_MARK = (0, 0, 255)  # BGR red, as the annotated video's confirmed holes


def hole_label(hole: ConfirmedHole) -> str:
    """"hole 3: 6x4 cm" (knot to knot on the net plane)."""
    return (f"hole {hole.hole_id}: {max(1, round(hole.width_m * 100))}x"
            f"{max(1, round(hole.height_m * 100))} cm")


class DamageCsv:
    """damage.csv and the crops: one row and one PNG per confirmed hole, written as they come
    (a replay that is interrupted keeps what it found)."""

    def __init__(self, out_dir: Path, bar_length_m: float) -> None:
        self.out_dir = out_dir
        self.bar_length_m = bar_length_m
        self.path = out_dir / DAMAGE_CSV
        self._file: IO[str] = self.path.open("w", newline="", encoding="utf-8")
        self._writer = csv.writer(self._file)
        self._writer.writerow(DAMAGE_COLUMNS)
        self.holes: list[tuple[ConfirmedHole, int]] = []

    def write(self, hole: ConfirmedHole, frame: int, time_s: float,
              time_unix: float | None = None) -> None:
        crop_name = ""
        if hole.crop is not None and hole.crop.size:
            crops = self.out_dir / CROPS_DIR
            crops.mkdir(exist_ok=True)
            crop_name = f"{CROPS_DIR}/hole_{hole.hole_id:03d}.png"
            cv2.imwrite(str(self.out_dir / crop_name), hole.crop)
        marked = evidence_image(hole, frame, time_s, time_unix, self.bar_length_m)
        evidence_name = ""
        if marked is not None:
            evidence_name = f"{CROPS_DIR}/hole_{hole.hole_id:03d}_evidence.png"
            cv2.imwrite(str(self.out_dir / evidence_name), marked)
        first = time_s - (hole.t_confirmed - hole.t_first)
        self._writer.writerow([
            hole.hole_id, frame, f"{time_s:.3f}", f"{hole.width_m * 100:.1f}",
            f"{hole.height_m * 100:.1f}", hole.cells, hole.missing_bars,
            f"{hole.centre_px[0]:.1f}", f"{hole.centre_px[1]:.1f}", f"{hole.plane_xy_m[0]:.3f}",
            f"{hole.plane_xy_m[1]:.3f}", f"{hole.range_m:.3f}", hole.bearing,
            f"{hole.confidence:.2f}", hole.detections, hole.looks, f"{first:.3f}", crop_name,
            "" if time_unix is None else f"{time_unix:.3f}", f"{self.bar_length_m:g}",
            evidence_name,
        ])
        self._file.flush()
        self.holes.append((hole, frame))

    def close(self) -> None:
        self._file.close()


def evidence_image(hole: ConfirmedHole, frame: int, time_s: float, time_unix: float | None,
                   bar_length_m: float) -> BGR | None:
    """A hole's crop as a report takes it: enlarged by whole pixels (each one kept as the camera
    gave it), the hole's knots boxed, a scale bar one bar long at the hole, and a caption with
    its number, size, place, frame and time. None without a crop."""
    crop = hole.crop
    if crop is None or not crop.size:
        return None
    grey = crop if crop.ndim == 2 else cv2.cvtColor(crop, cv2.COLOR_BGR2GRAY)
    k = max(1, math.ceil(EVIDENCE_MIN_PX / grey.shape[1]))
    image = cv2.cvtColor(cv2.resize(grey, (grey.shape[1] * k, grey.shape[0] * k),
                                    interpolation=cv2.INTER_NEAREST), cv2.COLOR_GRAY2BGR)
    thick = max(2, k // 2)
    box = hole.crop_box_px
    if box is not None and all(math.isfinite(v) for v in box):
        x0, y0, x1, y1 = (v * k for v in box)
        pad = 0.15 * max(x1 - x0, y1 - y0) + 2 * thick
        cv2.rectangle(image, (round(x0 - pad), round(y0 - pad)),
                      (round(x1 + pad), round(y1 + pad)), EVIDENCE_MARK, thick, cv2.LINE_AA)
        # Pixels per metre at the hole, of the sighting the crop is of.
        if hole.crop_px_per_m is not None:
            bar_px = round(bar_length_m * hole.crop_px_per_m * k)
            h = image.shape[0]
            x, y = 12, h - 14
            cv2.line(image, (x, y), (x + bar_px, y), (255, 255, 255), thick + 2, cv2.LINE_AA)
            cv2.line(image, (x, y), (x + bar_px, y), (0, 0, 0), max(1, thick - 1), cv2.LINE_AA)
            cv2.putText(image, f"1 bar = {bar_length_m * 100:g} cm", (x, y - 10),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    when = f"frame {frame}, {time_s:.1f} s"
    if time_unix is not None and math.isfinite(time_unix):
        when += ", " + time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(time_unix))
    lines = [f"{hole_label(hole)} ({hole.cells} cells, {hole.missing_bars} bars missing)",
             f"{hole.bearing} at {hole.range_m:.2f} m, confidence {hole.confidence:.2f}", when]
    caption = np.zeros((22 * len(lines) + 8, image.shape[1], 3), np.uint8)
    for i, text in enumerate(lines):
        cv2.putText(caption, text, (8, 20 + 22 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                    (255, 255, 255), 1, cv2.LINE_AA)
    return np.asarray(np.vstack([image, caption]), dtype=np.uint8)


def contact_sheet(holes: Sequence[tuple[ConfirmedHole, int]], tile: int = 160,
                  columns: int = 5) -> BGR | None:
    """The evidence crops side by side, each captioned with its hole, size and frame."""
    tiles = []
    for hole, frame in holes:
        crop = hole.crop
        if crop is None or not crop.size:
            image = np.zeros((tile, tile, 3), np.uint8)
        else:
            grey = crop if crop.ndim == 2 else cv2.cvtColor(crop, cv2.COLOR_BGR2GRAY)
            f = tile / max(grey.shape[:2])
            size = (max(1, round(grey.shape[1] * f)), max(1, round(grey.shape[0] * f)))
            small = cv2.resize(grey, size, interpolation=cv2.INTER_AREA if f < 1 else
                               cv2.INTER_LINEAR)
            image = np.zeros((tile, tile, 3), np.uint8)
            y0, x0 = (tile - size[1]) // 2, (tile - size[0]) // 2
            image[y0:y0 + size[1], x0:x0 + size[0]] = cv2.cvtColor(small, cv2.COLOR_GRAY2BGR)
        caption = np.zeros((36, tile, 3), np.uint8)
        cv2.putText(caption, hole_label(hole), (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.42,
                    (255, 255, 255), 1, cv2.LINE_AA)
        cv2.putText(caption, f"frame {frame}, {hole.range_m:.2f} m, {hole.bearing}", (4, 30),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.36, (200, 200, 200), 1, cv2.LINE_AA)
        tiles.append(np.vstack([image, caption]))
    if not tiles:
        return None
    columns = min(columns, len(tiles))
    while len(tiles) % columns:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.hstack(tiles[i:i + columns]) for i in range(0, len(tiles), columns)]
    return np.asarray(np.vstack(rows), dtype=np.uint8)


def write_contact_sheet(holes: Sequence[tuple[ConfirmedHole, int]], out_dir: Path
                        ) -> Path | None:
    sheet = contact_sheet(holes)
    if sheet is None:
        return None
    path = out_dir / CONTACT_SHEET
    cv2.imwrite(str(path), sheet)
    return path


def draw_damage(image: BGR, report: DamageReport | None, scale: float, font: float,
                thick: int) -> None:
    """Marks on an annotated frame (drawn in place): the part of the frame inspected in this
    frame, candidates being followed (yellow) and confirmed holes (red, with their size), with
    a thinner line where one not sighted in this frame is predicted."""
    if report is None:
        return
    scan = report.scan
    if scan is not None and len(scan.outline_px) >= 3:
        pts = np.round(np.array(scan.outline_px) * scale).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(image, [pts], True, INSPECTED, max(1, thick - 1), cv2.LINE_AA)
    for track in report.tracks:
        x0, y0, x1, y1 = (v * scale for v in track.box_px)
        if not all(math.isfinite(v) for v in (x0, y0, x1, y1)):
            continue
        pad = max(3.0, 0.25 * max(x1 - x0, y1 - y0))
        p0 = (round(x0 - pad), round(y0 - pad))
        p1 = (round(x1 + pad), round(y1 + pad))
        colour = CONFIRMED if track.confirmed else CANDIDATE
        # Not sighted in this frame (drawn where the net's motion puts it): a thinner line.
        weight = thick + (1 if track.confirmed else 0) - (0 if track.seen else 1)
        cv2.rectangle(image, p0, p1, colour, max(1, weight), cv2.LINE_AA)
        if track.confirmed:
            text = (f"hole {track.hole_id}: {max(1, round(track.width_m * 100))}x"
                    f"{max(1, round(track.height_m * 100))} cm")
            cv2.putText(image, text, (p0[0], max(12, p0[1] - 6)), cv2.FONT_HERSHEY_SIMPLEX,
                        font * 0.7, colour, max(1, thick), cv2.LINE_AA)
