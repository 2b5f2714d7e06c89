"""Feature matching and plane-induced similarity estimation between a frame and the mosaic (spec §2 "Pose")."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from services.core.registration.features import Features
from services.core.similarity import Similarity, fit_affine

PAIRS_KEPT = 64  # inlier pairs a fit keeps as evidence (1 KB): enough for the drag fit, bounded for long scans


@dataclass(frozen=True)
class SimilarityFit:
    """A RANSAC similarity fit: the transform (src -> dst units), unique inliers and their RMS residual.

    affine: the full affine (2x3, src -> dst) least-squares fitted on the same inliers (the edge's measurement,
    services.core.physics.tissue_model.corrected_relative). view_affine: the affine fitted on its own inliers
    (affine_inliers): its non-similarity part measures how differently the two frames are stretched, unshrunk;
    affine_sigma its standard error (dimensionless: RMS residual / (sqrt(inliers) * RMS spread of the inliers)).
    """

    transform: Similarity
    inliers: int
    rms: float
    inlier_mask: np.ndarray
    affine: np.ndarray | None = None
    affine_sigma: float = math.inf
    view_affine: np.ndarray | None = None
    centre: complex = 0j  # the inliers' centroid (src units): where the fit's translation is best known
    spread: float = 0.0  # the inliers' RMS distance from it (src units): the lever of its rotation and scale
    pairs: np.ndarray | None = None  # float32 (n, 4): the unique inliers, src x, y then dst x, y
    # float32 (n, 4): the unique pairs within drag_gate thresholds of the similarity (estimate_similarity), the skin
    # drag's evidence: the inliers alone are the pairs a drag moved least (the gate cuts the window's centre)
    drag_pairs: np.ndarray | None = None


def nearest_descriptors(
    query: np.ndarray, train: np.ndarray, k: int, allowed: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Return (indices, L2 distances), both (len(query), k), of each query descriptor's k nearest train ones.

    Brute force as one matrix product (|q|^2 + |t|^2 - 2 q.t, float32: SIFT's whole-number descriptors keep every
    sum below 2^24, so the squared distances are exact), nearest first (ties: the lower train index first); pairs
    `allowed` forbids (uint8 0) get +inf distance. The sum is built in the product's own array (a new 1 MB
    temporary per term cost more than the product at 500 x 500). The k nearest are taken by k row-wise argmins
    (k is small): 3x faster than an argpartition and a sort, and 2x faster than OpenCV's BFMatcher.knnMatch plus
    the Python loop over its DMatch lists.
    """
    q = np.asarray(query, np.float32)
    t = np.asarray(train, np.float32)
    d2 = q @ t.T
    d2 *= -2.0
    d2 += np.einsum("ij,ij->i", t, t)[None, :]
    d2 += np.einsum("ij,ij->i", q, q)[:, None]
    np.maximum(d2, 0.0, out=d2)
    if allowed is not None:
        np.copyto(d2, np.float32(np.inf), where=np.asarray(allowed) == 0)
    k = min(k, d2.shape[1])
    rows = np.arange(len(q))
    indices = np.empty((len(q), k), np.intp)
    nearest = np.empty((len(q), k), np.float32)
    for column in range(k):
        best = d2.argmin(axis=1)
        indices[:, column] = best
        nearest[:, column] = d2[rows, best]
        d2[rows, best] = np.inf
    return indices, np.sqrt(nearest)


