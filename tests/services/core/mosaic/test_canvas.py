"""The sparse mosaic canvas: linear (removable) pastes, tiles only where frames land, geometry, blending."""

from __future__ import annotations

import cmath
import math

import numpy as np
import pytest

from services.core.mosaic.canvas import FrameLayers, SparseCanvas, blend_weight, force_to_color
from services.core.similarity import IDENTITY, Similarity

H, W = 320, 400
CENTRE = (201.7, 157.9)  # the simulated probe's principal point (px), deliberately not a pixel centre
PPM = 8.0


def _window() -> np.ndarray:
    mask = np.zeros((H, W), np.uint8)
    mask[15:-15, 15:-15] = 255
    return mask


def _layers(intensity: np.ndarray, force_n: float = 5.0) -> FrameLayers:
    return FrameLayers.of(
        intensity=intensity.astype(np.float32),
        weight=blend_weight(_window()),
        force_n=np.full((H, W), force_n, np.float32),
        centre_px=CENTRE,
        px_per_mm=PPM,
    )


def _random_layers(seed: int) -> FrameLayers:
    return _layers(np.random.default_rng(seed).random((H, W)))


def _dot_layers(offset_px: tuple[float, float] = (0.0, 0.0)) -> FrameLayers:
    """A frame whose only bright feature is a Gaussian dot (sigma 1.5 px) at the principal point + offset."""
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    x0, y0 = CENTRE[0] + offset_px[0], CENTRE[1] + offset_px[1]
    return _layers(np.exp(-((xs - x0) ** 2 + (ys - y0) ** 2) / (2 * 1.5**2)))


def _bright_centroid(vein: np.ndarray) -> np.ndarray:
    """Return the (x, y) intensity centroid of the pixels above half the maximum (the dot)."""
    v = vein.astype(np.float64)
    ys, xs = np.nonzero(v > 0.5 * v.max())
    w = v[ys, xs]
    return np.array([np.sum(xs * w) / w.sum(), np.sum(ys * w) / w.sum()])


def test_paste_then_unpaste_returns_to_zero() -> None:
    canvas = SparseCanvas(PPM)
    layers = _random_layers(0)
    pose = Similarity(cmath.exp(1j * math.radians(17.0)), 12.5 - 7.25j)
    touched = canvas.paste(layers, pose)
    assert touched and sum(float(np.abs(t).sum()) for t in canvas.tiles.values()) > 1000
    canvas.paste(layers, pose, sign=-1.0)
    # x + p - p in float32 with the same warp both times: exactly zero
    for tile in canvas.tiles.values():
        assert np.max(np.abs(tile)) == 0.0


def test_moving_a_frame_equals_pasting_it_at_the_new_pose() -> None:
    old, new = Similarity(1 + 0j, 3 + 2j), Similarity(cmath.exp(0.1j), -4 + 1j)
    a, b = _random_layers(1), _random_layers(2)
    moved = SparseCanvas(PPM)
    moved.paste(a, IDENTITY)
    moved.paste(b, old)
    moved.paste(b, old, sign=-1.0)
    moved.paste(b, new)
    direct = SparseCanvas(PPM)
    direct.paste(a, IDENTITY)
    direct.paste(b, new)
    for key, tile in direct.tiles.items():
        # float32 sums of O(1..10) values added in a different order: a few ulps, 1e-5 is ample
        np.testing.assert_allclose(moved.tiles[key], tile, atol=1e-5)
    for key in set(moved.tiles) - set(direct.tiles):
        assert np.max(np.abs(moved.tiles[key])) < 1e-5  # tiles only the old pose touched are back to ~0


def test_tiles_exist_only_where_frames_landed() -> None:
    canvas = SparseCanvas(PPM)
    layers = _random_layers(3)
    canvas.paste(layers, IDENTITY)
    far = Similarity(1 + 0j, complex(200, 200) / math.sqrt(2))  # 200 mm away diagonally
    canvas.paste(layers, far)
    c0, r0, c1, r1 = canvas.extent_tiles()
    box = (c1 - c0 + 1) * (r1 - r0 + 1)
    # each 400 x 320 px frame touches at most 3 x 3 tiles of 256 px (measured 10 in all); the bounding
    # box of the two needs 7 x 6 = 42
    assert len(canvas.tiles) <= 18
    assert len(canvas.tiles) * 3 < box


def test_render_puts_frame_zero_centre_at_origin_px() -> None:
    canvas = SparseCanvas(PPM)
    canvas.paste(_dot_layers(), IDENTITY)
    image = canvas.render()
    # the dot sits at the principal point: it must render at origin_px (1 px = the budget)
    np.testing.assert_allclose(_bright_centroid(image.vein), image.origin_px, atol=1.0)
    assert image.meta()["origin_px"] == [image.origin_px[0], image.origin_px[1]]
    assert image.meta()["width"] == image.vein.shape[1] and image.meta()["height"] == image.vein.shape[0]


