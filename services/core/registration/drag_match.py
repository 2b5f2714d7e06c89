"""A loop closure's match across a skin dragged opposite ways: its inliers chosen with each frame's drag fitted.

Two rows of a raster drag the skin under the window opposite ways (services.core.physics.drag): between their
frames the overlap's centre moves against its rim by up to a few millimetres, more than a RANSAC gate about one
similarity allows, and a strong drag breaks every closure (issue 31). Here the pairs are gated about the model of
physics.drag instead: frame points p (src) and q (dst) show the same skin when their rest places agree,

    q - D_q phi(q) = a (p - D_p phi(p)) + t,   so   q = a p + t + D_q phi(q) - E phi(p),   E = a D_p,

linear in the four complex unknowns (a, t, D_q, E). A wide RANSAC similarity proposes the pairs, least squares
on that model re-gates them at the usual gate. The match it returns is measured as any other (the similarity and
affines of the raw inlier pairs): the drag is undone by the final drag fit, from the same pairs, as on every edge.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from services.core.physics.drag import profile
from services.core.registration.matching import (
    SimilarityFit,
    affine_inliers,
    centroid_and_spread,
    estimate_similarity,
    kept_pairs,
    unique_pairs,
)
from services.core.similarity import fit_affine, lsq_similarity

PROPOSAL_GATES = 8.0  # the wide RANSAC similarity that proposes pairs gates at this many usual gates
DRAG_PRIOR_MM = 2.0  # each frame's drag about 0 (1 sigma): a weak ridge that keeps a small overlap well posed
REGATE_ROUNDS = 3  # least squares on the drag model, re-gated at the usual gate, this many times
MAX_DRAG_MM = 4.0  # a fitted drag beyond this is no skin's: the match is refused


@dataclass(frozen=True)
class DraggedMatch:
    """A match gated about the drag model: the fit of its raw pairs (src -> dst), and the two frames' drags fitted
    with it (complex mm, each frame's own axes: D_p of src, D_q of dst)."""

    fit: SimilarityFit
    drag_src_mm: complex
    drag_dst_mm: complex


def estimate_dragged_match(
    src: np.ndarray,
    dst: np.ndarray,
    threshold: float,
    width_mm: float,
    seed: int = 0,
    min_inliers: int = 8,
    dedupe_radius: float = 0.0,
) -> DraggedMatch | None:
    """Return the match src -> dst (mm) of the raw pairs the drag model keeps within `threshold` (mm), or None.

    None when the wide proposal fails, fewer than min_inliers unique pairs stay, or a fitted drag exceeds
    MAX_DRAG_MM. width_mm: the drag profile's width (physics.drag.profile).
    """
    proposal = estimate_similarity(src, dst, PROPOSAL_GATES * threshold, seed, min_inliers, dedupe_radius)
    if proposal is None:
        return None
    p, q = src[:, 0] + 1j * src[:, 1], dst[:, 0] + 1j * dst[:, 1]
    fp, fq = profile(p, width_mm), profile(q, width_mm)
    keep = proposal.inlier_mask.copy()
    unknowns = np.zeros(4, complex)
    for _ in range(REGATE_ROUNDS):
        unknowns = _solve(p[keep], q[keep], fp[keep], fq[keep], threshold)
        keep = np.abs(_predict(unknowns, p, fp, fq) - q) < threshold
        if keep.sum() < min_inliers:
            return None
    a, _, drag_q, e = unknowns
    if abs(drag_q) > MAX_DRAG_MM or abs(e / a) > MAX_DRAG_MM:
        return None
    idx = np.flatnonzero(keep)
    if dedupe_radius > 0 and len(idx) > 1:
        idx = idx[unique_pairs(src[idx], dst[idx], dedupe_radius)]
    if len(idx) < min_inliers:
        return None
    inl = np.zeros(len(src), bool)
    inl[idx] = True
    transform = lsq_similarity(p[idx], q[idx])  # the raw pairs' similarity, as every edge is measured
    rms = float(np.sqrt(np.mean(np.sum((transform.apply(src[idx]) - dst[idx]) ** 2, axis=1))))
    affine = fit_affine(src[idx], dst[idx])
    view_affine, chosen = affine_inliers(src, dst, affine, inl, threshold)
    _, spread = centroid_and_spread(src[chosen])
    affine_sigma = rms / (math.sqrt(int(chosen.sum())) * spread) if spread > 0 else math.inf
    centre, lever = centroid_and_spread(src[idx])
    pairs = kept_pairs(src, dst, idx)
    fit = SimilarityFit(transform, len(idx), rms, inl, affine, affine_sigma, view_affine, centre, lever, pairs, pairs)
    return DraggedMatch(fit, complex(e / a), complex(drag_q))


def _predict(unknowns: np.ndarray, p: np.ndarray, fp: np.ndarray, fq: np.ndarray) -> np.ndarray:
    """Return where the model puts each src point p in dst (complex mm)."""
    a, t, drag_q, e = unknowns
    return a * p + t + drag_q * fq - e * fp


def _solve(p: np.ndarray, q: np.ndarray, fp: np.ndarray, fq: np.ndarray, noise_mm: float) -> np.ndarray:
    """Return (a, t, D_q, E) by complex least squares over the pairs, the drags ridged toward 0 (DRAG_PRIOR_MM)."""
    rows = np.column_stack([p, np.ones_like(p), fq, -fp])
    ridge = (noise_mm / DRAG_PRIOR_MM) * np.array([[0, 0, 1, 0], [0, 0, 0, 1]], complex)
    lhs = np.vstack([rows, ridge])
    rhs = np.concatenate([q, np.zeros(2, complex)])
    return np.linalg.lstsq(lhs, rhs, rcond=None)[0]
