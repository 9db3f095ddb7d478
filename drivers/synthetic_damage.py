"""Damage for the synthetic net: cut bars, missing knots and torn holes, with their truth.

A net is knots joined by bars. Knot (i, j) sits at lattice coordinates (s1, s2) = (i, j) (the
renderer's coordinates, phase included). Bars of the first family lie along s1 = i and join
knots (i, j) and (i, j + 1); bars of the second family lie along s2 = j and join (i, j) and
(i + 1, j). Cell (i, j) is the mesh opening with corners (i, j) .. (i + 1, j + 1).

Every kind of damage is a set of bars that are gone, which merges the openings they separated
into one hole:

- a **cut bar**: one bar, two cells merged (the smallest hole; the bar's ends stay on the knots
  as short stubs);
- a **missing knot**: the four bars of one knot, four cells merged;
- a **torn hole** of k cells (2..10): a connected set of k cells, every bar between two of them
  gone (and with it every knot inside), the torn bars' ends left as stubs.

The hole's size is that of the opening it makes: the extent of its merged cells, knot to knot,
on the net plane along the plane's horizontal and vertical (the camera's right and down laid
onto the plane) - what `service.core.damage` measures too.

`NetDamage` is what `NetRenderer.render(..., damage=...)` takes (`TwineCut`); it remembers the
truth mask of each hole from the last frame it cut.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from drivers.synthetic_net import NetPose
from service.core.camera import CameraModel
from service.core.mesh import MeshGeometry
from service.core.plane_frame import plane_axes

FloatMap = npt.NDArray[np.float64]
BoolMap = npt.NDArray[np.bool_]
Cell = tuple[int, int]
Bar = tuple[int, int, int]  # (family 1 or 2, i, j)

KINDS = ("cut_bar", "missing_knot", "torn")


@dataclass(frozen=True)
class Hole:
    """One hole: the cells it merges and the bars that are gone (with their stubs)."""

    kind: str
    cells: frozenset[Cell]
    bars: frozenset[Bar]
    # Stub length at each end of each missing bar, as a fraction of the bar (0 at a knot that
    # is itself gone).
    stubs: tuple[tuple[Bar, float, float], ...] = ()

    @property
    def size_cells(self) -> int:
        return len(self.cells)

    def knots(self) -> list[Cell]:
        """Corner knots of the hole's cells."""
        return sorted({(i + di, j + dj) for i, j in self.cells for di in (0, 1) for dj in (0, 1)})


def bars_between(cells: frozenset[Cell]) -> frozenset[Bar]:
    """Bars separating two cells of the set: bar (1, i, j) separates cells (i - 1, j) and
    (i, j); bar (2, i, j) separates (i, j - 1) and (i, j)."""
    bars: set[Bar] = set()
    for i, j in cells:
        if (i - 1, j) in cells:
            bars.add((1, i, j))
        if (i, j - 1) in cells:
            bars.add((2, i, j))
    return frozenset(bars)


def _stubbed(bars: frozenset[Bar], cells: frozenset[Cell], rng: np.random.Generator
             ) -> tuple[tuple[Bar, float, float], ...]:
    """Stubs of torn bars: where the bar's knot is still there (some of its four bars are),
    a random stub of up to a third of the bar stays on it."""

    def knot_gone(i: int, j: int) -> bool:
        return all(c in cells for c in ((i - 1, j - 1), (i, j - 1), (i - 1, j), (i, j)))

    out = []
    for bar in sorted(bars):
        fam, i, j = bar
        end_a, end_b = ((i, j), (i, j + 1)) if fam == 1 else ((i, j), (i + 1, j))
        lo = 0.0 if knot_gone(*end_a) else float(rng.uniform(0.0, 0.33))
        hi = 0.0 if knot_gone(*end_b) else float(rng.uniform(0.0, 0.33))
        out.append((bar, lo, hi))
    return tuple(out)


def cut_bar(cell: Cell, family: int, rng: np.random.Generator) -> Hole:
    """The bar on the low side of `cell` in `family` cut: `cell` and its neighbour merge."""
    i, j = cell
    other = (i - 1, j) if family == 1 else (i, j - 1)
    cells = frozenset({cell, other})
    bars = frozenset({(family, i, j)})
    return Hole("cut_bar", cells, bars, _stubbed(bars, cells, rng))


