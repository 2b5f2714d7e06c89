"""A live session's canvas: its newest frames pasted from remembered planes (exactly the canvas without them),
frames a refinement moved re-pasted a few at a time, within LIVE_REPASTE_PX of their poses once settled, and at the
finish only the frames not within FINISH_MOVED_PX of their final places pasted again, the mosaic then within a grey
level of a whole restitch (the offline pipeline's) and the path the same."""

from __future__ import annotations

import copy
import dataclasses
import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import pytest

from services.core import session_reconstruction
from services.core.inputs.calibration import Calibration, default_calibration
from services.core.inputs.scan import Scan
from services.core.methods import MethodOptions, method_options
from services.core.mosaic.canvas import MosaicImage, SparseCanvas
from services.core.mosaic.canvas_units import IDENTITY
from services.core.path_rows import PlacedCounts, path_rows_json
from services.core.pipeline import frame_forces, prepared_frames, window_radius_mm, window_setup
from services.core.registration.frame_prep import PreparedFrame
from services.core.registration.outcome import REASON_MISSING, STATUS_LOST
from services.core.registration.pose_graph import LEVER_MM
from services.core.session_reconstruction import (
    FINISH_MOVED_PX,
    NO_DRAG,
    RECENT_LAYERS,
    Place,
    SessionReconstruction,
)
from services.core.similarity import Similarity
from services.core.simulation.scenarios import simulate
from services.store.scan_folder import read_scan_folder
from tests.shared_scans import SHARED_SCANS
from tests.sim_cache import simulated
from tests.tolerances import TOL

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


def first_prepared(scan: Scan, options: MethodOptions, count: int) -> tuple[list[PreparedFrame], float]:
    """Return a scan's first `count` frames prepared (the rest never is) and its window radius (mm)."""
    mask, flat = window_setup(scan, options)
    prepared = prepared_frames(scan, frame_forces(scan), mask, flat, options)
    return list(itertools.takewhile(lambda pf: pf.index < count, prepared)), window_radius_mm(mask, scan.calibration)


@pytest.fixture(scope="module")
def live_run() -> LiveRun:
    """Return the raster's first FRAMES frames registered live once (the simulated raster made once per run)."""
    scan = simulated("raster", 1)
    options = method_options("best")
    calib = scan.calibration
    frames, radius_mm = first_prepared(scan, options, FRAMES)
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
    places: dict[str, dict[int, Place]] = {}
    live.finish(lambda step: places.setdefault(step, live.stitch_places()))
    assert list(places) == ["refine", "scales", "calibrate"]  # the finish's steps, named in order
    assert not live.stale
    # finish pastes again every frame not within FINISH_MOVED_PX of its final place (tolerance: the rule itself)
    final = live.stitch_places()
    assert all(np.array_equal(final[i][0], places["calibrate"][i][0]) for i in final)  # the restitch moves none
    # the gauge shows in the last step only: it divides every frame's linear part (float64 rounding)
    assert live.gauge != 1.0
    for i in final:
        np.testing.assert_allclose(final[i][0][:, :2], places["scales"][i][0][:, :2] / live.gauge, rtol=1e-12)
    assert set(live.pasted) == set(final)
    assert all(live.moved_px(live._pasted_place(i), final[i]) < FINISH_MOVED_PX for i in live.pasted)


def test_a_worker_far_behind_pastes_each_frame_alone_and_its_moved_frames_wait(live_run: LiveRun) -> None:
    # add(pf, repaint=False), as a live worker whose session is far behind its uploads: every frame a refinement
    # moved waits (stale), none is re-pasted, the new frame is pasted; settled later the canvas is the usual one
    live = SessionReconstruction(live_run.calib, live_run.options, live_run.radius_mm, live=True)
    moved: set[int] = set()
    for pf in live_run.frames:
        before = dict(live.pasted)
        result, _ = live.add(pf, repaint=False)
        moved.update(result.moved)
        assert pf.index in live.pasted or pf.index not in live.stitch_places()
        assert all(np.array_equal(live.pasted[i], a) for i, a in before.items())  # nothing re-pasted
    assert moved and moved <= set(live.stale)  # every moved frame waits (a refinement moved some)
    while live.stale:
        live.settle(16)
    # settled, every pasted frame lies within LIVE_REPASTE_PX of its pose, as when re-pasted as it goes (the rule)
    assert all(live._unseen_move(pasted, live._stitch_pose(i)) for i, pasted in live.pasted.items())
    assert set(live.pasted) == set(live.stitch_places())  # every frame that has a place is pasted


