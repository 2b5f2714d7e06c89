"""Sending a session's DICOM objects to a PACS the operator configured (spec §5: POST /v1/sessions/{id}/send).

The route only checks and queues: a durable job (services.jobs.job_records, the one job record; the ledger on
disk keeps the 202's promise) that a worker runs once the session's results are finished, retrying an
unreachable PACS with back-off (workers/stages/send.py). Re-sending stores the same instances: the objects'
UIDs come from the session's identity and content.
"""

from __future__ import annotations

import logging

from fastapi import APIRouter, status

from api.deps import AppSettings, IngestPrincipal, IngestSession, RedisClient, Store
from api.errors import Conflict, Validation
from api.schemas import JobAccepted, SendRequest
from services.jobs import job_records as jobs

router = APIRouter(prefix="/v1/sessions", tags=["export"])
log = logging.getLogger("veinmosaic.api")


@router.post("/{session_id}/send", status_code=status.HTTP_202_ACCEPTED, response_model=JobAccepted)
def send_session(
    body: SendRequest,
    meta: IngestSession,
    principal: IngestPrincipal,
    store: Store,
    r: RedisClient,
    settings: AppSettings,
) -> JobAccepted:
    """Return 202 {"job"} of a send queued of the session's DICOM objects (each layer, the report) to a destination."""
    if body.destination not in settings.pacs_destinations:  # the configured names are never listed to a client
        raise Validation("destination: not a configured PACS destination", code="unknown_destination")
    if meta.status == "failed":
        raise Conflict("the session failed: it has no results to send", code="session_failed")
    options = {"destination": body.destination}
    (job_id,) = jobs.enqueue_jobs(  # QueueFullError: 503 queue_full; OwnerQuotaError: 429 (api/errors.py)
        r,
        settings.redis_prefix,
        principal.fingerprint or "",
        [meta.id],
        options,
        ledger=store.jobs,
        kind="send",
        max_depth=settings.queue_max_depth,
        max_per_owner=settings.queue_max_jobs_per_key,
        in_flight=settings.queue_jobs_in_flight,
    )
    log.info("send queued", extra={"session": meta.id})
    return JobAccepted(job=job_id, session=meta.id, status_url=f"/v1/jobs/{job_id}")
