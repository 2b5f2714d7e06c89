"""Deep Zoom tiles of a growing mosaic: a fixed square DZI canvas centred on frame 0 and a pooled pyramid.

The DZI canvas is fixed in advance (half_extent_mm around frame 0), so a tile's address never changes while
the mosaic grows; its half size is a multiple of 256 px, so the mosaic canvas's tiles (services.core.mosaic.canvas,
canvas (0, 0) = frame 0's centre) are exactly the DZI tiles of the full-resolution level, shifted by
half / 256. Each level keeps the four weighted-sum planes of services.core.mosaic.canvas ([sum w I, sum w, sum w F,
coverage]); a parent is the 2x2 sum-pool of its children, so every level's intensity and force are exact
weighted averages of the full-resolution pixels below them.
"""

from __future__ import annotations

import math
import struct
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import cv2
import numpy as np

from services.core.mosaic.canvas import FORCE_FULL_SCALE_N, PLANES, TILE_PX, SparseCanvas
from services.core.mosaic.canvas_units import IDENTITY, CanvasUnits

TileKey = tuple[int, int, int]  # (level, col, row)
MIN_WEIGHT = 1e-3  # as SparseCanvas.render: a pixel with less blend weight is uncovered
PNG_LEVEL = 1  # zlib level: tiles are written often, read from cache; speed over size
FORCE_INDICES = 255  # colours of a force tile's palette (index 0 is the transparent "uncovered")


