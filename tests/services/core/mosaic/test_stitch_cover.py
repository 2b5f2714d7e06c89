"""Which placed frames are stitched (services/core/mosaic/stitch_cover.py): a frame is left out once the skin its
window covers is covered `cap` times by stitched frames, and stitched while it brings new skin."""

from __future__ import annotations

import math

import numpy as np

from services.core.mosaic.stitch_cover import CELL_MM, MAX_CELLS, NEW_SKIN_SHARE, StitchCover


def test_a_frame_over_skin_shown_cap_times_is_left_out_and_counts_nothing() -> None:
    cover = StitchCover(cap=3, radius_mm=30.0)
    assert [cover.admit((10.0, -4.0)) for _ in range(5)] == [True, True, True, False, False]
    assert int(cover.counts.max()) == 3  # the two left out counted nothing
    disc_cells = np.count_nonzero(cover.counts)
    assert abs(disc_cells * CELL_MM**2 - np.pi * 30.0**2) < 0.05 * np.pi * 30.0**2  # the window's disc, to 5 %


def test_a_frame_that_brings_new_skin_is_stitched_and_a_step_too_small_is_not() -> None:
    cover = StitchCover(cap=1, radius_mm=30.0)
    assert cover.admit((0.0, 0.0))
    # a disc of 30 mm moved by d uncovers about 2 r d / (pi r^2) of itself: 5 % at d = 2.4 mm
    assert not cover.admit((0.9, 0.0))  # about 2 % new skin (on 2 mm cells: below NEW_SKIN_SHARE)
    assert cover.admit((6.0, 0.0))  # about 13 % new skin
    assert NEW_SKIN_SHARE == 0.05


def test_cap_zero_stitches_every_frame_and_keeps_no_grid() -> None:
    cover = StitchCover(cap=0, radius_mm=30.0)
    assert all(cover.admit((0.0, 0.0)) for _ in range(50))
    assert cover.counts.size == 0


def test_the_grid_grows_every_way_and_keeps_its_counts() -> None:
    cover = StitchCover(cap=2, radius_mm=10.0)
    assert cover.admit((0.0, 0.0))
    for far in ((-500.0, 0.0), (0.0, 400.0), (300.0, -300.0)):  # each beyond the grid: it grows, and keeps the first
        assert cover.admit(far)
        assert cover.admit((0.0, 0.0)) is (far == (-500.0, 0.0))  # the second at the origin, then none
    one = StitchCover(cap=2, radius_mm=10.0)
    one.admit((0.0, 0.0))
    assert int(cover.counts.sum()) == 5 * int(one.counts.sum())  # five frames stitched: two at the origin, three far
    assert int(cover.counts.max()) == 2


def test_a_frame_placed_absurdly_far_or_nowhere_is_stitched_and_grows_nothing() -> None:
    cover = StitchCover(cap=1, radius_mm=30.0)
    assert cover.admit((0.0, 0.0))
    shape = cover.counts.shape
    far = (CELL_MM * MAX_CELLS * 4, 0.0)  # a pose many metres off (a wrong placement): no grid that large
    assert cover.admit(far) and cover.admit(far)  # stitched each time: nothing counted there
    assert cover.admit((math.nan, 0.0)) and cover.admit((0.0, math.inf))
    assert cover.counts.shape == shape
    assert not cover.admit((0.0, 0.0))  # the grid still counts the skin it held
