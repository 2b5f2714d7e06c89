"""The path row (spec §4): one row per frame of a session, its CSV columns and its JSON form, in one place.

PathRow is what a reconstruction says of each frame: when it was taken, where it was placed (x, y, yaw; NaN
when it was not), the load and tilts, its status and why, and its stroke. path.json holds path_rows_json's dicts
(null where a value is not finite), path.csv path_csv's text (blank cells there), a progress event the
path_tail of the rows it changed. The core builds the rows (SessionReconstruction.path_rows), the store writes
them, the workers and the API read them back with path_rows_from_json. PlacedCounts carries what the rows do not
say of their placed frames (how many were tracked, how many stitched), for the frame counts
(outputs.documents.frame_counts).
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from services.core.registration.outcome import REASON_BAD_FRAME, STATUS_REJECTED

PATH_COLUMNS = (
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
    "reason",  # this project's: why a frame was not placed (the spec's columns keep their order around it)
    "stroke",
    "drag_x_mm",  # the skin's friction drag under the window's centre (physics.drag), the path's axes
    "drag_y_mm",
)
_FLOAT_COLUMNS = frozenset(
    {"t_s", "x_mm", "y_mm", "yaw_deg", "fz_n", "tilt_x_deg", "tilt_y_deg", "stretch", "drag_x_mm", "drag_y_mm"}
)


@dataclass(frozen=True)
class PathRow:
    """One row of the path (spec §4); x, y, yaw are NaN for frames that were not registered."""

    seq: int
    t_s: float
    x_mm: float
    y_mm: float
    yaw_deg: float
    fz_n: float
    tilt_x_deg: float
    tilt_y_deg: float
    stretch: float
    inliers: int
    status: str
    reason: str = ""  # why a frame is lost or rejected (services.core.registration.outcome.REASONS); "" when ok
    stroke: int | None = None  # the run of contact frames it belongs to, from 0; None off the skin or missing
    # the skin under the window's centre displaced by friction (mm, the path's axes): x_mm, y_mm are where it
    # rests; NaN where the frame is not placed, 0 where no drag was learned (the scan's evidence did not keep it)
    drag_x_mm: float = math.nan
    drag_y_mm: float = math.nan


@dataclass(frozen=True)
class PlacedCounts:
    """What the path rows do not say of their placed frames: how many were tracked on a keyframe without features
    (SessionReconstruction.tracked_count: a live session behind its uploads, or a method with track_overlap; 0
    offline by default), and how many are pasted into the mosaic (SessionReconstruction.stitched_count: not blurred,
    not over skin already shown by MethodOptions.stitch_cover_cap stitched frames; None: not counted, results from
    before the count)."""

    tracked: int = 0
    stitched: int | None = None

    @classmethod
    def from_frames(cls, frames: Mapping[str, Any] | None) -> PlacedCounts:
        """Return the counts a document's frame counts carry (mosaic.json's "frames"; tracked 0 and stitched None where
        results from before them lack the keys)."""
        frames = frames or {}
        stitched = frames.get("stitched")
        return cls(int(frames.get("tracked", 0)), None if stitched is None else int(stitched))


UNCOUNTED = PlacedCounts()  # nothing tracked, the stitched frames not counted (every placed frame, frame_counts)


def rejected_row(seq: int, t_s: float = math.nan, reason: str = REASON_BAD_FRAME) -> PathRow:
    """Return the path row of a frame that could not be processed (status rejected, no pose)."""
    nan = math.nan
    return PathRow(int(seq), float(t_s), nan, nan, nan, nan, nan, nan, nan, 0, STATUS_REJECTED, reason)


def with_stored_times(rows: Sequence[PathRow], times: Mapping[int, float]) -> list[PathRow]:
    """Return the rows with the stored time of `times` where a row has none (a frame registered without a prepared
    frame, e.g. lost before it was prepared)."""
    return [replace(r, t_s=times[r.seq]) if not math.isfinite(r.t_s) and r.seq in times else r for r in rows]


# ----- JSON: path.json --------------------------------------------------------------------------------------------
def path_rows_json(rows: Sequence[PathRow]) -> list[dict[str, Any]]:
    """Return path rows as spec §4 dicts (null where a value is not finite, i.e. the frame was not placed)."""
    out = []
    for r in rows:
        d: dict[str, Any] = {}
        for c in PATH_COLUMNS:
            v = getattr(r, c)
            if isinstance(v, float | np.floating):
                v = float(v) if math.isfinite(v) else None
            elif isinstance(v, np.integer):
                v = int(v)
            d[c] = v
        out.append(d)
    return out


def path_row_from_json(d: Mapping[str, Any]) -> PathRow:
    """Return the PathRow of one path.json dict (null numbers become NaN)."""
    values: dict[str, Any] = {}
    for c in PATH_COLUMNS:
        v = d.get(c)
        if c in _FLOAT_COLUMNS:
            v = math.nan if v is None else float(v)
        values[c] = v
    values["seq"] = int(values["seq"])
    values["inliers"] = int(values["inliers"] or 0)
    values["status"] = str(values["status"])
    values["reason"] = str(values.get("reason") or "")
    values["stroke"] = None if values.get("stroke") is None else int(values["stroke"])
    return PathRow(**values)


def path_rows_from_json(docs: Iterable[Mapping[str, Any]]) -> list[PathRow]:
    """Return the PathRows of path.json dicts, sorted by seq."""
    return sorted((path_row_from_json(d) for d in docs), key=lambda r: r.seq)


def _num(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def path_tail(rows: Sequence[PathRow], seqs: Iterable[int]) -> list[list[Any]]:
    """Return the event's path tail: [seq, x_mm or None, y_mm or None, status, stroke or None, reason] of the rows
    of `seqs`, by seq."""
    by_seq = {r.seq: r for r in rows}
    return [
        [s, _num(r.x_mm), _num(r.y_mm), r.status, r.stroke, r.reason]
        for s in sorted(set(seqs))
        if (r := by_seq.get(s)) is not None
    ]


# ----- CSV: path.csv ----------------------------------------------------------------------------------------------
def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return "" if not math.isfinite(value) else f"{value:.4f}"
    return str(value)


def path_csv(rows: Sequence[PathRow]) -> str:
    """Return the path as CSV text (spec §4 columns; empty cells where a frame was not registered)."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(PATH_COLUMNS)
    for r in rows:
        writer.writerow([_cell(getattr(r, c)) for c in PATH_COLUMNS])
    return out.getvalue()
