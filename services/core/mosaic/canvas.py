"""The mosaic canvas: sparse tiles of weighted sums (vein intensity, force, coverage) in frame 0's axes.

Each tile holds four float32 planes: sum(w I), sum(w), sum(w F), sum(mask). Pasting is linear, so a frame
whose pose changes is moved exactly by pasting it again with weight -1 at the old pose and +1 at the new.
Memory follows the area scanned: only touched tiles exist.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from services.core.mosaic.canvas_units import IDENTITY, CanvasUnits
from services.core.similarity import Similarity

TILE_PX = 256
PLANES = 4  # weighted intensity, weight, weighted force, coverage
FORCE_FULL_SCALE_N = 30.0


@dataclass(frozen=True)
class FrameLayers:
    """What one rectified frame contributes, as the (H, W, 4) float32 planes it adds to the canvas tiles.

    planes: w I, w, w F, coverage (w > 0), with intensity I 0..1, blend weight w and local load F in N; built
    once per frame (`of`) and reused for every paste of it.
    """

    planes: np.ndarray
    centre_px: tuple[float, float]
    px_per_mm: float

    @classmethod
    def of(
        cls,
        intensity: np.ndarray,
        weight: np.ndarray,
        force_n: np.ndarray,
        centre_px: tuple[float, float],
        px_per_mm: float,
    ) -> FrameLayers:
        """Return the layers of a frame from its intensity (0..1 floats, or uint8 grey levels read as /255), blend
        weight and local load (N), all (H, W). Other integer intensities (e.g. 16-bit) are refused: read as 0..1
        they would paste nearly white.

        Each plane is made whole and the four interleaved once (cv2.merge): writing them into the interleaved
        array one strided plane at a time cost 1.5x the time.
        """
        w = np.ascontiguousarray(weight, np.float32)
        grey = np.asarray(intensity)
        if grey.dtype != np.uint8 and not np.issubdtype(grey.dtype, np.floating):
            raise ValueError(f"intensity must be uint8 grey levels or 0..1 floats, not {grey.dtype}")
        scale = 1.0 / 255.0 if grey.dtype == np.uint8 else 1.0
        weighted = cv2.multiply(grey, w, scale=scale, dtype=cv2.CV_32F)
        loaded = cv2.multiply(np.asarray(force_n, np.float32), w)
        planes = cv2.merge([weighted, w, loaded, (w > 0).astype(np.float32)])
        return cls(planes, centre_px, px_per_mm)

    @property
    def shape(self) -> tuple[int, int]:
        """Return the frame's (H, W) in pixels."""
        return self.planes.shape[:2]


@dataclass(frozen=True)
class MosaicImage:
    """A rendered mosaic: vein image (uint8), force (N, float32, NaN uncovered), coverage, and geometry."""

    vein: np.ndarray
    force_n: np.ndarray
    coverage: np.ndarray
    px_per_mm: float
    origin_px: tuple[float, float]

    def meta(self) -> dict[str, object]:
        """Return mosaic.json (spec §4): px_per_mm, origin_px (frame 0's centre), width, height."""
        h, w = self.vein.shape
        return {
            "px_per_mm": self.px_per_mm,
            "origin_px": [float(self.origin_px[0]), float(self.origin_px[1])],
            "width": int(w),
            "height": int(h),
            "force_full_scale_n": FORCE_FULL_SCALE_N,
        }