def match_features(
    query: Features,
    train: Features,
    ratio: float = 0.8,
    same_point: float = 2.0,
    candidates: int = 4,
    allowed: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Return index arrays (iq, it) of ratio-test matches from query to train.

    The second neighbour of the ratio test is the best one at a *different place* (farther than same_point
    from the first, in train units), so a point seen in several A-SIFT views or several frames does not
    veto its own match. `allowed` (len(query), len(train)) uint8 restricts candidates (guided matching).
    """
    if len(query) == 0 or len(train) < 2:
        return np.zeros(0, int), np.zeros(0, int)
    k = min(candidates, len(train))
    idx, dist = nearest_descriptors(query.descriptors, train.descriptors, k, allowed)
    found = np.isfinite(dist[:, 0])
    if not found.any():
        return np.zeros(0, int), np.zeros(0, int)
    iq, idx, dist = np.flatnonzero(found), idx[found], dist[found]
    tp = train.points
    gap = np.linalg.norm(tp[idx] - tp[idx[:, :1]], axis=2)  # each candidate's distance from the best's place
    elsewhere = (gap > same_point) & np.isfinite(dist)
    elsewhere[:, 0] = False
    has_second = elsewhere.any(axis=1)
    second = np.where(has_second, dist[np.arange(len(iq)), elsewhere.argmax(axis=1)], np.inf)
    # no candidate at another place: unambiguous; else Lowe's ratio against the best other place
    keep = ~has_second | (dist[:, 0] < ratio * second)
    return iq[keep], idx[keep, 0]


def unique_pairs(src: np.ndarray, dst: np.ndarray, radius: float = 2.0) -> np.ndarray:
    """Return a boolean mask keeping one of each group of matches whose ends both lie within radius.

    Greedy in order: a match goes when an earlier match that was kept has both ends within radius of its own (each
    coordinate: the Chebyshev distance of the 4-D points (src, dst)). The close pairs come from a k-d tree (scipy's
    query_pairs, O(n log n): the paper's A-SIFT matches run to thousands); only the matches with an earlier close one
    are walked in order.
    """
    keep = np.ones(len(src), bool)
    if len(src) < 2:
        return keep
    pairs = cKDTree(np.hstack([src, dst])).query_pairs(radius, p=np.inf, output_type="ndarray")  # rows i < j
    if len(pairs) == 0:
        return keep
    pairs = pairs[np.lexsort((pairs[:, 0], pairs[:, 1]))]  # by the later match
    later, starts = np.unique(pairs[:, 1], return_index=True)
    for j, earlier in zip(later, np.split(pairs[:, 0], starts[1:]), strict=True):
        keep[j] = not keep[earlier].any()
    return keep


def estimate_similarity(
    src: np.ndarray,
    dst: np.ndarray,
    threshold: float,
    seed: int = 0,
    min_inliers: int = 8,
    dedupe_radius: float = 0.0,
    drag_gate: float = 0.0,
) -> SimilarityFit | None:
    """Return the RANSAC similarity src -> dst (LM-refined on inliers), or None with too few inliers.

    `threshold` is the reprojection threshold in dst units; inliers are counted after merging matches
    repeated within dedupe_radius (src units scaled alike), so counts are honest for A-SIFT. drag_gate > 0: the
    fit's drag_pairs are the unique pairs within drag_gate x threshold of the similarity (0: none).
    """
    if len(src) < max(3, min_inliers):
        return None
    cv2.setRNGSeed(seed)
    M, mask = cv2.estimateAffinePartial2D(
        src.astype(np.float64),
        dst.astype(np.float64),
        method=cv2.RANSAC,
        ransacReprojThreshold=threshold,
        maxIters=2000,
        confidence=0.999,
        refineIters=20,
    )
    if M is None or mask is None:
        return None
    inl = mask.ravel().astype(bool)
    if dedupe_radius > 0 and inl.sum() > 1:
        idx = np.flatnonzero(inl)
        keep = unique_pairs(src[idx], dst[idx], dedupe_radius)
        inl = np.zeros_like(inl)
        inl[idx[keep]] = True
    n = int(inl.sum())
    if n < min_inliers:
        return None
    transform = Similarity(complex(M[0, 0], M[1, 0]), complex(M[0, 2], M[1, 2]))
    resid = transform.apply(src[inl]) - dst[inl]
    rms = float(np.sqrt(np.mean(np.sum(resid**2, axis=1))))
    affine = fit_affine(src[inl], dst[inl])
    view_affine, chosen = affine_inliers(src, dst, affine, inl, threshold)
    _, spread = centroid_and_spread(src[chosen])
    a_rms = _affine_rms(view_affine, src[chosen], dst[chosen]) if view_affine is not None else rms
    affine_sigma = a_rms / (math.sqrt(int(chosen.sum())) * spread) if spread > 0 else math.inf
    centre, lever = centroid_and_spread(src[inl])
    pairs = kept_pairs(src, dst, np.flatnonzero(inl))
    drag_pairs = None
    if drag_gate > 0:
        near = np.flatnonzero(np.hypot(*(transform.apply(src) - dst).T) < drag_gate * threshold)
        if dedupe_radius > 0 and len(near) > 1:
            near = near[unique_pairs(src[near], dst[near], dedupe_radius)]
        drag_pairs = kept_pairs(src, dst, near)
    return SimilarityFit(transform, n, rms, inl, affine, affine_sigma, view_affine, centre, lever, pairs, drag_pairs)


def kept_pairs(src: np.ndarray, dst: np.ndarray, chosen: np.ndarray) -> np.ndarray:
    """Return float32 (n, 4) pairs (src x, y then dst x, y) of at most PAIRS_KEPT of `chosen`, spread over it."""
    kept = chosen[np.linspace(0, len(chosen) - 1, min(len(chosen), PAIRS_KEPT)).astype(int)]
    return np.hstack([src[kept], dst[kept]]).astype(np.float32)


def centroid_and_spread(points: np.ndarray) -> tuple[complex, float]:
    """Return the centroid (complex, the points' units) of (N, 2) points and their RMS distance from it."""
    centroid = points.mean(axis=0)
    spread = float(np.sqrt(np.mean(np.sum((points - centroid) ** 2, axis=1))))
    return complex(centroid[0], centroid[1]), spread


def _affine_residuals(affine: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    return np.hypot(*(src @ affine[:, :2].T + affine[:, 2] - dst).T)


def _affine_rms(affine: np.ndarray, src: np.ndarray, dst: np.ndarray) -> float:
    return float(np.sqrt(np.mean(_affine_residuals(affine, src, dst) ** 2)))


def affine_inliers(
    src: np.ndarray,
    dst: np.ndarray,
    affine: np.ndarray | None,
    start: np.ndarray,
    threshold: float,
    rounds: int = 4,
) -> tuple[np.ndarray | None, np.ndarray]:
    """Return (the least-squares affine, its inliers), starting from `affine` fitted on a similarity's inliers
    `start`, re-selected by the affine's own residuals until they settle.

    A similarity's inliers are biased toward pairs whose noise hides the non-similar part (a stretch of 1 % moves
    points 20 mm from the centre by 0.2 mm, a few pixels): the affine fitted on them alone understates it.
    """
    chosen = start
    for _ in range(rounds):
        if affine is None:
            break
        again = _affine_residuals(affine, src, dst) < threshold
        if int(again.sum()) < 4 or np.array_equal(again, chosen):
            break
        chosen = again
        affine = fit_affine(src[chosen], dst[chosen])
    return affine, chosen
