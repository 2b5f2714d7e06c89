"""The one builder of each document of a results version: mosaic.json, the session extent, frame counts (the
path rows themselves: services.core.path_rows).

Pure functions (no I/O): the live register stage, the reprocess stage and the API routes all call them, so a
live session and a reprocess of the same scan publish the same fields computed the same way.

The session extent is the bounding box, in mm on frame 0's axes, of the mosaic's covered pixels (blend
weight > MIN_WEIGHT): exactly the bounds of the mosaic image a viewer shows (`SparseCanvas.render` crops to
these pixels). It is computed from the canvas the tiles are cut from, so it is the same live (every flush,
without rendering) and after a reprocess (the canvas made from the rendered mosaic). The older live
estimate, placed frame centres +- the radius of a circle with the window's area, was wrong three ways: the
window is not a circle, a frame's footprint grows and shrinks with its stretch and the compliance gauge, and
blurred frames are placed but not stitched.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping, Sequence
from typing import Any

from services.core.mosaic.canvas import FORCE_FULL_SCALE_N, SparseCanvas
from services.core.mosaic.canvas_units import IDENTITY, CanvasUnits
from services.core.mosaic.deepzoom import MIN_WEIGHT, DziGeometry
from services.core.path_rows import UNCOUNTED, PathRow, PlacedCounts
from services.core.physics.compliance import ComplianceFit
from services.core.registration.outcome import (
    REASON_FRAGMENT,
    REASON_NO_CONTACT,
    STATUS_LOST,
    STATUS_OK,
    STATUS_REJECTED,
)

LAYERS = ("vein", "force")
IMAGE_KEYS = ("px_per_mm", "origin_px", "width", "height", "force_full_scale_n")

Revisions = dict[str, dict[str, int]]


# ----- frame counts -----------------------------------------------------------------------------------------------
def frame_counts(rows: Sequence[PathRow], placed: PlacedCounts = UNCOUNTED) -> dict[str, int]:
    """Return the frame counts of path rows by status and reason, of the placed ones by kind (keyframes, tracked), and
    the placed frames the mosaic is made of (stitched).

    Keys: processed, ok, lost, rejected, no_contact (rejected frames taken off the skin, between strokes),
    in_fragments (lost frames placed on a fragment that has not joined the map, yet while live), keyframes,
    tracked and stitched. tracked: placed.tracked, at most the rows' placed frames (a count read beside older rows);
    keyframes: the other placed frames, registered by their features, so that ok = keyframes + tracked. stitched:
    placed.stitched, at most ok; None gives ok.
    """
    c = Counter(r.status for r in rows)
    why = Counter(r.reason for r in rows)
    ok = c[STATUS_OK]
    tracked = min(max(placed.tracked, 0), ok)
    stitched = ok if placed.stitched is None else min(max(placed.stitched, 0), ok)
    return {
        "processed": len(rows),
        "ok": ok,
        "lost": c[STATUS_LOST],
        "rejected": c[STATUS_REJECTED],
        "no_contact": why[REASON_NO_CONTACT],
        "in_fragments": why[REASON_FRAGMENT],
        "keyframes": ok - tracked,
        "tracked": tracked,
        "stitched": stitched,
    }


# ----- the session extent -----------------------------------------------------------------------------------------
def canvas_extent_mm(canvas: SparseCanvas, min_weight: float = MIN_WEIGHT) -> list[float] | None:
    """Return the session extent [xmin, ymin, xmax, ymax] in mm (frame 0's axes) of a canvas, None when empty.

    The box of the covered pixels' edges, as `render` crops them, in the path's mm (the canvas's units undone).
    """
    box = canvas.covered_box(min_weight)
    if box is None:
        return None
    k = canvas.px_per_mm
    x0, y0 = canvas.units.to_path_mm(box[0] / k, box[1] / k)
    x1, y1 = canvas.units.to_path_mm(box[2] / k, box[3] / k)
    return [float(x0), float(y0), float(x1), float(y1)]


def extent_view(extent_mm: Sequence[float] | None) -> dict[str, float] | None:
    """Return GET /v1/sessions/{id}'s extent: {x,y}_{min,max}_mm and width/height mm, or None."""
    if not extent_mm or len(extent_mm) != 4:
        return None
    x0, y0, x1, y1 = (float(e) for e in extent_mm)
    return {"xmin_mm": x0, "ymin_mm": y0, "xmax_mm": x1, "ymax_mm": y1, "width_mm": x1 - x0, "height_mm": y1 - y0}


# ----- mosaic.json ------------------------------------------------------------------------------------------------
def empty_image_meta(px_per_mm: float) -> dict[str, Any]:
    """Return the image part of mosaic.json before (or without) any rendered mosaic: 0 x 0 px."""
    return {
        "px_per_mm": float(px_per_mm),
        "origin_px": [0.0, 0.0],
        "width": 0,
        "height": 0,
        "force_full_scale_n": FORCE_FULL_SCALE_N,
    }


def image_meta(doc: Mapping[str, Any] | None, px_per_mm: float) -> dict[str, Any]:
    """Return the image part of a mosaic.json (IMAGE_KEYS), the empty one when it has none yet."""
    if not doc or not doc.get("width"):
        return empty_image_meta(px_per_mm)
    return {k: doc[k] for k in IMAGE_KEYS if k in doc}


def empty_revisions() -> Revisions:
    """Return the revisions of a version with no tile yet: {layer: {}}."""
    return {layer: {} for layer in LAYERS}


def mosaic_json(
    image: Mapping[str, Any],
    *,
    version: int,
    results_version: int,
    revisions: Revisions,
    geometry: DziGeometry,
    extent_mm: list[float] | None,
    rows: Sequence[PathRow],
    status: str,
    method: str,
    compliance: ComplianceFit | None = None,
    tissue: Mapping[str, Any] | None = None,
    placed: PlacedCounts = UNCOUNTED,
    units: CanvasUnits = IDENTITY,
) -> dict[str, Any]:
    """Return mosaic.json (spec §4 plus what the viewer needs), the one shape every producer writes.

    image: the rendered mosaic's meta (MosaicImage.meta(), or `image_meta`/`empty_image_meta`); version: the
    mosaic's change counter; revisions: {layer: {"level/col_row": revision}}; extent_mm: the session extent;
    rows: the path (frame counts); status: receiving, processing or done; compliance: the fit once finished;
    tissue: what the scan taught of the tissue and the probe (SessionReconstruction.learned_model); placed: how many
    of the rows' placed frames were tracked without features and how many are stitched (frame_counts); units: the
    canvas's (SparseCanvas.units), which place the path's origin on the tiles (the dzi block's origin_px).
    """
    doc: dict[str, Any] = {k: image[k] for k in IMAGE_KEYS if k in image}
    doc.update(
        {
            "version": int(version),
            "results_version": int(results_version),
            "revisions": revisions,
            "dzi": geometry.to_dict(units),
            "extent_mm": extent_mm,
            "frames": frame_counts(rows, placed),
            "status": status,
            "method": method,
        }
    )
    return _with_fit(doc, compliance, tissue)


def folder_mosaic_json(
    image: Mapping[str, Any],
    *,
    method: str,
    compliance: ComplianceFit | None = None,
    tissue: Mapping[str, Any] | None = None,
    scan_digest: str | None = None,
) -> dict[str, Any]:
    """Return an offline output folder's mosaic.json (spec §4): the image part (MosaicImage.meta()), the method,
    the compliance fit and what the scan taught of the tissue, and the scan's content digest (the key the DICOM
    export's UIDs derive from) when known. The service's mosaic.json is `mosaic_json`."""
    doc: dict[str, Any] = {k: image[k] for k in IMAGE_KEYS if k in image}
    doc["method"] = method
    doc = _with_fit(doc, compliance, tissue)
    if scan_digest:
        doc["scan_digest"] = scan_digest
    return doc


def _with_fit(
    doc: dict[str, Any], compliance: ComplianceFit | None, tissue: Mapping[str, Any] | None
) -> dict[str, Any]:
    """Return doc with the compliance fit (compliance_per_n, gauge) and the learned tissue model added, if any."""
    if compliance is not None:
        doc["compliance_per_n"] = compliance.compliance_per_n
        doc["gauge"] = compliance.gauge
    if tissue is not None:
        doc["tissue"] = dict(tissue)
    return doc
