"""GET /openapi.json: the OpenAPI document, for API keys only by default (VEINMOSAIC_API_DOCS).

The document describes every route, parameter and status: useful to an integrator, a map to anyone else, so it
is served to callers with a valid API key ("keys", the default), to everyone ("public"), or not at all ("off":
404, as for production behind a hospital's proxy). The interactive pages FastAPI would serve (/docs with Swagger
UI, /redoc) load their scripts from a CDN, so they are not served: any OpenAPI viewer reads the document.
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request

from api.auth import key_principal, remember
from api.deps import AppSettings
from api.errors import NotFound, Unauthorized
from api.limits import refuse_unauthenticated

router = APIRouter(tags=["openapi"])


@router.get("/openapi.json", include_in_schema=False)
async def openapi_document(request: Request, settings: AppSettings) -> dict[str, Any]:
    """Return the OpenAPI document: to any valid API key ("keys"), to anyone ("public"), or 404 ("off")."""
    if settings.api_docs == "off":
        raise NotFound("not found")
    if settings.api_docs == "keys":
        principal = key_principal(request)
        if principal is None:
            raise refuse_unauthenticated(request, Unauthorized("a valid bearer key is required"))
        remember(request, principal)
    document: dict[str, Any] = request.app.openapi()
    return document
