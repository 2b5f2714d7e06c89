"""A live session's canvas: its newest frames pasted from remembered planes (exactly the canvas without them), and
frames a refinement moved re-pasted a few at a time, within LIVE_REPASTE_PX of their poses once settled."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from services.core import session_reconstruction
from services.core.methods import method_options
from services.core.pipeline import frame_forces, prepared_frames, window_radius_mm, window_setup
from services.core.session_reconstruction import RECENT_LAYERS, SessionReconstruction
from services.core.simulation.scenarios import simulate

FRAMES = 80  # a raster's first row and the turn into the second: refinements move recent and older frames


def test_remembered_planes_give_the_same_canvas_bit_for_bit(monkeypatch: pytest.MonkeyPatch) -> None:
    scan = simulate("raster", 1)
    options = method_options("best")
    calib = scan.calibration
    mask, flat = window_setup(scan, options)
    frames = [pf for pf in prepared_frames(scan, frame_forces(scan), mask, flat, options) if pf.index < FRAMES]

    by_index = {pf.index: pf for pf in frames}
    read_back: list[int] = []

    def pixels(index: int) -> tuple[np.ndarray, np.ndarray]:  # as a live worker reads its prepared files
        read_back.append(index)
        return by_index[index].image, by_index[index].mask

    def run(
        source: Callable[[int], tuple[np.ndarray, np.ndarray]] | None = None,
    ) -> tuple[SessionReconstruction, int, int]:
        live = SessionReconstruction(calib, options, window_radius_mm(mask, calib), live=True, pixels=source)
        recent = old = 0
        for pf in frames:
            result, _ = live.add(pf)
            recent += sum(1 for i in result.moved if i > pf.index - RECENT_LAYERS)
            old += sum(1 for i in result.moved if i <= pf.index - RECENT_LAYERS)
            assert len(live.recent) <= session_reconstruction.RECENT_LAYERS
        return live, recent, old

    remembered, moved_recent, moved_old = run()
    assert moved_recent > 0 and moved_old > 0  # both paths taken: remembered planes and decoded kept frames
    assert len(remembered.recent) == RECENT_LAYERS
    monkeypatch.setattr(session_reconstruction, "RECENT_LAYERS", 0)  # every paste decodes what was kept
    decoded, _, _ = run()
    assert not decoded.recent
    assert set(remembered.canvas.tiles) == set(decoded.canvas.tiles)
    for key, tile in remembered.canvas.tiles.items():
        assert np.array_equal(tile, decoded.canvas.tiles[key]), key  # lossless kept images: the same sums
    # pixels read back from elsewhere (a live worker's prepared files): none kept in memory, the same canvas
    elsewhere, _, _ = run(pixels)
    assert read_back and all(not k.has_pixels for k in elsewhere.frames.values())
    assert sum(k.pasteable for k in elsewhere.frames.values()) == sum(k.pasteable for k in decoded.frames.values())
    assert set(elsewhere.canvas.tiles) == set(decoded.canvas.tiles)
    for key, tile in elsewhere.canvas.tiles.items():
        assert np.array_equal(tile, decoded.canvas.tiles[key]), key


def test_moved_frames_are_repainted_a_few_at_a_time_and_settle_within_the_tolerance() -> None:
    scan = simulate("raster", 1)
    options = method_options("best")
    calib = scan.calibration
    mask, flat = window_setup(scan, options)
    live = SessionReconstruction(calib, options, window_radius_mm(mask, calib), live=True)
    deferred = 0
    for pf in prepared_frames(scan, frame_forces(scan), mask, flat, options):
        if pf.index >= FRAMES:
            break
        waiting = set(live.stale)
        live.add(pf)
        # at most REPAINT_PER_FRAME of the frames waiting are re-pasted per registered frame
        assert len(waiting - set(live.stale)) <= session_reconstruction.REPAINT_PER_FRAME
        deferred = max(deferred, len(live.stale))
    assert deferred > 0  # a refinement moved older frames than a frame's paste can carry at once
    while live.stale:
        waiting = len(live.stale)
        live.settle(8)
        assert len(live.stale) == max(0, waiting - 8)
    # every pasted frame now lies within LIVE_REPASTE_PX of its current pose (tolerance: the rule itself)
    lagging = [i for i, pasted in live.pasted.items() if not live._unseen_move(pasted, live._stitch_pose(i))]
    assert not lagging
    live.finish()
    assert not live.stale
    # finish pastes every frame at its final pose, exactly
    assert all(np.array_equal(pasted, live._stitch_pose(i)) for i, pasted in live.pasted.items())