@dataclass(frozen=True)
class DziGeometry:
    """The fixed DZI canvas: width = height = 2 * half_px, frame 0's centre at (half_px, half_px)."""

    px_per_mm: float
    half_px: int
    tile_size: int = TILE_PX

    @classmethod
    def for_mosaic(cls, px_per_mm: float, half_extent_mm: float = 200.0) -> DziGeometry:
        """Return the geometry for a mosaic at px_per_mm covering +-half_extent_mm around frame 0."""
        if not (px_per_mm > 0 and half_extent_mm > 0):
            raise ValueError("px_per_mm and half_extent_mm must be positive")
        half = max(1, math.ceil(half_extent_mm * px_per_mm / TILE_PX)) * TILE_PX
        return cls(float(px_per_mm), int(half))

    @classmethod
    def from_dict(cls, dzi: Mapping[str, Any], px_per_mm: float) -> DziGeometry:
        """Return the geometry of a mosaic.json "dzi" block (`to_dict`'s output) at px_per_mm."""
        width, height = int(dzi["width"]), int(dzi["height"])
        geometry = cls(float(px_per_mm), width // 2, int(dzi["tile_size"]))
        if (geometry.width, geometry.height) != (width, height):
            raise ValueError("dzi: width and height must be one even size")
        return geometry

    @property
    def width(self) -> int:
        """Return the full-resolution width (= height) in px."""
        return 2 * self.half_px

    @property
    def height(self) -> int:
        """Return the full-resolution height in px."""
        return 2 * self.half_px

    @property
    def max_level(self) -> int:
        """Return the full-resolution level: ceil(log2(width)) (level 0 is 1x1 px)."""
        return math.ceil(math.log2(self.width))

    @property
    def origin_px(self) -> tuple[int, int]:
        """Return the canvas pixel 0 (frame 0's centre at identity units) in full-resolution DZI pixels."""
        return self.half_px, self.half_px

    @property
    def canvas_offset_tiles(self) -> int:
        """Return how many tiles the canvas's tile (0, 0) is shifted right/down at the max level."""
        return self.half_px // self.tile_size

    def level_size(self, level: int) -> tuple[int, int]:
        """Return (width, height) in px of a level: ceil(size / 2^(max_level - level))."""
        if not 0 <= level <= self.max_level:
            raise ValueError(f"level must be in 0..{self.max_level}")
        scale = 2 ** (self.max_level - level)
        return -(-self.width // scale), -(-self.height // scale)

    def tiles_at(self, level: int) -> tuple[int, int]:
        """Return (cols, rows) of tiles at a level."""
        w, h = self.level_size(level)
        return -(-w // self.tile_size), -(-h // self.tile_size)

    def in_range(self, level: int, col: int, row: int) -> bool:
        """Return True if (level, col, row) is a tile of this DZI."""
        if not 0 <= level <= self.max_level:
            return False
        cols, rows = self.tiles_at(level)
        return 0 <= col < cols and 0 <= row < rows

    def tile_shape(self, level: int, col: int, row: int) -> tuple[int, int]:
        """Return (height, width) of a tile: tile_size, less at the right and bottom edges."""
        w, h = self.level_size(level)
        return min(self.tile_size, h - row * self.tile_size), min(self.tile_size, w - col * self.tile_size)

    def canvas_tile_to_dzi(self, col: int, row: int) -> tuple[int, int]:
        """Return the max-level DZI tile of a canvas tile (col, row)."""
        off = self.canvas_offset_tiles
        return col + off, row + off

    def mm_to_px(self, x_mm: float, y_mm: float) -> tuple[float, float]:
        """Return the full-resolution DZI pixel of a point in frame 0's mm (pixel centres at integers)."""
        return self.half_px + x_mm * self.px_per_mm, self.half_px + y_mm * self.px_per_mm

    def tile_size_px(self, level: int, col: int, row: int) -> tuple[int, int] | None:
        """Return the (width, height) px of tile (level, col, row), or None when it is not a tile of this DZI."""
        if not self.in_range(level, col, row):
            return None
        h, w = self.tile_shape(level, col, row)
        return w, h

    def dzi_xml(self) -> str:
        """Return the .dzi descriptor (Deep Zoom XML, PNG tiles, no overlap)."""
        return (
            '<?xml version="1.0" encoding="UTF-8"?>\n'
            f'<Image TileSize="{self.tile_size}" Overlap="0" Format="png" '
            'xmlns="http://schemas.microsoft.com/deepzoom/2008">'
            f'<Size Width="{self.width}" Height="{self.height}"/></Image>\n'
        )

    def to_dict(self, units: CanvasUnits = IDENTITY) -> dict[str, object]:
        """Return the "dzi" part of mosaic.json: its origin_px is the path's origin (frame 0's rest centre) in
        full-resolution DZI pixels, the canvas pixel 0 (origin_px here) moved by the canvas's units."""
        ox, oy = units.origin_px(self.px_per_mm)
        origin = [self.half_px, self.half_px] if units == IDENTITY else [self.half_px + ox, self.half_px + oy]
        return {
            "width": self.width,
            "height": self.height,
            "tile_size": self.tile_size,
            "max_level": self.max_level,
            "origin_px": origin,
        }


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def _png(raw: np.ndarray, width: int, colour_type: int, extra: bytes = b"") -> bytes:
    """Return PNG bytes of 8-bit rows `raw` (h, bytes per row), each row "Up"-filtered, chunks `extra` before IDAT."""
    h = raw.shape[0]
    up = raw.copy()
    up[1:] = raw[1:] - raw[:-1]  # PNG filter 2 ("Up"), mod 256
    filters = np.full((h, 1), 2, np.uint8)
    filters[0] = 0  # the first row has no row above: filter 0
    up[0] = raw[0]
    body = zlib.compress(np.hstack([filters, up]).tobytes(), PNG_LEVEL)
    header = struct.pack(">IIBBBBB", width, h, 8, colour_type, 0, 0, 0)
    chunks = _png_chunk(b"IHDR", header) + extra + _png_chunk(b"IDAT", body) + _png_chunk(b"IEND", b"")
    return b"\x89PNG\r\n\x1a\n" + chunks


def encode_png_gray_alpha(gray: np.ndarray, alpha: np.ndarray) -> bytes:
    """Return PNG bytes (8-bit gray + alpha, colour type 4); OpenCV cannot write 2-channel PNGs."""
    h, w = gray.shape
    return _png(np.dstack([gray, alpha]).astype(np.uint8).reshape(h, 2 * w), w, 4)


@lru_cache(maxsize=1)
def _force_palette_chunks() -> bytes:
    """Return the PLTE + tRNS chunks of the force tiles: index 0 transparent, 1..255 the TURBO map over 0..full."""
    levels = np.round(np.arange(FORCE_INDICES) * 255.0 / (FORCE_INDICES - 1)).astype(np.uint8)
    rgb = cv2.applyColorMap(levels.reshape(-1, 1), cv2.COLORMAP_TURBO).reshape(-1, 3)[:, ::-1]
    plte = np.vstack([np.zeros((1, 3), np.uint8), rgb]).tobytes()
    trns = bytes([0] + [255] * FORCE_INDICES)
    return _png_chunk(b"PLTE", plte) + _png_chunk(b"tRNS", trns)


def encode_png_force(force_n: np.ndarray, covered: np.ndarray) -> bytes:
    """Return a force tile as an 8-bit palette PNG (colour type 3): TURBO over 0..FORCE_FULL_SCALE_N, clear where
    uncovered. One byte a pixel compresses like the vein tiles (an RGBA tile cost 3x the time to write)."""
    w = force_n.shape[1]
    level = np.clip(np.nan_to_num(force_n) / FORCE_FULL_SCALE_N, 0.0, 1.0) * (FORCE_INDICES - 1) + 1.5
    index = np.where(covered, level, 0).astype(np.uint8)
    return _png(index, w, 3, _force_palette_chunks())


def pool2(planes: np.ndarray) -> np.ndarray:
    """Return the 2x2 sum-pool of (2h, 2w, C) float32 planes as (h, w, C).

    OpenCV's area resampling at exactly half size is the 2x2 mean (times 4: the sum, to float32 rounding): 12x
    faster than four strided numpy slices, and a flush pools every changed tile's ancestors.
    """
    h, w = planes.shape[0] // 2, planes.shape[1] // 2
    pooled = cv2.resize(planes, (w, h), interpolation=cv2.INTER_AREA)
    pooled *= np.float32(4.0)
    return pooled.reshape(h, w, planes.shape[2])


@dataclass
class TilePyramid:
    """Pooled weighted-sum planes of every DZI level, for the tiles that have data."""

    geometry: DziGeometry
    levels: dict[int, dict[tuple[int, int], np.ndarray]] = field(default_factory=dict)

    def planes(self, level: int, col: int, row: int) -> np.ndarray | None:
        """Return the (256, 256, 4) planes of a tile, or None when it has no data."""
        return self.levels.get(level, {}).get((col, row))

    def _set(self, level: int, key: tuple[int, int], planes: np.ndarray | None) -> None:
        tiles = self.levels.setdefault(level, {})
        if planes is None or not np.any(planes[..., 1] > 0):
            tiles.pop(key, None)
        else:
            tiles[key] = planes

    def update(self, canvas: SparseCanvas, touched: set[tuple[int, int]] | list[tuple[int, int]]) -> set[TileKey]:
        """Return every (level, col, row) changed by copying the touched canvas tiles in and recomputing ancestors.

        Canvas tiles outside the DZI canvas are ignored. A touched tile absent from the canvas is cleared.
        """
        g = self.geometry
        top = g.max_level
        changed: set[TileKey] = set()
        current: set[tuple[int, int]] = set()
        for c, r in touched:
            col, row = g.canvas_tile_to_dzi(c, r)
            if not g.in_range(top, col, row):
                continue
            tile = canvas.tiles.get((c, r))
            self._set(top, (col, row), None if tile is None else tile.copy())
            current.add((col, row))
            changed.add((top, col, row))
        for level in range(top - 1, -1, -1):
            parents = {(col // 2, row // 2) for col, row in current}
            children = self.levels.get(level + 1, {})
            half = TILE_PX // 2
            for pc, pr in parents:
                parent = np.zeros((TILE_PX, TILE_PX, PLANES), np.float32)
                any_child = False
                for dy in (0, 1):
                    for dx in (0, 1):
                        child = children.get((2 * pc + dx, 2 * pr + dy))
                        if child is not None:
                            parent[dy * half : (dy + 1) * half, dx * half : (dx + 1) * half] = pool2(child)
                            any_child = True
                self._set(level, (pc, pr), parent if any_child else None)
                changed.add((level, pc, pr))
            current = parents
        return changed

    def render_png(self, level: int, col: int, row: int, layer: str) -> bytes | None:
        """Return a tile as PNG (vein: gray + alpha; force: RGBA colour map + alpha), None when it has no data.

        Edge tiles are cropped to the level's size, as Deep Zoom viewers expect.
        """
        planes = self.planes(level, col, row)
        if planes is None:
            return None
        h, w = self.geometry.tile_shape(level, col, row)
        planes = planes[:h, :w]
        weight = planes[..., 1]
        covered = weight > MIN_WEIGHT
        if not covered.any():
            return None
        den = np.where(covered, weight, 1.0)
        alpha = np.where(covered, 255, 0).astype(np.uint8)
        if layer == "vein":
            gray = np.where(covered, np.clip(planes[..., 0] / den, 0, 1) * 255.0 + 0.5, 0).astype(np.uint8)
            return encode_png_gray_alpha(gray, alpha)
        if layer == "force":
            return encode_png_force(planes[..., 2] / den, covered)
        raise ValueError("layer must be 'vein' or 'force'")

    def blank_png(self) -> bytes:
        """Return a fully transparent tile_size x tile_size PNG."""
        return blank_png(self.geometry.tile_size)


@lru_cache(maxsize=64)
def blank_png(width: int = TILE_PX, height: int | None = None) -> bytes:
    """Return a fully transparent gray + alpha PNG of width x height px (height defaults to width)."""
    z = np.zeros((width if height is None else height, width), np.uint8)
    return encode_png_gray_alpha(z, z)
