"""The path row in one place (services/core/path_rows.py): its spec §4 columns, path.csv with blank cells and
path.json with nulls for frames not placed, the round trip back from path.json, a rejected frame's row, the stored
time a row without one takes, and a progress event's path tail."""

from __future__ import annotations

import csv
import io
import json
import math

import pytest

from services.core.path_rows import (
    PATH_COLUMNS,
    UNCOUNTED,
    PathRow,
    PlacedCounts,
    path_csv,
    path_row_from_json,
    path_rows_from_json,
    path_rows_json,
    path_tail,
    rejected_row,
    with_stored_times,
)
from services.core.registration.outcome import REASON_BAD_FRAME, REASON_NO_CONTACT, STATUS_REJECTED

NAN = math.nan


def three_rows() -> list[PathRow]:
    """Return three rows: placed at the origin, lost, placed (shared with tests/services/store)."""
    return [
        PathRow(0, 0.0, 0.0, 0.0, 0.0, 3.25, 0.1, -0.2, 0.021, 300, "ok"),
        PathRow(1, 0.05, NAN, NAN, NAN, 4.0, 0.0, 0.0, 0.026, 0, "lost", "few_inliers"),
        PathRow(2, 0.1, 1.23456, -2.5, 1.5, 5.0, 0.0, 0.0, 0.032, 250, "ok"),
    ]


def test_path_csv_columns_and_blank_cells() -> None:
    text = path_csv(three_rows())
    table = list(csv.reader(io.StringIO(text)))
    assert tuple(table[0]) == PATH_COLUMNS
    assert PATH_COLUMNS == (
        "seq",
        "t_s",
        "x_mm",
        "y_mm",
        "yaw_deg",
        "fz_n",
        "tilt_x_deg",
        "tilt_y_deg",
        "stretch",
        "inliers",
        "status",
        "reason",
        "stroke",
        "drag_x_mm",
        "drag_y_mm",
    )  # spec §4 in its order, with why a frame was not placed after its status (issue 6: never fail silently)
    assert len(table) == 4
    assert table[2][2:5] == ["", "", ""]  # the lost frame has no position
    assert table[2][-5:] == ["lost", "few_inliers", "", "", ""] and table[2][0] == "1"  # no stroke, no drag: blank
    assert table[3][2] == "1.2346"  # 4 decimals: 0.1 um, far below any accuracy the probe reaches


def test_path_json_uses_null_for_unregistered() -> None:
    doc = path_rows_json(three_rows())
    assert list(doc[0]) == list(PATH_COLUMNS)
    assert doc[1]["x_mm"] is None and doc[1]["status"] == "lost"
    assert doc[2]["x_mm"] == pytest.approx(1.23456)
    json.dumps(doc, allow_nan=False)  # strict JSON: no NaN leaks


def _same(a: PathRow, b: PathRow) -> bool:
    """Return True when two rows are equal, a NaN equal to a NaN."""

    def equal(x: object, y: object) -> bool:
        both_nan = isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y)
        return x == y or both_nan

    return all(equal(getattr(a, c), getattr(b, c)) for c in PATH_COLUMNS)


def test_path_json_reads_back_as_the_rows_it_was_made_of() -> None:
    rows = [*three_rows(), PathRow(3, 0.15, 2.0, -2.0, 0.5, 5.5, 0.0, 0.0, 0.03, 120, "ok", "", 1)]
    doc = json.loads(json.dumps(path_rows_json(rows)))  # through strict JSON text, as path.json is stored
    back = path_rows_from_json(reversed(doc))  # sorted by seq whatever the order read
    assert [r.seq for r in back] == [0, 1, 2, 3]
    assert all(_same(a, b) for a, b in zip(rows, back, strict=True))
    assert back[3].stroke == 1 and back[0].stroke is None
    # a row written before reason and stroke existed reads with their defaults
    old = {c: doc[1][c] for c in PATH_COLUMNS if c not in ("reason", "stroke")}
    assert path_row_from_json(old).reason == "" and path_row_from_json(old).stroke is None


def test_a_rejected_frame_has_no_pose_and_says_why() -> None:
    row = rejected_row(7, 0.7)
    assert (row.seq, row.t_s, row.status, row.reason, row.inliers) == (7, 0.7, STATUS_REJECTED, REASON_BAD_FRAME, 0)
    assert all(math.isnan(getattr(row, c)) for c in ("x_mm", "y_mm", "yaw_deg", "fz_n", "stretch"))
    assert math.isnan(rejected_row(8).t_s) and rejected_row(8, reason=REASON_NO_CONTACT).reason == REASON_NO_CONTACT
    assert path_rows_json([row])[0]["x_mm"] is None and path_csv([row]).splitlines()[1].split(",")[2] == ""


def test_a_row_without_a_time_takes_the_stored_one() -> None:
    rows = [rejected_row(0), rejected_row(1, 0.1), rejected_row(2)]
    timed = with_stored_times(rows, {0: 0.0, 1: 9.9})
    assert timed[0].t_s == 0.0  # had none: the stored time
    assert timed[1].t_s == 0.1  # had its own: kept
    assert math.isnan(timed[2].t_s)  # none stored either


def test_the_path_tail_lists_the_rows_asked_for_by_seq() -> None:
    rows = [*three_rows(), PathRow(3, 0.15, 2.0, -2.0, 0.5, 5.5, 0.0, 0.0, 0.03, 120, "ok", "", 1)]
    assert path_tail(rows, [3, 1, 3, 9]) == [  # repeated and unknown seqs: once, or not at all
        [1, None, None, "lost", None, "few_inliers"],
        [3, 2.0, -2.0, "ok", 1, ""],
    ]
    json.dumps(path_tail(rows, range(4)), allow_nan=False)  # strict JSON: no NaN leaks into an event


def test_placed_counts_read_back_from_a_documents_counts_and_from_older_ones() -> None:
    # mosaic.json's "frames" carries tracked and stitched; a stored report is rebuilt from them (stored_report), and
    # results written before either count lack its key: nothing tracked, the stitched frames not counted
    assert PlacedCounts.from_frames({"ok": 6, "keyframes": 2, "tracked": 4, "stitched": 5}) == PlacedCounts(4, 5)
    assert PlacedCounts.from_frames({"ok": 6, "tracked": 4}) == PlacedCounts(4, None)
    assert PlacedCounts.from_frames({"ok": 6}) == PlacedCounts.from_frames(None) == UNCOUNTED == PlacedCounts(0, None)
