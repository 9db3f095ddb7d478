"""Which part of a large view net inspection looks at in this frame.

Inspection costs time in proportion to the cells it judges, so a view of more than
`max_cells_inspected` cells is inspected one window of cells per frame. Which window:

1. **Candidates first.** A candidate hole is confirmed by being found again where it was
   (damage_track.py): a window holding the predicted places of open candidates, with room for
   the hole and its ring, is preferred to any other. The more of them it holds the better.
2. **Then what was looked at longest ago.** Every place of the net (a bin of the net plane,
   about one cell) remembers the inspection that last judged it. Among the windows, the one
   whose judged cells were judged longest ago (never: the longest) is taken, so the whole view
   is covered in about as few frames as its windows' judged areas allow, without the fixed,
   overlapping strips a sequential scan needs.

Places are coordinates on the net plane (right and down of the camera's foot point, metres:
`NetFrame.plane_xy`), which move as the ROV moves along the net; the memory does not follow
that motion (netpose does not measure it), so it is only trusted for about as many inspections
as the view needs to be covered (`horizon`): older is as good as never.

Pure numpy; one planner per detector (its memory is that detector's).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]

# The net plane remembered: this far from the camera's foot point each way, in metres.
MEMORY_EXTENT_M = 6.0
# A judged hole needs this many inspected cells around it every way (its ring and the cells
# beyond, damage.py); a window's judged cells are its cells this far from its edges.
RING_CELLS = 3
# A candidate's place counts as held by a window only with this many cells to spare inside
# its judged cells (a hole of up to 4 x 4 cells around its centre).
PLACE_MARGIN_CELLS = 2


@dataclass(frozen=True)
class Window:
    """Cells of the region to inspect: first cell (i0, j0), counts (n1, n2); `windows`: about
    how many such windows the view needs (1: the whole view); `revisits`: open candidates'
    places it holds."""

    i0: int
    j0: int
    n1: int
    n2: int
    windows: int = 1
    revisits: int = 0


class InspectionPlanner:
    """Chooses the window of a region inspected in this frame, and remembers it."""

    def __init__(self, bin_m: float) -> None:
        self.bin_m = float(bin_m)
        side = int(math.ceil(2.0 * MEMORY_EXTENT_M / self.bin_m))
        # Number of the inspection that last judged each bin (-1: never); inspections counted.
        # int32: at a 25 mm bar this is 480 x 480 bins, 0.9 MB of the daemon's RSS as int64,
        # and 2**31 inspections are two years of frames (`choose` starts over before that).
        self._last = np.full((side, side), -1, dtype=np.int32)
        self._count = 0

    def reset(self) -> None:
        self._last[:] = -1
        self._count = 0

    def _bins(self, xy: F64) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64],
                                      npt.NDArray[np.bool_]]:
        side = self._last.shape[0]
        b = np.floor((xy + MEMORY_EXTENT_M) / self.bin_m).astype(np.int64)
        bx, by = b[..., 0], b[..., 1]
        # Compared coordinate by coordinate: a reduction over an axis of two costs ten times
        # as much on grids of this size.
        inside = np.asarray((bx >= 0) & (by >= 0) & (bx < side) & (by < side), dtype=bool)
        return np.clip(bx, 0, side - 1), np.clip(by, 0, side - 1), inside

    def choose(self, view: npt.NDArray[np.bool_], cells_xy: F64, cap: int,
               places: F64) -> Window:
        """The window (at most `cap` cells) of a region to inspect now.

        `view`: (n2, n1) cells of the region in view and resolved; `cells_xy`: (n2, n1, 2)
        their centres on the net plane; `places`: (k, 2) open candidates' predicted places in
        the region's cell coordinates (i, j, fractional)."""
        n2, n1 = view.shape
        if self._count >= np.iinfo(self._last.dtype).max:
            self.reset()
        self._count += 1
        if n1 * n2 <= cap:
            self._remember(cells_xy, view, 0, 0, n1, n2)
            return Window(0, 0, n1, n2)
        w1, w2 = _window_shape(n1, n2, cap)
        inner1, inner2 = w1 - 2 * RING_CELLS, w2 - 2 * RING_CELLS
        in_view = int(view.sum())
        horizon = max(2, math.ceil(in_view / max(inner1 * inner2, 1)))
        bi, bj, known = self._bins(cells_xy)
        last = np.where(known, self._last[bj, bi], -1)
        age = np.where(last >= 0, self._count - last, horizon)
        weight = np.where(view, np.minimum(age, horizon) / horizon, 0.0)
        # Sum of the weights of each window's judged cells, for every window position (a, b).
        integral = np.zeros((n2 + 1, n1 + 1))
        integral[1:, 1:] = weight.cumsum(axis=0).cumsum(axis=1)
        a = np.arange(n1 - w1 + 1)[None, :] + RING_CELLS
        b = np.arange(n2 - w2 + 1)[:, None] + RING_CELLS
        score = (integral[b + inner2, a + inner1] - integral[b, a + inner1]
                 - integral[b + inner2, a] + integral[b, a])
        # Each open candidate's place held with room to spare counts more than any coverage.
        held = np.zeros_like(score, dtype=np.int64)
        for pi, pj in np.asarray(places, dtype=np.float64).reshape(-1, 2):
            lo_i, hi_i = a + PLACE_MARGIN_CELLS, a + inner1 - PLACE_MARGIN_CELLS
            lo_j, hi_j = b + PLACE_MARGIN_CELLS, b + inner2 - PLACE_MARGIN_CELLS
            held += (lo_i <= pi) & (pi <= hi_i) & (lo_j <= pj) & (pj <= hi_j)
        total = score + held * (float(weight.sum()) + 1.0)
        jb, ia = np.unravel_index(int(np.argmax(total)), total.shape)
        i0, j0 = int(ia), int(jb)
        self._remember(cells_xy, view, i0 + RING_CELLS, j0 + RING_CELLS, inner1, inner2)
        return Window(i0, j0, w1, w2, windows=horizon, revisits=int(held[jb, ia]))

    def _remember(self, cells_xy: F64, view: npt.NDArray[np.bool_], i0: int, j0: int,
                  n1: int, n2: int) -> None:
        """The cells judged by this inspection: their bins were judged now."""
        sub = cells_xy[j0 : j0 + n2, i0 : i0 + n1]
        bi, bj, known = self._bins(sub)
        keep = known & view[j0 : j0 + n2, i0 : i0 + n1]
        self._last[bj[keep], bi[keep]] = self._count


def _window_shape(n1: int, n2: int, cap: int) -> tuple[int, int]:
    """A window of at most `cap` cells, as square as the region allows (the most judged cells
    for its cost: its ring of RING_CELLS is inspected but not judged)."""
    side = max(math.isqrt(cap), 2 * RING_CELLS + 2 * PLACE_MARGIN_CELLS + 1)
    if n1 <= side:
        return n1, min(n2, max(cap // n1, side))
    if n2 <= side:
        return min(n1, max(cap // n2, side)), n2
    return side, side
