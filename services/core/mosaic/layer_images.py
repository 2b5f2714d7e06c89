"""The coverage layer as an image, and the raw mosaic layers (force in N, coverage) as compact bytes.

Coverage = how many frames saw each mosaic point. Its colour scale here (VIRIDIS over 1..COVERAGE_FULL_SCALE
frames, transparent where no frame saw the point) is the viewer layer's and its legend's; the maps a person
reads (coverage_map.png, the one-page report) scale to the scan's 95th percentile instead
(services.core.outputs.plots.coverage_scale), as a fixed 10 frames is one flat colour on a normal scan.
The raw layers travel as an .npz of uint16 planes: force in centinewtons (0 where uncovered, flagged by
coverage 0) and coverage counts, so the DICOM export and the report can be rebuilt with real units.
"""

from __future__ import annotations

import io

import cv2
import numpy as np

from services.core.mosaic.canvas import MosaicImage, force_to_color
from services.core.npz import npz_bytes

COVERAGE_FULL_SCALE = 10  # frames: the top of the colour scale (more saturates)
FORCE_QUANTUM_N = 0.01  # the force plane's resolution in the raw layers (1 cN)
_MAX_U16 = 65535
# deflate level of layers.npz, written at a live session's end: numpy's 6 took twice the time for a quarter less
# (the clinical scan's 2015 x 2170 mosaic: 282 against 141 ms, 1.96 against 2.64 MB)
LAYERS_COMPRESS_LEVEL = 3


def coverage_to_color(coverage: np.ndarray, full_scale: int = COVERAGE_FULL_SCALE) -> np.ndarray:
    """Return a BGRA uint8 image of the coverage (VIRIDIS over 1..full_scale frames, alpha 0 where none)."""
    cov = np.nan_to_num(np.asarray(coverage, np.float32))
    seen = cov >= 0.5
    level = cov - np.float32(1.0)  # then / (full_scale - 1), clipped to 0..1, x 255, rounded: in place
    level /= np.float32(max(full_scale - 1, 1))
    np.clip(level, 0.0, 1.0, out=level)
    level *= np.float32(255.0)
    bgr = cv2.applyColorMap(np.rint(level, out=level).astype(np.uint8), cv2.COLORMAP_VIRIDIS)
    alpha = seen.view(np.uint8) * np.uint8(255)
    bgra = cv2.merge([*cv2.split(bgr), alpha])
    bgra[~seen] = 0
    return bgra


def layers_to_bytes(mosaic: MosaicImage) -> bytes:
    """Return the mosaic's force (cN) and coverage planes and geometry as .npz bytes (LAYERS_COMPRESS_LEVEL)."""
    cov = np.clip(np.rint(np.nan_to_num(mosaic.coverage)), 0, _MAX_U16).astype(np.uint16)
    covered = cov > 0
    force_cn = np.zeros(cov.shape, np.uint16)  # 0 where uncovered: only the covered pixels are converted
    force = np.nan_to_num(np.asarray(mosaic.force_n[covered], np.float64), nan=0.0) / FORCE_QUANTUM_N
    force_cn[covered] = np.clip(np.rint(force), 0, _MAX_U16)
    return npz_bytes(
        compress_level=LAYERS_COMPRESS_LEVEL,
        force_cn=force_cn,
        coverage=cov,
        px_per_mm=np.float64(mosaic.px_per_mm),
        origin_px=np.asarray(mosaic.origin_px, np.float64),
    )


def layers_from_bytes(data: bytes, vein: np.ndarray) -> MosaicImage:
    """Return a MosaicImage from layers_to_bytes output and the 8-bit vein mosaic of the same size."""
    with np.load(io.BytesIO(data)) as z:
        cov = z["coverage"].astype(np.float32)
        force = np.where(cov > 0, z["force_cn"].astype(np.float32) * FORCE_QUANTUM_N, np.nan).astype(np.float32)
        px_per_mm = float(z["px_per_mm"])
        origin = (float(z["origin_px"][0]), float(z["origin_px"][1]))
    if vein.shape != cov.shape:
        raise ValueError(f"layers: vein mosaic {vein.shape} and layers {cov.shape} differ in size")
    return MosaicImage(vein, force, cov, px_per_mm, origin)


def _png(image: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise ValueError("PNG encoding failed")
    return buf.tobytes()


def mosaic_image_files(mosaic: MosaicImage, raw_layers: bool = True) -> dict[str, bytes]:
    """Return the whole-mosaic files by name: mosaic.png (8-bit veins), force.png (TURBO over 0..30 N),
    coverage.png (VIRIDIS, transparent where never scanned) and, with raw_layers, layers.npz (layers_to_bytes).

    The one set the service's results versions and the offline output folder both write.
    """
    files = {
        "mosaic.png": _png(mosaic.vein),
        "force.png": _png(force_to_color(mosaic.force_n)),
        "coverage.png": _png(coverage_to_color(mosaic.coverage)),
    }
    if raw_layers:
        files["layers.npz"] = layers_to_bytes(mosaic)
    return files
