"""The one builder of a session's report (report.json and its images), for the CLI, the API and the workers.

report.json: "frames" (counts by status, lost/rejected per reason, registered fraction, and the placed frames by
kind, keyframes and tracked, and those stitched: documents.frame_counts), "warnings" (the 5 % rule,
services.core.outputs.scan_quality), "accuracy_summary" (one line), and — with a reference track — the spec §4
accuracy figures at the top level (rmse_mm, max_error_mm, ..., as before) with paths.png and errors.png.
With a mosaic, the one-page sheet (sheet.png, sheet.pdf, A4 portrait): identification (the caller's
SheetIdentity), mosaic with path, force and coverage maps with colour scales, accuracy, fitted tissue model,
lost-frame summary.

The report of a results version (`version_report`: what the reprocess stage writes and the API serves) is
the same document without the sheet (rendered on request), plus the version's identity. Its "plots" name the
image files ({"paths": "paths.png", "errors": "errors.png"}), as in a report folder the CLI writes; the API
turns them into links to its own routes when it serves the report (the core knows no URL).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from services.core.mosaic.canvas import MosaicImage
from services.core.outputs.documents import frame_counts
from services.core.outputs.evaluation import AccuracyReport, evaluate_angles, evaluate_path
from services.core.outputs.plots import plot_error_along_scan, plot_paths_over_mosaic
from services.core.outputs.scan_quality import FrameSummary, scan_warnings, summarize_frames
from services.core.outputs.sheet import SheetIdentity, build_sheet_figure, render_sheet
from services.core.path_rows import UNCOUNTED, PathRow, PlacedCounts

ACCURACY_PLOTS = ("paths.png", "errors.png")
PLOT_NAMES = ("paths", "errors")  # the report plots a results version keeps (ACCURACY_PLOTS without ".png")

Backdrop = tuple[np.ndarray, float, tuple[float, float]]  # (vein image uint8, px_per_mm, frame 0's centre px)


@dataclass(frozen=True)
class SessionReport:
    """report.json as a dict, the accuracy (None without reference), the frame summary and the images."""

    doc: dict[str, Any]
    accuracy: AccuracyReport | None
    frames: FrameSummary
    images: Mapping[str, bytes] = field(default_factory=dict)  # file name -> bytes

    @property
    def warnings(self) -> list[dict[str, str]]:
        """Return the report's warnings ([{"code", "message"}])."""
        return list(self.doc.get("warnings", []))


def path_arrays(rows: Sequence[PathRow]) -> tuple[np.ndarray, np.ndarray]:
    """Return (estimate (N, 2) mm with NaN where not placed, registered (N,) bool) of path rows in order."""
    estimate = np.array([[r.x_mm, r.y_mm] for r in rows], float).reshape(-1, 2)
    registered = np.array([r.status == "ok" for r in rows], bool)
    return estimate, registered


def path_strokes(rows: Sequence[PathRow]) -> np.ndarray | None:
    """Return (N,) each row's stroke number (spec §4), -1 where it has none (off the skin, missing); None when no
    row has one (results from before strokes: drawn as one line)."""
    if all(r.stroke is None for r in rows):
        return None
    return np.array([-1 if r.stroke is None else r.stroke for r in rows], np.int64)


def path_angles_deg(rows: Sequence[PathRow]) -> np.ndarray:
    """Return (N, 3) yaw, tilt_x, tilt_y in degrees of path rows in order (NaN where unknown)."""
    return np.array([[r.yaw_deg, r.tilt_x_deg, r.tilt_y_deg] for r in rows], float).reshape(-1, 3)


