"""Procedural NIR skin world: a branching dark vein network at several depths on diffuse skin (float32, 0..1).

At 850 nm the light is diffused by the tissue, so skin is smooth (low-frequency albedo and shading only) and the
veins are the only structure: darker by a few to ~35 %, softer and fainter the deeper they lie. The old
fine-grain skin texture survives only as the explicitly named easy `textured` skin.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter1d

SKIN_LEVEL = 0.65  # mean reflectance of skin at 850 nm (fraction of full scale)
SKIN_LAYERS = ((0.9, 0.012), (2.0, 0.035), (4.0, 0.04), (10.0, 0.03))  # textured skin only: (sigma px, amplitude)
SHADING_SIGMA_MM = 30.0  # low-frequency shading (curvature, fat) scale
SHADING_AMPLITUDE = 0.05
ALBEDO_LAYERS_MM = (
    (6.0, 0.025),
    (2.5, 0.015),
    (1.2, 0.008),
)  # smooth skin's diffuse albedo: (sigma mm, relative amplitude)
DEPTH_BLUR_PX = 7.0  # extra Gaussian blur (px at 8 px/mm) of the deepest vessels: scattering above them
TEXTURED_CONTRAST = (0.15, 0.35)  # the textured variant's vessel darkening (the original simulator's)
BAND_LIMIT_SIGMA_PX = 0.9  # final blur: nothing finer than this, so linear remapping does not alias
MAX_GAP_MM = 10.0  # no point of the world is farther than this from a vessel centreline
STEP_MM = 1.0  # centreline step
END_FADE_MM = 10.0  # a vessel's free end fades out over this length (vessels dive, they do not stop)
CURVINESS = 0.015  # centrelines' random turning (rad per mm, before smoothing)
PHOTO_BACKGROUND_SIGMA_PX = 25.0  # a photograph's local background: much wider than its vessels (photo pixels)
PHOTO_FLOOR = 0.15  # darkness below this share of the photo's darkest vessels is its background's mottle, not vessel
PHOTO_DEEP_BLUR_MM = 0.4  # the photograph's vessels seen through skin: scattered by this much (Gaussian sigma)


@dataclass(frozen=True)
class World:
    """The undeformed skin surface as an image: world pixel = (world mm - origin_mm) * px_per_mm."""

    image: np.ndarray  # float32 (H, W), reflectance 0..1
    px_per_mm: float
    origin_mm: tuple[float, float]

    def mm_to_px(self, xy_mm: np.ndarray) -> np.ndarray:
        """Return world pixel coordinates (..., 2) of world positions (..., 2) in mm."""
        xy = np.asarray(xy_mm, dtype=np.float64)
        return (xy - np.asarray(self.origin_mm)) * self.px_per_mm

    @property
    def extent_mm(self) -> tuple[float, float, float, float]:
        """Return (x_min, y_min, x_max, y_max) of the world in mm."""
        h, w = self.image.shape
        x0, y0 = self.origin_mm
        return x0, y0, x0 + w / self.px_per_mm, y0 + h / self.px_per_mm


@dataclass(frozen=True)
class Vessel:
    """A vessel: centreline (M, 2) world mm, width (M,) mm, contrast (peak fractional darkening before the
    depth blur) and depth (0 = just under the skin .. 1 = the deepest visible)."""

    points_mm: np.ndarray
    width_mm: np.ndarray
    contrast: float
    depth: float = 0.0
    fade: np.ndarray | None = None  # (M,) in 0..1: the contrast along the centreline (None = 1 everywhere)


def band_noise(rng: np.random.Generator, shape: tuple[int, int], sigma_px: float) -> np.ndarray:
    """Return zero-mean, unit-std Gaussian-filtered white noise (float32, shape) with blur sigma_px."""
    h, w = shape
    factor = max(1, int(sigma_px / 2.0))
    sh, sw = h // factor + 3, w // factor + 3
    small = rng.standard_normal((sh, sw), dtype=np.float32)
    small = cv2.GaussianBlur(small, (0, 0), sigma_px / factor, borderType=cv2.BORDER_REFLECT)
    full = small if factor == 1 else cv2.resize(small, (sw * factor, sh * factor), interpolation=cv2.INTER_CUBIC)
    full = full[:h, :w]
    return ((full - full.mean()) / max(float(full.std()), 1e-12)).astype(np.float32)


def skin_texture(rng: np.random.Generator, shape: tuple[int, int], px_per_mm: float) -> np.ndarray:
    """Return textured skin reflectance (float32, shape, 0..1): shading plus fine multi-scale grain (easy variant)."""
    skin = np.full(shape, SKIN_LEVEL, dtype=np.float32)
    skin += SHADING_AMPLITUDE * band_noise(rng, shape, SHADING_SIGMA_MM * px_per_mm)
    for sigma, amplitude in SKIN_LAYERS:
        skin += amplitude * band_noise(rng, shape, sigma)
    return skin


def smooth_skin(rng: np.random.Generator, shape: tuple[int, int], px_per_mm: float) -> np.ndarray:
    """Return diffuse skin reflectance (float32, shape, 0..1): SKIN_LEVEL times low-frequency shading and albedo."""
    relative = SHADING_AMPLITUDE * band_noise(rng, shape, SHADING_SIGMA_MM * px_per_mm)
    for sigma_mm, amplitude in ALBEDO_LAYERS_MM:
        relative += amplitude * band_noise(rng, shape, sigma_mm * px_per_mm)
    return (SKIN_LEVEL * (1.0 + relative)).astype(np.float32)


def depth_contrast(depth: float, contrast_range: tuple[float, float]) -> float:
    """Return a vessel's peak darkening (fraction): the range's top just under the skin, its bottom deepest."""
    lo, hi = contrast_range
    return float(hi - (hi - lo) * depth)


def centreline(
    rng: np.random.Generator,
    start_mm: np.ndarray,
    heading_rad: float,
    length_mm: float,
    bounds_mm: tuple[float, float, float, float],
    curviness: float = CURVINESS,
) -> np.ndarray:
    """Return a smooth random-walk centreline (M, 2) mm from start_mm, stopping at length or the bounds."""
    n = max(2, int(length_mm / STEP_MM))
    turn = gaussian_filter1d(rng.standard_normal(n), 6.0, mode="reflect") * curviness * 6.0
    heading = heading_rad + np.cumsum(turn)
    steps = STEP_MM * np.stack([np.cos(heading), np.sin(heading)], axis=1)
    pts = np.vstack([start_mm, start_mm + np.cumsum(steps, axis=0)])
    x0, y0, x1, y1 = bounds_mm
    inside = (pts[:, 0] >= x0) & (pts[:, 0] <= x1) & (pts[:, 1] >= y0) & (pts[:, 1] <= y1)
    stop = int(np.argmin(inside)) if not inside.all() else len(pts)
    return pts[: max(stop, 2)]


def _tapered(n: int, w_start: float, w_end: float) -> np.ndarray:
    return np.linspace(w_start, w_end, n)


def end_fade(n: int, fade_start: bool, fade_end: bool) -> np.ndarray:
    """Return a contrast profile (n,) in 0..1 along a centreline of n points STEP_MM apart, ramping over
    END_FADE_MM at the ends asked for."""
    s = np.arange(n, dtype=np.float64) * STEP_MM
    fade = np.ones(n)
    if fade_start:
        fade = np.minimum(fade, s / END_FADE_MM)
    if fade_end:
        fade = np.minimum(fade, (s[-1] - s) / END_FADE_MM)
    return np.clip(fade, 0.0, 1.0)


def vein_network(
    rng: np.random.Generator,
    bounds_mm: tuple[float, float, float, float],
    contrast_range: tuple[float, float] = (0.03, 0.35),
) -> list[Vessel]:
    """Return the vessels of a branching network covering bounds_mm: trunks, branches and gap fillers.

    Trunks lie shallow, branches and gap fillers at any depth; each vessel's contrast follows its depth
    within contrast_range (fractional darkening, lo = deepest, hi = shallowest).
    """
    x0, y0, x1, y1 = bounds_mm
    area = (x1 - x0) * (y1 - y0)
    diag = float(np.hypot(x1 - x0, y1 - y0))
    # grow beyond the world a little so vessels run off its edges instead of ending inside
    grow = (x0 - 20.0, y0 - 20.0, x1 + 20.0, y1 + 20.0)
    vessels: list[Vessel] = []
    n_trunks = max(3, round(area / 7000.0))
    for _ in range(n_trunks):
        start = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
        h = rng.uniform(0, 2 * np.pi)
        fwd = centreline(rng, start, h, diag, grow)
        back = centreline(rng, start, h + np.pi, diag, grow)
        pts = np.vstack([back[::-1], fwd[1:]])
        w = rng.uniform(1.6, 2.5)
        width = w * (1.0 + 0.15 * np.sin(np.linspace(0, rng.uniform(2, 6), len(pts)) + rng.uniform(0, 6)))
        depth = rng.uniform(0.0, 0.35)
        vessels.append(Vessel(pts, width, depth_contrast(depth, contrast_range), depth))
    # branches off existing vessels, then branches of branches
    for _ in range(n_trunks * 6):
        parent = vessels[int(rng.integers(len(vessels)))]
        if len(parent.points_mm) < 12:
            continue
        i = int(rng.integers(5, len(parent.points_mm) - 5))
        d = parent.points_mm[i + 1] - parent.points_mm[i - 1]
        h = np.arctan2(d[1], d[0]) + rng.choice([-1, 1]) * np.deg2rad(rng.uniform(25, 65))
        pts = centreline(rng, parent.points_mm[i], h, rng.uniform(15, 70), grow)
        w0 = max(0.6, parent.width_mm[i] * rng.uniform(0.45, 0.8))
        width = _tapered(len(pts), w0, max(0.6, 0.7 * w0))
        depth = max(parent.depth, rng.uniform(0.1, 1.0))
        fade = end_fade(len(pts), False, True)
        vessels.append(Vessel(pts, width, depth_contrast(depth, contrast_range), depth, fade))
    # gap fillers: short free vessels wherever the network leaves a hole
    for _ in range(400):
        gap_mm, where = _largest_gap(vessels, bounds_mm)
        if gap_mm <= MAX_GAP_MM:
            break
        h = rng.uniform(0, 2 * np.pi)
        half = rng.uniform(25, 60)
        fwd = centreline(rng, where, h, half, grow)
        back = centreline(rng, where, h + np.pi, half, grow)
        pts = np.vstack([back[::-1], fwd[1:]])
        w0 = rng.uniform(0.7, 1.6)
        depth = rng.uniform(0.2, 1.0)
        width = _tapered(len(pts), w0, max(0.6, 0.75 * w0))
        fade = end_fade(len(pts), True, True)
        vessels.append(Vessel(pts, width, depth_contrast(depth, contrast_range), depth, fade))
    return vessels


def _largest_gap(vessels: list[Vessel], bounds_mm: tuple[float, float, float, float]) -> tuple[float, np.ndarray]:
    """Return (distance mm, position mm) of the point of bounds_mm farthest from every centreline."""
    x0, y0, x1, y1 = bounds_mm
    w, h = int(np.ceil(x1 - x0)) + 1, int(np.ceil(y1 - y0)) + 1
    occ = np.full((h, w), 255, np.uint8)
    for v in vessels:
        pts = np.round(v.points_mm - (x0, y0)).astype(np.int32)
        cv2.polylines(occ, [pts.reshape(-1, 1, 2)], False, 0, 1)
    dist = cv2.distanceTransform(occ, cv2.DIST_L2, 5)
    iy, ix = np.unravel_index(int(np.argmax(dist)), dist.shape)
    return float(dist[iy, ix]), np.array([x0 + ix, y0 + iy], dtype=np.float64)


def vein_darkness(
    vessels: list[Vessel], shape: tuple[int, int], origin_mm: tuple[float, float], px_per_mm: float
) -> np.ndarray:
    """Return the vessels' fractional darkening (float32, shape, 0..1): soft profiles blurred by depth,
    combined as transmissions (1 - prod(1 - d_i)) where they cross."""
    h, w = shape
    transmission = np.ones(shape, np.float32)
    shift = 4  # cv2 sub-pixel drawing: coordinates in 1/16 px
    for v in vessels:
        px = (v.points_mm - np.asarray(origin_mm)) * px_per_mm
        wpx = v.width_mm * px_per_mm
        sigma = max(BAND_LIMIT_SIGMA_PX, 0.22 * float(wpx.mean())) + DEPTH_BLUR_PX * v.depth * px_per_mm / 8.0
        pad = int(wpx.max() + 4 * sigma + 3)
        bx0, by0 = int(np.floor(px[:, 0].min())) - pad, int(np.floor(px[:, 1].min())) - pad
        bx1, by1 = int(np.ceil(px[:, 0].max())) + pad, int(np.ceil(px[:, 1].max())) + pad
        cx0, cy0, cx1, cy1 = max(bx0, 0), max(by0, 0), min(bx1, w), min(by1, h)
        if cx0 >= cx1 or cy0 >= cy1:
            continue
        canvas = np.zeros((by1 - by0, bx1 - bx0), np.uint8)
        fixed = np.round((px - (bx0, by0)) * (1 << shift)).astype(np.int64)
        fade = np.ones(len(fixed)) if v.fade is None else v.fade
        for i in range(len(fixed) - 1):
            thickness = max(1, round(0.5 * (wpx[i] + wpx[i + 1])))
            level = round(255 * 0.5 * (fade[i] + fade[i + 1]))
            if level == 0:
                continue
            p, q = (int(fixed[i, 0]), int(fixed[i, 1])), (int(fixed[i + 1, 0]), int(fixed[i + 1, 1]))
            cv2.line(canvas, p, q, level, thickness, cv2.LINE_AA, shift)
        layer = cv2.GaussianBlur(canvas.astype(np.float32) * (v.contrast / 255.0), (0, 0), sigma)
        sub = layer[cy0 - by0 : cy1 - by0, cx0 - bx0 : cx1 - bx0]
        transmission[cy0:cy1, cx0:cx1] *= 1.0 - sub
    return 1.0 - transmission


def make_world(
    rng: np.random.Generator,
    bounds_mm: tuple[float, float, float, float],
    px_per_mm: float = 8.0,
    vessel_contrast: tuple[float, float] = (0.03, 0.35),
    textured_skin: bool = False,
) -> World:
    """Return a World (reflectance 0..1) covering bounds_mm (x_min, y_min, x_max, y_max in mm) at px_per_mm.

    vessel_contrast: the vessels' fractional darkening range (deepest, shallowest); textured_skin: the easy
    fine-grain skin instead of smooth diffuse skin.
    """
    x0, y0, x1, y1 = bounds_mm
    w = int(np.ceil((x1 - x0) * px_per_mm))
    h = int(np.ceil((y1 - y0) * px_per_mm))
    skin = skin_texture(rng, (h, w), px_per_mm) if textured_skin else smooth_skin(rng, (h, w), px_per_mm)
    vessels = vein_network(rng, (x0, y0, x0 + w / px_per_mm, y0 + h / px_per_mm), vessel_contrast)
    dark = vein_darkness(vessels, (h, w), (x0, y0), px_per_mm)
    image = cv2.GaussianBlur(skin * (1.0 - dark), (0, 0), BAND_LIMIT_SIGMA_PX)
    return World(np.clip(image, 0.02, 0.98).astype(np.float32), px_per_mm, (float(x0), float(y0)))


def photo_vessel_darkness(photo: np.ndarray) -> np.ndarray:
    """Return the vessels of a photograph (float32 0..1, the photo's shape): dark lines on a brighter ground.

    photo: grayscale (H, W) or BGR (H, W, 3; its green channel, where a fundus's vessels stand out), 8 or 16 bit.
    Darkness is 1 - I / background (a masked Gaussian mean of PHOTO_BACKGROUND_SIGMA_PX over the photo's lit
    region), scaled so the photo's 99.5th percentile is 1; what stays below PHOTO_FLOOR is set to 0 (the ground's
    mottle), and the unlit border of a fundus photograph carries no vessel.
    """
    g = np.asarray(photo)
    if g.ndim == 3:
        g = g[..., 1]
    if g.ndim != 2 or g.dtype not in (np.uint8, np.uint16):
        raise ValueError("a texture photograph must be an 8- or 16-bit grayscale or colour image")
    g = g.astype(np.float32) / float(np.iinfo(g.dtype).max)
    lit = (cv2.GaussianBlur(g, (0, 0), 5.0) > 0.08).astype(np.float32)
    lit = cv2.erode(lit, np.ones((41, 41), np.uint8))  # the lit region's rim is its vignetting, not vessel
    if not np.any(lit):
        raise ValueError("the texture photograph is dark everywhere")
    ground = cv2.GaussianBlur(g * lit, (0, 0), PHOTO_BACKGROUND_SIGMA_PX)
    ground /= np.maximum(cv2.GaussianBlur(lit, (0, 0), PHOTO_BACKGROUND_SIGMA_PX), 1e-3)
    dark = cv2.GaussianBlur(np.clip(1.0 - g / np.maximum(ground, 1e-3), 0.0, None) * lit, (0, 0), 1.0)
    top = float(np.percentile(dark[lit > 0], 99.5))
    if top <= 0.0:
        raise ValueError("the texture photograph shows no dark vessels")
    dark = np.clip(dark / top, 0.0, 1.0)
    dark[dark < PHOTO_FLOOR] = 0.0
    return dark.astype(np.float32)


def make_photo_world(
    rng: np.random.Generator,
    bounds_mm: tuple[float, float, float, float],
    photo: np.ndarray,
    photo_mm_per_px: float,
    px_per_mm: float = 8.0,
    vessel_contrast: tuple[float, float] = (0.03, 0.35),
) -> World:
    """Return a World covering bounds_mm whose veins are a photograph's vessels (photo_vessel_darkness).

    The photo is scaled to photo_mm_per_px, mirror-tiled until it covers the world and cropped at a random
    offset; its vessels darken smooth skin by up to the top of vessel_contrast (a vessel half as dark in the photo
    by half as much: its faint ones fainter than that), seen through PHOTO_DEEP_BLUR_MM of scattering.
    """
    x0, y0, x1, y1 = bounds_mm
    w = int(np.ceil((x1 - x0) * px_per_mm))
    h = int(np.ceil((y1 - y0) * px_per_mm))
    scale = photo_mm_per_px * px_per_mm
    dark = cv2.resize(photo_vessel_darkness(photo), None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)
    while dark.shape[0] < h + 1 or dark.shape[1] < w + 1:
        dark = np.block([[dark, dark[:, ::-1]], [dark[::-1], dark[::-1, ::-1]]])
    oy = int(rng.integers(0, dark.shape[0] - h))
    ox = int(rng.integers(0, dark.shape[1] - w))
    dark = cv2.GaussianBlur(dark[oy : oy + h, ox : ox + w], (0, 0), PHOTO_DEEP_BLUR_MM * px_per_mm)
    skin = smooth_skin(rng, (h, w), px_per_mm)
    image = cv2.GaussianBlur(skin * (1.0 - np.float32(vessel_contrast[1]) * dark), (0, 0), BAND_LIMIT_SIGMA_PX)
    return World(np.clip(image, 0.02, 0.98).astype(np.float32), px_per_mm, (float(x0), float(y0)))
