"""A canvas's own units: the scale and shift fitted to frames' corners, and what carries them (render, extent, DZI)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.core.mosaic import canvas_units
from services.core.mosaic.canvas import FrameLayers, SparseCanvas
from services.core.mosaic.canvas_units import IDENTITY, CanvasUnits, fit_units
from services.core.mosaic.deepzoom import DziGeometry
from services.core.outputs.documents import canvas_extent_mm

P = 8.0  # canvas px per mm
RNG = np.random.default_rng(7)


def corners(n: int) -> np.ndarray:
    """Return (n, 4) frames' corners (complex canvas px) scattered over a 100 mm scan, seeded."""
    centres = RNG.uniform(-400, 400, n) + 1j * RNG.uniform(-400, 400, n)
    return centres[:, None] + np.array([-320 - 240j, 320 - 240j, -320 + 240j, 320 + 240j])[None, :]


def test_on_canvas_maps_a_point_by_the_scale_then_the_shift() -> None:
    units = CanvasUnits(1.02, 0.5 - 0.25j)
    affine = np.array([[0.9, -0.1, 3.0], [0.1, 0.9, -2.0]])
    point = np.array([1.5, -4.0, 1.0])
    mapped = units.on_canvas(affine) @ point
    expected = 1.02 * (affine @ point) + np.array([0.5, -0.25])
    assert np.allclose(mapped, expected, atol=1e-12)
    assert np.allclose(units.to_path_mm(*mapped), affine @ point, atol=1e-12)  # and back
    assert units.path_px_per_mm(P) == pytest.approx(8.16) and units.origin_px(P) == pytest.approx((4.0, -2.0))
    assert np.array_equal(IDENTITY.on_canvas(affine), affine)


def test_fit_units_recovers_a_scale_and_shift_and_leaves_out_a_frame_that_moved_by_itself(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # tolerance 1e-9 px: a least-squares fit of exact data
    path = corners(60)
    truth = CanvasUnits(0.985, 1.25 + 0.5j)
    canvas = truth.scale * path + complex(*truth.origin_px(P))
    fitted = fit_units(path, canvas, P)
    assert fitted.scale == pytest.approx(truth.scale, abs=1e-12)
    assert abs(fitted.shift_mm - truth.shift_mm) < 1e-9 / P
    # one frame moved 5 px by itself: the second fit leaves it out and finds the same units
    canvas[7] += 5.0
    refit = fit_units(path, canvas, P)
    assert refit.scale == pytest.approx(truth.scale, abs=1e-12) and abs(refit.shift_mm - truth.shift_mm) < 1e-9
    # the comparison can fail: one fit over every frame (no second) is pulled off by it
    monkeypatch.setattr(canvas_units, "REFIT_OUTLIER_PX", math.inf)
    once = fit_units(path, canvas, P)
    assert abs(once.scale - truth.scale) > 1e-6 or abs(once.shift_mm - truth.shift_mm) > 1e-4
    assert fit_units(np.zeros((0, 4)), np.zeros((0, 4)), P) == IDENTITY


def _dot() -> FrameLayers:
    intensity = np.full((64, 64), 0.5, np.float32)
    return FrameLayers.of(intensity, np.ones((64, 64), np.float32), np.zeros((64, 64)), (32.0, 32.0), P)


def test_render_extent_and_dzi_carry_the_units() -> None:
    # the same frame pasted on an identity canvas and, at its place mapped by the units, on a canvas in those units:
    # the rendered mosaic's px_per_mm is P s, its origin_px the path's origin, and the extent the same path mm
    units = CanvasUnits(1.25, 2.0 - 1.0j)
    place = np.array([[1.0, 0.0, 10.0], [0.0, 1.0, 6.0]])
    plain, scaled = SparseCanvas(P), SparseCanvas(P, units=units)
    plain.paste(_dot(), place)
    scaled.paste(_dot(), units.on_canvas(place))
    mosaic = scaled.render()
    assert mosaic.px_per_mm == pytest.approx(P * 1.25)
    # the frame's centre lies at 10, 6 path mm: origin_px + (10, 6) * px_per_mm is its pixel in the cropped mosaic
    box = scaled.covered_box()
    assert box is not None
    centre = np.array(mosaic.origin_px) + np.array([10.0, 6.0]) * mosaic.px_per_mm
    assert centre == pytest.approx(P * (1.25 * np.array([10.0, 6.0]) + [2.0, -1.0]) - box[:2], abs=1e-9)
    # the extent in path mm: the identity canvas's, to the pixel the scaled canvas rounds the box to (1 px / P s)
    assert np.allclose(canvas_extent_mm(scaled), canvas_extent_mm(plain), atol=1.0 / (P * 1.25) + 1e-9)
    # the DZI origin: the path's origin, the canvas pixel 0 moved by P c
    g = DziGeometry.for_mosaic(P, 200.0)
    assert g.to_dict(units)["origin_px"] == [g.half_px + 16.0, g.half_px - 8.0]
    assert g.to_dict()["origin_px"] == [g.half_px, g.half_px]
    assert DziGeometry.from_dict(g.to_dict(units), P) == g  # its size and tiles as before
