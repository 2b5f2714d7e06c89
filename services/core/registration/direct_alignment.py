"""Direct (intensity-based) alignment of two vein maps: refinement and fallback for feature registration.

Vein maps are smooth and have few corners, so intensity alignment is the natural partner of features (as in
fetoscopic vessel-map mosaicking, Bano et al., MICCAI 2020). From an initial similarity (the feature estimate,
or the motion prediction when features fail), the moving frame's vein map is aligned to a placed frame's,
coarse to fine: phase correlation re-centres the coarsest level (it recovers shifts far beyond a gradient
method's basin), then ECC (Evangelidis & Psarakis 2008, OpenCV's findTransformECCWithMask) refines an affine
warp at each level, which is projected to the nearest similarity. The result carries its own evidence: the
ECC correlation over the overlap and the overlap's share of the window.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from services.core.similarity import Similarity

WORK_SCALE = 0.5  # alignment runs at half resolution (0.25 mm per pixel at 8 px/mm): veins are 2-12 px wide
LEVELS = 2  # pyramid levels at WORK_SCALE: 1/2 and 1/4 of full resolution (at 1/8 the veins vanish)
ECC_ITERATIONS = 60
ECC_EPS = 1e-5
PHASE_MIN_RESPONSE = 0.05  # phase-correlation peaks below this are noise: keep the initial estimate


@dataclass(frozen=True)
class AlignmentImage:
    """A vein map prepared for direct alignment: float32 pyramid (finest first) and window masks, at WORK_SCALE."""

    levels: tuple[np.ndarray, ...]
    masks: tuple[np.ndarray, ...]
    centre_px: tuple[float, float]  # the principal point, full-resolution pixels
    px_per_mm: float  # full-resolution pixels per mm


@dataclass(frozen=True)
class DirectFit:
    """A direct alignment: the similarity (moving mm -> fixed mm), ECC correlation and overlap share (0..1)."""

    transform: Similarity
    correlation: float
    overlap: float
    affine: np.ndarray | None = None  # the alignment's affine (2x3, moving mm -> fixed mm) it was projected from


def alignment_image(
    vein: np.ndarray, mask: np.ndarray, centre_px: tuple[float, float], px_per_mm: float, scale: float = 1.0
) -> AlignmentImage:
    """Return the alignment pyramid of an 8-bit vein map and its window mask (0/255).

    scale: the vein map's pixels per full-resolution pixel (0.5 for a half-resolution map).
    """
    image = vein.astype(np.float32) / 255.0
    window = mask
    if scale != WORK_SCALE:
        k = WORK_SCALE / scale
        size = (round(vein.shape[1] * k), round(vein.shape[0] * k))
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        window = cv2.resize(mask, size, interpolation=cv2.INTER_NEAREST)
    levels, masks = [image], [window]
    for _ in range(LEVELS - 1):
        levels.append(cv2.pyrDown(levels[-1]))
        masks.append(cv2.resize(masks[-1], levels[-1].shape[::-1], interpolation=cv2.INTER_NEAREST))
    return AlignmentImage(tuple(levels), tuple(masks), centre_px, px_per_mm)


def _level_frame(img: AlignmentImage, level: int) -> tuple[float, np.ndarray]:
    """Return (one level's pixels per mm, the principal point (2,) in that level's pixels)."""
    scale = WORK_SCALE / 2**level
    return img.px_per_mm * scale, np.asarray(img.centre_px, np.float64) * scale


def level_matrix_px(s: Similarity, img: AlignmentImage, level: int) -> np.ndarray:
    """Return the 2x3 matrix of a mm similarity (moving -> fixed) in one level's pixels."""
    k, centre = _level_frame(img, level)
    c = complex(*centre)
    a, t = s.a, c + k * s.t - s.a * c
    return np.array([[a.real, -a.imag, t.real], [a.imag, a.real, t.imag]], np.float32)


def level_similarity_mm(m: np.ndarray, img: AlignmentImage, level: int) -> Similarity:
    """Return the nearest mm similarity (moving -> fixed) of a 2x3 pixel matrix at one level."""
    a = complex((m[0, 0] + m[1, 1]) / 2.0, (m[1, 0] - m[0, 1]) / 2.0)
    k, centre = _level_frame(img, level)
    c = complex(*centre)
    t = complex(m[0, 2], m[1, 2])
    return Similarity(a, (t - c + a * c) / k)


def level_affine_mm(m: np.ndarray, img: AlignmentImage, level: int) -> np.ndarray:
    """Return the 2x3 mm affine (moving -> fixed) of a 2x3 pixel matrix at one level (_affine_px's inverse)."""
    k, c = _level_frame(img, level)
    a = np.asarray(m[:, :2], np.float64)
    return np.hstack([a, ((a @ c + m[:, 2] - c) / k)[:, None]])


def _affine_px(affine_mm: np.ndarray, img: AlignmentImage, level: int) -> np.ndarray:
    """Return the 2x3 pixel matrix at one level of a mm affine (moving -> fixed) (level_affine_mm's inverse)."""
    k, c = _level_frame(img, level)
    a, t = np.asarray(affine_mm, np.float64)[:, :2], np.asarray(affine_mm, np.float64)[:, 2]
    return np.hstack([a, (k * t + c - a @ c)[:, None]])


