"""Outputs a hospital archives: the DICOM study of a session (each layer, the report) and the one-page report.

Both need the finished mosaic's raw layers (layers.npz, written when a results version completes): before
that they answer 404 not_ready. Both are built by services.store.session_export, as the PACS send job's are, so
a download and a send are the same objects with the same UIDs. Patient attributes come only from the session's
study context, and only for its owner and admins; without one they are present and empty. The files are patient
images: never cached by shared caches, never logged. Each output of a finished version is made once and kept
(services.store.session_export: made again when the reference or the version's files change); the first
rendering of the one-page report takes about a second, so the sheet and export.dcm?layer=report are also
rate-limited per client and caller (api.limits: 429 with Retry-After).
"""

from __future__ import annotations

import logging
from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request, Response
from fastapi.concurrency import run_in_threadpool

from api.caching import PRIVATE_NO_STORE
from api.deps import Store, ViewPrincipal, ViewSession
from api.limits import check_expensive
from api.results_access import Results, VersionQuery, served_version
from services.core.outputs.dicom_export import STUDY_OBJECTS
from services.store.session_export import session_objects, session_sheet

router = APIRouter(prefix="/v1/sessions", tags=["export"])
log = logging.getLogger("veinmosaic.api")
PRIVATE = {"Cache-Control": PRIVATE_NO_STORE}
ExportLayer = Literal["vein", "force", "coverage", "report"]


@router.get(
    "/{session_id}/export.dcm",
    response_class=Response,
    responses={200: {"content": {"application/dicom": {}}}, 404: {"description": "no finished mosaic yet"}},
)
async def get_export(
    meta: ViewSession,
    principal: ViewPrincipal,
    rs: Results,
    store: Store,
    request: Request,
    layer: Annotated[ExportLayer, Query(description=f"one of {', '.join(STUDY_OBJECTS)}")] = "vein",
    v: VersionQuery = None,
) -> Response:
    """Return one object of the session's DICOM study: a layer (SC, pixel spacing in mm) or the report (PDF).

    The study context (patient, order, laterality) goes into the file for the session's owner and admins; a
    viewer link, which never sees patient data, gets the objects without it (and so with their own UIDs).
    """
    version = served_version(rs, meta.id, v)
    if layer == "report":
        check_expensive(request, principal)  # the one-page report is rendered per call: 429 over the limit
    with_study = principal.session_id is None
    objects = await run_in_threadpool(session_objects, store, rs, meta.id, version, with_study, (layer,))
    log.info("dicom exported", extra={"session": meta.id})
    headers = {
        **PRIVATE,
        "X-Results-Version": str(version),
        "Content-Disposition": f'attachment; filename="{layer}.dcm"',
    }
    return Response(objects[layer], media_type="application/dicom", headers=headers)


@router.get(
    "/{session_id}/sheet.{fmt}",
    response_class=Response,
    responses={200: {"content": {"image/png": {}, "application/pdf": {}}}, 404: {"description": "not ready"}},
)
async def get_sheet(
    meta: ViewSession,
    principal: ViewPrincipal,
    store: Store,
    rs: Results,
    request: Request,
    fmt: Literal["png", "pdf"],
    v: VersionQuery = None,
) -> Response:
    """Return the one-page report (A4): identification, mosaic with path, force and coverage maps, accuracy.

    The study context (patient, order, laterality) is on the page for the session's owner and admins; a viewer
    link, which never sees patient data, gets the page with those fields "not given".
    """
    version = served_version(rs, meta.id, v)
    check_expensive(request, principal)  # rendered per call: 429 over the limit
    data = await run_in_threadpool(session_sheet, store, rs, meta.id, version, fmt, principal.session_id is None)
    media = "image/png" if fmt == "png" else "application/pdf"
    return Response(data, media_type=media, headers={**PRIVATE, "X-Results-Version": str(version)})
