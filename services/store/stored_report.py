"""Write the report of a results version (report.json, paths.png, errors.png) from what the version stores.

The one adapter over `services.core.outputs.session_report.version_report`: the reprocess stage calls it when a
version is complete, the API when a reference is posted or the served report is stale, so both write the same document
from the same inputs (the version's path.json, mosaic layers, mosaic.json and options, the session's
reference.csv aligned to every frame seq of the session).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import cv2
import numpy as np

from services.core.inputs.reference import parse_reference_csv
from services.core.outputs.session_report import Backdrop, version_report
from services.core.path_rows import PathRow, PlacedCounts, path_rows_from_json
from services.store.results_store import ResultsStore


class BadReferenceError(ValueError):
    """reference.csv is malformed or holds no data row (the message names the line)."""


class NoPathYetError(ValueError):
    """The results version has no path yet: nothing to evaluate."""


class NothingToCompareError(ValueError):
    """No frame of the path can be compared with the reference."""


def parse_reference(text: str, frame_seqs: Iterable[int]) -> tuple[list[int], np.ndarray]:
    """Return (every frame seq in order, the reference track (N, 5) aligned to them) or raise BadReferenceError."""
    ordered = sorted({int(s) for s in frame_seqs})
    try:
        reference = parse_reference_csv(text, ordered)
    except ValueError as exc:
        raise BadReferenceError(str(exc)) from None
    if not np.any(np.all(np.isfinite(reference[:, :2]), axis=1)):
        raise BadReferenceError("reference.csv: no data rows (expected seq,x_mm,y_mm lines)")
    return ordered, reference


def reference_for_rows(text: str, rows: Sequence[PathRow], frame_seqs: Iterable[int]) -> np.ndarray:
    """Return the reference track (len(rows), 5) aligned to path rows (NaN where it has none); BadReferenceError.

    frame_seqs: the session's stored frame seqs; the reference may name any of them or of the rows.
    """
    ordered, reference = parse_reference(text, [*frame_seqs, *(r.seq for r in rows)])
    position = {s: i for i, s in enumerate(ordered)}
    return reference[[position[r.seq] for r in rows]].reshape(-1, reference.shape[1])


def _backdrop(rs: ResultsStore, sid: str, v: int, mosaic_doc: dict[str, Any]) -> Backdrop | None:
    """Return the served mosaic.png with its geometry (a live version has no layers yet), or None."""
    try:
        raw = rs.image_path(sid, v, "mosaic.png").read_bytes()
    except FileNotFoundError:
        return None
    vein = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_GRAYSCALE)
    if vein is None or "origin_px" not in mosaic_doc or not mosaic_doc.get("px_per_mm"):
        return None
    origin = (float(mosaic_doc["origin_px"][0]), float(mosaic_doc["origin_px"][1]))
    return vein, float(mosaic_doc["px_per_mm"]), origin


def write_version_report(
    rs: ResultsStore, sid: str, v: int, reference_text: str, frame_seqs: Iterable[int]
) -> dict[str, Any]:
    """Return report.json of version v's path evaluated against reference_text, written with its plots.

    frame_seqs: the session's stored frame seqs (the reference may name any of them). Raises BadReferenceError
    (bad reference), NoPathYetError (version v has no path rows), NothingToCompareError (no frame comparable).
    """
    # mosaic.json before path.json (a flush writes them the other way round): its frame counts, of which the report
    # takes the tracked frames, are never newer than the rows they count
    mosaic_doc = rs.read_mosaic_meta(sid, v) or {}
    rows = path_rows_from_json(rs.read_path(sid, v) or [])
    reference = reference_for_rows(reference_text, rows, frame_seqs)  # a bad file is named first
    if not rows:
        raise NoPathYetError("no path yet: post the reference after frames have been processed")
    mosaic = rs.read_mosaic_layers(sid, v)
    try:
        report = version_report(
            rows,
            reference,
            mosaic,
            session_id=sid,
            version=v,
            mosaic_version=int(mosaic_doc.get("version", 0)),
            method=(rs.read_options(sid, v) or {}).get("method"),
            backdrop=_backdrop(rs, sid, v, mosaic_doc) if mosaic is None else None,
            tissue=mosaic_doc.get("tissue"),
            placed=PlacedCounts.from_frames(mosaic_doc.get("frames")),
        )
    except ValueError as exc:
        raise NothingToCompareError(f"reference.csv: {exc}") from None
    for name, data in report.images.items():
        rs.write_image(sid, v, name, data)
    rs.write_report(sid, v, report.doc)
    return report.doc


def report_is_stale(report: dict[str, Any] | None, mosaic_doc: dict[str, Any] | None) -> bool:
    """Return True when a stored report.json is missing, was made from another mosaic.json version, or predates a
    field every report now has (global_error, where the accuracy figures' error lies)."""
    if report is None or "global_error" not in report:
        return True
    return int(report.get("mosaic_version", -1)) != int((mosaic_doc or {}).get("version", 0))
