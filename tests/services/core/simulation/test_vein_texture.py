"""The procedural vein world: size, range, band limit, vessel coverage and determinism; a photograph's world."""

from __future__ import annotations

from functools import cache

import cv2
import numpy as np
import pytest

from services.core.simulation.vein_texture import (
    MAX_GAP_MM,
    World,
    _largest_gap,
    band_noise,
    make_photo_world,
    make_world,
    photo_vessel_darkness,
    skin_texture,
    smooth_skin,
    vein_network,
)
from tests.services.core.synthetic_veins import vessel_photo

BOUNDS = (-40.0, -30.0, 60.0, 50.0)


@cache
def world() -> World:
    return make_world(np.random.default_rng(9), BOUNDS, 8.0)


def test_world_covers_the_bounds_at_the_scale() -> None:
    w = world()
    assert w.image.dtype == np.float32
    assert w.image.shape == (640, 800)
    assert w.extent_mm == pytest.approx(BOUNDS)
    np.testing.assert_allclose(w.mm_to_px(np.array([-40.0, -30.0])), [0.0, 0.0])
    assert w.image.min() > 0.0 and w.image.max() < 1.0


def test_world_is_band_limited() -> None:
    # content near Nyquist (|f| > 0.4 cycles/px) that linear remapping would alias: its RMS amplitude is
    # measured at 9e-4 of full scale (0.23 of an 8-bit grey level, from the cubic upsampling of the coarse
    # shading noise); 2e-3 (0.5 DN, a quarter of the sensor noise) keeps it negligible. A guard against gross
    # aliasing only: the textured skin's 0.9 px grain band alone measures 1e-3, unblurred white noise of the
    # same amplitude ~7e-3
    img = world().image - world().image.mean()
    spec = np.abs(np.fft.fftshift(np.fft.fft2(img))) ** 2
    fy = np.fft.fftshift(np.fft.fftfreq(img.shape[0]))[:, None]
    fx = np.fft.fftshift(np.fft.fftfreq(img.shape[1]))[None, :]
    f = np.hypot(fx, fy)
    assert np.sqrt(spec[f > 0.4].sum()) / img.size < 2e-3


def test_veins_are_dark_and_everywhere() -> None:
    rng = np.random.default_rng(2)
    vessels = vein_network(rng, BOUNDS)
    gap, _ = _largest_gap(vessels, BOUNDS)
    assert gap <= MAX_GAP_MM
    widths = np.concatenate([v.width_mm for v in vessels])
    assert widths.min() >= 0.6 - 1e-9 and widths.max() <= 2.5 * 1.15 + 1e-9
    # contrast follows depth within the default range: shallow vessels dark, deep ones faint
    assert all(0.03 - 1e-12 <= v.contrast <= 0.35 + 1e-12 for v in vessels)
    depth = np.array([v.depth for v in vessels])
    contrast = np.array([v.contrast for v in vessels])
    assert depth.min() <= 0.35 and depth.max() > 0.7  # trunks lie within 0.35; fillers reach the deepest
    assert np.all(np.diff(contrast[np.argsort(depth)]) <= 1e-12)  # deeper = fainter
    # the darkest 3% of the world (vessel cores) is well below the skin level
    img = world().image
    assert np.percentile(img, 3) < 0.85 * np.median(img)


def test_smooth_skin_has_no_fine_grain_but_textured_skin_does() -> None:
    rng = np.random.default_rng(3)
    smooth = smooth_skin(rng, (400, 400), 8.0)
    textured = skin_texture(np.random.default_rng(3), (400, 400), 8.0)
    # fine grain: std of the image minus a 2 px Gaussian mean; smooth skin's finest albedo layer is 1.2 mm
    # (~10 px), so its residual is < 0.1 % of full scale; the textured skin's 0.9-2 px bands give ~2 %
    fine = lambda img: float((img - cv2.GaussianBlur(img, (0, 0), 2.0)).std())  # noqa: E731
    assert fine(smooth) < 0.001 and fine(textured) > 0.01


def test_band_noise_is_normalised_and_smooth() -> None:
    n = band_noise(np.random.default_rng(0), (200, 300), 6.0)
    assert n.shape == (200, 300)
    assert n.mean() == pytest.approx(0.0, abs=1e-5) and n.std() == pytest.approx(1.0, abs=1e-4)
    assert np.abs(np.diff(n, axis=1)).mean() < 0.3  # sigma 6 px: neighbours nearly equal


def test_world_is_deterministic_for_a_seed() -> None:
    a = make_world(np.random.default_rng(1), (0.0, 0.0, 30.0, 20.0))
    b = make_world(np.random.default_rng(1), (0.0, 0.0, 30.0, 20.0))
    np.testing.assert_array_equal(a.image, b.image)


def test_a_photographs_dark_lines_are_its_vessels_and_its_shading_is_not() -> None:
    photo, lines = vessel_photo()
    dark = photo_vessel_darkness(photo)
    far = cv2.dilate((lines > 0).astype(np.uint8), np.ones((41, 41), np.uint8)) == 0  # 20 px from any vessel
    # measured: median 0.62 on the vessels' cores, exactly 0 on the shaded ground 20 px away (PHOTO_FLOOR)
    assert np.median(dark[lines > 0.25]) > 0.4
    assert np.all(dark[far] == 0.0)
    bgr = cv2.merge([np.zeros_like(photo), photo, np.zeros_like(photo)])  # colour: its green channel is read
    np.testing.assert_array_equal(photo_vessel_darkness(bgr), dark)


@pytest.mark.parametrize("photo", [np.zeros((64, 64), np.uint8), np.full((64, 64), 0.5, np.float32)])
def test_a_photograph_without_vessels_or_of_another_type_is_refused(photo: np.ndarray) -> None:
    with pytest.raises(ValueError, match="texture photograph"):
        photo_vessel_darkness(photo)


def test_a_photo_world_covers_the_bounds_and_darkens_as_the_contrast_says() -> None:
    photo, _ = vessel_photo()
    strong = make_photo_world(np.random.default_rng(3), BOUNDS, photo, 0.375, 8.0, (0.03, 0.35))
    faint = make_photo_world(np.random.default_rng(3), BOUNDS, photo, 0.375, 8.0, (0.02, 0.10))
    assert strong.image.shape == (640, 800) and strong.extent_mm == pytest.approx(BOUNDS)
    again = make_photo_world(np.random.default_rng(3), BOUNDS, photo, 0.375, 8.0, (0.03, 0.35))
    np.testing.assert_array_equal(strong.image, again.image)  # deterministic for a seed
    # the same crop and skin: the darkest 1 % goes 35 % of the way down at most (the vessels' cores scattered),
    # a tenth with the faint contrast; measured 0.700 and 0.887 of the median
    assert np.percentile(strong.image, 1) < 0.8 * np.median(strong.image)
    assert 0.85 * np.median(faint.image) < np.percentile(faint.image, 1) < 0.95 * np.median(faint.image)
