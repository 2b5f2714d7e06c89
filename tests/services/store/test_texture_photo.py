"""A texture photograph is read as stored, and a path that holds no image is a clear error."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from services.store.texture_photo import read_texture_photo

SIXTEEN_BIT_GREY = np.arange(64 * 48, dtype=np.uint16).reshape(48, 64)
EIGHT_BIT_COLOUR = np.full((48, 64, 3), 7, np.uint8)


@pytest.mark.parametrize("photo", [SIXTEEN_BIT_GREY, EIGHT_BIT_COLOUR])
def test_a_photo_is_read_as_stored(tmp_path: Path, photo: np.ndarray) -> None:
    cv2.imwrite(str(tmp_path / "photo.png"), photo)
    np.testing.assert_array_equal(read_texture_photo(tmp_path / "photo.png"), photo)  # depth and channels kept


def test_a_path_without_an_image_names_it(tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("not an image")
    for path in (tmp_path / "missing.png", tmp_path / "notes.txt"):
        with pytest.raises(ValueError, match=f"cannot read an image from {path}"):
            read_texture_photo(path)
