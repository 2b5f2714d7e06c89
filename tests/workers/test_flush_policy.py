"""When a flush happens and when it writes the whole mosaic images, and when a session counts as behind its uploads
(workers/stages/register/flush.py: flush_every_s, images_due, images_every_s, is_behind, tracking_due)."""

from __future__ import annotations

import pytest

from workers.stages.register.flush import (
    IMAGES_COST_FACTOR,
    flush_every_s,
    images_due,
    images_every_s,
    is_behind,
    tracking_due,
)


@pytest.mark.parametrize(
    ("final", "written", "caught_up", "since_s", "units_changed", "due"),
    [
        (True, True, False, 0.0, False, True),  # the final flush writes everything, behind or not
        (False, False, False, 0.0, False, True),  # the first flush gives the session its images
        (False, True, True, 2.5, False, True),  # caught up and image_every_s has passed
        (False, True, True, 1.5, False, False),  # caught up, too soon
        (False, True, False, 60.0, False, False),  # behind: the CPU goes to placing frames, however long
        (False, True, True, 0.1, True, True),  # a run ahead changed the canvas's units: mosaic.json is theirs
    ],
)
def test_whole_images_wait_until_the_session_has_caught_up(
    final: bool, written: bool, caught_up: bool, since_s: float, units_changed: bool, due: bool
) -> None:
    assert images_due(final, written, caught_up, since_s, every_s=2.0, units_changed=units_changed) is due


@pytest.mark.parametrize(
    ("last_s", "every"),
    [
        (0.0, 2.0),  # none written yet: image_every_s
        (0.05, 2.0),  # a raster's images, quick: image_every_s
        (0.4, 0.4 * IMAGES_COST_FACTOR),  # a long examination's: they wait ten times as long as they took
    ],
)
def test_whole_images_that_take_long_are_written_less_often(last_s: float, every: float) -> None:
    assert IMAGES_COST_FACTOR * 0.4 > 2.0  # the last case is the cost rule's, not image_every_s's
    assert images_every_s(2.0, last_s) == pytest.approx(every)


@pytest.mark.parametrize(
    ("caught_up", "lags_s", "held_s", "every"),
    [
        (True, [9.0, 8.0], 60.0, 0.5),  # caught up: the usual cadence, however late the frames it just placed
        (False, [1.2, 0.8], 60.0, 0.5),  # a frame or two waiting for preparation, as one probe often has: not behind
        (False, [9.0, 6.0], 60.0, 2.0),  # even its newest frame waited over behind_lag_s: behind, flush less often
        (False, [9.0, 4.0], 60.0, 0.5),  # the newest one is within behind_lag_s: catching up
        (False, [], 60.0, 0.5),  # nothing published (or a reprocessed version, whose lags are not recorded)
        # held 3 s: its first frames waited for the window set-up (frame 23) or an earlier holder, not for this worker
        (False, [9.0, 6.0], 3.0, 0.5),
    ],
)
def test_a_session_far_behind_its_uploads_is_flushed_less_often(
    caught_up: bool, lags_s: list[float], held_s: float, every: float
) -> None:
    behind = is_behind(caught_up, lags_s, 5.0, held_s)
    assert flush_every_s(behind, every_s=0.5, behind_every_s=2.0) == every
    # the same rule says when its frames are placed without re-pasting the frames a refinement moved (cursor)
    assert behind is (every == 2.0)


@pytest.mark.parametrize(
    ("caught_up", "lags_s", "track_lag_s", "held_s", "due"),
    [
        (False, [3.0, 2.0], 1.5, 20.0, True),  # even its newest frame waited over track_lag_s: its next frames tracked
        (False, [3.0, 1.0], 1.5, 20.0, False),  # the newest is within it: catching up, described again
        (True, [9.0, 8.0], 1.5, 20.0, False),  # caught up: every frame described, however late the ones just placed
        (False, [9.0, 8.0], 0.0, 20.0, False),  # 0: never (the tests that compare a live path with the offline one)
        # taken 0.6 s ago: its first frames waited for the window set-up (frame 23), not for this worker
        (False, [3.1, 3.0], 1.5, 0.6, False),
    ],
)
def test_a_session_behind_its_uploads_has_its_next_frames_prepared_to_be_tracked(
    caught_up: bool, lags_s: list[float], track_lag_s: float, held_s: float, due: bool
) -> None:
    assert tracking_due(caught_up, lags_s, track_lag_s, held_s) is due