def missing_knot(knot: Cell, rng: np.random.Generator) -> Hole:
    i, j = knot
    cells = frozenset({(i - 1, j - 1), (i, j - 1), (i - 1, j), (i, j)})
    bars = bars_between(cells)
    return Hole("missing_knot", cells, bars, _stubbed(bars, cells, rng))


def torn_hole(seed_cell: Cell, size: int, rng: np.random.Generator) -> Hole:
    """A connected set of `size` cells grown at random from `seed_cell` (compact: each new cell
    touches the set on as many sides as the candidates allow, like a tear opening up)."""
    cells = {seed_cell}
    while len(cells) < size:
        frontier: dict[Cell, int] = {}
        for i, j in cells:
            for n in ((i + 1, j), (i - 1, j), (i, j + 1), (i, j - 1)):
                if n not in cells:
                    frontier[n] = frontier.get(n, 0) + 1
        options = sorted(frontier)
        weights = np.array([4.0 ** frontier[c] for c in options])
        cells.add(options[int(rng.choice(len(options), p=weights / weights.sum()))])
    frozen = frozenset(cells)
    bars = bars_between(frozen)
    return Hole("torn", frozen, bars, _stubbed(bars, frozen, rng))


@dataclass(frozen=True)
class HoleTruth:
    """What a rendered hole is: its cells and bars, size on the plane and place in the image."""

    hole: Hole
    width_m: float  # knot to knot, along the plane's horizontal
    height_m: float  # along the plane's vertical
    centre_px: tuple[float, float]
    box_px: tuple[float, float, float, float]  # x0, y0, x1, y1 of its knots in the image
    range_m: float  # camera to the hole's centre
    mask: BoolMap | None = field(default=None, compare=False)  # pixels of its opening

    @property
    def cells(self) -> int:
        return self.hole.size_cells

    @property
    def missing_bars(self) -> int:
        return len(self.hole.bars)


class NetDamage:
    """Holes in the rendered net (a `TwineCut` for `NetRenderer.render`). After each render,
    `masks[k]` holds the pixels of hole k's opening in that frame."""

    def __init__(self, holes: list[Hole]) -> None:
        self.holes = list(holes)
        self.masks: list[BoolMap] = []

    def __call__(self, s1: FloatMap, s2: FloatMap) -> tuple[FloatMap, FloatMap]:
        kept1 = np.ones_like(s1)
        kept2 = np.ones_like(s2)
        self.masks = []
        for hole in self.holes:
            box = self._near(hole, s1, s2)
            self.masks.append(self._opening(hole, s1, s2, box))
            if box is None:
                continue
            ys, xs = box
            a, b = s1[ys, xs], s2[ys, xs]
            for (fam, i, j), lo, hi in hole.stubs:
                along, across, line = (b, a, i) if fam == 1 else (a, b, j)
                start = j if fam == 1 else i
                t = along - start
                cut = (np.abs(across - line) < 0.5) & (t > lo) & (t < 1.0 - hi)
                # Where the cut bar crosses a knot that is gone, nothing of the other family's
                # twine is left on that knot either (its own bars are in `stubs` too).
                target = kept1 if fam == 1 else kept2
                sub = target[ys, xs]
                sub[cut] = 0.0
                target[ys, xs] = sub
        return kept1, kept2

    @staticmethod
    def _near(hole: Hole, s1: FloatMap, s2: FloatMap) -> tuple[slice, slice] | None:
        """Pixel box around the hole (its cells plus one cell), or None when out of view."""
        i0 = min(i for i, _ in hole.cells) - 1
        i1 = max(i for i, _ in hole.cells) + 2
        j0 = min(j for _, j in hole.cells) - 1
        j1 = max(j for _, j in hole.cells) + 2
        inside = (s1 >= i0) & (s1 <= i1) & (s2 >= j0) & (s2 <= j1)
        rows = np.flatnonzero(inside.any(axis=1))
        cols = np.flatnonzero(inside.any(axis=0))
        if rows.size == 0 or cols.size == 0:
            return None
        return slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1)

    @staticmethod
    def _opening(hole: Hole, s1: FloatMap, s2: FloatMap, box: tuple[slice, slice] | None
                 ) -> BoolMap:
        mask = np.zeros(s1.shape, dtype=bool)
        if box is None:
            return mask
        ys, xs = box
        ci = np.floor(s1[ys, xs]).astype(np.int64)
        cj = np.floor(s2[ys, xs]).astype(np.int64)
        sub = np.zeros(ci.shape, dtype=bool)
        for i, j in hole.cells:
            sub |= (ci == i) & (cj == j)
        mask[ys, xs] = sub
        return mask


