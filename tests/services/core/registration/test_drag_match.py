"""A closure's match across a skin dragged opposite ways (registration.drag_match), on synthetic pairs."""

from __future__ import annotations

import numpy as np

from services.core.physics.drag import profile
from services.core.registration.drag_match import MAX_DRAG_MM, estimate_dragged_match
from services.core.registration.matching import estimate_similarity
from services.core.similarity import Similarity

GATE_MM = 0.25  # ransac_px 2 at 8 px/mm, the default gate
WIDTH_MM = 15.0  # the profile width the pairs are made with and the match assumes
REST = Similarity(1.002 * np.exp(0.01j), complex(-24.0, 3.0))  # rest places, frame p -> frame q
MIN_INLIERS = 20


def _dragged_pairs(
    drag_p: complex, drag_q: complex, n: int = 120, outliers: int = 40, seed: int = 3
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return src, dst (mm, (N, 2)) of one skin seen by two frames dragged by drag_p, drag_q (physics.drag's
    model), 0.02 mm of noise, with `outliers` random pairs appended; and the mask of the true pairs."""
    rng = np.random.default_rng(seed)
    p = complex(12.0, 0.0) + rng.uniform(-14, 14, n) + 1j * rng.uniform(-20, 20, n)  # the overlap: q's half
    rest_q = REST.a * (p - drag_p * profile(p, WIDTH_MM)) + REST.t
    q = rest_q.copy()
    for _ in range(50):  # q - D_q phi(q) = rest_q, by fixed point (phi is smooth and |D_q| small)
        q = rest_q + drag_q * profile(q, WIDTH_MM)
    q = q + 0.02 * (rng.standard_normal(n) + 1j * rng.standard_normal(n))
    bad_p = rng.uniform(-25, 25, outliers) + 1j * rng.uniform(-20, 20, outliers)
    bad_q = rng.uniform(-25, 25, outliers) + 1j * rng.uniform(-20, 20, outliers)
    src = np.concatenate([p, bad_p])
    dst = np.concatenate([q, bad_q])
    truth = np.r_[np.ones(n, bool), np.zeros(outliers, bool)]
    return np.column_stack([src.real, src.imag]), np.column_stack([dst.real, dst.imag]), truth


def test_opposite_drags_break_one_similarity_and_the_drag_model_keeps_the_pairs() -> None:
    src, dst, truth = _dragged_pairs(1.5, -1.5)
    plain = estimate_similarity(src, dst, GATE_MM, min_inliers=MIN_INLIERS)
    assert plain is None or plain.inliers < 0.6 * truth.sum()  # the premise: the usual gate loses the closure
    match = estimate_dragged_match(src, dst, GATE_MM, WIDTH_MM, min_inliers=MIN_INLIERS)
    assert match is not None
    # the drags it fits with the pairs (each frame's axes); 0.3 mm: the ridge toward 0 and the overlap's half window
    assert abs(match.drag_src_mm - 1.5) < 0.3 and abs(match.drag_dst_mm + 1.5) < 0.3, match
    fit = match.fit
    kept = fit.inlier_mask
    assert kept[truth].mean() > 0.9  # nearly every true pair
    assert not kept[~truth].any()  # and no random one
    assert fit.pairs is not None and len(fit.pairs) >= MIN_INLIERS
    # the pairs are the raw ones (the final drag fit undoes the drag from them, as on every edge)
    rows = {tuple(np.round(r, 3)) for r in np.hstack([src[kept], dst[kept]])}
    assert all(tuple(np.round(r.astype(float), 3)) in rows for r in fit.pairs.astype(np.float64))


def test_without_a_drag_it_is_the_similarity() -> None:
    src, dst, truth = _dragged_pairs(0j, 0j)
    match = estimate_dragged_match(src, dst, GATE_MM, WIDTH_MM, min_inliers=MIN_INLIERS)
    assert match is not None and match.fit.inlier_mask[truth].mean() > 0.95
    assert abs(match.drag_src_mm) < 0.3 and abs(match.drag_dst_mm) < 0.3
    fit = match.fit
    probe = np.array([[0.0, 0.0], [20.0, 10.0]])
    assert np.allclose(fit.transform.apply(probe), REST.apply(probe), atol=0.01)  # 0.02 mm noise over 120 pairs


def test_random_pairs_and_drags_no_skin_has_are_refused() -> None:
    rng = np.random.default_rng(5)
    src, dst = rng.uniform(-25, 25, (150, 2)), rng.uniform(-25, 25, (150, 2))
    assert estimate_dragged_match(src, dst, GATE_MM, WIDTH_MM, min_inliers=MIN_INLIERS) is None
    src, dst, _ = _dragged_pairs(2.5 * MAX_DRAG_MM, 0j)
    assert estimate_dragged_match(src, dst, GATE_MM, WIDTH_MM, min_inliers=MIN_INLIERS) is None