def blend_weight(mask: np.ndarray, ramp_px: float = 40.0, centre_sigma_frac: float = 0.45) -> np.ndarray:
    """Return the blend weight (H, W) float32: a smooth ramp from the window edge times a centre preference.

    The ramp removes seams; the centre preference makes each mosaic pixel come mostly from the frames that
    saw it nearest their centre (least rectification error), which keeps vessels sharp without ghosting.
    """
    inside = mask > 0
    h, w = mask.shape
    # the distance to the window's edge at half resolution, doubled and brought back (a 40 px ramp is smooth at
    # that scale; 4x faster than at full resolution), at least one pixel inside the window and zero outside
    half = cv2.resize(inside.astype(np.uint8), (max(1, w // 2), max(1, h // 2)), interpolation=cv2.INTER_NEAREST)
    dist = cv2.resize(cv2.distanceTransform(half, cv2.DIST_L2, 5), (w, h), interpolation=cv2.INTER_LINEAR)
    dist *= np.float32(2.0 / ramp_px)
    np.clip(dist, np.float32(1.0 / ramp_px), np.float32(1.0), out=dist)
    weight = np.multiply(dist, inside, out=dist)  # zero outside: in place (np.where's new array cost 2x)
    weight *= weight
    sigma = centre_sigma_frac * min(h, w)
    # the Gaussian centre preference is separable: two 1-D profiles instead of a full grid
    gx = np.exp(-((np.arange(w, dtype=np.float32) - w / 2) ** 2) / (2 * sigma**2)).astype(np.float32)
    gy = np.exp(-((np.arange(h, dtype=np.float32) - h / 2) ** 2) / (2 * sigma**2)).astype(np.float32)
    weight *= gy[:, None]
    weight *= gx[None, :]
    return weight


@dataclass(frozen=True)
class Warped:
    """A frame's planes warped onto the canvas: the patch whose pixel (0, 0) is canvas pixel (x0, y0), and the
    tiles it adds weight to."""

    patch: np.ndarray
    x0: int
    y0: int
    keys: list[tuple[int, int]]

    def part(self, key: tuple[int, int]) -> tuple[np.ndarray, tuple[int, int, int, int]] | None:
        """Return the patch's part over tile `key` and its canvas box (x0, y0, x1, y1), or None when it has none."""
        h, w = self.patch.shape[:2]
        tx, ty = key[0] * TILE_PX, key[1] * TILE_PX
        ax, ay = max(self.x0, tx), max(self.y0, ty)
        bx, by = min(self.x0 + w, tx + TILE_PX), min(self.y0 + h, ty + TILE_PX)
        if bx <= ax or by <= ay:
            return None
        return self.patch[ay - self.y0 : by - self.y0, ax - self.x0 : bx - self.x0], (ax, ay, bx, by)


@dataclass
class SparseCanvas:
    """A mosaic canvas in mm of frame 0 at px_per_mm, stored as sparse TILE_PX tiles keyed by (col, row).

    Frames are pasted in the canvas's millimetres; `units` maps the path's onto them (canvas_units: the identity
    offline), and the rendered mosaic's px_per_mm and origin_px carry it.
    """

    px_per_mm: float
    tiles: dict[tuple[int, int], np.ndarray] = field(default_factory=dict)
    units: CanvasUnits = IDENTITY

    def frame_to_canvas(self, pose: Similarity | np.ndarray, layers: FrameLayers) -> np.ndarray:
        """Return the 2x3 affine from frame pixels to canvas pixels (canvas (0, 0) = frame 0's centre).

        pose: frame mm (about its centre) -> mosaic mm, a similarity or a 2x3 affine.
        """
        return self.pixels_to_canvas(pose, layers.centre_px, layers.px_per_mm)

    def pixels_to_canvas(
        self, pose: Similarity | np.ndarray, centre_px: tuple[float, float], frame_px_per_mm: float
    ) -> np.ndarray:
        """Return the 2x3 affine from the pixels of a frame (centre and scale given) to canvas pixels."""
        m = pose.matrix() if isinstance(pose, Similarity) else np.asarray(pose, np.float64)
        k = self.px_per_mm / frame_px_per_mm
        cx, cy = centre_px
        # canvas = px_per_mm * (L (u - c) / frame px_per_mm + t)
        linear = m[:, :2] * k
        offset = m[:, 2] * self.px_per_mm - linear @ np.array([cx, cy])
        return np.hstack([linear, offset[:, None]])

    def footprint_tiles(self, affine: np.ndarray, shape: tuple[int, int]) -> list[tuple[int, int]]:
        """Return the tile keys a frame of shape (H, W) covers under the frame->canvas affine."""
        h, w = shape
        corners = np.array([[0, 0, 1], [w, 0, 1], [0, h, 1], [w, h, 1]], float) @ affine.T
        c0, r0 = np.floor(corners.min(axis=0) / TILE_PX).astype(int)
        c1, r1 = np.floor(corners.max(axis=0) / TILE_PX).astype(int)
        return [(c, r) for r in range(r0, r1 + 1) for c in range(c0, c1 + 1)]

    def paste(
        self,
        layers: FrameLayers,
        pose: Similarity | np.ndarray,
        sign: float = 1.0,
        only: set[tuple[int, int]] | None = None,
    ) -> list[tuple[int, int]]:
        """Return the tile keys touched by adding (sign=+1) or removing (sign=-1) a frame at a pose (`warp`, `add`).

        only: the tiles it may touch (None: all); a tile's part is the same whichever others are pasted.
        """
        warped = self.warp(layers, pose, only)
        return [] if warped is None else self.add(warped, sign)

    def warp(
        self, layers: FrameLayers, pose: Similarity | np.ndarray, only: set[tuple[int, int]] | None = None
    ) -> Warped | None:
        """Return a frame's planes warped onto the canvas at a pose, with the tiles it adds weight to (within
        `only`, None: any), or None when it adds to none. Reads no tile, so it may run on another thread.

        The frame is warped once, into its bounding box on the canvas, and each tile adds its part: warping
        whole tiles one by one cost 2.5x the pixels (a frame spans up to 4 x 3 tiles) and 2x the time.
        """
        affine = self.frame_to_canvas(pose, layers)
        keys = self.footprint_tiles(affine, layers.shape)
        if only is not None:
            keys = [key for key in keys if key in only]
            if not keys:
                return None
        h, w = layers.shape
        corners = np.array([[0, 0, 1], [w, 0, 1], [0, h, 1], [w, h, 1]], float) @ affine.T
        x0, y0 = (int(v) for v in np.floor(corners.min(axis=0)))
        x1, y1 = (int(v) + 1 for v in np.ceil(corners.max(axis=0)))
        shift = affine.copy()
        shift[:, 2] -= (x0, y0)
        patch = cv2.warpAffine(
            layers.planes, shift, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
        )
        warped = Warped(patch, x0, y0, [])
        for key in keys:
            part = warped.part(key)
            # no weight here (weights are >= 0; OpenCV's sum is 3x np.any's speed)
            if part is not None and cv2.sumElems(part[0])[1] > 0.0:
                warped.keys.append(key)
        return warped if warped.keys else None

    def add(self, warped: Warped, sign: float = 1.0) -> list[tuple[int, int]]:
        """Return the tile keys touched by adding (sign=+1) or removing (sign=-1) a warped frame (`warp`)."""
        touched = []
        for key in warped.keys:
            got = warped.part(key)
            assert got is not None  # warp keeps only the tiles its patch reaches
            part, (ax, ay, bx, by) = got
            tx, ty = key[0] * TILE_PX, key[1] * TILE_PX
            tile = self.tiles.get(key)
            if tile is None:
                if sign < 0:
                    continue
                tile = np.zeros((TILE_PX, TILE_PX, PLANES), np.float32)
                self.tiles[key] = tile
            region = tile[ay - ty : by - ty, ax - tx : bx - tx]
            summed = (cv2.add if sign > 0 else cv2.subtract)(region, part, dst=region)  # in place: 2x numpy's speed
            if summed is not region:  # a binding that would not write into the view: copy the result in
                region[...] = summed
            touched.append(key)
        return touched

    @classmethod
    def from_mosaic(cls, mosaic: MosaicImage) -> SparseCanvas:
        """Return a canvas holding a rendered mosaic (unit weight per covered pixel): the inverse of render() at
        identity units (its pixel grid kept: canvas pixel 0 is the mosaic's origin_px, rounded)."""
        canvas = cls(mosaic.px_per_mm)
        h, w = mosaic.vein.shape
        ox, oy = (round(v) for v in mosaic.origin_px)  # the canvas pixel 0 is mosaic pixel origin_px
        covered = np.isfinite(mosaic.force_n) & (mosaic.coverage > 0)
        planes = np.zeros((h, w, PLANES), np.float32)
        planes[..., 0] = np.where(covered, mosaic.vein / 255.0, 0)
        planes[..., 1] = covered
        planes[..., 2] = np.where(covered, np.nan_to_num(mosaic.force_n), 0)
        planes[..., 3] = np.where(covered, mosaic.coverage, 0)
        c0, r0 = (-ox) // TILE_PX, (-oy) // TILE_PX
        c1, r1 = (w - 1 - ox) // TILE_PX, (h - 1 - oy) // TILE_PX
        for r in range(r0, r1 + 1):
            for c in range(c0, c1 + 1):
                x0, y0 = c * TILE_PX + ox, r * TILE_PX + oy  # tile origin in mosaic pixels
                tile = np.zeros((TILE_PX, TILE_PX, PLANES), np.float32)
                sx0, sy0 = max(0, x0), max(0, y0)
                sx1, sy1 = min(w, x0 + TILE_PX), min(h, y0 + TILE_PX)
                if sx1 <= sx0 or sy1 <= sy0:
                    continue
                tile[sy0 - y0 : sy1 - y0, sx0 - x0 : sx1 - x0] = planes[sy0:sy1, sx0:sx1]
                if np.any(tile[..., 1] > 0):
                    canvas.tiles[(c, r)] = tile
        return canvas

    def extent_tiles(self) -> tuple[int, int, int, int] | None:
        """Return (col0, row0, col1, row1) inclusive of the tiles present, or None when empty."""
        if not self.tiles:
            return None
        keys = np.array(list(self.tiles))
        return int(keys[:, 0].min()), int(keys[:, 1].min()), int(keys[:, 0].max()), int(keys[:, 1].max())

    def covered_box(self, min_weight: float = 1e-3) -> tuple[int, int, int, int] | None:
        """Return the canvas pixel box (x0, y0, x1, y1; ends exclusive) of the pixels with more blend weight than
        min_weight, or None when there are none (found tile by tile: no whole-canvas array)."""
        lo, hi = [math.inf, math.inf], [-math.inf, -math.inf]
        for (c, r), tile in self.tiles.items():
            covered = tile[..., 1] > min_weight
            rows = np.flatnonzero(covered.any(axis=1))
            if rows.size == 0:
                continue
            cols = np.flatnonzero(covered.any(axis=0))
            x0, y0 = c * TILE_PX, r * TILE_PX
            lo = [min(lo[0], x0 + cols[0]), min(lo[1], y0 + rows[0])]
            hi = [max(hi[0], x0 + cols[-1] + 1), max(hi[1], y0 + rows[-1] + 1)]
        if lo[0] == math.inf:
            return None
        return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])

    def render(self, min_weight: float = 1e-3) -> MosaicImage:
        """Return the whole mosaic cropped to covered pixels, with frame 0's rest centre (the path's origin) at
        origin_px and px_per_mm per path mm (both through `units`).

        Only the covered box is assembled, and each layer computed in place (a 2816 x 2048 px mosaic took 1.3 s in
        whole-canvas temporaries on a busy machine).
        """
        box = self.covered_box(min_weight)
        path_px_per_mm = self.units.path_px_per_mm(self.px_per_mm)
        ox, oy = self.units.origin_px(self.px_per_mm)  # the path's origin on the canvas (0, 0 at identity units)
        if box is None:
            z = np.zeros((1, 1), np.float32)
            return MosaicImage(z.astype(np.uint8), z * np.nan, z, path_px_per_mm, (ox, oy))
        x0, y0, x1, y1 = box
        big = np.zeros((y1 - y0, x1 - x0, PLANES), np.float32)
        for (c, r), tile in self.tiles.items():
            tx, ty = c * TILE_PX, r * TILE_PX
            ax, ay, bx, by = max(x0, tx), max(y0, ty), min(x1, tx + TILE_PX), min(y1, ty + TILE_PX)
            if bx > ax and by > ay:
                big[ay - y0 : by - y0, ax - x0 : bx - x0] = tile[ay - ty : by - ty, ax - tx : bx - tx]
        covered = big[..., 1] > min_weight
        uncovered = ~covered
        den = np.where(covered, big[..., 1], np.float32(1.0))
        vein = big[..., 0] / den  # then clip to 0..1, x 255, + 0.5, truncated: as the tiles' PNGs
        np.clip(vein, 0, 1, out=vein)
        vein *= np.float32(255.0)
        vein += np.float32(0.5)
        vein[uncovered] = 0
        force = big[..., 2] / den
        force[uncovered] = np.nan
        coverage = big[..., 3].copy()
        coverage[uncovered] = 0
        return MosaicImage(vein.astype(np.uint8), force, coverage, path_px_per_mm, (float(ox - x0), float(oy - y0)))


def force_to_color(force_n: np.ndarray, full_scale_n: float = FORCE_FULL_SCALE_N) -> np.ndarray:
    """Return a BGR uint8 image of the force layer (TURBO colour map over 0..full_scale N, black uncovered)."""
    valid = np.isfinite(force_n)
    level = np.nan_to_num(np.asarray(force_n, np.float32))  # then / full scale, clipped to 0..1, x 255: in place
    level /= np.float32(full_scale_n)
    np.clip(level, 0, 1, out=level)
    level *= np.float32(255.0)
    color = cv2.applyColorMap(level.astype(np.uint8), cv2.COLORMAP_TURBO)
    color[~valid] = 0
    return color