def build_session_report(
    rows: Sequence[PathRow],
    reference: np.ndarray | None,
    mosaic: MosaicImage | None,
    extra: Mapping[str, Any] | None = None,
    identity: SheetIdentity | None = None,
    sheet: bool = True,
    backdrop: Backdrop | None = None,
    draw: bool = True,
    placed: PlacedCounts = UNCOUNTED,
) -> SessionReport:
    """Return the report of a path (rows in seq order) with an optional reference track and mosaic.

    draw: False gives the figures and warnings only (no plots, no sheet): what a caller prints before the
    images are rendered.

    reference: (N, 2) positions in mm, or the (N, 5) track of services.core.inputs.reference (positions, yaw and tilts
    in degrees): with angles, report.json also has "angles" (yaw and tilt errors, evaluate_angles).
    identity: who and what the sheet is about (None: every field "not given"); extra["tissue"], when given, is
    shown on the sheet as the fitted tissue and probe model.
    backdrop: the image paths.png is drawn over when there is no mosaic with layers yet (a live version).
    placed: how many placed frames were tracked without features and how many are pasted into the mosaic
    (documents.frame_counts).
    Raises ValueError when a reference is given but no frame can be compared with it.
    """
    frames = summarize_frames(rows)
    estimate, registered = path_arrays(rows)
    reference_mm = None if reference is None else np.asarray(reference, float)[:, :2]
    accuracy = evaluate_path(estimate, registered, reference_mm) if reference_mm is not None else None
    doc: dict[str, Any] = {}
    if accuracy is not None:
        doc.update(accuracy.to_dict())
    if reference is not None and np.shape(reference)[1] > 2:
        angles = evaluate_angles(path_angles_deg(rows), registered, np.asarray(reference, float)[:, 2:5])
        if angles:
            doc["angles"] = angles
    doc["registered_fraction"] = frames.registered_fraction
    counts = frame_counts(rows, placed)  # the one owner of the counts by kind, as in mosaic.json
    doc["frames"] = {**frames.to_dict(), **{k: counts[k] for k in ("keyframes", "tracked", "stitched")}}
    doc["warnings"] = scan_warnings(frames)
    doc["accuracy_summary"] = accuracy.summary() if accuracy is not None else "no reference track: not measured"
    doc.update(extra or {})
    images: dict[str, bytes] = {}
    plots: dict[str, str] = {}
    if accuracy is not None and draw:
        if mosaic is not None:
            vein, px, origin = mosaic.vein, mosaic.px_per_mm, mosaic.origin_px
        else:
            vein, px, origin = backdrop if backdrop is not None else (None, 1.0, (0.0, 0.0))
        images["paths.png"] = plot_paths_over_mosaic(
            estimate, registered, reference_mm, vein, px, origin, strokes=path_strokes(rows)
        )
        images["errors.png"] = plot_error_along_scan(accuracy)
        plots.update({"paths": "paths.png", "errors": "errors.png"})
    if mosaic is not None and sheet and draw:
        png, pdf = render_sheet(build_sheet_figure(
            mosaic, estimate, registered, reference_mm, accuracy, frames, doc["warnings"],
            identity if identity is not None else SheetIdentity(session=""),
            angles=doc.get("angles"), tissue=doc.get("tissue"), strokes=path_strokes(rows),
        ))  # fmt: skip
        images["sheet.png"], images["sheet.pdf"] = png, pdf
        plots.update({"sheet": "sheet.png", "sheet_pdf": "sheet.pdf"})
    doc["plots"] = plots
    return SessionReport(doc, accuracy, frames, images)


def version_report(
    rows: Sequence[PathRow],
    reference: np.ndarray,
    mosaic: MosaicImage | None,
    *,
    session_id: str,
    version: int,
    mosaic_version: int,
    method: str | None,
    backdrop: Backdrop | None = None,
    tissue: Mapping[str, Any] | None = None,
    placed: PlacedCounts = UNCOUNTED,
) -> SessionReport:
    """Return the report of results version `version` (report.json + paths.png, errors.png), see the docstring.

    rows: the version's path in seq order; reference: (N, 2) or (N, 5) aligned to rows; mosaic_version: the
    mosaic.json change counter it was made from (the API rebuilds the report when it changes); placed: its placed
    frames tracked without features and stitched (mosaic.json's counts: path_rows.PlacedCounts.from_frames).
    Raises ValueError when no frame can be compared with the reference.
    """
    extra = {
        "session": session_id,
        "results_version": int(version),
        "mosaic_version": int(mosaic_version),
        "path_rows": len(rows),
        "method": method,
    }
    if tissue is not None:
        extra["tissue"] = dict(tissue)
    report = build_session_report(rows, reference, mosaic, extra, sheet=False, backdrop=backdrop, placed=placed)
    images = {name: data for name, data in report.images.items() if name in ACCURACY_PLOTS}
    doc = {**report.doc, "plots": {name: f"{name}.png" for name in PLOT_NAMES}}
    return SessionReport(doc, report.accuracy, report.frames, images)
