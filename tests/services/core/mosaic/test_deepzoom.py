"""Deep Zoom geometry and the pooled tile pyramid: known answers, placement, exact averages, PNG output."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from services.core.mosaic.canvas import TILE_PX, FrameLayers, SparseCanvas, force_to_color
from services.core.mosaic.deepzoom import DziGeometry, TilePyramid, blank_png, encode_png_gray_alpha, pool2
from services.core.similarity import Similarity


def test_geometry_known_answers() -> None:
    g = DziGeometry.for_mosaic(8.0, 200.0)
    # 200 mm * 8 px/mm = 1600 px, rounded up to a multiple of 256: 1792
    assert g.half_px == 1792 and g.width == g.height == 3584
    assert g.max_level == 12  # 2^11 = 2048 < 3584 <= 4096
    assert g.origin_px == (1792, 1792) and g.canvas_offset_tiles == 7
    assert g.level_size(12) == (3584, 3584) and g.level_size(11) == (1792, 1792)
    assert g.level_size(10) == (896, 896) and g.level_size(0) == (1, 1) and g.level_size(2) == (4, 4)
    assert g.tiles_at(12) == (14, 14) and g.tiles_at(10) == (4, 4) and g.tiles_at(0) == (1, 1)
    assert g.tile_shape(10, 3, 3) == (128, 128) and g.tile_shape(10, 2, 3) == (128, 256)
    assert g.in_range(12, 13, 13) and not g.in_range(12, 14, 0) and not g.in_range(13, 0, 0)
    assert g.canvas_tile_to_dzi(0, 0) == (7, 7) and g.canvas_tile_to_dzi(-7, -7) == (0, 0)
    assert g.mm_to_px(0.0, 0.0) == (1792.0, 1792.0) and g.mm_to_px(1.0, -2.0) == (1800.0, 1776.0)
    xml = g.dzi_xml()
    assert 'TileSize="256"' in xml and 'Overlap="0"' in xml and 'Format="png"' in xml
    assert '<Size Width="3584" Height="3584"/>' in xml and "schemas.microsoft.com/deepzoom/2008" in xml
    assert g.to_dict() == {"width": 3584, "height": 3584, "tile_size": 256, "max_level": 12, "origin_px": [1792, 1792]}
    assert DziGeometry.for_mosaic(8.0, 1.0).half_px == 256  # at least one tile each side
    with pytest.raises(ValueError):
        DziGeometry.for_mosaic(0.0)
    with pytest.raises(ValueError):
        g.level_size(13)


def _dot_frame() -> FrameLayers:
    intensity = np.full((64, 64), 0.5, np.float32)
    intensity[32, 32] = 1.0  # the frame's centre pixel
    force = np.full((64, 64), 10.0, np.float32)
    return FrameLayers.of(intensity, np.ones((64, 64), np.float32), force, (32.0, 32.0), 8.0)


def _decode(png: bytes) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img is not None
    return img


def test_pasted_frame_lands_at_the_right_tile_and_pixel() -> None:
    g = DziGeometry.for_mosaic(8.0, 200.0)
    canvas = SparseCanvas(8.0)
    touched = canvas.paste(_dot_frame(), Similarity(1 + 0j, 0j))  # frame 0: its centre at canvas (0, 0)
    pyr = TilePyramid(g)
    changed = pyr.update(canvas, set(touched))
    assert (12, 7, 7) in changed and (12, 6, 6) in changed and (0, 0, 0) in changed
    assert {lvl for lvl, _, _ in changed} == set(range(13))  # every ancestor recomputed
    tile = _decode(pyr.render_png(12, 7, 7, "vein"))  # gray + alpha decodes as BGRA
    assert tile.shape == (256, 256, 4)
    assert tile[0, 0, 0] == 255 and tile[0, 0, 3] == 255  # the dot at DZI (1792, 1792) = tile (7, 7) px (0, 0)
    assert tile[5, 5, 0] == 128 and tile[100, 100, 3] == 0  # 0.5 grey nearby; uncovered far away
    left = _decode(pyr.render_png(12, 6, 6, "vein"))
    assert left[255, 255, 3] == 255 and left[0, 0, 3] == 0  # the frame reaches 32 px up-left, not 256
    # a point 1 mm right of frame 0's centre in a second frame lands 8 px right of the origin
    canvas2 = SparseCanvas(8.0)
    t2 = canvas2.paste(_dot_frame(), Similarity(1 + 0j, complex(1.0, 0.0)))
    pyr2 = TilePyramid(g)
    pyr2.update(canvas2, set(t2))
    assert _decode(pyr2.render_png(12, 7, 7, "vein"))[0, 8, 0] == 255
    # level 11: DZI px 896 -> tile (3, 3) px (128, 128) = mean of full-res (1792..1793)^2 = (1 + 3 * 0.5) / 4
    planes = pyr.planes(11, 3, 3)
    assert planes is not None
    assert planes[128, 128, 0] / planes[128, 128, 1] == pytest.approx(0.625, abs=1e-6)
    low = _decode(pyr.render_png(11, 3, 3, "vein"))
    assert low[128, 128, 0] == int(0.625 * 255 + 0.5)
    force = _decode(pyr.render_png(12, 7, 7, "force"))  # palette + tRNS decodes as BGRA
    assert force.shape == (256, 256, 4) and force[0, 0, 3] == 255 and force[100, 100, 3] == 0
    # 10 N in TURBO over 0..30 N, as force_to_color draws it: the palette's 255 levels are within one of its 256
    want = force_to_color(np.array([[9.9, 10.0, 10.1]], np.float32)).astype(int)
    assert np.all(np.abs(force[0, 0, :3].astype(int) - want[0, 1]) <= np.abs(want[0, 2] - want[0, 0]) + 1)
    assert pyr.render_png(12, 0, 0, "vein") is None  # no data there
    with pytest.raises(ValueError):
        pyr.render_png(12, 7, 7, "other")


def test_parents_are_exact_weighted_averages() -> None:
    rng = np.random.default_rng(3)
    g = DziGeometry.for_mosaic(8.0, 40.0)  # half 512 px: 4x4 tiles at max level 10
    canvas = SparseCanvas(8.0)
    for key in [(-2, -2), (-1, -2), (0, 0), (1, 1), (-1, 0)]:
        tile = np.zeros((TILE_PX, TILE_PX, 4), np.float32)
        w = rng.random((TILE_PX, TILE_PX)).astype(np.float32) * (rng.random((TILE_PX, TILE_PX)) > 0.3)
        tile[..., 0] = w * rng.random((TILE_PX, TILE_PX))
        tile[..., 1] = w
        tile[..., 2] = w * rng.random((TILE_PX, TILE_PX)) * 30
        tile[..., 3] = w > 0
        canvas.tiles[key] = tile
    pyr = TilePyramid(g)
    pyr.update(canvas, set(canvas.tiles))
    full = np.zeros((g.height, g.width, 4), np.float64)
    for (c, r), tile in canvas.tiles.items():
        col, row = g.canvas_tile_to_dzi(c, r)
        full[row * 256 : (row + 1) * 256, col * 256 : (col + 1) * 256] = tile
    for level in range(g.max_level - 1, g.max_level - 4, -1):
        k = 2 ** (g.max_level - level)
        pooled = full.reshape(g.height // k, k, g.width // k, k, 4).sum(axis=(1, 3))
        for (col, row), planes in pyr.levels[level].items():
            want = pooled[row * 256 : (row + 1) * 256, col * 256 : (col + 1) * 256]
            h, w = want.shape[:2]
            # float32 sums of up to 64 pixels against float64: relative 1e-5 is float32 rounding
            np.testing.assert_allclose(planes[:h, :w], want, rtol=1e-5, atol=1e-5)


def test_removal_clears_tiles_and_edge_tiles_are_cropped() -> None:
    g = DziGeometry.for_mosaic(8.0, 20.0)  # half 256: width 512, max level 9
    assert g.max_level == 9 and g.tile_shape(7, 0, 0) == (128, 128)
    canvas = SparseCanvas(8.0)
    pose = Similarity(1 + 0j, 0j)
    touched = set(canvas.paste(_dot_frame(), pose))
    pyr = TilePyramid(g)
    pyr.update(canvas, touched)
    small = _decode(pyr.render_png(7, 0, 0, "vein"))
    assert small.shape[:2] == (128, 128)  # cropped to the level's size
    touched |= set(canvas.paste(_dot_frame(), pose, sign=-1.0))
    pyr.update(canvas, touched)
    assert pyr.render_png(9, 1, 1, "vein") is None and pyr.render_png(0, 0, 0, "vein") is None
    far = canvas.paste(_dot_frame(), Similarity(1 + 0j, complex(500.0, 0.0)))  # outside the DZI canvas
    assert pyr.update(canvas, set(far)) == set()


def test_png_encoders() -> None:
    gray = np.arange(256 * 3, dtype=np.uint32).reshape(3, 256).astype(np.uint8)
    alpha = np.full((3, 256), 200, np.uint8)
    img = _decode(encode_png_gray_alpha(gray, alpha))
    assert np.array_equal(img[..., 0], gray) and np.array_equal(img[..., 3], alpha)
    blank = _decode(blank_png())
    assert blank.shape == (256, 256, 4) and not blank[..., 3].any()


def test_pool2_is_the_two_by_two_block_sum() -> None:
    # the pyramid's parents are sums of their children's 2x2 pixel blocks; OpenCV computes them as 4 x the area
    # mean, so float32 rounding of sums of four values in 0..1 (1e-6 relative) is the only difference
    planes = np.random.default_rng(3).random((256, 256, 4), dtype=np.float32)
    want = planes.reshape(128, 2, 128, 2, 4).sum(axis=(1, 3), dtype=np.float64)
    got = pool2(planes)
    assert got.shape == (128, 128, 4) and got.dtype == np.float32
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)
