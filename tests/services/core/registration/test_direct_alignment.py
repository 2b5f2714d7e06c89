"""Direct alignment of vein maps: recovers a known similarity from near and far starts, rejects unrelated maps."""

from __future__ import annotations

import cmath
import math

import numpy as np
import pytest

from services.core.methods import MethodOptions
from services.core.registration.direct_alignment import (
    AlignmentImage,
    DirectFit,
    align,
    alignment_image,
    correlation,
    level_matrix_px,
    overlap_pairs,
)
from services.core.registration.vein_enhancement import enhance_veins
from services.core.similarity import Similarity
from tests.services.core import synthetic_veins as sv
from tests.tolerances import TOL

MARGIN_PX = 6  # frame_prep's FEATURE_MARGIN_PX
MIN_CORRELATION = MethodOptions(name="best").min_correlation  # the registrar's acceptance threshold (0.6)


def _similarity(dx_mm: float, dy_mm: float, yaw_deg: float, scale: float) -> Similarity:
    return Similarity(scale * cmath.exp(1j * math.radians(yaw_deg)), complex(dx_mm, dy_mm))


VEIN_SCALE = MethodOptions(name="best").vein_scale  # vein maps at the resolution frame_prep makes them (0.5)


def _pyramid(frame: np.ndarray, mask: np.ndarray, scale: float = VEIN_SCALE) -> AlignmentImage:
    vein = enhance_veins(frame, mask, MARGIN_PX, scale)
    return alignment_image(vein.image, vein.mask, sv.CENTRE_PX, sv.PX_PER_MM, vein.scale)


def _pair(truth: Similarity, seed: int, scale: float = VEIN_SCALE) -> tuple[AlignmentImage, AlignmentImage]:
    fixed, moving, mask = sv.frame_pair(truth, seed)
    return _pyramid(fixed, mask, scale), _pyramid(moving, mask, scale)


def _assert_recovers(fit: DirectFit | None, truth: Similarity) -> None:
    assert fit is not None
    got = fit.transform
    assert abs(got.t - truth.t) < TOL.direct_shift_mm
    assert abs(math.degrees(got.yaw_rad - truth.yaw_rad)) < TOL.direct_yaw_deg
    assert abs(got.scale - truth.scale) < TOL.direct_scale
    assert fit.correlation > 0.9  # measured 0.99-1.0


# (shift x, shift y mm, yaw deg, scale), seed of the vein field. Measured errors (shift, yaw, scale):
# small 0.017 mm / 0.006 deg / 0.0004 and 0.015 / 0.003 / 0.0001; large 0.069 / 0.042 / 0.0023 and
# 0.007 / 0.008 / 0.0005. (On a field where a single curved vessel dominates the window the error reached
# 0.16-0.5 mm and ECC could fail from a 1 mm perturbation: see the report of this test's commit.)
CASES = [
    pytest.param((3.0, -4.0, 1.0, 1.01), 0, id="small-seed0"),
    pytest.param((3.0, -4.0, 1.0, 1.01), 2, id="small-seed2"),
    pytest.param((12.0, 5.0, -4.0, 1.01), 0, id="large-seed0"),
    pytest.param((12.0, 5.0, -4.0, 1.01), 2, id="large-seed2"),
]


def test_pixel_convention_matches_the_synthetic_warp() -> None:
    # the test's mm -> px matrix (p_px = centre + px_per_mm p_mm) is the module's at full resolution
    truth = _similarity(7.0, -3.0, 4.0, 1.02)
    img = AlignmentImage((), (), sv.CENTRE_PX, sv.PX_PER_MM)
    full = level_matrix_px(truth, img, 0).astype(np.float64)  # WORK_SCALE pixels: scale back to full resolution
    expected = sv.similarity_px(truth, sv.CENTRE_PX, sv.PX_PER_MM)
    assert np.allclose(full[:, :2], expected[:, :2], atol=1e-6)
    assert np.allclose(full[:, 2] * 2, expected[:, 2], atol=1e-3)  # float32 of ~300 px


