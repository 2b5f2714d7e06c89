"""A live session's canvas: its newest frames pasted from remembered planes (exactly the canvas without them), and
frames a refinement moved re-pasted a few at a time, within LIVE_REPASTE_PX of their poses once settled."""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pytest

from services.core import session_reconstruction
from services.core.inputs.calibration import Calibration
from services.core.methods import MethodOptions, method_options
from services.core.pipeline import frame_forces, prepared_frames, window_radius_mm, window_setup
from services.core.registration.frame_prep import PreparedFrame
from services.core.session_reconstruction import RECENT_LAYERS, SessionReconstruction
from tests.sim_cache import simulated

FRAMES = 80  # a raster's first row and the turn into the second: refinements move recent and older frames


@dataclass
class LiveRun:
    """The raster's first FRAMES frames added to a live SessionReconstruction once (remembered planes, pixels
    kept), with what each add did; both tests below read it (the registration is the slow part)."""

    calib: Calibration
    options: MethodOptions
    radius_mm: float
    frames: list[PreparedFrame]
    live: SessionReconstruction  # after the last add (the second test settles and finishes it)
    tiles: dict[tuple[int, int], np.ndarray]  # the canvas right after the last add
    recent: int  # len(live.recent) right after the last add
    moved_recent: int  # moved frames among the last RECENT_LAYERS (pasted from remembered planes)
    moved_old: int  # moved frames older than that (decoded from what was kept)
    most_recent: int  # the largest len(live.recent) after any add
    most_repainted: int  # the most frames waiting before an add that it re-pasted
    deferred: int  # the most frames waiting to be re-pasted after an add


@pytest.fixture(scope="module")
def live_run() -> LiveRun:
    """Return the raster's first FRAMES frames registered live once (the simulated raster made once per run)."""
    scan = simulated("raster", 1)
    options = method_options("best")
    calib = scan.calibration
    mask, flat = window_setup(scan, options)
    prepared = prepared_frames(scan, frame_forces(scan), mask, flat, options)
    frames = list(itertools.takewhile(lambda pf: pf.index < FRAMES, prepared))  # the rest is never prepared
    radius_mm = window_radius_mm(mask, calib)
    live = SessionReconstruction(calib, options, radius_mm, live=True)
    moved_recent = moved_old = most_recent = most_repainted = deferred = 0
    for pf in frames:
        waiting = set(live.stale)
        result, _ = live.add(pf)
        moved_recent += sum(1 for i in result.moved if i > pf.index - RECENT_LAYERS)
        moved_old += sum(1 for i in result.moved if i <= pf.index - RECENT_LAYERS)
        most_recent = max(most_recent, len(live.recent))
        most_repainted = max(most_repainted, len(waiting - set(live.stale)))
        deferred = max(deferred, len(live.stale))
    tiles = {key: tile.copy() for key, tile in live.canvas.tiles.items()}
    return LiveRun(
        calib, options, radius_mm, frames, live, tiles, len(live.recent), moved_recent, moved_old, most_recent,
        most_repainted, deferred,
    )  # fmt: skip


def test_remembered_planes_give_the_same_canvas_bit_for_bit(live_run: LiveRun, monkeypatch: pytest.MonkeyPatch) -> None:
    by_index = {pf.index: pf for pf in live_run.frames}
    read_back: list[int] = []

    def pixels(index: int) -> tuple[np.ndarray, np.ndarray]:  # as a live worker reads its prepared files
        read_back.append(index)
        return by_index[index].image, by_index[index].mask

    def run(source: Callable[[int], tuple[np.ndarray, np.ndarray]] | None = None) -> SessionReconstruction:
        live = SessionReconstruction(live_run.calib, live_run.options, live_run.radius_mm, live=True, pixels=source)
        for pf in live_run.frames:
            live.add(pf)
            assert len(live.recent) <= session_reconstruction.RECENT_LAYERS
        return live

    assert live_run.moved_recent > 0 and live_run.moved_old > 0  # both paths taken: remembered planes, kept frames
    assert live_run.most_recent <= RECENT_LAYERS
    assert live_run.recent == RECENT_LAYERS
    monkeypatch.setattr(session_reconstruction, "RECENT_LAYERS", 0)  # every paste decodes what was kept
    decoded = run()
    assert not decoded.recent
    assert set(live_run.tiles) == set(decoded.canvas.tiles)
    for key, tile in live_run.tiles.items():
        assert np.array_equal(tile, decoded.canvas.tiles[key]), key  # lossless kept images: the same sums
    # pixels read back from elsewhere (a live worker's prepared files): none kept in memory, the same canvas
    elsewhere = run(pixels)
    assert read_back and all(not k.has_pixels for k in elsewhere.frames.values())
    assert sum(k.pasteable for k in elsewhere.frames.values()) == sum(k.pasteable for k in decoded.frames.values())
    assert set(elsewhere.canvas.tiles) == set(decoded.canvas.tiles)
    for key, tile in elsewhere.canvas.tiles.items():
        assert np.array_equal(tile, decoded.canvas.tiles[key]), key


def test_moved_frames_are_repainted_a_few_at_a_time_and_settle_within_the_tolerance(live_run: LiveRun) -> None:
    live = live_run.live
    # at most REPAINT_PER_FRAME of the frames waiting are re-pasted per registered frame
    assert live_run.most_repainted <= session_reconstruction.REPAINT_PER_FRAME
    assert live_run.deferred > 0  # a refinement moved older frames than a frame's paste can carry at once
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
