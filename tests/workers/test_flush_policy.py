"""When a flush writes the whole mosaic images (workers/stages/register/flush.py: images_due)."""

from __future__ import annotations

import pytest

from workers.stages.register.flush import images_due


@pytest.mark.parametrize(
    ("final", "written", "caught_up", "since_s", "due"),
    [
        (True, True, False, 0.0, True),  # the final flush writes everything, behind or not
        (False, False, False, 0.0, True),  # the first flush gives the session its images
        (False, True, True, 2.5, True),  # caught up and image_every_s has passed
        (False, True, True, 1.5, False),  # caught up, too soon
        (False, True, False, 60.0, False),  # behind: the CPU goes to placing frames, however long
    ],
)
def test_whole_images_wait_until_the_session_has_caught_up(
    final: bool, written: bool, caught_up: bool, since_s: float, due: bool
) -> None:
    assert images_due(final, written, caught_up, since_s, every_s=2.0) is due
