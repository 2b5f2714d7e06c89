"""GET /v1/audit and /v1/audit/verify: the audit log (services/store/audit.py), for admin keys only."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Query, Request
from fastapi.concurrency import run_in_threadpool

from api.deps import AdminPrincipal
from api.schemas import AuditPage, AuditVerification
from services.store.audit import AuditLog

router = APIRouter(prefix="/v1/audit", tags=["audit"])


def get_audit(request: Request) -> AuditLog:
    """Return the application's audit log."""
    return request.app.state.audit


@router.get("", response_model=AuditPage)
async def read_audit(
    request: Request,
    principal: AdminPrincipal,
    session: Annotated[str | None, Query(max_length=64, description="only records of this session id")] = None,
    actor: Annotated[str | None, Query(max_length=80, description='e.g. "key:<16 hex>" or "token:<session>"')] = None,
    action: Annotated[str | None, Query(max_length=40, description='e.g. "frame.upload", "viewer.open"')] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
) -> AuditPage:
    """Return the newest audit records matching the filters, newest first (admin scope)."""
    records: list[dict[str, Any]] = await run_in_threadpool(get_audit(request).query, session, actor, action, limit)
    return AuditPage(records=records, count=len(records))


@router.get("/verify", response_model=AuditVerification)
async def verify_audit(request: Request, principal: AdminPrincipal) -> AuditVerification:
    """Return the check of the whole keyed chain: ok false with the first bad line if a record was altered (admin)."""
    result = await run_in_threadpool(get_audit(request).verify)
    return AuditVerification(**result.to_dict())
