"""A canvas's own millimetres: one scale and shift (no turn) from the path's millimetres to where frames are pasted.

A live session's canvas keeps the units it was pasted in when a finish (or a finish run ahead) changes the path's
units by one scale and shift, as the compliance gauge and frame 0's rest centre do: mosaic.json's px_per_mm and
origin_px carry them (spec §4: the mosaic is in frame 0's axes, its scale and origin given), and only the frames that
moved otherwise are pasted again. Offline the units are the identity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# A frame whose corners miss the first fit by this many canvas pixels or more (a frame the path moved by itself)
# is left out of the second: the units follow the frames that only the scale and shift moved.
REFIT_OUTLIER_PX = 1.0


@dataclass(frozen=True)
class CanvasUnits:
    """canvas mm = scale * path mm + shift_mm (complex: x + iy), in frame 0's axes."""

    scale: float = 1.0
    shift_mm: complex = 0j

    def on_canvas(self, affine: np.ndarray) -> np.ndarray:
        """Return a stitch affine (2x3, frame mm -> path mm) as one onto the canvas (frame mm -> canvas mm)."""
        out = np.asarray(affine, np.float64) * self.scale
        out[:, 2] += (self.shift_mm.real, self.shift_mm.imag)
        return out

    def path_px_per_mm(self, canvas_px_per_mm: float) -> float:
        """Return the mosaic's pixels per path mm for a canvas at canvas_px_per_mm pixels per canvas mm."""
        return canvas_px_per_mm * self.scale

    def origin_px(self, canvas_px_per_mm: float) -> tuple[float, float]:
        """Return the canvas pixel (x, y) of the path's origin (frame 0's rest centre)."""
        return self.shift_mm.real * canvas_px_per_mm, self.shift_mm.imag * canvas_px_per_mm

    def to_path_mm(self, x_mm: float, y_mm: float) -> tuple[float, float]:
        """Return a canvas point (mm) in path mm."""
        return (x_mm - self.shift_mm.real) / self.scale, (y_mm - self.shift_mm.imag) / self.scale


IDENTITY = CanvasUnits()


def _fit(path_px: np.ndarray, canvas_px: np.ndarray) -> tuple[float, complex]:
    """Return (s, o) of canvas = s path + o (complex pixels) by least squares."""
    zero, one = np.zeros(path_px.size), np.ones(path_px.size)
    design = np.vstack([np.column_stack([path_px.real, one, zero]), np.column_stack([path_px.imag, zero, one])])
    s, ox, oy = np.linalg.lstsq(design, np.concatenate([canvas_px.real, canvas_px.imag]), rcond=None)[0]
    return float(s), complex(ox, oy)


def fit_units(path_px: np.ndarray, canvas_px: np.ndarray, canvas_px_per_mm: float) -> CanvasUnits:
    """Return the units that map frames' corners placed in path units (path_px: (N, 4) complex canvas pixels at
    identity units) best onto where they are pasted (canvas_px, the same shape): least squares over every corner,
    then again without the frames the first fit misses by REFIT_OUTLIER_PX or more (when a tenth of them stay).
    The identity when no frame is given."""
    path_px, canvas_px = np.asarray(path_px, complex), np.asarray(canvas_px, complex)
    if path_px.size == 0:
        return IDENTITY
    s, o = _fit(path_px.ravel(), canvas_px.ravel())
    miss = np.abs(s * path_px + o - canvas_px).max(axis=1)
    kept = miss < REFIT_OUTLIER_PX
    if 10 * np.count_nonzero(kept) >= len(kept) and not kept.all():
        s, o = _fit(path_px[kept].ravel(), canvas_px[kept].ravel())
    if not (s > 0 and np.isfinite(s) and np.isfinite(o)):
        return IDENTITY
    return CanvasUnits(s, o / canvas_px_per_mm)
