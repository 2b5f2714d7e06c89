"""One session's reconstruction, frame by frame: the same object serves the offline CLI and the live workers.

Feeding the same prepared frames in the same order gives the same path and mosaic, whether the frames
come from a scan folder in one process or from a queue across worker processes (a worker that takes a
session over replays the prepared frames it has not seen; registration is deterministic).
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from services.core.contact import ContactDetector
from services.core.inputs.calibration import Calibration
from services.core.lookahead import in_order_ahead
from services.core.methods import MethodOptions
from services.core.mosaic.canvas import FrameLayers, MosaicImage, SparseCanvas, Warped, blend_weight
from services.core.mosaic.canvas_units import IDENTITY, CanvasUnits, fit_units
from services.core.mosaic.stitch_cover import StitchCover
from services.core.path_rows import PathRow, PlacedCounts
from services.core.physics.compliance import ComplianceFit, fit_compliance
from services.core.physics.drag import undrag_maps
from services.core.physics.force_clock import ClockOffset, estimate_clock_offset
from services.core.physics.tissue_model import tilt_angles_rad
from services.core.registration.atlas import Atlas
from services.core.registration.edge_corrections import EdgeCorrections
from services.core.registration.frame_prep import PreparedFrame, load_map_n
from services.core.registration.kept_frame import KeptFrame, keep_frame
from services.core.registration.outcome import (
    REASON_BAD_FRAME,
    REASON_FRAGMENT,
    REASON_MISSING,
    REASON_NO_CONTACT,
    STATUS_LOST,
    STATUS_OK,
    STATUS_REJECTED,
    FrameResult,
)
from services.core.registration.pose_graph import edge_yaw_sigma_deg
from services.core.registration.registrar import Registrar
from services.core.similarity import Similarity

# The newest frames whose paste planes a live session keeps (~5 MB each at 640 x 480): each new frame is pasted
# from its prepared image directly, and half of the re-pastes a refinement asks for are of frames this recent
# (measured on a simulated raster: 116 of 268 within 8 frames); older ones are decoded from what was kept.
KEYFRAME, TRACKED, UNPLACED = FRAME_KINDS = ("keyframe", "tracked", "unplaced")  # SessionReconstruction.frame_kind
RECENT_LAYERS = 12
# While a live scan goes on, a refined frame is re-pasted only when some point of its window moved by this many
# mosaic pixels or more since it was pasted: smaller moves are invisible, and re-pasting every frame a local pass
# nudged by 0.4 px (refinement.MOVED_MM) cost a third of a long examination's registration time. The final
# mosaic is unaffected: finish() re-pastes every frame that is not within FINISH_MOVED_PX of its final place.
LIVE_REPASTE_PX = 2.0
# At the finish a frame is pasted afresh when some point of it lies this many mosaic pixels or more from where it is
# pasted (its pose, view or drag changed): the finished mosaic is within a grey level of a whole restitch at its
# final poses (tests/services/core/test_session_reconstruction.py). Only the tiles such frames cover, at their old
# and new places, are made again; the final pass, the drag and the gauge usually move every frame of a `best` session.
FINISH_MOVED_PX = 0.25
# A finish run ahead (run_ahead) pastes a frame again when it moved this far from where it is pasted: half the
# finish's rule, so that the moves of runs that follow do not add up past FINISH_MOVED_PX unseen.
AHEAD_MOVED_PX = 0.5 * FINISH_MOVED_PX
# What moving a pasted frame costs (_move_pasted: its planes built once, warped and added twice) against pasting a
# frame afresh (planes built, warped and added once): building the planes (reading the pixels back, the blend weight,
# the load map) is about half of a paste (docs/performance.md, "A frame pasted again").
MOVE_COST = 1.5
NO_DRAG: tuple[complex, float] = (0j, 0.0)  # a frame's planes undo no drag: (drag mm, profile width mm)
# where a frame is pasted: its stitch affine (rectified frame mm -> mosaic mm, 2x3) and the drag its planes undo
Place = tuple[np.ndarray, tuple[complex, float]]
# Frames a refinement moved are re-pasted a few per registered frame (oldest first), not all at once: a global
# pass moves most of a long examination's frames, whose re-paste at once held one frame for seconds. The new frame
# and the moved frames whose planes are kept (the newest) are pasted at once; settle() lets a caught-up worker
# repaint more.
REPAINT_PER_FRAME = 4
RESTITCH_AHEAD = 4  # a restitch builds and warps this many frames (~5 + 10 MB each) ahead of adding them
REPAINT_AT_ONCE = 12  # moved frames this recent are re-pasted at once (their planes are usually kept)
# A session that keeps its frames' pixels (offline) keeps the images uncompressed up to this many bytes (~430 frames
# at 640 x 480: every stitched frame of the shared scans), as PNG beyond: encoding and decoding them cost ~4.5 ms of a
# frame's ~60 ms of CPU. Bounded so that a long examination stays within its 1.5 GB (bench/long_exam.py: at 256 MB
# the 2400-frame examination peaked at 1433 MB, at none 1259 MB).
RAW_PIXELS_BUDGET = 128 * 2**20


def _in_output_units(pose: Similarity, gauge: float, origin_shift: complex) -> Similarity:
    """Return a registrar pose in output units: divided by the compliance gauge, its origin moved by origin_shift
    (registrar mm) to where the skin under frame 0's centre rests."""
    return Similarity(pose.a / gauge, (pose.t + origin_shift) / gauge)