def test_a_frames_move_is_its_farthest_corner_plus_the_most_its_undone_drag_shifts_a_pixel(live_run: LiveRun) -> None:
    live = live_run.live
    affine = next(iter(live.stitch_places().values()))[0]
    place = (affine, NO_DRAG)
    assert live.moved_px(place, place) == 0.0
    # a shift of the whole frame by 0.1 mm moves every corner by 0.1 mm at the canvas's scale (float64 rounding)
    shifted = affine.copy()
    shifted[:, 2] += (0.06, 0.08)
    assert live.moved_px(place, (shifted, NO_DRAG)) == pytest.approx(0.1 * live.canvas.px_per_mm, rel=1e-9)
    # a turn about the frame's centre moves its corners by the turn times their distance from the centre
    turn = 1e-3
    turned = affine.copy()
    turned[:, :2] = affine[:, :2] @ np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
    w, h = live.calibration.image_size
    cx, cy = live.calibration.principal_point
    corners_mm = np.array([[x - cx, y - cy] for x in (0, w) for y in (0, h)]) / live.calibration.px_per_mm
    moves_mm = (turned[:, :2] - affine[:, :2]) @ corners_mm.T
    expected = float(np.max(np.hypot(*moves_mm))) * live.canvas.px_per_mm
    assert live.moved_px(place, (turned, NO_DRAG)) == pytest.approx(expected, rel=1e-6)
    # a drag undone anew (0.05 mm) adds at most its size at the affine's largest stretch; on two profiles, both
    stretch = np.linalg.norm(affine[:, :2], 2) * live.canvas.px_per_mm
    assert live.drag_shift_px(place, (affine, (0.05j, 15.0))) == pytest.approx(0.05 * stretch, rel=1e-9)
    both = live.drag_shift_px((affine, (0.03 + 0j, 12.0)), (affine, (0.05j, 15.0)))
    assert both == pytest.approx(0.08 * stretch, rel=1e-9)


def on_one_grid(*mosaics: MosaicImage) -> list[tuple[np.ndarray, np.ndarray]]:
    """Return each mosaic's vein image and covered pixels on one grid (their canvas's pixels: the union of their
    extents), uncovered outside each."""
    corners = [(-math.floor(m.origin_px[0]), -math.floor(m.origin_px[1])) for m in mosaics]  # its pixel 0 on the canvas
    x0, y0 = min(c[0] for c in corners), min(c[1] for c in corners)
    x1 = max(c[0] + m.vein.shape[1] for c, m in zip(corners, mosaics, strict=True))
    y1 = max(c[1] + m.vein.shape[0] for c, m in zip(corners, mosaics, strict=True))
    out = []
    for (cx, cy), m in zip(corners, mosaics, strict=True):
        vein, covered = np.zeros((y1 - y0, x1 - x0), np.int16), np.zeros((y1 - y0, x1 - x0), bool)
        h, w = m.vein.shape
        vein[cy - y0 : cy - y0 + h, cx - x0 : cx - x0 + w] = m.vein
        covered[cy - y0 : cy - y0 + h, cx - x0 : cx - x0 + w] = m.coverage > 0
        out.append((vein, covered))
    return out


