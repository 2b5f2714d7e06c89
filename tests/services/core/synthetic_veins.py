"""Synthetic NIR vein frames built in memory, for the vein-map, feature and direct-alignment tests, and a
synthetic vessel photograph for the simulator's photo worlds.

Skin is smooth (a low-frequency shading), the veins are soft dark curves a few per cent to ~30 % darker than
the skin around them, the housing outside the window is dark, and there is a little sensor noise: the
features of a real frame that matter for registration, at the probe's 8 px/mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from services.core.similarity import Similarity

H, W = 480, 640  # the probe's frame size (pixels)
PX_PER_MM = 8.0
CENTRE_PX = ((W - 1) / 2.0, (H - 1) / 2.0)  # the principal point used with these frames
WINDOW_RADIUS_PX = 200  # the circular window (25 mm radius at 8 px/mm)
SKIN_DN = 150.0  # mean skin grey level
HOUSING_DN = 15.0  # the dark housing outside the window
NOISE_DN = 2.0  # sensor noise, standard deviation
VESSEL_BLUR_PX = 2.0  # soft vessel edges


@dataclass(frozen=True)
class Vessel:
    """One vessel: a smooth polyline (canvas pixels), its width (pixels) and darkness (0..1 of the skin)."""

    points: np.ndarray  # (N, 2) int32
    width_px: int
    contrast: float


def window_mask(shape: tuple[int, int] = (H, W), radius_px: int = WINDOW_RADIUS_PX) -> np.ndarray:
    """Return the probe's circular window (uint8 0/255) centred in the frame."""
    mask = np.zeros(shape, np.uint8)
    cv2.circle(mask, (shape[1] // 2, shape[0] // 2), radius_px, 255, -1)
    return mask


def random_vessels(
    rng: np.random.Generator, shape: tuple[int, int], count: int, contrast: tuple[float, float]
) -> list[Vessel]:
    """Return `count` smooth, gently curving vessels crossing a canvas of `shape` (H, W)."""
    h, w = shape
    vessels = []
    for _ in range(count):
        p = np.array([rng.uniform(0, w), rng.uniform(0, h)])
        heading = rng.uniform(0, 2 * np.pi)
        turn = rng.normal(0.0, 0.04)
        pts = []
        for _ in range(int(1.5 * max(h, w) / 10)):  # 10 px steps, long enough to cross the canvas
            pts.append(p.copy())
            turn = 0.9 * turn + rng.normal(0.0, 0.03)
            heading += turn
            p = p + 10.0 * np.array([np.cos(heading), np.sin(heading)])
        vessels.append(
            Vessel(np.round(np.array(pts)).astype(np.int32), int(rng.integers(8, 17)), float(rng.uniform(*contrast)))
        )
    return vessels


def vessel_darkness(shape: tuple[int, int], vessels: list[Vessel]) -> np.ndarray:
    """Return the fractional darkening (float32, 0 on skin, up to each vessel's contrast on its axis)."""
    dark = np.zeros(shape, np.float32)
    for v in vessels:
        one = np.zeros(shape, np.float32)
        cv2.polylines(one, [v.points.reshape(-1, 1, 2)], False, 1.0, v.width_px, cv2.LINE_AA)
        one = cv2.GaussianBlur(one, (0, 0), VESSEL_BLUR_PX)
        np.maximum(dark, v.contrast * one, out=dark)
    return dark


def shading(shape: tuple[int, int], strength: float = 0.25, phase: float = 0.0) -> np.ndarray:
    """Return a smooth multiplicative shading (float32, mean ~1, +-strength over the frame)."""
    h, w = shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    u, v = xs / w, ys / h
    s = 1.0 + strength * (0.6 * np.sin(2.1 * u + 0.7 * v + phase) + 0.4 * np.cos(1.3 * v - 0.9 * u + 2 * phase))
    return s.astype(np.float32)


def skin_field(shape: tuple[int, int], vessels: list[Vessel], seed: int, shading_strength: float = 0.15) -> np.ndarray:
    """Return a noiseless canvas of skin (float32 DN) with smooth shading, darkened by the vessels."""
    return SKIN_DN * shading(shape, shading_strength, phase=seed) * (1.0 - vessel_darkness(shape, vessels))


def observe(field: np.ndarray, mask: np.ndarray, seed: int, noise_dn: float = NOISE_DN) -> np.ndarray:
    """Return an 8-bit frame: the field plus sensor noise inside the window, the dark housing outside."""
    rng = np.random.default_rng(seed)
    img = field + rng.normal(0.0, noise_dn, field.shape).astype(np.float32)
    img = np.where(mask > 0, img, HOUSING_DN + rng.normal(0.0, noise_dn, field.shape))
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def frame(
    seed: int, count: int = 6, contrast: tuple[float, float] = (0.05, 0.3), mask: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (8-bit frame, window mask, vessel darkness) of a seeded random vein pattern."""
    rng = np.random.default_rng(seed)
    mask = window_mask() if mask is None else mask
    vessels = random_vessels(rng, (H, W), count, contrast)
    field = skin_field((H, W), vessels, seed)
    return observe(field, mask, seed + 1000), mask, vessel_darkness((H, W), vessels)


def similarity_px(transform: Similarity, centre_px: tuple[float, float], px_per_mm: float) -> np.ndarray:
    """Return the 2x3 pixel matrix of a mm similarity (moving -> fixed), direct_alignment._to_px's convention:
    p_px = centre + px_per_mm * p_mm, so q_fixed = a q_moving + (c + k t - a c)."""
    c = complex(*centre_px)
    a, t = transform.a, c + px_per_mm * transform.t - transform.a * c
    return np.array([[a.real, -a.imag, t.real], [a.imag, a.real, t.imag]], np.float64)


def frame_pair(
    transform: Similarity, seed: int, count: int = 10, contrast: tuple[float, float] = (0.08, 0.3)
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (fixed frame, moving frame, window mask): two views of one vein field, moving -> fixed = transform.

    The field is drawn on a canvas with a margin around the fixed frame so the moving one, seen through the
    same window elsewhere on the skin, is covered by vessels too.
    """
    margin = 240  # canvas pixels around the fixed frame: shifts up to ~25 mm stay on the canvas
    rng = np.random.default_rng(seed)
    shape = (H + 2 * margin, W + 2 * margin)
    vessels = random_vessels(rng, shape, count, contrast)
    field = skin_field(shape, vessels, seed)
    mask = window_mask()
    fixed = field[margin : margin + H, margin : margin + W]
    to_canvas = similarity_px(transform, CENTRE_PX, PX_PER_MM)  # moving px -> fixed px
    to_canvas[:, 2] += margin  # ... -> canvas px
    moving = cv2.warpAffine(field, to_canvas, (W, H), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    return observe(fixed, mask, seed + 1000), observe(moving, mask, seed + 2000), mask


def vessel_photo(seed: int = 4, size: int = 600) -> tuple[np.ndarray, np.ndarray]:
    """Return a photograph (uint8) of 30 dark straight vessels (3-9 px, 30-60 % darker) on shaded ground, and
    the vessels' darkness as drawn (float32 0..1)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size]
    ground = 170 + 20 * np.sin(xx / 97.0) * np.cos(yy / 131.0)  # slow shading, as a fundus's illumination
    lines = np.zeros((size, size), np.float32)
    for _ in range(30):
        p = rng.uniform(0, size, 2)
        a, length = rng.uniform(0, np.pi), rng.uniform(100, 400)
        q = p + length * np.array([np.cos(a), np.sin(a)])
        layer = np.zeros_like(lines)
        start, end = (int(p[0]), int(p[1])), (int(q[0]), int(q[1]))
        cv2.line(layer, start, end, float(rng.uniform(0.3, 0.6)), int(rng.integers(3, 10)), cv2.LINE_AA)
        lines = np.maximum(lines, layer)
    return np.clip(ground * (1 - cv2.GaussianBlur(lines, (0, 0), 1.5)), 0, 255).astype(np.uint8), lines
