"""Outputs a hospital archives: the DICOM export of a session's layers and the one-page report (PNG/PDF).

Both need the finished mosaic's raw layers (layers.npz, written when a results version completes): before
that they answer 404 not_ready. Patient attributes in the DICOM file come only from the integrator; a session
carries none today, so they are present and empty. The files are patient images: never cached by shared
caches, never logged.
"""

from __future__ import annotations

import contextlib
import logging
from datetime import UTC, datetime
from typing import Annotated, Literal

from fastapi import APIRouter, Query, Response
from fastapi.concurrency import run_in_threadpool

from api.deps import Store, ViewSession
from api.errors import NotFound
from api.results_access import Results, VersionQuery, resolve_version
from services.core.dicom_export import EXPORT_LAYERS, ExportInfo, export_layer
from services.core.mosaic import MosaicImage
from services.core.results_docs import path_rows_from_json
from services.core.session_report import build_session_report
from services.store.results_report import BadReferenceError, reference_for_rows
from services.store.results_store import ResultsStore
from services.store.storage import SessionMeta

router = APIRouter(prefix="/v1/sessions", tags=["export"])
log = logging.getLogger("veinmosaic.api")
PRIVATE = {"Cache-Control": "private, no-store"}
ExportLayer = Literal["vein", "force", "coverage"]


def finished_layers(rs: ResultsStore, sid: str, requested: int | None) -> tuple[int, MosaicImage]:
    """Return (version, the finished mosaic with force in N and coverage) or raise 404 not_ready."""
    version = resolve_version(rs, sid, requested)
    mosaic = rs.read_mosaic_layers(sid, version) if version is not None else None
    if version is None or mosaic is None:
        raise NotFound("no finished mosaic yet: the export is available when processing is done", code="not_ready")
    return version, mosaic


@router.get(
    "/{session_id}/export.dcm",
    response_class=Response,
    responses={200: {"content": {"application/dicom": {}}}, 404: {"description": "no finished mosaic yet"}},
)
async def get_export(
    meta: ViewSession,
    rs: Results,
    layer: Annotated[ExportLayer, Query(description=f"one of {', '.join(EXPORT_LAYERS)}")] = "vein",
    v: VersionQuery = None,
) -> Response:
    """Return one layer (vein, force in N, coverage) as a DICOM Secondary Capture with pixel spacing in mm."""
    version, mosaic = await run_in_threadpool(finished_layers, rs, meta.id, v)
    info = ExportInfo(
        session_key=meta.id,
        acquired=datetime.fromtimestamp(meta.created, UTC),
        exported=datetime.now(UTC),
        method=str((rs.read_options(meta.id, version) or {}).get("method") or ""),
        results_version=version,
    )
    data = await run_in_threadpool(export_layer, mosaic, layer, info)
    log.info("dicom exported", extra={"session": meta.id})
    headers = {
        **PRIVATE,
        "X-Results-Version": str(version),
        "Content-Disposition": f'attachment; filename="{layer}.dcm"',
    }
    return Response(data, media_type="application/dicom", headers=headers)


def _sheet(store: Store, rs: ResultsStore, meta: SessionMeta, requested: int | None, fmt: str) -> tuple[int, bytes]:
    version, mosaic = finished_layers(rs, meta.id, requested)
    rows = path_rows_from_json(rs.read_path(meta.id, version) or [])
    reference = None
    text = rs.read_reference(meta.id)
    if text is not None and rows:
        with contextlib.suppress(BadReferenceError):  # the sheet without accuracy
            reference = reference_for_rows(text, rows, (f.seq for f in store.list_frames(meta.id)))
    method = (rs.read_options(meta.id, version) or {}).get("method") or "?"
    heading = f"veinmosaic session {meta.id[:8]}, results version {version}, method {method}"
    try:
        report = build_session_report(rows, reference, mosaic, heading=heading)
    except ValueError:  # the reference matches no registered frame: the sheet without accuracy
        report = build_session_report(rows, None, mosaic, heading=heading)
    return version, report.images[f"sheet.{fmt}"]


@router.get(
    "/{session_id}/sheet.{fmt}",
    response_class=Response,
    responses={200: {"content": {"image/png": {}, "application/pdf": {}}}, 404: {"description": "not ready"}},
)
async def get_sheet(
    meta: ViewSession, store: Store, rs: Results, fmt: Literal["png", "pdf"], v: VersionQuery = None
) -> Response:
    """Return the one-page report: mosaic with path, force and coverage maps, accuracy, lost-frame summary."""
    version, data = await run_in_threadpool(_sheet, store, rs, meta, v, fmt)
    media = "image/png" if fmt == "png" else "application/pdf"
    return Response(data, media_type=media, headers={**PRIVATE, "X-Results-Version": str(version)})