def grey_gap(live: MosaicImage, whole: SparseCanvas) -> float:
    """Return the largest difference in grey levels between a live mosaic and a whole restitch's canvas, at every
    pixel where the whole restitch's blend weight is TOL.restitch_firm_weight or more (inf: the live mosaic misses
    such a pixel, or covers one beyond the whole mosaic's outermost ring).

    Below that weight only the faint rim of one window covers a pixel (the mosaic's outer band): a frame left where
    it is pasted (moved less than FINISH_MOVED_PX) covers it or not, and its grey there is a ratio of two near-zero
    sums a tenth of a pixel's move changes by levels (tests/tolerances.py). Everywhere else the tolerance holds.
    """
    firm_render = whole.render(min_weight=TOL.restitch_firm_weight)
    (live_vein, live_covered), (whole_vein, whole_covered), (_, firm) = on_one_grid(live, whole.render(), firm_render)
    ring = cv2.dilate(whole_covered.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    if np.any(live_covered & ~ring) or np.any(firm & ~live_covered):
        return math.inf
    return float(np.max(np.abs(live_vein - whole_vein)[firm]))


def shared_short() -> Scan:
    """Return the shared short_veins_21 scan without its mask, as a live session has it."""
    return dataclasses.replace(read_scan_folder(SHARED_SCANS / "short_veins_21"), mask=None)


@pytest.mark.parametrize(
    ("source", "count"),
    [
        pytest.param(lambda: simulated("raster", 1), FRAMES, id="simulated-raster"),
        pytest.param(
            shared_short,
            40,
            id="shared-short",
            marks=pytest.mark.skipif(
                not (SHARED_SCANS / "short_veins_21").is_dir(), reason="the shared reference scans are not here"
            ),
        ),
    ],
)
def test_the_finished_live_mosaic_is_a_whole_restitch_within_a_grey_level(
    source: Callable[[], Scan], count: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    scan, options = source(), method_options("best")
    frames, radius_mm = first_prepared(scan, options, count)
    live = SessionReconstruction(scan.calibration, options, radius_mm, live=True)
    offline = SessionReconstruction(scan.calibration, options, radius_mm)  # pastes every frame at the end
    for pf in frames:
        live.add(pf)
        offline.add(pf)
    unfinished = copy.deepcopy(live.canvas)
    live.finish()
    offline.finish()
    assert path_rows_json(live.path_rows()) == path_rows_json(offline.path_rows())  # the path: identical
    offline.canvas.units = live.canvas.units  # the whole restitch in the live canvas's units
    offline.render()  # every frame pasted at its final place
    assert grey_gap(live.canvas.render(), offline.canvas) <= TOL.finish_restitch_grey
    # the comparison can fail: the canvas as it was before the finish is far from it
    assert grey_gap(unfinished.render(), offline.canvas) > TOL.finish_restitch_grey


def test_frames_over_skin_shown_enough_are_placed_not_stitched_live_as_offline() -> None:
    # the revisit scan passes over its skin again: with a cap of 2 stitched frames over a skin cell, frames that show
    # only such skin are placed on the path and left out of the mosaic, live as offline; the path is the one a cap of
    # 0 (every frame stitched) gives, and the live mosaic is still a whole restitch (of the frames stitched)
    scan = simulated("revisit", 1)
    capped = dataclasses.replace(method_options("best"), stitch_cover_cap=2)
    frames, radius_mm = first_prepared(scan, capped, 160)
    live = SessionReconstruction(scan.calibration, capped, radius_mm, live=True)
    offline = SessionReconstruction(scan.calibration, capped, radius_mm)
    every = SessionReconstruction(scan.calibration, dataclasses.replace(capped, stitch_cover_cap=0), radius_mm)
    for pf in frames:
        for session in (live, offline, every):
            session.add(pf)
    for session in (live, offline, every):
        session.finish()
    placed = {i for i, r in live.results.items() if r.status == "ok"}
    assert 10 <= len(live.unstitched) <= len(placed) // 2  # frames left out (18 of 160 here), most stitched
    assert live.unstitched == offline.unstitched and not every.unstitched
    assert path_rows_json(live.path_rows()) == path_rows_json(every.path_rows())  # the stitch leaves the path alone
    assert set(live.pasted) == placed - live.unstitched  # the others are pasted, once each
    # what the frame counts report as stitched (documents.frame_counts): the frames the mosaic is made of
    assert live.stitched_count() == offline.stitched_count() == len(live.pasted)
    assert every.stitched_count() == len(placed)
    assert not any(live.frames[i].has_pixels or offline.frames[i].has_pixels for i in live.unstitched)
    offline.canvas.units = live.canvas.units
    offline.render()
    assert set(offline.pasted) == set(live.pasted)
    assert grey_gap(live.canvas.render(), offline.canvas) <= TOL.finish_restitch_grey


def test_the_finish_pastes_again_only_the_frames_that_moved(live_run: LiveRun, monkeypatch: pytest.MonkeyPatch) -> None:
    # a live canvas whose frames all lie at their poses; then four frames move by 4 px and one by 0.08 px, and a
    # finish without a final pass or self-calibration (nothing else moves) pastes only the four again
    options = dataclasses.replace(live_run.options, refine=False, self_calibrate=False)
    live = SessionReconstruction(live_run.calib, options, live_run.radius_mm, live=True)
    for pf in live_run.frames:
        live.add(pf)
    live.restitch()
    poses = live.registrar.poses
    far, near = [30, 31, 32, 33], 50
    for i in far:
        poses[i] = Similarity(poses[i].a, poses[i].t + 0.5 + 0.0j)  # 4 px at 8 px/mm
    poses[near] = Similarity(poses[near].a, poses[near].t + 0.01j)  # 0.08 px
    before = dict(live.pasted)
    tiles = set(live.canvas.tiles)
    # without a final pass or self-calibration a finish changes no pose: it can run twice. First pasting nothing
    # again, which the comparison below must catch
    monkeypatch.setattr(session_reconstruction, "FINISH_MOVED_PX", math.inf)
    assert not live.finish()
    unfinished = live.canvas.render()
    monkeypatch.undo()
    planes = {key: tile.copy() for key, tile in live.canvas.tiles.items()}
    touched = live.finish()
    again = [i for i in live.pasted if not np.array_equal(live.pasted[i], before[i])]
    assert again == far
    assert touched and len(touched) < len(tiles)  # only the tiles the moved frames cover
    # ... and those it reports are all that changed: the worker re-renders only them
    assert all(np.array_equal(live.canvas.tiles[key], planes[key]) for key in planes if key not in touched)
    finished = live.canvas.render()
    live.restitch()  # every frame afresh at its final place, the near one too
    assert not np.array_equal(live.pasted[near], before[near])
    assert grey_gap(finished, live.canvas) <= TOL.finish_restitch_grey
    assert grey_gap(unfinished, live.canvas) > TOL.finish_restitch_grey


def test_a_scale_and_shift_of_the_whole_path_moves_no_frame_the_mosaics_units_carry_it(live_run: LiveRun) -> None:
    # a session that ran its finish ahead (which moved nothing: no final pass or self-calibration), then every pose
    # scaled by 1.5 % about a point 2 mm off frame 0 (as a change of the gauge and of frame 0's rest centre moves a
    # path) and four frames moved by 4 px besides: the finish pastes only those four again, in the canvas's units
    # refitted to the rest, which the rendered mosaic carries
    options = dataclasses.replace(live_run.options, refine=False, self_calibrate=False)
    live = SessionReconstruction(live_run.calib, options, live_run.radius_mm, live=True)
    for pf in live_run.frames:
        live.add(pf)
    live.restitch()
    assert live.run_ahead() == 0 and live.canvas.units == IDENTITY
    before = dict(live.pasted)
    poses, k, shift = live.registrar.poses, 1.015, 2.0 - 1.0j
    far = [30, 31, 32, 33]
    for i, pose in poses.items():
        poses[i] = Similarity(pose.a * k, pose.t * k + shift + (0.5 if i in far else 0.0))  # 4 px at 8 px/mm
    live.finish()
    again = [i for i in live.pasted if not np.array_equal(live.pasted[i], before[i])]
    assert again == far
    # the units undo the scale and shift to 1e-9 (a least-squares fit of exact corners)
    units = live.canvas.units
    assert units.scale == pytest.approx(1 / k, abs=1e-9) and abs(units.shift_mm + shift / k) < 1e-9
    mosaic = live.canvas.render()
    assert mosaic.px_per_mm == pytest.approx(live_run.calib.px_per_mm / k, abs=1e-9)
    live.restitch()  # every frame afresh at its final place in the same units
    assert grey_gap(mosaic, live.canvas) <= TOL.finish_restitch_grey
    # the comparison can fail: the path's own units (the identity) put every frame elsewhere
    live.canvas.units = IDENTITY
    live.restitch()
    assert grey_gap(mosaic, live.canvas) > TOL.finish_restitch_grey


@pytest.mark.parametrize(("reselect", "gate_px"), [(False, 0.0), (True, 2.0)])
def test_each_map_reselects_the_drags_pairs_at_the_ransac_gate_only_when_asked(reselect: bool, gate_px: float) -> None:
    calib = default_calibration()
    options = dataclasses.replace(method_options("best"), drag_reselect=reselect)
    session = SessionReconstruction(calib, options, 30.0)
    corrections = session.registrar.corrections
    assert corrections.gate_mm == pytest.approx(gate_px / calib.px_per_mm)  # the RANSAC gate, in mm; 0: off
    assert corrections.drag_pair_gates == options.drag_pair_gate


def test_frame_kind_tells_keyframes_from_tracked_and_unplaced_frames(live_run: LiveRun) -> None:
    # without tracking (best's default) every placed frame is registered by its features
    live = live_run.live
    placed = [pf.index for pf in live_run.frames if live.results[pf.index].status == "ok"]
    assert placed and {live.frame_kind(i) for i in placed} == {"keyframe"}
    assert live.frame_kind(max(live.results) + 1) == "unplaced"  # not handled yet
    # tracking on keyframes: the frames aligned on a keyframe are "tracked", exactly those without features
    scan = simulated("short", 1)
    options = method_options("best").with_overrides({"track_overlap": 0.85})
    frames, radius_mm = first_prepared(scan, options, 30)
    session = SessionReconstruction(scan.calibration, options, radius_mm)
    kinds = {}
    for pf in frames:
        result, _ = session.add(pf)
        kinds[pf.index] = session.frame_kind(pf.index)
        assert (kinds[pf.index] == "unplaced") == (result.status != "ok")
    described = set(session.registrar.features)
    assert {i for i, k in kinds.items() if k == "keyframe"} == described & set(kinds)
    assert list(kinds.values()).count("tracked") >= 5  # most frames of a slow short scan overlap their keyframe
    # the frame counts' `tracked` (mosaic.json, report.json): the frames frame_kind calls tracked; none without tracking
    assert session.tracked_count() == list(kinds.values()).count("tracked") and live.tracked_count() == 0
    # and the documents read both counts from placed_counts
    assert session.placed_counts() == PlacedCounts(session.tracked_count(), session.stitched_count())


def test_edge_yaws_are_the_graphs_edges_as_it_uses_them(live_run: LiveRun) -> None:
    """One row per edge of the main map: its frames, the yaw its undeformed measurement gives, its loop flag, the
    SD the graph weighs that yaw with (its sigma over its a-row's lever, in degrees) and its frames' mean load."""
    reg = live_run.live.registrar
    rows = live_run.live.edge_yaws()
    edges = reg.corrections.undeformed(reg.edges, reg.poses)
    assert rows.shape == (len(reg.edges), 6) and len(reg.edges) > live_run.frames[-1].index  # more than a chain
    loads = {pf.index: pf.load.fz_n for pf in live_run.frames}
    assert np.allclose(rows[:, 5], [(loads[e.i] + loads[e.j]) / 2 for e in edges], rtol=1e-12)
    levers = [e.lever_mm if e.lever_mm > 0 else LEVER_MM for e in edges]
    assert np.allclose(
        rows[:, 4], [np.degrees(e.sigma_mm / lever) for e, lever in zip(edges, levers, strict=True)], rtol=1e-12
    )
    assert np.all(rows[:, 4] > 0)
    assert [(int(i), int(j)) for i, j in rows[:, :2]] == [(e.i, e.j) for e in edges]
    assert np.allclose(rows[:, 2], [np.degrees(np.angle(e.relative.a)) for e in edges], atol=1e-12)
    assert rows[:, 3].tolist() == [float(e.loop) for e in edges] and rows[:, 3].sum() > 0  # row 2 closes loops


def test_a_finish_run_ahead_gives_the_finishs_places_and_leaves_the_session_as_it_was() -> None:
    # the simulated short scan with its skin dragged (40 frames; the final pass learns the drag, refits the view and
    # moves the frames: the state a run ahead must not share): places_if_finished at the end equals the real finish's
    # places exactly, and called halfway it changes nothing of what the session then does
    scan, options = simulate("short", 1, tissue="linear", drag=True), method_options("best")
    frames, radius_mm = first_prepared(scan, options, 40)

    def finished(ahead_at: int) -> tuple[SessionReconstruction, dict[int, Place], dict[int, Place]]:
        recon = SessionReconstruction(scan.calibration, options, radius_mm, live=True)
        ahead: dict[int, Place] = {}
        for k, pf in enumerate(frames):
            if k == ahead_at:
                ahead = recon.places_if_finished()
                assert ahead and not recon.finished and recon.compliance is None  # computed on a copy
            recon.add(pf)
        live_places, live_poses = recon.stitch_places(), dict(recon.registrar.poses)
        if ahead_at == len(frames):
            ahead = recon.places_if_finished()
            assert recon.registrar.poses == live_poses and not recon.finished  # the live state untouched
        recon.finish()
        return recon, ahead, live_places

    whole, ahead, live_places = finished(len(frames))
    final = whole.stitch_places()
    assert whole.registrar.corrections.dragged()  # the drag's fit and caches were in play
    assert ahead.keys() == final.keys()
    assert all(np.array_equal(ahead[i][0], final[i][0]) and ahead[i][1] == final[i][1] for i in final)
    # the comparison can fail: the finish moves frames from their live places by a quarter pixel and more
    assert max(whole.moved_px(live_places[i], final[i]) for i in final) >= FINISH_MOVED_PX
    halfway, _, _ = finished(len(frames) // 2)
    assert path_rows_json(halfway.path_rows()) == path_rows_json(whole.path_rows())
    assert all(np.array_equal(halfway.stitch_places()[i][0], final[i][0]) for i in final)


def test_add_next_records_the_seqs_the_camera_dropped_as_lost() -> None:
    # frames 5 and 6 of the simulated short scan never come: add_next records them lost (missing) before frame 7,
    # and the path keeps one row per seq; add alone would leave them out
    scan, options = simulated("short", 1), method_options("best")
    frames, radius_mm = first_prepared(scan, options, 12)
    recon = SessionReconstruction(scan.calibration, options, radius_mm)
    for pf in frames:
        if pf.index not in (5, 6):
            recon.add_next(pf)
    assert [recon.results[i].reason for i in (5, 6)] == [REASON_MISSING, REASON_MISSING]
    assert all(recon.results[i].status == STATUS_LOST for i in (5, 6))
    assert [row.seq for row in recon.path_rows()] == list(range(12))


@pytest.mark.parametrize(
    ("self_calibrate", "runs", "in_place"),
    [
        (True, (40, 70), False),  # best: each run's law and final pass move most frames; the finish pastes most again
        (False, (40, 76), True),  # no gauge: the finish pastes again only the frames placed since, in place
    ],
)
def test_a_canvas_kept_at_finishes_run_ahead_finishes_as_a_whole_restitch(
    live_run: LiveRun, monkeypatch: pytest.MonkeyPatch, self_calibrate: bool, runs: tuple[int, int], in_place: bool
) -> None:
    # the simulated raster's first FRAMES frames live, the finish run ahead after frames `runs` and the canvas
    # settled each time (as a caught-up worker): the canvas then lies at the run's places, the path stays the one
    # a session without runs gives, and the mosaic finishes within the tolerance of a whole restitch; the finish
    # pastes again only what moved since, in place (_move_pasted) when few did
    moved_in_place: list[int] = []
    original = SessionReconstruction._move_pasted

    def spy(self: SessionReconstruction, moved: list[int], final: dict[int, Place]) -> set[tuple[int, int]]:
        moved_in_place.append(len(moved))
        return original(self, moved, final)

    monkeypatch.setattr(SessionReconstruction, "_move_pasted", spy)
    options = dataclasses.replace(live_run.options, self_calibrate=self_calibrate)
    live = SessionReconstruction(live_run.calib, options, live_run.radius_mm, live=True)
    offline = SessionReconstruction(live_run.calib, options, live_run.radius_mm)
    for pf in live_run.frames:
        live.add(pf)
        offline.add(pf)
        if pf.index in runs:
            assert live.run_ahead() > 0
            run = live.ahead
            assert run is not None and not live.finished and live.gauge == 1.0  # run on a copy
            assert (run.gauge != 1.0) == self_calibrate
            while live.stale:
                live.settle(16)
            # every frame of the run lies within AHEAD_MOVED_PX of the run's place (tolerance: the rule itself)
            assert set(run.places) <= set(live.pasted)
            for i, place in run.places.items():
                assert live.moved_px(live._pasted_place(i), place) < session_reconstruction.AHEAD_MOVED_PX
    # frames placed since the last run are pasted at their live places mapped onto its mosaic, no drag undone
    assert live.ahead is not None
    newest = max(live.pasted)
    assert newest not in live.ahead.places and newest not in live.pasted_drag
    assert np.allclose(live.pasted[newest], live.ahead.mapped(live._stitch_pose(newest)), atol=1e-12)
    # the live path is in the run's units: its gauge and origin applied to the registrar's poses
    row = next(row for row in live.path_rows() if row.seq == newest)
    moved_pose = live.ahead.output_pose(live.registrar.poses[newest])
    assert (row.x_mm, row.y_mm) == pytest.approx((moved_pose.t.real, moved_pose.t.imag), abs=1e-12)
    before = {i: live._pasted_place(i) for i in live.pasted}
    live.finish()
    offline.finish()
    assert path_rows_json(live.path_rows()) == path_rows_json(offline.path_rows())  # the path: identical
    again = [i for i in live.pasted if not np.array_equal(live.pasted[i], before[i][0])]
    if in_place:
        assert moved_in_place == [len(again)] and 0 < len(again) < len(live.pasted) // 4
    else:
        assert not moved_in_place and len(again) > len(live.pasted) // 2
    offline.canvas.units = live.canvas.units  # the whole restitch in the live canvas's units
    offline.render()
    assert grey_gap(live.canvas.render(), offline.canvas) <= TOL.finish_restitch_grey


def test_images_kept_uncompressed_within_the_budget_then_as_png_stitch_the_same(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """An offline session keeps its frames' images as they are up to RAW_PIXELS_BUDGET, as PNG beyond it: the
    mosaic is the same to the grey level either way (both are lossless)."""
    scan = simulated("raster", 1)
    options = method_options("best")
    frames, radius_mm = first_prepared(scan, options, 12)

    def rendered(budget: int) -> tuple[SessionReconstruction, MosaicImage]:
        monkeypatch.setattr(session_reconstruction, "RAW_PIXELS_BUDGET", budget)
        session = SessionReconstruction(scan.calibration, options, radius_mm)
        for pf in frames:
            session.add_next(pf)
        session.finish()
        return session, session.render()

    image_bytes = frames[0].image.nbytes
    budgeted, mosaic = rendered(int(2.5 * image_bytes))
    unlimited, reference = rendered(10**12)
    kept = [budgeted.frames[i] for i in sorted(budgeted.frames) if budgeted.frames[i].has_pixels]
    assert len(kept) >= 10
    assert [k.raw_bytes > 0 for k in kept] == [True, True] + [False] * (len(kept) - 2)
    assert all(k.image_png is not None for k in kept[2:])
    assert budgeted.raw_pixel_bytes == 2 * image_bytes
    assert all(k.raw_bytes > 0 for k in unlimited.frames.values() if k.has_pixels)
    np.testing.assert_array_equal(mosaic.vein, reference.vein)
    np.testing.assert_array_equal(mosaic.force_n, reference.force_n)
