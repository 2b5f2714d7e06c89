"""What a session keeps of a registered frame: its pixels exactly, as PNG or uncompressed (read-only), or none."""

from __future__ import annotations

import numpy as np
import pytest

from services.core.methods import method_options
from services.core.pipeline import frame_forces, prepared_frames, window_setup
from services.core.registration.frame_prep import PreparedFrame
from services.core.registration.kept_frame import keep_frame
from tests.sim_cache import simulated


@pytest.fixture(scope="module")
def prepared() -> PreparedFrame:
    """Return the simulated raster's first frame, prepared as `best` prepares it."""
    scan = simulated("raster", 1)
    options = method_options("best")
    mask, flat = window_setup(scan, options)
    return next(iter(prepared_frames(scan, frame_forces(scan), mask, flat, options)))


@pytest.mark.parametrize("compress", [True, False])
def test_a_kept_frame_gives_back_its_image_and_mask_exactly(prepared: PreparedFrame, compress: bool) -> None:
    kept = keep_frame(prepared, pasteable=True, compress=compress)
    assert kept.has_pixels
    np.testing.assert_array_equal(kept.image(), prepared.image)
    np.testing.assert_array_equal(kept.mask() > 0, prepared.mask > 0)
    assert (kept.image_png is None) == (not compress)
    assert kept.raw_bytes == (0 if compress else prepared.image.nbytes)


def test_an_uncompressed_image_cannot_be_changed_through_what_was_kept(prepared: PreparedFrame) -> None:
    image = keep_frame(prepared, pasteable=True, compress=False).image()
    with pytest.raises(ValueError, match="read-only"):
        image[0, 0] = 1


@pytest.mark.parametrize(("pasteable", "keep_pixels"), [(False, True), (True, False)])
def test_a_frame_not_pasted_here_keeps_no_pixels(prepared: PreparedFrame, pasteable: bool, keep_pixels: bool) -> None:
    kept = keep_frame(prepared, pasteable=pasteable, keep_pixels=keep_pixels, compress=False)
    assert not kept.has_pixels and kept.raw_bytes == 0
    with pytest.raises(ValueError, match="kept no image"):
        kept.image()
