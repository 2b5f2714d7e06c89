"""Vein enhancement: the paper's segmentation step (its §V) as a soft, multi-scale ridge map.

Real NIR frames of skin are smooth; the veins are the only structure, 3-35 % darker than the skin around them
with soft edges. Registration therefore runs on a map of the vein pattern rather than on raw grey levels:

1. flat-field: divide by the local skin level (a masked Gaussian mean much wider than a vein), which removes
   shading, vignetting left-overs and gain drift, so darkness is relative (1 - I / skin);
2. multi-scale ridge strength: the largest eigenvalue of the Hessian of the flat-fielded image (positive across
   a dark line), scale-normalised by sigma^2, the maximum over vein-sized scales (Frangi et al. 1998, without the
   blob/background terms, which smooth skin does not need);
3. local contrast normalisation to 8 bits by a robust high percentile of the window, so faint and strong
   vessel patterns use the same grey range and fixed detector thresholds become meaningful.

The map may be computed at a fraction of the frame's resolution (`scale`): vessels are 1-6 mm wide, so at half
resolution (0.25 mm per pixel at 8 px/mm) they still span 2-24 pixels, and every filter costs a quarter.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

VEIN_SCALES_PX = (2.0, 3.5, 6.0)  # Hessian scales (px at 8 px/mm): vessels about 1-6 mm wide
SKIN_SIGMA_PX = 20.0  # local skin level: several vein widths, below the vignetting's scale
NORMALISE_PERCENTILE = 99.5  # this percentile of the window's ridge strength maps to grey 255
MIN_RIDGE = 1e-3  # ridge strength below this (a 0.1 % dip) is no vessel: a featureless window stays black


@dataclass(frozen=True)
class VeinMap:
    """A frame's vein pattern: ridge strength as 8-bit (0 = skin) and the window it is valid in (0/255)."""

    image: np.ndarray  # (h, w) uint8, at `scale` of the frame's resolution
    mask: np.ndarray  # (h, w) uint8 0/255
    scale: float = 1.0  # the map's pixels per frame pixel (0.5: half resolution)


def skin_level(image: np.ndarray, mask: np.ndarray, sigma_px: float = SKIN_SIGMA_PX) -> np.ndarray:
    """Return the local skin grey level (float32, the image's units): a Gaussian mean over the window only."""
    inside = (mask > 0).astype(np.float32)
    num = cv2.GaussianBlur(image.astype(np.float32) * inside, (0, 0), sigma_px)
    den = cv2.GaussianBlur(inside, (0, 0), sigma_px)
    return num / np.maximum(den, 1e-3)


def ridge_strength(relative: np.ndarray, scales_px: tuple[float, ...] = VEIN_SCALES_PX) -> np.ndarray:
    """Return the scale-normalised dark-ridge strength (float32, >= 0; ~contrast) of a flat-fielded image."""
    best = np.zeros(relative.shape, np.float32)
    for s in scales_px:
        g = cv2.GaussianBlur(relative, (0, 0), s)
        dxx = cv2.Sobel(g, cv2.CV_32F, 2, 0, ksize=3)
        dyy = cv2.Sobel(g, cv2.CV_32F, 0, 2, ksize=3)
        dxy = cv2.Sobel(g, cv2.CV_32F, 1, 1, ksize=3)
        lam = 0.5 * (dxx + dyy + np.sqrt((dxx - dyy) ** 2 + 4.0 * dxy * dxy))  # largest Hessian eigenvalue
        np.maximum(best, (s * s) * lam, out=best)
    return best


def enhance_veins(image: np.ndarray, mask: np.ndarray, margin_px: int = 0, scale: float = 1.0) -> VeinMap:
    """Return the 8-bit vein map of a frame (uint8 or float grey levels) inside its window, at `scale` of its size.

    The window is eroded by margin_px (frame pixels) so the housing's dark edge never reads as a vessel. Filter
    sizes are given in frame pixels and scaled with the map, so the map's content does not depend on `scale`.
    """
    f = image.astype(np.float32)
    if scale != 1.0:
        size = (round(image.shape[1] * scale), round(image.shape[0] * scale))
        f = cv2.resize(f, size, interpolation=cv2.INTER_AREA)
        # a map pixel belongs to the window only when all of it does
        mask = np.where(cv2.resize(mask, size, interpolation=cv2.INTER_AREA) >= 255, 255, 0).astype(np.uint8)
    margin = round(margin_px * scale)
    inner = cv2.erode(mask, np.ones((2 * margin + 1,) * 2, np.uint8)) if margin > 0 else mask
    relative = f / np.maximum(skin_level(f, mask, SKIN_SIGMA_PX * scale), 1.0)  # 1 on skin, 0.65-0.97 on a vessel
    # outside the window the housing is dark: fill it with skin so it makes no ridge at the edge
    relative = np.where(mask > 0, relative, 1.0).astype(np.float32)
    ridge = ridge_strength(relative, tuple(s * scale for s in VEIN_SCALES_PX))
    ridge[inner == 0] = 0.0
    inside = ridge[inner > 0]
    top = float(np.percentile(inside, NORMALISE_PERCENTILE)) if inside.size else 0.0
    gain = 255.0 / top if top > MIN_RIDGE else 0.0
    return VeinMap(np.clip(ridge * gain, 0, 255).astype(np.uint8), inner, scale)
