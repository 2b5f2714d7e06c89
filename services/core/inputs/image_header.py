"""Frame image headers read before any decoding, and the decoders' pixel limits (decompression bombs).

A PNG/TIFF/JPEG states its size and pixel format in its header (PNG IHDR, TIFF IFD, JPEG SOF). Pillow
parses that header without decoding the pixels (`Image.open` is lazy), so a small file that claims a huge
image is refused in microseconds and costs no memory. Decoding itself stays with OpenCV (what the pipeline
uses). The decoders' process-wide pixel caps are set by the shells, not here: OpenCV's in services/__init__.py,
Pillow's by services/decoder_limits.py.
"""

from __future__ import annotations

import io
import struct
import warnings
import zlib
from dataclasses import dataclass
from types import MappingProxyType

import cv2
import numpy as np
from PIL import Image

# The probe's camera is 640x480. 2048 px a side (4.2 Mpx) leaves three times that on each axis for another
# sensor, while a decoded 16-bit frame stays at 8 MiB and the worker's float32 working planes (remap maps,
# rectified frame, feature pyramid: about a dozen) stay near 200 MiB, inside the 400 MB per-process budget.
DEFAULT_MAX_FRAME_SIDE = 2048
GRAYSCALE_MODES = frozenset({"1", "L", "I;16", "I;16B", "I;16L", "I;16N"})
FORMATS = MappingProxyType({"PNG": "png", "TIFF": "tif", "JPEG": "jpg"})


class BadImageError(ValueError):
    """A frame whose header is unreadable, or whose size or pixel format is not acceptable (its own content)."""


@dataclass(frozen=True)
class ImageHeader:
    """What an image's header states: format ("png" | "tif" | "jpg"), width, height (px), Pillow mode."""

    format: str
    width: int
    height: int
    mode: str

    @property
    def grayscale(self) -> bool:
        """Return True for a single-channel 1/8/16-bit image."""
        return self.mode in GRAYSCALE_MODES


def read_header(data: bytes) -> ImageHeader:
    """Return the header of a PNG, TIFF or JPEG file without decoding it; BadImageError if unreadable."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            # formats= keeps Pillow from trying its other (less used, more exotic) parsers
            with Image.open(io.BytesIO(data), formats=tuple(FORMATS)) as img:
                width, height = img.size
                return ImageHeader(FORMATS[img.format or ""], int(width), int(height), str(img.mode))
    except Image.DecompressionBombError:
        raise BadImageError("image: larger than the maximum frame size") from None
    except (OSError, ValueError, KeyError, SyntaxError, struct.error):
        raise BadImageError("image: the file is corrupt (unreadable header)") from None


def check_header(header: ImageHeader, max_side: int, expected_size: tuple[int, int] | None = None) -> None:
    """Raise BadImageError unless the header is grayscale, within max_side a side and of expected_size."""
    if header.width > max_side or header.height > max_side:
        raise BadImageError(
            f"image: {header.width}x{header.height} pixels is larger than the maximum frame size "
            f"({max_side} pixels a side)"
        )
    if expected_size is not None and (header.width, header.height) != tuple(expected_size):
        raise BadImageError(
            f"image: expected {expected_size[0]}x{expected_size[1]} pixels (calibration image_size), "
            f"got {header.width}x{header.height}"
        )
    if not header.grayscale:
        raise BadImageError(f"image: expected a single-channel (grayscale) 8- or 16-bit image, got mode {header.mode}")


def sniff_image(data: bytes) -> str | None:
    """Return "png", "tif" or "jpg" from the file's magic bytes, or None for anything else."""
    if data.startswith(b"\x89PNG\r\n\x1a\n"):
        return "png"
    if data[:4] in (b"II*\x00", b"MM\x00*"):
        return "tif"
    if data.startswith(b"\xff\xd8\xff"):
        return "jpg"
    return None


MAX_PNG_CHUNKS = 65_536  # encoders write 8-64 KiB data chunks: a frame under max_frame_bytes has far fewer


def png_complete(data: bytes) -> bool:
    """Return True if a PNG's chunks are all whole with matching CRCs, ending with IEND (no pixels decoded).

    At most MAX_PNG_CHUNKS chunks are walked: a file made of millions of tiny chunks costs no more than that.
    """
    pos, end = 8, len(data)
    view = memoryview(data)
    for _ in range(MAX_PNG_CHUNKS):
        if pos + 12 > end:
            return False
        (length,) = struct.unpack_from(">I", data, pos)
        stop = pos + 12 + length
        if stop > end:
            return False
        if zlib.crc32(view[pos + 4 : stop - 4]) != struct.unpack_from(">I", data, stop - 4)[0]:
            return False
        if view[pos + 4 : pos + 8] == b"IEND":
            return True
        pos = stop
    return False


def check_frame_file(data: bytes, size: tuple[int, int], max_side: int) -> None:
    """Raise BadImageError unless the header states a grayscale `size` (width, height) image and the file is whole.

    The header is read (Pillow, no decoding) first: a file claiming a huge or a colour image costs no memory.
    Then the file's completeness is checked without decoding its pixels (the costly part of an upload): a
    PNG's every chunk CRC and its IEND, a JPEG's end-of-image marker; a TIFF (rare) is decoded, bounded by
    the checked size. A whole file whose compressed pixels are still bad is the frame's own content: the
    worker rejects it (poison, status rejected), never as an infrastructure fault.
    """
    header = read_header(data)
    check_header(header, max_side, size)
    if header.format == "png":
        ok = png_complete(data)
    elif header.format == "jpg":
        ok = data.rstrip(b"\0\r\n").endswith(b"\xff\xd9")
    else:
        try:
            img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        except cv2.error:  # over OpenCV's own pixel limit
            img = None
        ok = img is not None and img.ndim == 2 and img.dtype in (np.uint8, np.uint16)
        ok = ok and (img.shape[1], img.shape[0]) == tuple(size)
    if not ok:
        raise BadImageError("image: the file is corrupt or truncated")
