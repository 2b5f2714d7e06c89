"""Sparse inverse-compositional tracking: recovers a known similarity as ECC does, and refuses what ECC refuses."""

from __future__ import annotations

import numpy as np
import pytest

from services.core.registration.direct_alignment import align
from services.core.registration.sparse_alignment import MAX_POINTS, sparse_align, sparse_template
from services.core.similarity import Similarity
from tests.services.core.registration.test_direct_alignment import CASES, _assert_recovers, _pair, _similarity
from tests.tolerances import TOL


@pytest.mark.parametrize(("motion", "seed"), CASES)
def test_recovers_a_similarity_from_the_motion_prediction(motion: tuple[float, float, float, float], seed: int) -> None:
    # a tracked frame starts from the motion prediction: within a millimetre of the truth
    truth = _similarity(*motion)
    fixed, moving = _pair(truth, seed)
    start = Similarity(truth.a, truth.t + complex(0.8, -0.6))
    _assert_recovers(sparse_align(sparse_template(fixed), moving, start), truth)


# a tracked frame's motion: consecutive frames at 10 frames/s (1.5 mm) and a faster one (5 mm); seeds of the field
TRACKING_CASES = [((1.5, 0.5, 0.3, 1.002), 0), ((1.5, 0.5, 0.3, 1.002), 2), ((3.0, -4.0, 1.0, 1.01), 0)]


@pytest.mark.parametrize(("motion", "seed"), TRACKING_CASES)
def test_agrees_with_ecc(motion: tuple[float, float, float, float], seed: int) -> None:
    # both minimise the same intensity misfit over the same pyramid: where most of the window overlaps, as when
    # tracking, they land within a tenth of a work pixel (0.025 mm; measured 0.004) at the window's corners.
    # (With half the window overlapping, CASES' large motion, they part by up to 0.05 mm, both within
    # TOL.direct_shift_mm of the truth.)
    truth = _similarity(*motion)
    fixed, moving = _pair(truth, seed)
    start = Similarity(truth.a, truth.t + complex(0.3, 0.2))
    ecc, sparse = align(fixed, moving, start, recentre=False), sparse_align(sparse_template(fixed), moving, start)
    assert ecc is not None and sparse is not None
    corners = np.array([complex(x, y) for x in (-20, 20) for y in (-15, 15)])  # the window's extent, mm
    apart = np.abs(ecc.transform.apply(corners) - sparse.transform.apply(corners)).max()
    assert apart < TOL.direct_shift_mm / 6  # 0.025 mm
    assert sparse.affine is not None
    assert sparse.correlation == pytest.approx(ecc.correlation, abs=0.01)


def test_the_template_keeps_the_strongest_gradients_inside_the_window() -> None:
    fixed, _ = _pair(_similarity(0.0, 0.0, 0.0, 1.0), 0)
    template = sparse_template(fixed)
    for level, chosen in enumerate(template.levels):
        assert chosen is not None
        assert 0 < len(chosen.values) <= MAX_POINTS
        x, y = chosen.points[:, 0, 0].astype(int), chosen.points[:, 0, 1].astype(int)
        assert np.all(fixed.masks[level][y, x] > 0)
        assert np.allclose(chosen.hessian, chosen.steepest.T @ chosen.steepest)


def test_unrelated_frames_are_not_tracked() -> None:
    fixed, _ = _pair(_similarity(0.0, 0.0, 0.0, 1.0), 100)
    _, moving = _pair(_similarity(0.0, 0.0, 0.0, 1.0), 200)
    fit = sparse_align(sparse_template(fixed), moving, _similarity(0.0, 0.0, 0.0, 1.0))
    assert fit is None or fit.correlation < 0.6  # the tracking gate (MethodOptions.track_correlation)


def test_disjoint_windows_give_none() -> None:
    fixed, moving = _pair(_similarity(3.0, 0.0, 0.0, 1.0), 0)
    assert sparse_align(sparse_template(fixed), moving, Similarity(1 + 0j, 80.0 + 0j)) is None
