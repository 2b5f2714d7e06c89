"""Reprocessing (spec §5): a new results version from the stored raw uploads, with other options; jobs.

The options document is validated by services.core.method_options (exactly as the workers read it); jobs and
batches are written and read by services.jobs.job_records. Jobs are visible to the key that created them and to
admin keys.
"""

from __future__ import annotations

import hmac
import logging
import re
from typing import Any

from fastapi import APIRouter, status

from api.auth import Principal, visible_session
from api.deps import AppSettings, IngestPrincipal, IngestSession, ReadPrincipal, RedisClient, Store
from api.errors import Conflict, NotFound, Validation
from api.schemas import BatchAccepted, BatchReprocessRequest, BatchState, JobAccepted, JobState, ReprocessRequest
from services.core import method_options
from services.core.inputs.calibration import Calibration, CalibrationError
from services.jobs import job_records as jobs
from services.store.storage import SessionMeta, SessionStore

router = APIRouter(tags=["reprocess"])
log = logging.getLogger("veinmosaic.api")

_ID = re.compile(r"^[0-9a-f]{32}$")


def _validated(options: dict[str, Any], calibration: Calibration) -> dict[str, Any]:
    try:
        return method_options.validate_options(options, calibration)
    except CalibrationError:  # api/errors.py maps it: 422 invalid_calibration
        raise
    except ValueError as exc:  # any ValueError of the options check; too broad for api/errors.py's table
        raise Validation(str(exc), code="invalid_options") from None


def _check_reprocessable(store: SessionStore, meta: SessionMeta) -> None:
    refusal = store.reprocess_refusal(meta)
    if refusal is not None:
        code, message = refusal
        raise Conflict(message, code=code)


def _enqueue(
    r: RedisClient,
    settings: AppSettings,
    principal: Principal,
    store: Store,
    sessions: list[str],
    options: dict[str, Any],
    batch: str = "",
) -> list[str]:
    owner = principal.fingerprint or ""  # QueueFullError: 503 queue_full; OwnerQuotaError: 429 (api/errors.py)
    return jobs.enqueue_jobs(
        r,
        settings.redis_prefix,
        owner,
        sessions,
        options,
        batch=batch,
        ledger=store.jobs,
        max_depth=settings.queue_max_depth,
        max_per_owner=settings.queue_max_jobs_per_key,
        in_flight=settings.queue_jobs_in_flight,
    )


def _may_see(principal: Principal, owner: str) -> bool:
    return principal.is_admin or (
        principal.fingerprint is not None and hmac.compare_digest(principal.fingerprint, owner)
    )


@router.post("/v1/sessions/{session_id}/reprocess", status_code=status.HTTP_202_ACCEPTED, response_model=JobAccepted)
def reprocess_session(
    body: ReprocessRequest,
    meta: IngestSession,
    principal: IngestPrincipal,
    store: Store,
    r: RedisClient,
    settings: AppSettings,
) -> JobAccepted:
    """Return 202 {"job"} of a reprocess of one session queued (a new results version; raw uploads untouched)."""
    options = _validated(body.options.document(), store.calibration(meta.id))
    _check_reprocessable(store, meta)
    (job_id,) = _enqueue(r, settings, principal, store, [meta.id], options)
    log.info("reprocess queued", extra={"session": meta.id, "method": options["method"]})
    return JobAccepted(job=job_id, session=meta.id, status_url=f"/v1/jobs/{job_id}")


@router.post("/v1/reprocess", status_code=status.HTTP_202_ACCEPTED, response_model=BatchAccepted)
def reprocess_batch(
    body: BatchReprocessRequest, principal: IngestPrincipal, store: Store, r: RedisClient, settings: AppSettings
) -> BatchAccepted:
    """Return 202 {"batch", "jobs"} of a reprocess of several sessions queued (admin, or the owner of every one).

    Otherwise 404, naming none of them.
    """
    sessions = list(dict.fromkeys(body.sessions))  # de-duplicated, order kept
    if not all(isinstance(sid, str) and _ID.match(sid) for sid in sessions):
        raise NotFound("no such session")
    metas = [visible_session(store, principal, sid) for sid in sessions]
    checked = [_validated(body.options.document(), store.calibration(m.id)) for m in metas]
    for m in metas:
        _check_reprocessable(store, m)
    batch = jobs.new_id()
    ids = _enqueue(r, settings, principal, store, sessions, checked[0], batch=batch)
    log.info("batch reprocess queued: %d jobs", len(ids), extra={"method": checked[0]["method"]})
    return BatchAccepted(batch=batch, jobs=ids, status_url=f"/v1/batches/{batch}")


@router.get("/v1/jobs/{job_id}", response_model=JobState)
def get_job(job_id: str, r: RedisClient, settings: AppSettings, principal: ReadPrincipal) -> JobState:
    """Return a job's state and progress (visible to the key that created it and to admin keys)."""
    raw = jobs.read_job(r, settings.redis_prefix, job_id) if _ID.match(job_id) else {}
    if not raw or not _may_see(principal, raw.get("owner", "")):
        raise NotFound("no such job")
    return JobState(**jobs.job_view(raw, job_id))


@router.get("/v1/batches/{batch_id}", response_model=BatchState)
def get_batch(batch_id: str, r: RedisClient, settings: AppSettings, principal: ReadPrincipal) -> BatchState:
    """Return a batch's jobs; its state is done when every job is done or failed, failed if any failed."""
    raw, found = jobs.read_batch(r, settings.redis_prefix, batch_id) if _ID.match(batch_id) else ({}, [])
    if not raw or not _may_see(principal, raw.get("owner", "")):
        raise NotFound("no such batch")
    states = [JobState(**jobs.job_view(h, job_id)) for job_id, h in found]
    status = jobs.batch_state({j.status for j in states})
    return BatchState(batch=batch_id, status=status, state=status, jobs=states)