# -- where things are ---------------------------------------------------------------------------
def knot_points(pose: NetPose, mesh: MeshGeometry, knots: npt.ArrayLike) -> FloatMap:
    """Camera-frame 3D points (metres) of knots (i, j) of the rendered net (flat: billowing
    moves them along the normal by millimetres, which no size here depends on)."""
    k = np.asarray(knots, dtype=np.float64).reshape(-1, 2)
    s1 = k[:, 0] - pose.phase[0]
    s2 = k[:, 1] - pose.phase[1]
    alpha = math.radians(mesh.opening_angle_deg)
    pu = mesh.bar_length_m * (s1 + s2 * math.cos(alpha))
    pv = mesh.bar_length_m * s2 * math.sin(alpha)
    rot = pose.rotation()
    p0 = np.array([0.0, 0.0, pose.range_m])
    return np.asarray(p0 + np.outer(pu, rot[:, 0]) + np.outer(pv, rot[:, 1]), dtype=np.float64)


def lattice_at_pixels(camera: CameraModel, pose: NetPose, mesh: MeshGeometry,
                      pixels: npt.ArrayLike) -> FloatMap:
    """Lattice coordinates (s1, s2) where the rays of these pixels meet the (flat) net; NaN
    where they miss it."""
    px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    rays = camera.undistort_pixels(px)
    r = np.concatenate([rays, np.ones((len(rays), 1))], axis=1)
    rot = pose.rotation()
    away = rot[:, 2]
    denom = r @ away
    t = np.where(denom > 1e-6, pose.distance_m() / np.where(denom > 1e-6, denom, 1.0), np.nan)
    pts = r * t[:, None] - np.array([0.0, 0.0, pose.range_m])
    pu, pv = pts @ rot[:, 0], pts @ rot[:, 1]
    alpha = math.radians(mesh.opening_angle_deg)
    s2 = pv / (mesh.bar_length_m * math.sin(alpha))
    s1 = pu / mesh.bar_length_m - s2 * math.cos(alpha)
    return np.stack([s1 + pose.phase[0], s2 + pose.phase[1]], axis=1)


def hole_truth(hole: Hole, camera: CameraModel, pose: NetPose, mesh: MeshGeometry,
               mask: BoolMap | None = None) -> HoleTruth:
    """Size on the plane (knot to knot along its horizontal and vertical) and place in the
    image of a hole in the rendered net."""
    pts = knot_points(pose, mesh, hole.knots())
    h, v = plane_axes(pose.normal_towards_camera())
    width = float(np.ptp(pts @ h))
    height = float(np.ptp(pts @ v))
    centre = pts.mean(axis=0)
    px = camera.project_normalized(pts[:, :2] / pts[:, 2:3])
    c = camera.project_normalized(centre[:2] / centre[2])
    return HoleTruth(
        hole=hole, width_m=width, height_m=height, centre_px=(float(c[0]), float(c[1])),
        box_px=(float(px[:, 0].min()), float(px[:, 1].min()), float(px[:, 0].max()),
                float(px[:, 1].max())),
        range_m=float(np.linalg.norm(centre)), mask=mask,
    )


def random_hole(rng: np.random.Generator, at: Cell, size_cells: int | None = None,
                kind: str | None = None) -> Hole:
    """A hole of a random kind (or the one asked for) whose first cell is `at`; torn holes have
    `size_cells` cells (2..10, drawn when None)."""
    kind = kind or str(rng.choice(KINDS))
    if kind == "cut_bar":
        return cut_bar(at, int(rng.integers(1, 3)), rng)
    if kind == "missing_knot":
        return missing_knot(at, rng)
    size = size_cells if size_cells is not None else int(rng.integers(2, 11))
    return torn_hole(at, size, rng)


def cell_at_pixel(camera: CameraModel, pose: NetPose, mesh: MeshGeometry,
                  pixel: tuple[float, float]) -> Cell | None:
    """The mesh cell under a pixel, or None when its ray misses the net."""
    s = lattice_at_pixels(camera, pose, mesh, [pixel])[0]
    if not np.isfinite(s).all():
        return None
    return int(math.floor(s[0])), int(math.floor(s[1]))
