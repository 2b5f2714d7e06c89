"""A texture photograph read from disk for the simulator's photo worlds (vein_texture.make_photo_world)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np


def read_texture_photo(path: str | Path) -> np.ndarray:
    """Return a photograph as stored (8/16-bit grayscale or BGR); ValueError naming the path if none can be read."""
    photo = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if photo is None:
        raise ValueError(f"--texture: cannot read an image from {path}")
    return photo