def _as_3x3(affine: np.ndarray) -> np.ndarray:
    """Return a 2x3 affine as its 3x3 homogeneous matrix."""
    return np.vstack([affine, [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class AheadRun:
    """A finish run ahead of the scan's end on a copy of the session (run_ahead): where it would paste each frame
    then, and how a live pose maps onto it. While live, the canvas is kept at these places, so that the real finish
    pastes again only what moved since."""

    places: dict[int, Place]  # the run's stitch places (output mm, drags undone), by frame
    gauge: float  # the run's compliance gauge (_output_pose)
    origin_shift: complex  # the run's shift of frame 0's rest centre (registrar mm)
    correction: np.ndarray  # 3x3, mosaic mm -> mosaic mm: the run's newest frame's live stitch affine onto its place

    def output_pose(self, pose: Similarity) -> Similarity:
        """Return a live registrar pose in the run's output units (its gauge and origin)."""
        return _in_output_units(pose, self.gauge, self.origin_shift)

    def mapped(self, affine: np.ndarray) -> np.ndarray:
        """Return a live stitch affine (2x3, mm) mapped onto the run's mosaic by its newest frame's correction: where
        a frame placed since the run is pasted."""
        return (self.correction @ _as_3x3(affine))[:2]


@dataclass
class SessionReconstruction:
    """Registration state, kept frames and (when live) the canvas of one session."""

    calibration: Calibration
    options: MethodOptions
    window_radius_mm: float
    live: bool = False  # paste as frames arrive and move frames when refinement moves them
    atlas: Atlas = field(init=False)  # the main map (`registrar`) and the fragments not joined to it yet
    contact: ContactDetector = field(default_factory=ContactDetector)
    strokes: dict[int, int] = field(default_factory=dict)  # contact frame -> its stroke (from 0)
    in_fragment: dict[int, FrameResult] = field(default_factory=dict)  # placed on a fragment: its own result
    canvas: SparseCanvas = field(init=False)
    results: dict[int, FrameResult] = field(default_factory=dict)
    frames: dict[int, KeptFrame] = field(default_factory=dict)  # compact: row data, and pixels if pasteable
    pasted: dict[int, np.ndarray] = field(default_factory=dict)  # frame -> the 2x3 affine it is pasted with
    pasted_drag: dict[int, tuple[complex, float]] = field(default_factory=dict)  # the drag its planes undid (NO_DRAG)
    compliance: ComplianceFit | None = None
    clock: ClockOffset | None = None  # the force logger's clock against the camera's, estimated at the finish
    gauge: float = 1.0
    finished: bool = False
    finish_seconds: dict[str, float] = field(default_factory=dict)  # finish()'s parts, timed (s)
    finish_pasted_again: int = 0  # frames the finish pasted again (moved by FINISH_MOVED_PX; live)
    recent: dict[int, FrameLayers] = field(default_factory=dict)  # paste planes of the newest frames (live)
    stale: dict[int, None] = field(default_factory=dict)  # moved frames not re-pasted yet, oldest first (live)
    ahead: AheadRun | None = None  # the last finish run ahead (live): the canvas is kept at its places
    cover: StitchCover = field(init=False)  # how often the stitched frames cover the skin (stitch_cover)
    unstitched: set[int] = field(default_factory=set)  # placed frames left out of the stitch: their skin was shown
    raw_pixel_bytes: int = 0  # bytes of the images kept uncompressed (RAW_PIXELS_BUDGET)
    heartbeat: Callable[[], None] = field(default=lambda: None, repr=False)  # called between long steps
    # where a placed frame's rectified image and mask are read back by index (a live worker: its prepared file,
    # so a long examination does not hold every frame's pixels); None keeps them here (RAW_PIXELS_BUDGET)
    pixels: Callable[[int], tuple[np.ndarray, np.ndarray]] | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        self.atlas = Atlas(self._new_map, self.window_radius_mm)
        self.canvas = SparseCanvas(self.calibration.px_per_mm)
        w, h = self.calibration.image_size  # the window's inscribed disc: within the window and the image
        inscribed_mm = min(self.window_radius_mm, 0.5 * min(w, h) / self.calibration.px_per_mm)
        self.cover = StitchCover(self.options.stitch_cover_cap, inscribed_mm)

    def _new_map(self) -> Registrar:
        """Return an empty map (registration state) with this session's calibration and options."""
        return Registrar(
            self.options,
            self.calibration.px_per_mm,
            self.window_radius_mm,
            centre_px=self.calibration.principal_point,
            corrections=EdgeCorrections(
                separation_mm=self.calibration.sensor_separation_mm,
                kappa_prior_n_per_mm=self.calibration.hooke_n_per_mm,
                compliance_per_n=self.calibration.compliance_per_n,
                gate_mm=self.options.ransac_px / self.calibration.px_per_mm if self.options.drag_reselect else 0.0,
                drag_pair_gates=self.options.drag_pair_gate,
                drag_across_sigma_mm=self.options.drag_across_sigma_mm,
            ),
        )

    @property
    def registrar(self) -> Registrar:
        """Return the main map: every placed frame's pose, in the first contact frame's coordinates."""
        return self.atlas.main

    def frame_kind(self, index: int) -> str:
        """Return how a handled frame was placed, one of FRAME_KINDS: "keyframe" (registered by its features),
        "tracked" (aligned on a keyframe without features: MethodOptions.track_overlap) or "unplaced" (lost,
        rejected or waiting on a fragment)."""
        result = self.results.get(index)
        if result is None or result.status != STATUS_OK:
            return UNPLACED
        return KEYFRAME if any(index in m.features for m in self.atlas.maps) else TRACKED

    def tracked_count(self) -> int:
        """Return how many handled frames are placed as "tracked" (frame_kind): the frame counts' `tracked`."""
        return sum(self.frame_kind(i) == TRACKED for i in self.results)

    def stitched_count(self) -> int:
        """Return how many handled frames are pasted into the mosaic (_stitched): frame_counts' `stitched`."""
        return sum(self._stitched(i) for i in self.results)

    def placed_counts(self) -> PlacedCounts:
        """Return the counts of the placed frames tracked (tracked_count) and stitched (stitched_count) that the
        frame counts of mosaic.json, report.json and the events carry (documents.frame_counts)."""
        return PlacedCounts(self.tracked_count(), self.stitched_count())

    def _stitched(self, index: int) -> bool:
        """Return whether a frame is stitched into the mosaic: placed on the main map, sharp, and not left out over
        skin already shown (stitch_cover). The one rule of _stitch_pose and stitched_count."""
        result = self.results.get(index)
        return (
            result is not None
            and result.status == STATUS_OK
            and not result.blurred
            and index not in self.unstitched
            and index in self.registrar.poses
        )

    def add(self, pf: PreparedFrame, repaint: bool = True) -> tuple[FrameResult, set[tuple[int, int]]]:
        """Return the result of a frame (in index order: contact, then registration) and the canvas tiles changed.

        Live, the frame is pasted, and the frames a refinement moved are re-pasted: the newest at once, older ones
        a few at a time (settle). repaint=False (a live worker far behind its uploads) pastes the frame alone and
        leaves every moved frame to settle later, when caught up, or to the finish.
        """
        self.heartbeat()
        result = self._register(pf)
        self.heartbeat()
        self.results[pf.index] = result
        pasteable = (result.status == STATUS_OK or pf.index in self.in_fragment) and not result.blurred
        if pasteable and result.status == STATUS_OK and not self._admitted(pf.index):
            self.unstitched.add(pf.index)  # placed, not stitched: nor are its pixels kept
            pasteable = False
        kept = keep_frame(pf, pasteable, keep_pixels=self.pixels is None, compress=self._compress(pf.image.nbytes))
        self.frames[pf.index] = kept
        self.raw_pixel_bytes += kept.raw_bytes
        touched: set[tuple[int, int]] = set()
        if self.live:
            if kept.pasteable:  # the planes straight from the prepared frame: the kept image is the same, losslessly
                self._remember(pf.index, self._build_layers(pf.image, pf.mask, kept, self._drag_state(pf.index)))
            at_once = pf.index - REPAINT_AT_ONCE if repaint else math.inf
            now = tuple(i for i in result.moved if i > at_once)
            self.stale.update((i, None) for i in result.moved if i <= at_once)
            touched |= self._sync_canvas((pf.index, *now))
            touched |= self.settle(REPAINT_PER_FRAME if repaint else 0)
        return result, touched

    def _admitted(self, index: int) -> bool:
        """Return True when a frame just placed on the main map is to be stitched (stitch_cover: decided once, at the
        place it was given now); a frame without a pose is."""
        pose = self.registrar.poses.get(index)
        return pose is None or self.cover.admit((pose.t.real, pose.t.imag))

    def add_next(self, pf: PreparedFrame) -> tuple[FrameResult, set[tuple[int, int]]]:
        """Return add(pf) after recording as lost the seqs before it that never came (frames the camera dropped):
        a scan's frames replayed in order, as offline (a live worker's queue declares its own lost frames)."""
        for missing in range(len(self.results), pf.index):
            self.lose(missing)
        return self.add(pf)

    def _register(self, pf: PreparedFrame) -> FrameResult:
        """Return a frame's result: rejected off the skin, else placed on the atlas (a join places more frames)."""
        if not self.contact.decide(pf.load.fz_n, pf.focus).contact:
            return FrameResult(pf.index, STATUS_REJECTED, None, 0, False, reason=REASON_NO_CONTACT)
        landing = not self.strokes or self._previous_status(pf.index) == REASON_NO_CONTACT
        self.strokes[pf.index] = max(self.strokes.values(), default=-1) + int(landing)
        placed = self.atlas.add(pf, landing)
        result = placed.result
        if result.status == STATUS_OK and not placed.on_main:  # waits on a fragment until it joins the map
            self.in_fragment[pf.index] = result
            result = FrameResult(pf.index, STATUS_LOST, None, result.inliers, result.blurred, reason=REASON_FRAGMENT)
        for i in placed.joined:
            if i != pf.index:  # the joining frame itself may have been on the fragment: it is placed now
                self.results[i] = self.in_fragment.pop(i)
        if placed.joined or placed.moved:
            result = dataclasses.replace(result, moved=(*result.moved, *placed.joined, *placed.moved))
        return result

    def _previous_status(self, index: int) -> str:
        """Return the reason of the newest frame before `index` that arrived ("" when placed or none)."""
        for i in range(index - 1, -1, -1):
            r = self.results.get(i)
            if r is not None and r.reason != REASON_MISSING:
                return r.reason
        return ""

    def settle(self, limit: int) -> set[tuple[int, int]]:
        """Return the canvas tiles changed by re-pasting up to `limit` moved frames not re-pasted yet (oldest first)."""
        batch = list(itertools.islice(self.stale, limit))
        for i in batch:
            del self.stale[i]
        return self._sync_canvas(tuple(batch))

    def lose(self, index: int) -> None:
        """Record a frame that never arrived (declared lost by the queue) so path rows stay complete."""
        self.results[index] = FrameResult(index, STATUS_LOST, None, 0, False, reason=REASON_MISSING)

    def reject(self, index: int, reason: str = REASON_BAD_FRAME) -> None:
        """Record a frame whose content could not be processed, so path rows stay complete."""
        self.results[index] = FrameResult(index, STATUS_REJECTED, None, 0, False, reason=reason)

    def final_poses(self) -> dict[int, Similarity]:
        """Return the placed poses in output units (after the compliance gauge when finished)."""
        return {i: self._output_pose(p) for i, p in self.registrar.poses.items()}

    def _output_pose(self, pose: Similarity) -> Similarity:
        """Return a registrar pose in output units: divided by the gauge (1 until finish), its origin moved to
        where the skin under frame 0's centre rests (0 until a drag is learned: physics.drag)."""
        return _in_output_units(pose, self.gauge, self._origin_shift())

    def _origin_shift(self) -> complex:
        """Return mm (registrar units) to add to every pose so frame 0's rest centre is the origin (spec §4)."""
        if not self.registrar.order:
            return 0j
        first = self.registrar.order[0]
        return self.registrar.poses[first].a * self._drag(first)

    def _drag(self, index: int) -> complex:
        """Return a placed frame's learned drag (complex mm, its own axes; 0 until one is learned and kept: the
        drag is fitted by the final refinement only, so never while live)."""
        fit = self.registrar.corrections.drag_fit
        return fit.of(index) if fit is not None else 0j

    def finish(self, observe: Callable[[str], None] | None = None) -> set[tuple[int, int]]:
        """Return the canvas tiles changed by running the final refinement and compliance self-calibration.

        The seconds each part took are kept in `finish_seconds` (refine, calibrate, restitch). observe, if given, is
        called with a step's name once it is done, before the next starts: "refine" (the final pass, the skin's drag
        learned), "scales" (the path held to the law's scales; the gauge not applied yet) and "calibrate" (the gauge
        and the origin at frame 0's rest centre applied): bench/finish.py reads how far each step moves the frames'
        places. Its own time counts in the next part.
        """
        note = observe or (lambda _part: None)
        started = time.perf_counter()
        if self.options.refine:
            self.registrar.refine(final=True)
        note("refine")
        refined = time.perf_counter()
        self.clock = self._estimate_clock()
        if self.options.self_calibrate:
            self.compliance = self._fit_compliance()
            if self.compliance is not None and self.options.refine and self.options.scale_prior > 0:
                # the path held to the scales the law and its gauge say (fitted on the scales as registered, not
                # refitted on the held ones, which would only return them): a chain's scale no longer wanders
                self.registrar.refine_scales(self._expected_scales(self.compliance), self.options.scale_prior)
            self.gauge = self.compliance.gauge if self.compliance is not None else 1.0
        note("scales")  # the places are in registrar units until finished: the gauge does not show yet
        self.finished = True
        if self.registrar.corrections.dragged():
            self.recent = {}  # the newest frames' planes were built with their drag in: rebuilt, undragged
        note("calibrate")
        calibrated = time.perf_counter()
        touched = self._restitch_moved() if self.live else set()
        self.finish_seconds = {
            "refine": round(refined - started, 3),
            "calibrate": round(calibrated - refined, 3),
            "restitch": round(time.perf_counter() - calibrated, 3),
        }
        return touched

    def places_if_finished(self) -> dict[int, Place]:
        """Return the stitch places the finish would give now (stitch_places after finish()), computed on a copy of
        the main map's registration state: this session is left as it was (a finish run ahead of the scan's end,
        bench/finish_ahead.py)."""
        return self._finished_copy().stitch_places()

    def _finished_copy(self) -> SessionReconstruction:
        """Return a finished copy of this session, nothing pasted: the finish run on a copy of the main map's state
        (registrar and corrections with their own containers; copy.deepcopy stops at the place index's FLANN tree)."""
        ahead = copy.copy(self)
        ahead.live = False  # nothing pasted
        ahead.ahead = None
        ahead.canvas = SparseCanvas(self.calibration.px_per_mm)  # its places in the path's units (identity)
        ahead.atlas = copy.copy(self.atlas)
        main = _with_own_containers(self.registrar)
        main.corrections = _with_own_containers(main.corrections)
        ahead.atlas.maps = [main, *self.atlas.maps[1:]]
        ahead.finish()
        return ahead

    def run_ahead(self) -> int:
        """Return how many frames now wait to be pasted again (stale), after running the finish ahead of the scan's
        end on a copy (places_if_finished) and keeping the live canvas at its places from now on, in the canvas's
        units refitted to them (_fitted_units: the run's change of gauge and origin moves no frame): each frame it
        moved by AHEAD_MOVED_PX or more from where it is pasted is re-pasted a few at a time (settle), and frames
        placed since are pasted at their live places mapped onto its mosaic (AheadRun.mapped). The path and every
        registration state are left as they were; the real finish then pastes again only what moved since.
        """
        if not self.live or self.finished:
            return 0
        twin = self._finished_copy()
        places = self._onto_canvas(twin.stitch_places(), AHEAD_MOVED_PX)
        newest = max(places, default=None)  # its live place against the run's maps the frames placed since
        live = self._stitch_pose(newest) if newest is not None else None
        correction = np.eye(3)
        if newest is not None and live is not None:
            correction = _as_3x3(places[newest][0]) @ np.linalg.inv(_as_3x3(live))
        self.ahead = AheadRun(places, twin.gauge, twin._origin_shift(), correction)
        moved = (i for i in sorted(set(self.pasted) | set(places)) if i in self.frames)
        self.stale.update((i, None) for i in moved if self._repaste_needed(i, self._pasted_place(i), self._target(i)))
        return len(self.stale)

    def _estimate_clock(self) -> ClockOffset | None:
        """Return the force clock's offset fitted to the placed frames' stretches (physics.force_clock), or None."""
        placed = sorted(i for i in self.registrar.order if i in self.frames)
        kept = [self.frames[i] for i in placed]
        stretch = np.array(
            [1.0 / (abs(self.registrar.poses[i].a) * (1.0 - k.stretch)) for i, k in zip(placed, kept, strict=True)]
        )
        return estimate_clock_offset(
            stretch,
            np.array([k.t_s for k in kept]),
            np.array([k.load.fz_n for k in kept]),
            np.array([self.strokes.get(i, -1) for i in placed]),
        )

    def _expected_scales(self, fit: ComplianceFit) -> dict[int, float]:
        """Return each placed frame's pose scale |a| as the fitted law and gauge say it is (frame 0's too)."""
        placed = self.registrar.order
        loads = np.array([self.frames[i].load.fz_n for i in placed])
        expected = fit.expected_scales(loads, self.calibration.compliance_per_n)
        return {i: float(a) for i, a in zip(placed, expected, strict=True)}

    def _fit_compliance(self) -> ComplianceFit | None:
        placed = [i for i, r in self.results.items() if r.status == STATUS_OK and i in self.registrar.poses]
        scales = np.array([abs(self.registrar.poses[i].a) for i in placed])
        loads = np.array([self.frames[i].load.fz_n for i in placed])
        return fit_compliance(scales, loads, self.calibration.compliance_per_n, stiffening=self.options.stiffening)

    def _build_layers(
        self, image: np.ndarray, mask: np.ndarray, kept: KeptFrame, drag: tuple[complex, float]
    ) -> FrameLayers:
        """Return a frame's paste planes: its intensity, blend weight and load, with `drag` undone (_drag_state)."""
        image, mask = self._undragged(image, mask, drag)
        return FrameLayers.of(
            intensity=image,  # uint8 grey levels, read as /255
            weight=blend_weight(mask),
            force_n=load_map_n(self.calibration, kept.load),
            centre_px=self.calibration.principal_point,
            px_per_mm=self.calibration.px_per_mm,
        )

    def _drag_state(self, index: int) -> tuple[complex, float]:
        """Return what a frame's planes undo now: its learned drag (mm) and the profile's width (mm), or NO_DRAG."""
        drag, fit = self._drag(index), self.registrar.corrections.drag_fit
        return NO_DRAG if fit is None or drag == 0 else (drag, fit.width_mm)

    def _undragged(
        self, image: np.ndarray, mask: np.ndarray, drag: tuple[complex, float]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Return a rectified frame and its window mask resampled with a drag (mm, width mm) undone (physics.drag),
        so the mosaic shows the skin at rest as the path does; as they are for NO_DRAG."""
        if drag == NO_DRAG:
            return image, mask
        maps = undrag_maps(image.shape[:2], self.calibration.principal_point, self.calibration.px_per_mm, *drag)
        return (
            cv2.remap(image, *maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0),
            cv2.remap(mask, *maps, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0),
        )

    def _layers(self, index: int) -> FrameLayers:
        """Return a frame's paste planes: remembered for the newest frames, else rebuilt from what was kept."""
        layers = self.recent.get(index)
        if layers is None:
            layers = self._build_layers(*self._pixels(index), self.frames[index], self._drag_state(index))
            self._remember(index, layers)
        return layers

    def _pixels(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """Return a pasted frame's rectified image and window mask: kept here, or read back through `pixels`."""
        kept = self.frames[index]
        if kept.has_pixels or self.pixels is None:
            return kept.image(), kept.mask()
        return self.pixels(index)

    def _compress(self, image_bytes: int) -> bool:
        """Return whether a kept image of image_bytes goes over RAW_PIXELS_BUDGET with the images kept so far."""
        return self.raw_pixel_bytes + image_bytes > RAW_PIXELS_BUDGET

    def _remember(self, index: int, layers: FrameLayers) -> None:
        """Keep the planes of the RECENT_LAYERS newest frames: new frames and most re-pastes after a refinement."""
        if not self.live:
            return
        newest = next(reversed(self.frames))  # frames are added in index order
        if index <= newest - RECENT_LAYERS:
            return
        self.recent[index] = layers
        for old in [i for i in self.recent if i <= newest - RECENT_LAYERS]:
            del self.recent[old]

    def _stitch_pose(self, index: int) -> np.ndarray | None:
        """Return the 2x3 affine (rectified frame mm -> mosaic mm) a frame is pasted with, or None (not pasted).

        The pose after the frame's tilt foreshortening is undone (its view D^-1), so the mosaic is undeformed; once
        finished, in output units mapped onto the canvas's (SparseCanvas.units), else in the registrar's.
        """
        if not self._stitched(index):
            return None
        pose = self.registrar.poses[index]
        pose = self._output_pose(pose) if self.finished else pose
        pose = pose.rigid() if self.options.rigid_stitch else pose
        m = pose.matrix()
        view = self.registrar.corrections.view(index, self.registrar.poses)
        affine = np.hstack([m[:, :2] @ np.linalg.inv(view), m[:, 2:]])
        return self.canvas.units.on_canvas(affine) if self.finished and self.canvas.units != IDENTITY else affine

    def _target(self, index: int) -> Place | None:
        """Return where a live frame is to be pasted now, or None (not pasted): its place in the last run ahead, its
        live place mapped onto that run's mosaic when placed since (no drag undone), else its current place."""
        pose = self._stitch_pose(index)
        if pose is None:
            return None
        run = self.ahead
        if run is None or self.finished:
            return pose, self._drag_state(index)
        return run.places.get(index) or (run.mapped(pose), NO_DRAG)

    def _repaste_needed(self, index: int, old: Place | None, new: Place | None) -> bool:
        """Return True when a frame pasted at `old` (None: not pasted) must be pasted again for `new`: pasted or not;
        moved by AHEAD_MOVED_PX or more to a place of the last run ahead (so the finish pastes few again); else,
        while live, moved by LIVE_REPASTE_PX (_unseen_move) or its undone drag changed."""
        if old is None or new is None:
            return old is not new
        if self.ahead is not None and not self.finished and index in self.ahead.places:
            return self.moved_px(old, new) >= AHEAD_MOVED_PX
        return old[1] != new[1] or not self._unseen_move(old[0], new[0])

    def _planes(self, index: int, drag: tuple[complex, float], remember: bool = True) -> FrameLayers:
        """Return a frame's paste planes with `drag` undone: when that is the drag it undoes now, the remembered ones
        or (_layers) rebuilt and remembered if `remember` (False: from another thread, nothing changed); else built
        afresh and not remembered (a place of a run ahead, or the drag it undid before the finish learned one)."""
        if drag == self._drag_state(index):
            if remember:
                return self._layers(index)
            if (layers := self.recent.get(index)) is not None:
                return layers
        return self._build_layers(*self._pixels(index), self.frames[index], drag)

    def _sync_canvas(self, indices: tuple[int, ...]) -> set[tuple[int, int]]:
        """Paste frames where they are to be pasted now (_target), removing them first from where they were pasted."""
        touched: set[tuple[int, int]] = set()
        for i in indices:
            old, new = self._pasted_place(i), self._target(i)
            if not self._repaste_needed(i, old, new):
                continue
            self.heartbeat()
            layers: FrameLayers | None = None
            if old is not None:  # the planes it was pasted with: remembered, rebuilt, or with the run's drag undone
                layers = self._planes(i, old[1])
                touched.update(self.canvas.paste(layers, old[0], sign=-1.0))
            if new is not None:
                if old is None or new[1] != old[1]:  # else the planes it was pasted with serve
                    layers = self._planes(i, new[1])
                touched.update(self.canvas.paste(layers, new[0]))
            self._record_pasted(i, new)
        return touched

    def _record_pasted(self, index: int, place: Place | None) -> None:
        """Record where a frame is pasted now (`pasted`, and `pasted_drag` unless its planes undo no drag); None: it
        is not pasted."""
        self.pasted.pop(index, None)
        self.pasted_drag.pop(index, None)
        if place is not None:
            self.pasted[index] = place[0]
            if place[1] != NO_DRAG:
                self.pasted_drag[index] = place[1]

    def _unseen_move(self, old: np.ndarray, new: np.ndarray) -> bool:
        """Return True when a frame pasted with affine `old` (2x3, mm) needs no re-paste at `new`: the same, or
        (while live and not finished) no point of its window moved by LIVE_REPASTE_PX mosaic pixels."""
        if np.array_equal(old, new):
            return True
        if self.finished:
            return False
        delta = new - old
        reach_mm = float(np.hypot(*delta[:, 2])) + float(np.linalg.norm(delta[:, :2], 2)) * self.window_radius_mm
        return reach_mm * self.calibration.px_per_mm < LIVE_REPASTE_PX

    def render(self) -> MosaicImage:
        """Return the mosaic: the live canvas, or (offline) a stitch of every sharp placed frame."""
        if not self.live:
            self.restitch()
        return self.canvas.render()

    def restitch(self) -> set[tuple[int, int]]:
        """Paste every frame afresh at its place now on an empty canvas in the same units; return the tiles of the
        old and the new canvas (what the finish does when every frame moved; offline, every render)."""
        old = set(self.canvas.tiles)
        self.canvas = SparseCanvas(self.calibration.px_per_mm, units=self.canvas.units)
        self.pasted = {}
        self.pasted_drag = {}
        self.stale = {}
        return old | self._paste_in_order(self.stitch_places())

    def _restitch_moved(self) -> set[tuple[int, int]]:
        """Paste afresh the frames not within FINISH_MOVED_PX of their final places, and nothing else; return the
        tiles changed. After a run ahead the final places are in the canvas's units refitted to them (_fitted_units),
        so that a change of the gauge and of frame 0's rest centre alone moves no frame: mosaic.json's px_per_mm and
        origin_px carry it. The tiles they cover (pasted and final) are emptied and made again from every frame over
        them, in index order, as a whole restitch makes them (a frame that did not move stays where it is pasted); or,
        when that is dearer than moving each moved frame (MOVE_COST pastes: a finish run ahead left few to move),
        those frames are moved in place (_move_pasted)."""
        self.stale = {}
        if self.ahead is not None:  # else the canvas lags the live places by up to LIVE_REPASTE_PX: no gain
            self.canvas.units = IDENTITY
            final = self._onto_canvas(self.stitch_places(), FINISH_MOVED_PX)
        else:
            final = self.stitch_places()
        moved = [i for i in sorted(set(final) | set(self.pasted)) if self._moved(self._pasted_place(i), final.get(i))]
        self.finish_pasted_again = len(moved)
        tiles: set[tuple[int, int]] = set()
        for i in moved:
            for place in (self._pasted_place(i), final.get(i)):
                if place is not None:
                    tiles.update(self._footprint(place[0]))
        if not tiles:
            return set()
        staying = set(self.pasted).difference(moved)
        places = {i: place for i in staying if (place := self._pasted_place(i)) is not None}
        places.update((i, final[i]) for i in moved if i in final)
        over = {i: places[i] for i in sorted(places) if not tiles.isdisjoint(self._footprint(places[i][0]))}
        if MOVE_COST * len(moved) < len(over):
            return self._move_pasted(moved, final)
        for i in moved:
            self._record_pasted(i, None)
        emptied = {key for key in tiles if self.canvas.tiles.pop(key, None) is not None}
        return emptied | self._paste_in_order(over, only=tiles)

    def _move_pasted(self, moved: list[int], final: dict[int, Place]) -> set[tuple[int, int]]:
        """Remove the frames `moved` from where they are pasted and paste them at their places in `final` (absent:
        not pasted); return the tiles changed. A frame's planes built once (when its undone drag is the same at both
        places) and warped twice, where emptying their tiles and pasting every frame over them again
        (_restitch_moved) costs one paste a frame over those tiles: cheaper when fewer than 1 / MOVE_COST of them
        moved. The sums are a whole restitch's to float32 rounding (the removed planes are the pasted ones, rebuilt
        the same). Warped up to RESTITCH_AHEAD frames ahead on two threads, as _paste_in_order."""

        def warp(i: int) -> list[tuple[Warped | None, float]]:
            old, new = self._pasted_place(i), final.get(i)
            parts: list[tuple[Warped | None, float]] = []
            built: dict[tuple[complex, float], FrameLayers] = {}
            for place, sign in ((old, -1.0), (new, 1.0)):
                if place is not None:
                    if place[1] not in built:
                        built[place[1]] = self._planes(i, place[1], remember=False)
                    parts.append((self.canvas.warp(built[place[1]], place[0]), sign))
            return parts

        touched: set[tuple[int, int]] = set()
        for i, parts in zip(moved, in_order_ahead(warp, moved, ahead=RESTITCH_AHEAD), strict=True):
            self.heartbeat()
            for warped, sign in parts:
                if warped is not None:
                    touched.update(self.canvas.add(warped, sign))
            self._record_pasted(i, final.get(i))
        return touched

    def stitch_places(self) -> dict[int, Place]:
        """Return, in index order, each pasteable frame's stitch affine (rectified frame mm -> mosaic mm, 2x3) and the
        drag its planes undo (mm, profile width mm), as they are now: where a restitch would paste it."""
        return {
            i: (pose, self._drag_state(i)) for i in sorted(self.frames) if (pose := self._stitch_pose(i)) is not None
        }

    def _onto_canvas(self, places: dict[int, Place], moved_px: float) -> dict[int, Place]:
        """Return stitch places given in the path's units (identity) mapped onto the canvas, whose units become
        those that leave the fewest frames moved by `moved_px` or more from where they are pasted (_fitted_units)."""
        self.canvas.units = self._fitted_units(places, moved_px)
        return {i: (self.canvas.units.on_canvas(affine), drag) for i, (affine, drag) in places.items()}

    def _fitted_units(self, places: dict[int, Place], moved_px: float) -> CanvasUnits:
        """Return the canvas units that map `places` (stitch places at identity units) onto where their frames are
        pasted with the fewest frames to paste again (moved by `moved_px` or more): the one scale and shift of the whole
        canvas that fits them best (canvas_units.fit_units), or the identity when that leaves no fewer."""
        both = [i for i in places if i in self.pasted]
        path_px = np.array([self.corners_px(places[i][0]) for i in both]).reshape(-1, 4)
        canvas_px = np.array([self.corners_px(self.pasted[i]) for i in both]).reshape(-1, 4)
        units = fit_units(path_px, canvas_px, self.calibration.px_per_mm)
        if units == IDENTITY:
            return units
        scaled = units.scale * path_px + complex(*units.origin_px(self.calibration.px_per_mm))
        pasted = [(self.pasted[i], self.pasted_drag.get(i, NO_DRAG)) for i in both]
        drags = np.array([self.drag_shift_px(old, places[i]) for old, i in zip(pasted, both, strict=True)])
        fitted = np.count_nonzero(np.abs(scaled - canvas_px).max(axis=1) + drags >= moved_px)
        kept = np.count_nonzero(np.abs(path_px - canvas_px).max(axis=1) + drags >= moved_px)
        return units if fitted < kept else IDENTITY

    def _pasted_place(self, index: int) -> Place | None:
        """Return the stitch affine a frame is pasted with and the drag its planes undid, or None (not pasted)."""
        pose = self.pasted.get(index)
        return None if pose is None else (pose, self.pasted_drag.get(index, NO_DRAG))

    def _moved(self, old: Place | None, new: Place | None) -> bool:
        """Return True when a frame pasted at `old` (None: not pasted) must be pasted again for `new`: pasted or not,
        or moved by FINISH_MOVED_PX mosaic pixels or more (moved_px)."""
        if old is None or new is None:
            return old is not new
        return self.moved_px(old, new) >= FINISH_MOVED_PX

    def corners_px(self, affine: np.ndarray) -> np.ndarray:
        """Return the (4,) canvas positions (complex, mosaic px) of the corners of a frame pasted with the stitch
        affine `affine` (rectified frame mm -> mosaic mm, 2x3): where an affine moves a frame most."""
        calib = self.calibration
        w, h = calib.image_size
        corners = np.array([[0, 0, 1], [w, 0, 1], [0, h, 1], [w, h, 1]], float).T
        on_canvas = self.canvas.pixels_to_canvas(affine, calib.principal_point, calib.px_per_mm) @ corners
        return on_canvas[0] + 1j * on_canvas[1]

    def drag_shift_px(self, old: Place, new: Place) -> float:
        """Return the most (mosaic px) a change of a frame's undone drag from place `old` to `new` shifts a pixel:
        D phi with phi <= 1 (physics.drag), so |D1 - D0| on one profile, |D0| + |D1| across two, through the new
        affine's largest stretch."""
        (d0, w0), (d1, w1) = old[1], new[1]
        drag_mm = abs(d1 - d0) if w0 == w1 or 0 in (d0, d1) else abs(d0) + abs(d1)
        calib = self.calibration
        affine = self.canvas.pixels_to_canvas(new[0], calib.principal_point, calib.px_per_mm)
        return drag_mm * calib.px_per_mm * float(np.linalg.norm(affine[:, :2], 2))

    def moved_px(self, old: Place, new: Place) -> float:
        """Return how far (mosaic px) a frame pasted at place `old` moves when pasted at `new`: its farthest corner's
        move plus the most its undone drag's change shifts a pixel (the finish's rule against FINISH_MOVED_PX)."""
        corner = float(np.max(np.abs(self.corners_px(new[0]) - self.corners_px(old[0]))))
        return corner + self.drag_shift_px(old, new)

    def _footprint(self, pose: np.ndarray) -> list[tuple[int, int]]:
        """Return the canvas tiles a frame pasted with the stitch affine `pose` may cover."""
        calib = self.calibration
        w, h = calib.image_size
        return self.canvas.footprint_tiles(
            self.canvas.pixels_to_canvas(pose, calib.principal_point, calib.px_per_mm), (h, w)
        )

    def _paste_in_order(
        self, places: dict[int, Place], only: set[tuple[int, int]] | None = None
    ) -> set[tuple[int, int]]:
        """Paste frames at their places (index order: the same sums a whole restitch makes), within `only` (None:
        anywhere); return the tiles touched.

        Each frame's planes are built and warped up to RESTITCH_AHEAD frames ahead on two threads (decoding and
        OpenCV free the GIL), and added to the tiles here in order; the remembered planes (built with the drag now
        learned) are read, never changed, from the threads.
        """

        def warp(i: int) -> Warped | None:
            pose, drag = places[i]
            return self.canvas.warp(self._planes(i, drag, remember=False), pose, only)

        touched: set[tuple[int, int]] = set()
        for i, warped in zip(places, in_order_ahead(warp, list(places), ahead=RESTITCH_AHEAD), strict=True):
            self.heartbeat()
            if warped is not None:
                touched.update(self.canvas.add(warped))
            self._record_pasted(i, places[i])
        return touched

    def learned_model(self) -> dict[str, Any]:
        """Return what the scan taught about the tissue and the probe (mosaic.json and report.json "tissue").

        The calibration's priors, the fitted view model (effective kappa with its 68 % range, tissue anisotropy,
        services.core.physics.tissue_model; kappa_source "images", or "imu+images" with the IMU's kappa) once
        fitted, and the compliance fit once finished: E in kPa, gauge, and the strain law (linear or stiffening:
        zero-load compliance, half-strain load with 68 % ranges; compliance.py).
        """
        calib = self.calibration
        doc: dict[str, Any] = {
            "kappa_prior_n_per_mm": calib.hooke_n_per_mm,
            "young_modulus_prior_kpa": calib.young_modulus_kpa,
        }
        if self.registrar.corrections.view_fit is not None:
            doc.update(self.registrar.corrections.view_fit.to_dict())
            reference = self.registrar.corrections.kappa_reference
            doc["kappa_source"] = "imu+images" if reference is not None else "images"
            if reference is not None:  # kappa of the IMU's tilts against the force differences: the fit's prior
                doc["kappa_imu_n_per_mm"] = reference.hooke_n_per_mm
                doc["kappa_imu_samples"] = reference.n_samples
                doc["kappa_imu_residual_n"] = reference.residual_rms_n
        if self.clock is not None:
            doc.update(self.clock.to_dict())
        if self.registrar.corrections.drag_fit is not None:
            doc.update(self.registrar.corrections.drag_fit.to_dict())
        if self.compliance is not None:
            doc["compliance_per_n"] = self.compliance.compliance_per_n
            doc["young_modulus_kpa"] = self.compliance.young_modulus_kpa(calib.poisson_ratio, calib.scanner_area_m2)
            doc["gauge"] = self.compliance.gauge
            doc["compliance_residual_rms"] = self.compliance.residual_rms
            doc.update(self.compliance.law_dict())
        # strict JSON (mosaic.json, report.json): an unbounded range or an unfitted value is null, never inf or NaN
        return {k: None if isinstance(v, float) and not math.isfinite(v) else v for k, v in doc.items()}

    def _tilts_deg(self, kept: Sequence[KeptFrame]) -> np.ndarray:
        """Return (N, 2) frames' (tilt_x, tilt_y) in degrees: spec §2 with the fitted kappa, else the calibration's."""
        fit = self.registrar.corrections.view_fit
        if not kept:
            return np.zeros((0, 2))
        if fit is None:
            return np.degrees([[k.load.theta_x_rad, k.load.theta_y_rad] for k in kept])
        forces = np.array([k.forces_n for k in kept], np.float64)
        return np.degrees(tilt_angles_rad(forces, fit.kappa_n_per_mm, self.calibration.sensor_separation_mm))

    def edge_yaws(self) -> np.ndarray:
        """Return the main map's pose-graph edges as (E, 6) float64 rows: frame i, frame j, the relative yaw (deg) the
        edge measures between the undeformed frames (as the graph uses it: view and drag corrections applied), 1 for
        a loop closure (0 otherwise), the SD (deg) the graph weighs that yaw with (pose_graph.edge_yaw_sigma_deg) and
        the mean load F_Z of its two frames (N): what a tracker's yaw can check edge by edge (outputs.evaluation)."""
        reg = self.registrar
        edges = reg.corrections.undeformed(reg.edges, reg.poses)
        sigmas = edge_yaw_sigma_deg(edges)
        load = {i: kept.load.fz_n for i, kept in self.frames.items()}  # every frame added is kept, placed or not
        rows = [
            (e.i, e.j, math.degrees(np.angle(e.relative.a)), float(e.loop), s, (load[e.i] + load[e.j]) / 2)
            for e, s in zip(edges, sigmas, strict=True)
        ]
        return np.array(rows, np.float64).reshape(-1, 6)

    def path_rows(self) -> list[PathRow]:
        """Return one PathRow per frame seen so far (spec §4), in index order."""
        poses = self.final_poses() if self.finished else self.registrar.poses
        if self.ahead is not None and not self.finished:  # live: in the units of the mosaic kept at the run's places
            poses = {i: self.ahead.output_pose(p) for i, p in poses.items()}
        indices = sorted(self.results)
        kept = [self.frames[i] for i in indices if i in self.frames]
        tilts = iter(self._tilts_deg(kept))  # in the order of the frames kept, one vectorised call
        rows = []
        for index in indices:
            r = self.results[index]
            pf = self.frames.get(index)
            pose = poses.get(index) if r.status == STATUS_OK else None
            drag = pose.a * self._drag(index) if pose else complex(math.nan, math.nan)  # the path's axes, mm
            centre = pose.t - drag if pose else complex(math.nan, math.nan)  # where the skin under it rests
            x, y, yaw = (centre.real, centre.imag, math.degrees(pose.yaw_rad)) if pose else (math.nan,) * 3
            tilt_x, tilt_y = next(tilts) if pf else (math.nan, math.nan)
            rows.append(
                PathRow(
                    seq=pf.seq if pf else index,
                    t_s=pf.t_s if pf else math.nan,
                    x_mm=x,
                    y_mm=y,
                    yaw_deg=yaw,
                    fz_n=pf.load.fz_n if pf else math.nan,
                    tilt_x_deg=float(tilt_x),
                    tilt_y_deg=float(tilt_y),
                    stretch=pf.stretch if pf else math.nan,
                    inliers=r.inliers,
                    status=r.status,
                    reason=r.reason,
                    stroke=self.strokes.get(index),
                    drag_x_mm=drag.real,
                    drag_y_mm=drag.imag,
                )
            )
        return rows


def _with_own_containers(state: Any) -> Any:
    """Return a shallow copy of a dataclass whose dict, list and set fields are copies too (their items shared, as
    values a refinement replaces and never changes in place): what a finish run on it may change is its own."""
    twin = copy.copy(state)
    for f in dataclasses.fields(state):
        value = getattr(state, f.name)
        if isinstance(value, dict | list | set):
            setattr(twin, f.name, copy.copy(value))
    return twin
