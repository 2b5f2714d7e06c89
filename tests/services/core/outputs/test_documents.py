"""The two mosaic.json documents (services/core/outputs/documents.py): the folder's and the service's share parts;
the frame counts (frame_counts), the same in mosaic.json and report.json."""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

from services.core.mosaic.canvas import MosaicImage
from services.core.mosaic.deepzoom import DziGeometry
from services.core.outputs.documents import empty_revisions, folder_mosaic_json, frame_counts, mosaic_json
from services.core.outputs.session_report import build_session_report
from services.core.path_rows import PathRow, PlacedCounts
from services.core.physics.compliance import ComplianceFit

IMAGE = MosaicImage(
    vein=np.zeros((60, 80), np.uint8),
    force_n=np.full((60, 80), np.nan, np.float32),
    coverage=np.zeros((60, 80), np.uint16),
    px_per_mm=8.0,
    origin_px=(20.0, 30.0),
).meta()
FIT = ComplianceFit(compliance_per_n=0.006, gauge=1.002, residual_rms=0.001, n_frames=40)
TISSUE = {"kappa_n_per_mm": 0.15}


def test_the_folders_mosaic_json_is_the_spec_image_part_with_the_fit_and_the_digest() -> None:
    doc = folder_mosaic_json(IMAGE, method="best", compliance=FIT, tissue=TISSUE, scan_digest="ab" * 16)
    assert doc["px_per_mm"] == 8.0 and doc["origin_px"] == [20.0, 30.0] and (doc["width"], doc["height"]) == (80, 60)
    assert doc["method"] == "best" and doc["compliance_per_n"] == 0.006 and doc["gauge"] == 1.002
    assert doc["tissue"] == TISSUE and doc["scan_digest"] == "ab" * 16
    json.dumps(doc, allow_nan=False)
    bare = folder_mosaic_json(IMAGE, method="paper")
    assert not {"compliance_per_n", "gauge", "tissue", "scan_digest"} & set(bare)


def _served(rows: list[PathRow], **fields: Any) -> dict[str, Any]:
    """Return the service's mosaic.json of rows (an empty image)."""
    return mosaic_json(
        IMAGE,
        version=1,
        results_version=1,
        revisions=empty_revisions(),
        geometry=DziGeometry.for_mosaic(8.0),
        extent_mm=None,
        rows=rows,
        status="receiving",
        method="best",
        **fields,
    )


def test_the_service_and_the_folder_agree_on_every_key_they_share() -> None:
    folder = folder_mosaic_json(IMAGE, method="best", compliance=FIT, tissue=TISSUE)
    served = _served([], compliance=FIT, tissue=TISSUE)
    assert set(folder) <= set(served)
    assert {k: served[k] for k in folder} == folder


def _row(seq: int, status: str = "ok", reason: str = "") -> PathRow:
    """Return a path row of frame seq with a status and reason (placed at x = seq mm when ok)."""
    x = float(seq) if status == "ok" else math.nan
    return PathRow(seq, 0.1 * seq, x, 0.0 if status == "ok" else math.nan, 0.0, 5.0, 0.0, 0.0, 1.0, 50, status, reason)


# 6 placed, a lost frame, one waiting in a fragment, one rejected as blurred, one taken off the skin
ROWS = [
    *(_row(i) for i in range(6)),
    _row(6, "lost", "few_inliers"),
    _row(7, "lost", "unjoined_fragment"),
    _row(8, "rejected", "blur"),
    _row(9, "rejected", "no_contact"),
]


def test_frame_counts_split_the_placed_frames_into_keyframes_and_tracked() -> None:
    # offline (nothing tracked) every placed frame is a keyframe; a live session behind its uploads passes how many
    # of its placed frames it tracked without features (SessionReconstruction.tracked_count): ok = keyframes + tracked
    base = {"processed": 10, "ok": 6, "lost": 2, "rejected": 2, "no_contact": 1, "in_fragments": 1}
    assert frame_counts(ROWS) == {**base, "keyframes": 6, "tracked": 0, "stitched": 6}
    assert frame_counts(ROWS, PlacedCounts(tracked=4)) == {**base, "keyframes": 2, "tracked": 4, "stitched": 6}
    nine = frame_counts(ROWS, PlacedCounts(tracked=9))
    assert nine["tracked"] == 6 and nine["keyframes"] == 0  # at most the placed
    assert frame_counts([]) == dict.fromkeys([*base, "keyframes", "tracked", "stitched"], 0)


def test_frame_counts_count_the_placed_frames_stitched_into_the_mosaic() -> None:
    # a session passes how many placed frames it pasted (SessionReconstruction.stitched_count: not those over skin
    # already shown, nor blurred ones); results from before the count (None) give every placed frame; at most ok
    four = PlacedCounts(stitched=4)
    assert frame_counts(ROWS, four)["stitched"] == 4
    assert frame_counts(ROWS)["stitched"] == 6
    assert frame_counts(ROWS, PlacedCounts(stitched=9))["stitched"] == 6
    assert frame_counts(ROWS, PlacedCounts(stitched=-1))["stitched"] == 0
    assert _served(ROWS, placed=four)["frames"]["stitched"] == 4
    assert build_session_report(ROWS, None, None, draw=False, placed=four).doc["frames"]["stitched"] == 4


def test_mosaic_json_report_json_and_the_events_count_the_tracked_frames_alike() -> None:
    # one owner: mosaic.json's frames (which the progress, done and version events spread) and report.json's frames
    # take keyframes and tracked from frame_counts
    served = _served(ROWS, placed=PlacedCounts(tracked=4))
    assert served["frames"] == frame_counts(ROWS, PlacedCounts(tracked=4))
    assert _served(ROWS)["frames"]["tracked"] == 0 and _served(ROWS)["frames"]["keyframes"] == 6
    report = build_session_report(ROWS, None, None, draw=False, placed=PlacedCounts(tracked=4)).doc["frames"]
    assert (report["keyframes"], report["tracked"], report["ok"]) == (2, 4, 6)
    offline = build_session_report(ROWS, None, None, draw=False).doc["frames"]
    assert (offline["keyframes"], offline["tracked"]) == (6, 0)
