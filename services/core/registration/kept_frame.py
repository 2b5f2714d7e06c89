"""What a session keeps of each frame once it is registered: enough to stitch it again and to write its path row.

A minutes-long examination registers thousands of frames and refinement may move any of them, so each placed
frame must stay pasteable until the end; what it keeps is made compact (issue 15: memory bounded by what is
needed, not a full PreparedFrame per frame). A live session reads a placed frame's pixels back from its prepared
file and keeps none (keep_pixels=False); otherwise the rectified image is kept as it is while the session's
budget of uncompressed pixels lasts (compress=False: no encoding now, no decoding at the stitch), and losslessly
as PNG beyond it (2.4x smaller on the shared scans' kind of frame, ~2.5 ms to encode and ~2 ms to decode at
640x480); the window mask is bit-packed (8x); frames that will never be pasted (lost, rejected, blurred, not
stitched) keep no image at all. Decoding gives back exactly the arrays kept, so the mosaic is the same either way.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from services.core.physics.force_model import LoadState
from services.core.registration.frame_prep import PreparedFrame

# PNG of the kept images: every row "Up"-filtered and Huffman-coded only. Rectified NIR frames are smooth, so the
# row differences are small numbers that Huffman codes well without LZ77's search: on a simulated raster frame
# (640 x 480) 2.9 ms to encode and 2.1 to decode for 112 kB, against 7.1 / 3.7 ms and 130 kB for zlib level 1
# with adaptive filters (what this was before); levels 6 and higher cost 5-10x the time for 1-3 % less memory.
PNG_PARAMS = (
    cv2.IMWRITE_PNG_COMPRESSION, 1,
    cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY,
    cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_UP,
)  # fmt: skip


@dataclass(frozen=True)
class KeptFrame:
    """A registered frame's row data (seq, time, load, forces, stretch) and, if pasteable, its image and mask."""

    index: int
    seq: int
    t_s: float
    forces_n: np.ndarray  # (4,) N
    load: LoadState
    stretch: float
    shape: tuple[int, int]  # (H, W) of the rectified image
    pasteable: bool = False  # placed and sharp: it is stitched into the mosaic
    image_png: bytes | None = None  # the rectified 8-bit image, PNG; None when not pasted or not kept here
    mask_bits: np.ndarray | None = None  # np.packbits of mask > 0
    image_raw: np.ndarray | None = None  # the rectified 8-bit image itself (read-only), kept instead of image_png

    @property
    def has_pixels(self) -> bool:
        """Return True when the frame's image and mask are kept here (else they are read back from elsewhere)."""
        return (self.image_png is not None or self.image_raw is not None) and self.mask_bits is not None

    @property
    def raw_bytes(self) -> int:
        """Return the bytes of image kept uncompressed (0 when kept as PNG or not kept)."""
        return 0 if self.image_raw is None else self.image_raw.nbytes

    def image(self) -> np.ndarray:
        """Return the rectified image (H, W) uint8 exactly as it was kept (read-only when kept uncompressed)."""
        if self.image_raw is not None:
            return self.image_raw
        if self.image_png is None:
            raise ValueError(f"frame {self.index} kept no image (it is not pasted, or its pixels are elsewhere)")
        return cv2.imdecode(np.frombuffer(self.image_png, np.uint8), cv2.IMREAD_UNCHANGED)

    def mask(self) -> np.ndarray:
        """Return the window mask (H, W) uint8 0/255."""
        if self.mask_bits is None:
            raise ValueError(f"frame {self.index} kept no mask (it is not pasted, or its pixels are elsewhere)")
        h, w = self.shape
        return (np.unpackbits(self.mask_bits, count=h * w).reshape(h, w) * np.uint8(255)).astype(np.uint8)


def keep_frame(pf: PreparedFrame, pasteable: bool, keep_pixels: bool = True, compress: bool = True) -> KeptFrame:
    """Return what a session keeps of a prepared frame (its image and mask only when pasted and keep_pixels; the
    image as PNG when compress, else as a read-only view of the array)."""
    image_png = mask_bits = image_raw = None
    if pasteable and keep_pixels:
        if compress:
            ok, buf = cv2.imencode(".png", pf.image, PNG_PARAMS)
            if not ok:
                raise ValueError(f"frame {pf.index}: the rectified image could not be kept")
            image_png = buf.tobytes()
        else:
            image_raw = np.ascontiguousarray(pf.image).view()  # as it is (uint8), never cast
            image_raw.flags.writeable = False
        mask_bits = np.packbits(pf.mask > 0)
    return KeptFrame(
        pf.index,
        pf.seq,
        pf.t_s,
        pf.forces_n,
        pf.load,
        pf.stretch,
        pf.image.shape[:2],
        pasteable,
        image_png,
        mask_bits,
        image_raw,
    )
