"""The accuracy report (spec §4): POST a reference track, GET the report and its plots.

The report of a results version is built and written by services.store.stored_report (the reprocess stage calls
the same function) with its plots named by file; `served` turns them into links to GET .../plots/{name}.png?v=<v>.
"""

from __future__ import annotations

import logging
from typing import Any, Literal

from fastapi import APIRouter, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse

from api.caching import file_response, version_headers
from api.deps import AppSettings, IngestSession, Store, ViewPrincipal, ViewSession, read_body
from api.errors import Conflict, NotFound, UnsupportedMediaType, Validation
from api.limits import check_expensive
from api.results_access import Results, VersionQuery, resolve_version, served_version
from services.store.results_store import ResultsStore
from services.store.storage import SessionStore
from services.store.stored_report import parse_reference, report_is_stale, write_version_report

router = APIRouter(prefix="/v1/sessions", tags=["results"])
log = logging.getLogger("veinmosaic.api")

REFERENCE_TYPES = {"text/csv", "text/plain", "application/csv", "application/octet-stream", ""}


def _frame_seqs(store: SessionStore, sid: str) -> list[int]:
    return [f.seq for f in store.list_frames(sid)]


def served(doc: dict[str, Any], sid: str, v: int) -> dict[str, Any]:
    """Return a version's report as served: its "plots" as links to this API's plot route for version v."""
    plots = {name: f"/v1/sessions/{sid}/plots/{name}.png?v={int(v)}" for name in doc.get("plots", {})}
    return {**doc, "plots": plots}


def _report(store: SessionStore, rs: ResultsStore, sid: str, v: int, reference: str) -> dict[str, Any]:
    return write_version_report(rs, sid, v, reference, _frame_seqs(store, sid))


def _store_and_report(store: SessionStore, rs: ResultsStore, sid: str, v: int, text: str) -> dict[str, Any]:
    doc = _report(store, rs, sid, v, text)  # validates before anything is stored
    rs.write_reference(sid, text)
    return doc


@router.post(
    "/{session_id}/reference",
    responses={
        200: {"description": "the accuracy report (spec §4)"},
        409: {"description": "no path yet"},
        415: {"description": "not text/csv"},
        422: {"description": "bad reference.csv (the message names the line)"},
    },
)
async def post_reference(
    meta: IngestSession, request: Request, store: Store, rs: Results, settings: AppSettings
) -> JSONResponse:
    """Return the accuracy report of the current results version after storing reference.csv (seq,x_mm,y_mm)."""
    media = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if media not in REFERENCE_TYPES:
        raise UnsupportedMediaType("reference: expected a text/csv body (seq,x_mm,y_mm)")
    body = await read_body(request, settings.max_json_bytes)
    try:
        text = body.decode("utf-8")
    except UnicodeDecodeError:
        raise Validation("reference.csv: not UTF-8 text", code="invalid_reference") from None
    version = resolve_version(rs, meta.id, None)
    if version is None:
        await run_in_threadpool(parse_reference, text, _frame_seqs(store, meta.id))  # a bad file is named first
        raise Conflict("no path yet: post the reference after frames have been processed", code="not_ready")
    doc = await run_in_threadpool(_store_and_report, store, rs, meta.id, version, text)
    log.info("reference evaluated", extra={"session": meta.id})
    return JSONResponse(served(doc, meta.id, version), headers={"X-Results-Version": str(version)})


def _fresh_report(store: SessionStore, rs: ResultsStore, sid: str, v: int, reference: str) -> dict[str, Any]:
    doc = rs.read_report(sid, v)
    if doc is None or report_is_stale(doc, rs.read_mosaic_meta(sid, v)):
        return _report(store, rs, sid, v, reference)
    return doc


@router.get("/{session_id}/report", responses={404: {"description": "no reference posted yet"}})
async def get_report(
    meta: ViewSession, principal: ViewPrincipal, request: Request, store: Store, rs: Results, v: VersionQuery = None
) -> JSONResponse:
    """Return the accuracy report (spec §4) with plot links; recomputed when the mosaic has changed since.

    It may be evaluated (and written) on the call, so it is rate-limited per client and caller (429, api.limits).
    """
    reference = await run_in_threadpool(rs.read_reference, meta.id)
    if reference is None:
        raise NotFound("no report: no reference track has been posted for this session", code="no_reference")
    version = resolve_version(rs, meta.id, v)
    if version is None:
        raise NotFound("no report: no frame has been processed yet", code="not_ready")
    check_expensive(request, principal)
    doc = await run_in_threadpool(_fresh_report, store, rs, meta.id, version, reference)
    return JSONResponse(served(doc, meta.id, version), headers=version_headers(version))


@router.get("/{session_id}/plots/{name}.png", response_class=Response, responses={200: {"content": {"image/png": {}}}})
def get_plot(
    meta: ViewSession, name: Literal["paths", "errors"], rs: Results, request: Request, v: VersionQuery = None
) -> Response:
    """Return a report plot: paths (estimate and reference over the mosaic) or errors (error along the scan)."""
    version = served_version(rs, meta.id, v)
    return file_response(request, rs.image_path(meta.id, version, f"{name}.png"), version, "image/png", "no plot yet")