def _phase_shift(fixed: np.ndarray, moving_warped: np.ndarray, overlap: np.ndarray) -> tuple[float, float, float]:
    """Return (dx, dy, response): the shift that moves the warped moving image onto the fixed one (pixels)."""
    win = cv2.createHanningWindow(fixed.shape[::-1], cv2.CV_32F)
    w = win * (overlap > 0)
    (dx, dy), response = cv2.phaseCorrelate(moving_warped * w, fixed * w, win)
    return float(dx), float(dy), float(response)


def _ecc(fixed: np.ndarray, fmask: np.ndarray, moving: np.ndarray, mmask: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Return the ECC-refined affine (moving -> fixed pixels); raises cv2.error when ECC does not converge."""
    warp = cv2.invertAffineTransform(m)  # ECC's warp maps template (fixed) pixels to input (moving) pixels
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, ECC_ITERATIONS, ECC_EPS)
    _, warp = cv2.findTransformECCWithMask(fixed, moving, fmask, mmask, warp, cv2.MOTION_AFFINE, criteria, 3)
    return cv2.invertAffineTransform(warp)


def _overlap(fixed: AlignmentImage, moving: AlignmentImage, m: np.ndarray, level: int) -> np.ndarray:
    """Return the fixed level's mask where the moving window lands too (0/255)."""
    fm = fixed.masks[level]
    landed = cv2.warpAffine(moving.masks[level], m, fm.shape[::-1], flags=cv2.INTER_NEAREST)
    return cv2.bitwise_and(fm, landed)


def overlap_pairs(fixed: AlignmentImage, moving: AlignmentImage, affine_mm: np.ndarray, step_px: int) -> np.ndarray:
    """Return (n, 4) point pairs (moving x, y, fixed x, y; mm) on a grid of the overlap under an alignment's affine.

    What a feature match's inlier pairs are to its edge: the places the alignment relates, to undo a deformation
    that varies across the window (physics.drag) from. Grid every step_px pixels of the finest level.
    """
    k, c = _level_frame(fixed, 0)
    ys, xs = np.nonzero(
        _overlap(fixed, moving, _affine_px(affine_mm, fixed, 0).astype(np.float32), 0)[::step_px, ::step_px]
    )
    fixed_mm = (np.stack([xs, ys], axis=1) * float(step_px) - c) / k
    a, t = np.asarray(affine_mm, np.float64)[:, :2], np.asarray(affine_mm, np.float64)[:, 2]
    moving_mm = (fixed_mm - t) @ np.linalg.inv(a).T
    return np.hstack([moving_mm, fixed_mm])


def correlation(fixed: AlignmentImage, moving: AlignmentImage, transform: Similarity) -> tuple[float, float]:
    """Return (normalised correlation, overlap share of the fixed window) of two vein maps under a transform."""
    m = level_matrix_px(transform, fixed, 0)
    both = _overlap(fixed, moving, m, 0) > 0
    share = float(np.count_nonzero(both)) / max(float(np.count_nonzero(fixed.masks[0])), 1.0)
    if np.count_nonzero(both) < 100:
        return 0.0, share
    warped = cv2.warpAffine(moving.levels[0], m, fixed.levels[0].shape[::-1], flags=cv2.INTER_LINEAR)
    a = fixed.levels[0][both] - fixed.levels[0][both].mean()
    b = warped[both] - warped[both].mean()
    denom = float(np.sqrt(np.sum(a * a) * np.sum(b * b)))
    return (float(np.sum(a * b)) / denom if denom > 0 else 0.0), share


def align(
    fixed: AlignmentImage, moving: AlignmentImage, initial: Similarity, *, recentre: bool, finest: int = 0
) -> DirectFit | None:
    """Return the direct alignment of moving onto fixed (mm similarity moving -> fixed), or None.

    recentre: start with phase correlation at the coarsest level (use it when the initial estimate comes from
    the motion prediction rather than from features). finest: the finest pyramid level refined (0 = WORK_SCALE).
    None when the windows do not overlap under the estimate or ECC diverges.
    """
    top = LEVELS - 1
    m = level_matrix_px(initial, fixed, top)
    if recentre:
        overlap = _overlap(fixed, moving, m, top)
        if np.count_nonzero(overlap) < 50:
            return None
        warped = cv2.warpAffine(moving.levels[top], m, fixed.levels[top].shape[::-1], flags=cv2.INTER_LINEAR)
        dx, dy, response = _phase_shift(fixed.levels[top], warped, overlap)
        if response >= PHASE_MIN_RESPONSE:
            m = m.copy()
            m[0, 2] += dx
            m[1, 2] += dy
    estimate = level_similarity_mm(m, fixed, top)
    affine = None
    for level in range(top, finest - 1, -1):
        m = level_matrix_px(estimate, fixed, level)
        if np.count_nonzero(_overlap(fixed, moving, m, level)) < 50:
            return None
        try:
            m = _ecc(fixed.levels[level], fixed.masks[level], moving.levels[level], moving.masks[level], m)
        except cv2.error:
            return None
        estimate, affine = level_similarity_mm(m, fixed, level), level_affine_mm(m, fixed, level)
    corr, share = correlation(fixed, moving, estimate)
    return DirectFit(estimate, corr, share, affine)
