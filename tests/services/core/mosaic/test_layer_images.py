"""The whole-mosaic files (services/core/mosaic/layer_images.py): what every writer of a mosaic writes."""

from __future__ import annotations

import io

import cv2
import numpy as np

from services.core.mosaic.canvas import MosaicImage
from services.core.mosaic.layer_images import (
    COVERAGE_FULL_SCALE,
    coverage_to_color,
    layers_from_bytes,
    layers_to_bytes,
    mosaic_image_files,
)


def _mosaic() -> MosaicImage:
    vein = np.zeros((40, 50), np.uint8)
    vein[10:30, 5:45] = 200
    force = np.full((40, 50), np.nan, np.float32)
    force[10:30, 5:45] = 12.34
    coverage = np.zeros((40, 50), np.float32)
    coverage[10:30, 5:45] = 3
    return MosaicImage(vein, force, coverage, px_per_mm=4.0, origin_px=(7.0, 9.5))


def test_the_files_decode_to_the_layers_and_carry_their_units() -> None:
    mosaic = _mosaic()
    files = mosaic_image_files(mosaic)
    assert set(files) == {"mosaic.png", "force.png", "coverage.png", "layers.npz"}
    vein = cv2.imdecode(np.frombuffer(files["mosaic.png"], np.uint8), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(vein, mosaic.vein)  # lossless
    force = cv2.imdecode(np.frombuffer(files["force.png"], np.uint8), cv2.IMREAD_UNCHANGED)
    assert force.shape == (40, 50, 3) and force[0, 0].tolist() == [0, 0, 0] and force[20, 20].sum() > 0
    coverage = cv2.imdecode(np.frombuffer(files["coverage.png"], np.uint8), cv2.IMREAD_UNCHANGED)
    assert coverage.shape == (40, 50, 4) and coverage[0, 0, 3] == 0 and coverage[20, 20, 3] == 255
    back = layers_from_bytes(files["layers.npz"], vein)
    assert back.origin_px == (7.0, 9.5) and back.px_per_mm == 4.0
    np.testing.assert_allclose(back.force_n[20, 20], 12.34, atol=0.005)  # stored in centinewtons
    assert np.isnan(back.force_n[0, 0]) and back.coverage[20, 20] == 3


def test_without_raw_layers_only_the_images() -> None:
    assert set(mosaic_image_files(_mosaic(), raw_layers=False)) == {"mosaic.png", "force.png", "coverage.png"}


def test_coverage_colours_and_raw_layers_follow_their_definitions_pixel_for_pixel() -> None:
    """On fractional coverage and forces at every centinewton's half (the rims of pasted windows), the colour image
    is VIRIDIS of round(clip((c - 1) / (full - 1)) x 255) with alpha where c >= 0.5, and the raw force is round(F /
    1 cN) where covered, 0 elsewhere: the in-place arithmetic changes no value."""
    rng = np.random.default_rng(7)
    coverage = rng.uniform(0.0, 14.0, (60, 70)).astype(np.float32)
    coverage[:5] = 0.0
    force = (rng.integers(0, 3000, (60, 70)) + 0.5).astype(np.float32) * np.float32(0.01)
    force[coverage < 0.5] = np.nan
    mosaic = MosaicImage(np.zeros((60, 70), np.uint8), force, coverage, px_per_mm=8.0, origin_px=(0.0, 0.0))
    level = np.rint(np.clip((coverage.astype(np.float64) - 1.0) / (COVERAGE_FULL_SCALE - 1), 0, 1) * 255.0)
    expected = cv2.applyColorMap(level.astype(np.uint8), cv2.COLORMAP_VIRIDIS)
    seen = coverage >= 0.5
    colour = coverage_to_color(coverage)
    assert np.array_equal(colour[..., :3][seen], expected[seen]) and np.all(colour[..., 3][seen] == 255)
    assert not colour[~seen].any()
    with np.load(io.BytesIO(layers_to_bytes(mosaic))) as z:
        counts, force_cn = z["coverage"], z["force_cn"]
    assert np.array_equal(counts, np.rint(coverage).astype(np.uint16))
    covered = counts > 0
    assert np.array_equal(force_cn[covered], np.rint(force[covered].astype(np.float64) / 0.01).astype(np.uint16))
    assert not force_cn[~covered].any()
