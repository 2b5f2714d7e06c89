"""Which placed frames the mosaic is stitched from: a frame that shows only skin enough stitched frames already show is
left out of the stitch (it is still placed on the path).

A long examination passes over the same skin again and again (the simulated 4-minute one stitches 570 of its 2400
frames: bench/finish.py): every frame over skin already shown costs a paste live and at the finish, which pastes every
frame that moved again, and adds little the mosaic lacks. Each frame is decided once, when it is placed, from its
centre at that place: it is stitched when at least NEW_SKIN_SHARE of the skin its window covers is covered by fewer
than `cap` stitched frames. The window is taken as its inscribed disc, the same at any yaw, and the skin as a grid of
CELL_MM cells in mosaic mm. A scan in rows or strokes brings new skin with nearly every frame and leaves none out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

CELL_MM = 2.0  # the skin's cells (mm): fine against a window of 60 mm, coarse against a pose's later moves
MAX_CELLS = 2500  # the grid's largest side (5 m of skin): a frame placed beyond it is stitched, and counts nothing
NEW_SKIN_SHARE = 0.05  # a frame is stitched when this share of its disc's cells is covered fewer than `cap` times


@dataclass
class StitchCover:
    """How many stitched frames cover each cell of the skin, and the rule that admits a frame to the stitch.

    cap: the cover above which skin counts as shown (0: every frame is stitched); radius_mm: the window's inscribed
    disc. The grid grows with the skin scanned (cells in mosaic mm, counts as int32).
    """

    cap: int
    radius_mm: float
    counts: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.int32))
    origin: tuple[int, int] = (0, 0)  # the cell (col, row) of counts[0, 0]
    _disc: tuple[np.ndarray, np.ndarray] = field(init=False, repr=False)  # the disc's cells about its centre's
    _reach: int = field(init=False, repr=False)  # the disc's radius in cells

    def __post_init__(self) -> None:
        self._reach = max(0, math.floor(self.radius_mm / CELL_MM))
        dy, dx = np.mgrid[-self._reach : self._reach + 1, -self._reach : self._reach + 1]
        inside = (dx * dx + dy * dy) * CELL_MM**2 <= self.radius_mm**2
        self._disc = (dy[inside].astype(np.intp), dx[inside].astype(np.intp))

    def admit(self, centre_mm: tuple[float, float]) -> bool:
        """Return True when a frame whose window is centred at `centre_mm` (mosaic mm) is to be stitched, and count
        its window's cells as covered once more if so; False leaves the counts as they were."""
        if self.cap <= 0 or not all(math.isfinite(v) for v in centre_mm):
            return True
        cells = self._cells(centre_mm)
        if cells is None:  # too far from the skin counted so far to grow the grid to it
            return True
        rows, cols = cells
        if np.count_nonzero(self.counts[rows, cols] < self.cap) < NEW_SKIN_SHARE * rows.size:
            return False
        self.counts[rows, cols] += 1
        return True

    def _cells(self, centre_mm: tuple[float, float]) -> tuple[np.ndarray, np.ndarray] | None:
        """Return the (rows, cols) of `counts` under a window centred at `centre_mm`, the grid grown to hold them, or
        None when that would make it larger than MAX_CELLS a side."""
        col, row = (math.floor(v / CELL_MM) for v in centre_mm)
        dy, dx = self._disc
        reach = self._reach
        if not self._grow(col - reach, row - reach, col + reach, row + reach):
            return None
        return dy + (row - self.origin[1]), dx + (col - self.origin[0])

    def _grow(self, c0: int, r0: int, c1: int, r1: int) -> bool:
        """Return True once the grid holds cells c0..c1, r0..r1 (inclusive), grown by a margin of at least a quarter
        each way; False (the grid unchanged) when the cells it would have to hold span more than MAX_CELLS a side."""
        h, w = self.counts.shape
        oc, orow = self.origin
        if h and w:
            if c0 >= oc and r0 >= orow and c1 < oc + w and r1 < orow + h:
                return True
            c0, r0, c1, r1 = min(c0, oc), min(r0, orow), max(c1, oc + w - 1), max(r1, orow + h - 1)
        if max(c1 - c0, r1 - r0) >= MAX_CELLS:
            return False
        margin = max(8, w // 4, h // 4)
        c0, r0, c1, r1 = c0 - margin, r0 - margin, c1 + margin, r1 + margin
        grown = np.zeros((r1 - r0 + 1, c1 - c0 + 1), np.int32)
        if h and w:
            grown[orow - r0 : orow - r0 + h, oc - c0 : oc - c0 + w] = self.counts
        self.counts, self.origin = grown, (c0, r0)
        return True