def test_render_follows_the_spec_pose_convention() -> None:
    # spec §4: a point p (mm, about frame k's centre) lands at R(yaw) p + (x, y) in frame 0's mm
    p_mm = np.array([6.0, 2.0])
    yaw = math.radians(90.0)
    t_mm = np.array([-3.0, 4.0])
    canvas = SparseCanvas(PPM)
    canvas.paste(_dot_layers(tuple(p_mm * PPM)), Similarity(cmath.exp(1j * yaw), complex(*t_mm)))
    canvas.paste(_layers(np.zeros((H, W))), IDENTITY)  # frame 0 present (dark) so origin_px is defined alike
    image = canvas.render()
    rot = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    expected_px = np.array(image.origin_px) + (rot @ p_mm + t_mm) * PPM  # (-2, 6) + (-3, 4) = (-5, 10) mm
    np.testing.assert_allclose(_bright_centroid(image.vein), expected_px, atol=1.0)


def test_render_of_empty_canvas() -> None:
    image = SparseCanvas(PPM).render()
    assert image.vein.shape == (1, 1) and np.isnan(image.force_n).all()


def test_render_force_layer_and_coverage() -> None:
    canvas = SparseCanvas(PPM)
    canvas.paste(_layers(np.full((H, W), 0.5), force_n=7.0), IDENTITY)
    canvas.paste(_layers(np.full((H, W), 0.5), force_n=7.0), Similarity(1 + 0j, 10 + 0j))
    image = canvas.render()
    covered = np.isfinite(image.force_n)
    # weighted mean of a constant is the constant (float32 sums: 1e-4 N)
    np.testing.assert_allclose(image.force_n[covered], 7.0, atol=1e-4)
    assert abs(int(np.median(image.vein[covered])) - 128) <= 1  # 0.5 -> 127.5 + 0.5 rounding
    assert image.coverage.max() == pytest.approx(2.0, abs=1e-6)  # the overlap is seen by both frames
    assert np.all(image.vein[~covered] == 0)


def test_a_rendered_mosaic_read_back_into_a_canvas_renders_the_same() -> None:
    # the reprocess stage tiles a rendered mosaic again for its Deep Zoom pyramid: from_mosaic inverts render
    canvas = SparseCanvas(PPM)
    canvas.paste(_random_layers(3), Similarity(cmath.exp(0.3j), 5.5 - 3.0j))
    canvas.paste(_layers(np.full((H, W), 0.25), force_n=11.0), Similarity(1 + 0j, -20.0 + 9.0j))
    image = canvas.render()
    again = SparseCanvas.from_mosaic(image).render()
    assert again.origin_px == image.origin_px and again.vein.shape == image.vein.shape
    assert np.array_equal(again.vein, image.vein)  # 8-bit values survive the round trip exactly
    np.testing.assert_allclose(again.force_n, image.force_n, atol=1e-5)  # float32 N, NaN where uncovered alike
    np.testing.assert_array_equal(again.coverage, image.coverage)


def test_frame_planes_read_grey_levels_as_fractions_and_refuse_other_integers() -> None:
    grey = np.random.default_rng(5).integers(0, 256, (H, W), dtype=np.uint8)
    weight, force = blend_weight(_window()), np.full((H, W), 5.0, np.float32)
    from_levels = FrameLayers.of(grey, weight, force, CENTRE, PPM)
    from_floats = FrameLayers.of(grey.astype(np.float32) / 255.0, weight, force, CENTRE, PPM)
    # the same planes to float32 rounding (1 ulp of a weighted intensity <= 1)
    np.testing.assert_allclose(from_levels.planes, from_floats.planes, rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match="uint16"):  # 16-bit levels read as 0..1 would paste nearly white
        FrameLayers.of(grey.astype(np.uint16) * 257, weight, force, CENTRE, PPM)


def test_blend_weight_is_zero_outside_and_peaks_inside() -> None:
    mask = _window()
    w = blend_weight(mask)
    assert w.dtype == np.float32 and w.shape == mask.shape
    assert np.all(w[mask == 0] == 0)
    assert np.all(w[mask > 0] > 0)
    peak = np.unravel_index(np.argmax(w), w.shape)
    assert mask[peak] > 0
    # the peak is near the window's centre, far from its edge (ramp 40 px), and the edge itself is ~0
    assert abs(peak[0] - H / 2) < 10 and abs(peak[1] - W / 2) < 10
    assert w[15, W // 2] < 0.01 * w.max()
    assert w[H // 2, W // 2] > 0.9 * w.max()


def test_force_to_color_black_where_uncovered() -> None:
    force = np.array([[np.nan, 0.0, 15.0, 30.0, 100.0]], np.float32)
    color = force_to_color(force)
    assert color.shape == (1, 5, 3) and color.dtype == np.uint8
    assert color[0, 0].tolist() == [0, 0, 0]
    assert np.all(color[0, 1:].sum(axis=-1) > 0)  # TURBO is never black, even at 0 N
    assert color[0, 3].tolist() == color[0, 4].tolist()  # clipped at full scale
    assert color[0, 1].tolist() != color[0, 3].tolist()