@pytest.mark.parametrize("scale", [VEIN_SCALE, 1.0], ids=["half-res-map", "full-res-map"])
@pytest.mark.parametrize(("motion", "seed"), CASES)
def test_recovers_a_similarity_from_a_nearby_start(
    motion: tuple[float, float, float, float], seed: int, scale: float
) -> None:
    # a vein map at full or half resolution gives the same alignment pyramid geometry (WORK_SCALE)
    truth = _similarity(*motion)
    fixed, moving = _pair(truth, seed, scale)
    start = Similarity(truth.a, truth.t + complex(0.8, -0.6))  # 1 mm off, as from a rough feature estimate
    _assert_recovers(align(fixed, moving, start, recentre=False), truth)


@pytest.mark.parametrize(("motion", "seed"), CASES)
def test_recovers_a_similarity_from_a_far_start_with_recentring(
    motion: tuple[float, float, float, float], seed: int
) -> None:
    truth = _similarity(*motion)
    fixed, moving = _pair(truth, seed)
    start = Similarity(truth.a / abs(truth.a), truth.t + complex(-8.0, 6.0))  # 10 mm off, unit scale
    _assert_recovers(align(fixed, moving, start, recentre=True), truth)
    # ECC alone has no such basin: from 10 mm off it fails or lands elsewhere (measured: None every time)
    alone = align(fixed, moving, start, recentre=False)
    assert alone is None or abs(alone.transform.t - truth.t) > 1.0


def test_correlation_is_high_on_the_true_overlap_and_low_off_it() -> None:
    truth = _similarity(6.0, 0.0, 3.0, 1.0)
    fixed, moving = _pair(truth, 3)
    corr, share = correlation(fixed, moving, truth)
    assert corr > 0.9  # measured 0.996
    assert 0.5 < share < 1.0  # a 6 mm shift of a 25 mm-radius window: most of it still overlaps
    off, _ = correlation(fixed, moving, Similarity(truth.a, truth.t + 3.0))  # 3 mm off: different vessels
    assert off < 0.5 * corr


def test_unrelated_vein_frames_are_not_aligned() -> None:
    fixed, _ = _pair(_similarity(0.0, 0.0, 0.0, 1.0), 100)
    _, moving = _pair(_similarity(0.0, 0.0, 0.0, 1.0), 200)
    for recentre in (True, False):
        fit = align(fixed, moving, _similarity(0.0, 0.0, 0.0, 1.0), recentre=recentre)
        # measured: None, and 0.04 with recentring on other seeds
        assert fit is None or fit.correlation < MIN_CORRELATION


def test_disjoint_windows_give_none() -> None:
    truth = _similarity(3.0, 0.0, 0.0, 1.0)
    fixed, moving = _pair(truth, 0)
    far = Similarity(1 + 0j, 80.0 + 0j)  # 80 mm: the windows (50 mm wide) cannot overlap
    assert align(fixed, moving, far, recentre=True) is None
    assert align(fixed, moving, far, recentre=False) is None
    assert correlation(fixed, moving, far) == (0.0, 0.0)


def test_the_affine_and_its_overlap_pairs_agree_with_the_alignment() -> None:
    # a tracked frame's edge keeps the alignment's affine (the view model's evidence) and pairs sampled on its
    # overlap (to undo the skin's drag from): both must be the same geometry as the similarity it reports
    truth = _similarity(3.0, -4.0, 1.0, 1.01)
    fixed, moving = _pair(truth, 0)
    fit = align(fixed, moving, Similarity(truth.a, truth.t + 0.5), recentre=False)
    assert fit is not None and fit.affine is not None
    assert np.allclose(fit.affine[:, :2], truth.matrix()[:, :2], atol=TOL.direct_scale)
    assert np.allclose(fit.affine[:, 2], truth.matrix()[:, 2], atol=TOL.direct_shift_mm)
    pairs = overlap_pairs(fixed, moving, fit.affine, step_px=8)
    assert len(pairs) > 100  # a 2 mm grid over most of the 25 mm-radius window
    assert np.allclose(pairs[:, :2] @ fit.affine[:, :2].T + fit.affine[:, 2], pairs[:, 2:], atol=1e-9)
    radius = sv.WINDOW_RADIUS_PX / sv.PX_PER_MM  # both points of every pair lie in their windows (0.5 mm: pixels)
    assert np.all(np.hypot(*pairs[:, :2].T) <= radius + 0.5) and np.all(np.hypot(*pairs[:, 2:].T) <= radius + 0.5)
