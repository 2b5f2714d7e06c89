"""The image decoders' process-wide pixel caps (decompression bombs), set once by each process's shell.

OpenCV reads its cap (OPENCV_IO_MAX_IMAGE_PIXELS) when it loads, so services/__init__.py sets it; Pillow's
(Image.MAX_IMAGE_PIXELS) is a module global, set here from the frame size cap by the API and the workers at start.
"""

from __future__ import annotations

from PIL import Image


def set_decoder_limits(max_frame_side: int) -> None:
    """Cap Pillow's decodes at a max_frame_side square (pixels)."""
    Image.MAX_IMAGE_PIXELS = int(max_frame_side) ** 2
