"""Force rectification of whole frames (spec §2 order: undistort, then rectify about cx, cy): the remap maps."""

from __future__ import annotations

import cv2
import numpy as np

from services.core.inputs.calibration import Calibration
from services.core.physics.camera import distort_points_px, mm_to_px, px_to_mm
from services.core.physics.force_model import LoadState, deform_points_mm


def pixel_grid(width: int, height: int) -> np.ndarray:
    """Return the (height, width, 2) array of pixel-centre coordinates (x, y) as float64."""
    xs, ys = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    return np.stack([xs, ys], axis=-1)


MAP_STEP_PX = 8  # rectify_map evaluates the model every this many pixels and interpolates (error << 0.01 px)


def _exact_map(calib: Calibration, state: LoadState, grid_px: np.ndarray) -> np.ndarray:
    """Return the raw pixel (..., 2) each rectified pixel of grid_px (..., 2) comes from (spec §2 order)."""
    observed_mm = deform_points_mm(px_to_mm(grid_px, calib), state, calib)
    return distort_points_px(mm_to_px(observed_mm, calib), calib)


def rectify_map(calib: Calibration, state: LoadState, step_px: int = MAP_STEP_PX) -> tuple[np.ndarray, np.ndarray]:
    """Return (map_x, map_y) float32 for cv2.remap: for each rectified pixel, the raw pixel it comes from.

    The rectified frame shares the raw frame's pixel grid and principal point, in undeformed mm times
    px_per_mm: undeformed mm -> observed mm (inverse rectification) -> ideal pixel -> lens distortion.
    The map is smooth (lens distortion and a load-proportional stretch), so it is evaluated exactly on a grid
    every step_px pixels, one sample beyond each edge, and interpolated bilinearly (step_px = 1: exact).
    """
    w, h = calib.image_size
    if step_px <= 1:
        raw = _exact_map(calib, state, pixel_grid(w, h))
        return raw[..., 0].astype(np.float32), raw[..., 1].astype(np.float32)
    # sample j covers full pixels (j - 1 + 0.5) step - 0.5, so cv2.resize's pixel-centre convention makes
    # output pixel X of the resized grid full pixel X - step: resize, then crop [step, step + size)
    nx, ny = -(-w // step_px) + 2, -(-h // step_px) + 2
    xs = (np.arange(nx) - 0.5) * step_px - 0.5
    ys = (np.arange(ny) - 0.5) * step_px - 0.5
    coarse = _exact_map(calib, state, np.stack(np.meshgrid(xs, ys), axis=-1)).astype(np.float32)
    fine = cv2.resize(coarse, (nx * step_px, ny * step_px), interpolation=cv2.INTER_LINEAR)
    fine = fine[step_px : step_px + h, step_px : step_px + w]
    return np.ascontiguousarray(fine[..., 0]), np.ascontiguousarray(fine[..., 1])
