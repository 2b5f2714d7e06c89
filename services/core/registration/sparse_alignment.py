"""Sparse inverse-compositional alignment of a frame's vein map onto a keyframe's: tracking's cheap direct alignment.

What SVO's sparse image alignment is to its keyframes (Forster et al. 2014/2017), after Baker & Matthews' inverse
compositional algorithm (IJCV 2004): the keyframe is the template. Its pixels that carry the alignment (the vein
map's strongest gradients inside the window, direct_alignment's pyramid levels) and their steepest-descent rows
for an affine warp are computed once per keyframe (`sparse_template`); every frame tracked on it then costs one
bilinear sampling of its own map at those pixels and one 6x6 solve per iteration. The moving samples are
normalised to the template's mean and spread over the pixels both windows hold (ECC's invariance to gain and
bias). The result is the same DirectFit as direct_alignment.align: the nearest similarity, the affine, and the
correlation and overlap share over the whole overlap (direct_alignment.correlation).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from services.core.registration.direct_alignment import (
    AlignmentImage,
    DirectFit,
    correlation,
    level_affine_mm,
    level_matrix_px,
    level_similarity_mm,
)
from services.core.similarity import Similarity

TEMPLATE_SHARE = 0.25  # the share of the window's pixels kept per level: the strongest gradients (veins' flanks)
MAX_POINTS = 6000  # per level, at most
MIN_POINTS = 200  # a level with fewer usable template pixels, or fewer landing inside the frame, is not aligned
ITERATIONS = 30  # per level, at most
STEP_EPS_PX = 1e-2  # stop when the update moves no corner of a STEP_CORNER_PX square by more than this (level px)
STEP_CORNER_PX = 100.0
MIN_LANDED = 0.25  # the share of a level's template pixels that must land inside the moving window


@dataclass(frozen=True)
class _Level:
    """One level of a sparse template: pixel coordinates (N, 1, 2) float32, values (N,), steepest-descent rows
    (N, 6) and their Gauss-Newton Hessian (6, 6)."""

    points: np.ndarray
    values: np.ndarray
    steepest: np.ndarray
    hessian: np.ndarray


@dataclass(frozen=True)
class SparseTemplate:
    """A keyframe prepared for sparse tracking: its alignment pyramid and, per level, its selected pixels."""

    image: AlignmentImage
    levels: tuple[_Level | None, ...]  # None: too few pixels carry gradient at that level


def sparse_template(image: AlignmentImage) -> SparseTemplate:
    """Return the sparse template of a keyframe's alignment pyramid (its strongest-gradient window pixels)."""
    return SparseTemplate(image, tuple(_level(lv, mk) for lv, mk in zip(image.levels, image.masks, strict=True)))


def _level(values: np.ndarray, mask: np.ndarray) -> _Level | None:
    """Return one level's selected pixels and their affine steepest-descent rows (warp parameters p1..p6 of
    x' = (1 + p1) x + p3 y + p5, y' = p2 x + (1 + p4) y + p6, Baker & Matthews' order), or None."""
    gx = cv2.Sobel(values, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8)
    gy = cv2.Sobel(values, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)
    inner = cv2.erode(mask, np.ones((3, 3), np.uint8)) > 0  # the gradient straddles no window edge
    magnitude = np.where(inner, gx * gx + gy * gy, 0.0)
    count = min(MAX_POINTS, int(TEMPLATE_SHARE * np.count_nonzero(inner)))
    if count < MIN_POINTS:
        return None
    flat = magnitude.ravel()
    chosen = np.argpartition(flat, flat.size - count)[flat.size - count :]
    chosen = chosen[flat[chosen] > 0]
    if len(chosen) < MIN_POINTS:
        return None
    ys, xs = np.divmod(chosen, values.shape[1])
    x, y = xs.astype(np.float32), ys.astype(np.float32)
    dx, dy = gx.ravel()[chosen], gy.ravel()[chosen]
    steepest = np.stack([dx * x, dy * x, dx * y, dy * y, dx, dy], axis=1).astype(np.float64)
    points = np.stack([x, y], axis=1).reshape(-1, 1, 2)
    return _Level(points, values.ravel()[chosen].astype(np.float64), steepest, steepest.T @ steepest)


def _compose_inverse(warp: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Return W(x; p) o W(x; delta)^-1 as a 2x3 matrix (the inverse compositional update)."""
    step = np.array([[1 + delta[0], delta[2], delta[4]], [delta[1], 1 + delta[3], delta[5]], [0, 0, 1]])
    full = np.vstack([warp, [0, 0, 1]]) @ np.linalg.inv(step)
    return full[:2]


def _refine(level: _Level, moving: np.ndarray, moving_mask: np.ndarray, warp: np.ndarray) -> np.ndarray | None:
    """Return the refined template -> moving affine (2x3, level pixels), or None when too little lands inside."""
    need = max(MIN_POINTS, MIN_LANDED * len(level.values))
    for _ in range(ITERATIONS):
        mapped = cv2.transform(level.points, warp)  # (N, 1, 2) float32: where each template pixel lands
        sampled = cv2.remap(moving, mapped, None, cv2.INTER_LINEAR, borderValue=0).ravel().astype(np.float64)
        inside = cv2.remap(moving_mask, mapped, None, cv2.INTER_NEAREST, borderValue=0).ravel() > 0
        count = int(np.count_nonzero(inside))
        if count < need:
            return None
        t, s = level.values, sampled
        hessian = level.hessian
        if count < len(t):  # the pixels landing outside the moving window drop out of the sums
            out = ~inside
            hessian = hessian - level.steepest[out].T @ level.steepest[out]
            t, s = np.where(inside, t, 0.0), np.where(inside, s, 0.0)
        s_mean, t_mean = s.sum() / count, t.sum() / count
        s_spread = np.sqrt(max((s * s).sum() / count - s_mean * s_mean, 0.0))
        t_spread = np.sqrt(max((t * t).sum() / count - t_mean * t_mean, 0.0))
        if s_spread <= 1e-9:
            return None
        error = ((s - s_mean) * (t_spread / s_spread) + t_mean - t) * inside  # moving at the template's gain
        try:
            delta = np.linalg.solve(hessian, level.steepest.T @ error)
        except np.linalg.LinAlgError:
            return None
        warp = _compose_inverse(warp, delta)
        if np.hypot(delta[4], delta[5]) + STEP_CORNER_PX * np.abs(delta[:4]).max() < STEP_EPS_PX:
            break
    return warp


def sparse_align(template: SparseTemplate, moving: AlignmentImage, initial: Similarity) -> DirectFit | None:
    """Return the alignment of moving onto the template's keyframe (mm similarity moving -> keyframe, its affine,
    correlation and overlap share), coarse to fine from `initial`; None when a level cannot be aligned."""
    fixed = template.image
    estimate: Similarity = initial
    affine: np.ndarray | None = None
    for level in range(len(fixed.levels) - 1, -1, -1):
        chosen = template.levels[level]
        if chosen is None:
            continue
        to_moving = cv2.invertAffineTransform(level_matrix_px(estimate, fixed, level)).astype(np.float64)
        refined = _refine(chosen, moving.levels[level], moving.masks[level], to_moving)
        if refined is None:
            return None
        m = cv2.invertAffineTransform(refined)
        estimate, affine = level_similarity_mm(m, fixed, level), level_affine_mm(m, fixed, level)
    if affine is None:
        return None
    corr, share = correlation(fixed, moving, estimate)
    return DirectFit(estimate, corr, share, affine)
