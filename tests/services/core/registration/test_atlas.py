"""The atlas: a landing is relocalised on the map wherever it is; frames that match nothing placed chain into a
fragment, which joins the map by one similarity once one of its frames overlaps it (real frames of the shared
clinical scan's first stroke, fed out of their order of capture)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from services.core.methods import method_options
from services.core.pipeline import frame_forces, prepare_scan_frame, window_setup
from services.core.registration.atlas import Atlas
from services.core.registration.frame_prep import PreparedFrame
from services.core.registration.outcome import REASON_FRAGMENT, STATUS_LOST, STATUS_OK
from services.core.registration.registrar import Registrar
from services.core.session_reconstruction import SessionReconstruction
from tests.shared_scans import SHARED_CLINICAL, clinical_until

pytestmark = pytest.mark.skipif(
    not SHARED_CLINICAL.is_dir(), reason="the shared reference scans are not on this machine"
)

# Frames placed through a join are tied to the map by the join's edge and those that follow; on the shared scan's
# first stroke the whole stroke is within 0.3 mm of the tracker (drag 0.1-0.3 mm under load, see docs/accuracy.md):
# 0.6 mm leaves room for the join and fails a join off by a vein's width (~1 mm) or a wrong one.
JOINED_MAX_ERROR_MM = 0.6


Stroke = tuple[dict[int, PreparedFrame], dict[int, tuple[complex, float]]]


@pytest.fixture(scope="module")
def stroke() -> Stroke:
    """Return the first stroke's prepared frames and tracker (position mm as x + iy, yaw rad) by seq."""
    scan = clinical_until(42)
    options = method_options("best")
    forces, (mask, flat) = frame_forces(scan), window_setup(scan, options)
    frames = {int(scan.frame_seq[i]): prepare_scan_frame(scan, i, forces[i], mask, flat, options)
              for i in range(len(scan))}  # fmt: skip
    yaw = np.radians(scan.reference_angles_deg[:, 0])
    reference = {int(s): (complex(*r), a) for s, r, a in zip(scan.frame_seq, scan.reference_mm, yaw, strict=True)}
    return frames, reference


WINDOW_RADIUS_MM = 37.0  # the shared scans' window: 80 x 60 mm less its rounded corners


def _atlas() -> Atlas:
    options = method_options("best")
    return Atlas(lambda: Registrar(options, 8.0, WINDOW_RADIUS_MM, centre_px=(320.0, 240.0)), WINDOW_RADIUS_MM)


def _feed(frames: dict[int, PreparedFrame], seqs: list[int]) -> list[PreparedFrame]:
    """Return the frames of `seqs` re-indexed 0, 1, ... in that order, their times increasing (a new capture)."""
    return [dataclasses.replace(frames[s], index=k, t_s=0.1 * k) for k, s in enumerate(seqs)]


def test_a_landing_is_relocalised_where_no_motion_predicts_it(stroke: Stroke) -> None:
    frames, _ = stroke
    atlas = _atlas()
    # the stroke's first part, then the probe set down 5 frames (19 mm) further on: a landing, no prediction
    seqs = [s for s in range(0, 16) if s in frames] + [20, 21]
    results = [atlas.add(pf, landing=(k == len(seqs) - 2)) for k, pf in enumerate(_feed(frames, seqs))]
    assert all(r.result.status == STATUS_OK and r.on_main for r in results)
    assert len(atlas.maps) == 1 and atlas.main.run_start == len(seqs) - 2  # no velocity across the jump


def test_a_fragment_chains_then_joins_and_every_frame_is_placed(stroke: Stroke) -> None:
    frames, reference = stroke
    scan = clinical_until(0)
    session = SessionReconstruction(scan.calibration, method_options("best"), WINDOW_RADIUS_MM)
    # the map: the stroke's end (x 100-160 mm); then the probe lands at its start (x 0: no overlap) and strokes on
    end = [s for s in range(31, 43) if s in frames]
    start = [s for s in range(0, 25) if s in frames]
    seqs = end + start
    results = [session.add(pf)[0] for pf in _feed(frames, seqs)]
    first = results[len(end)]
    assert first.status == STATUS_LOST and first.reason == REASON_FRAGMENT  # it overlaps nothing placed
    assert len(session.atlas.maps) == 1  # ... the fragment joined the map later
    assert [i for i, r in enumerate(results) if set(r.moved) >= {len(end)}]  # the join moved its frames
    session.finish()
    rows = session.path_rows()
    assert all(r.status == STATUS_OK for r in rows)
    # positions against the tracker, both in the map's origin (the stroke end's first frame: its centre and axes)
    origin, yaw = reference[end[0]]
    estimate = np.array([complex(r.x_mm, r.y_mm) for r in rows])
    truth = np.array([(reference[s][0] - origin) * np.exp(-1j * yaw) for s in seqs])
    assert np.max(np.abs(estimate - truth)) <= JOINED_MAX_ERROR_MM, np.round(np.abs(estimate - truth), 2)


def _fragmented(frames: dict[int, PreparedFrame], dragged_map: int | None) -> tuple[Atlas, list[PreparedFrame]]:
    """Return an atlas holding the stroke's end and, after a landing at its start (no overlap), a fragment of one
    frame; `dragged_map` (0 the main map, 1 the fragment, None neither) has found the skin dragged. Also return
    the start's frames still to feed."""
    end = [s for s in range(31, 43) if s in frames]
    start = [s for s in range(0, 25) if s in frames]
    fed = _feed(frames, end + start)
    atlas = _atlas()
    for pf in fed[: len(end)]:
        atlas.add(pf, landing=False)
    if dragged_map == 0:
        atlas.main.drag_evident = True
    atlas.add(fed[len(end)], landing=True)
    assert len(atlas.maps) == 2  # the landing overlaps nothing placed: a fragment
    if dragged_map == 1:
        atlas.maps[1].drag_evident = True
    return atlas, fed[len(end) + 1 :]


def test_a_fragment_begun_after_a_lift_knows_the_skin_is_dragged(stroke: Stroke) -> None:
    frames, _ = stroke
    atlas, _ = _fragmented(frames, dragged_map=0)
    assert atlas.maps[1].drag_evident  # the patient's skin: the fragment's closures get the looser gate too
    atlas, _ = _fragmented(frames, dragged_map=None)
    assert not any(m.drag_evident for m in atlas.maps)  # nothing found: nothing assumed


def test_a_drag_a_fragment_found_reaches_the_main_map(stroke: Stroke) -> None:
    frames, _ = stroke
    atlas, rest = _fragmented(frames, dragged_map=1)
    atlas.add(rest[0], landing=False)
    assert atlas.main.drag_evident
    for pf in rest[1:]:  # ... and stays with it when the fragment joins the map
        atlas.add(pf, landing=False)
    assert len(atlas.maps) == 1 and atlas.main.drag_evident
