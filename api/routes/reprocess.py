"""Reprocessing (spec §5): a new results version from the stored raw uploads, with other options; jobs.

Options document (validated here exactly as the workers will read it, by services.core.method_options):
{"method": "best"|"paper"|"sift-chain", "method_options": {<services.core.methods.MethodOptions field>: value},
"calibration": {<calibration.json field>: value}}; every part optional. A job is a Redis hash
<prefix>job:<id> {state: queued|running|done|failed, done, total, session, version, error, owner, created,
options, batch} plus an entry {"kind": "reprocess", "job", "session", "options"} on the stream <prefix>jobs,
written in one MULTI so a worker never sees an entry without its hash. Jobs are visible to the key that
created them and to admin keys; batches <prefix>batch:<id> {jobs: json list, owner, created}.
"""

from __future__ import annotations

import contextlib
import hmac
import json
import logging
import re
import time
import uuid
from typing import Any

import redis
from fastapi import APIRouter, Depends, status

from api.auth import Principal, require_scope, visible_session
from api.deps import AppSettings, IngestPrincipal, IngestSession, RedisClient, Store
from api.errors import Conflict, NotFound, ServiceUnavailable, Validation
from api.schemas import BatchAccepted, BatchReprocessRequest, BatchState, JobAccepted, JobState, ReprocessRequest
from services.core import method_options
from services.core.calibration import Calibration, CalibrationError
from services.jobs import queue
from services.store.storage import JobLedger, SessionMeta, SessionStore

router = APIRouter(tags=["reprocess"])
log = logging.getLogger("veinmosaic.api")

JOB_TTL_S = queue.JOB_TTL_S
_ID = re.compile(r"^[0-9a-f]{32}$")
FIXED_CALIBRATION = ("image_size",)  # the stored frames have this size: it cannot be overridden


def validate_options(options: dict[str, Any], calibration: Calibration) -> dict[str, Any]:
    """Return the normalised options document (services.core.method_options), or raise 422 naming the bad field."""
    try:
        return method_options.validate_options(options, calibration)
    except CalibrationError as exc:
        raise Validation(f"calibration: {exc}", code="invalid_calibration") from None
    except ValueError as exc:
        raise Validation(str(exc), code="invalid_options") from None


def _check_reprocessable(store: SessionStore, meta: SessionMeta) -> None:
    if meta.finished_at is None:
        raise Conflict("the session is still receiving uploads: finish it before reprocessing", code="not_finished")
    if store.count_frames(meta.id) == 0:
        raise Conflict("the session has no frames to reprocess", code="no_frames")


def _job_fields(job_id: str, sid: str, owner: str, options: dict[str, Any], now: float, batch: str) -> dict[str, str]:
    return {
        "id": job_id,
        "state": "queued",
        "done": "0",
        "total": "0",
        "session": sid,
        "version": "",
        "error": "",
        "owner": owner,
        "created": repr(float(now)),
        "options": json.dumps(options, separators=(",", ":")),
        "batch": batch,
    }


def enqueue_jobs(
    r: redis.Redis,
    prefix: str,
    principal: Principal,
    sessions: list[str],
    options: dict[str, Any],
    batch: str = "",
    ledger: JobLedger | None = None,
) -> list[str]:
    """Write one job hash per session and its stream entry (one MULTI), then record each job durably in the
    ledger (the 202's promise: the reconciler re-enqueues a recorded job Redis lost); return the job ids.

    If the durable record fails (a full disk), the jobs are taken off Redis again and the error is raised (503).
    """
    owner = principal.fingerprint or ""
    now = time.time()
    ids = [uuid.uuid4().hex for _ in sessions]
    pipe = r.pipeline(transaction=True)
    if batch:
        pipe.hset(
            queue.batch_key(batch, prefix),
            mapping={"jobs": json.dumps(ids), "owner": owner, "created": repr(now), "sessions": json.dumps(sessions)},
        )
        pipe.expire(queue.batch_key(batch, prefix), JOB_TTL_S)
    encoded = json.dumps(options, separators=(",", ":"))
    records = {
        job_id: _job_fields(job_id, sid, owner, options, now, batch) for job_id, sid in zip(ids, sessions, strict=True)
    }
    for job_id, sid in zip(ids, sessions, strict=True):
        pipe.hset(queue.job_key(job_id, prefix), mapping=records[job_id])
        pipe.expire(queue.job_key(job_id, prefix), JOB_TTL_S)
        pipe.xadd(queue.jobs_stream(prefix), queue.job_entry(job_id, sid, encoded))
    replies = pipe.execute()
    if ledger is not None:
        try:
            for job_id in ids:
                fields = records[job_id]
                ledger.record(job_id, {k: fields[k] for k in ("session", "owner", "created", "options", "batch")})
        except OSError:
            entries = replies[2 if batch else 0 :][2::3]  # the XADD replies: the entry ids
            with contextlib.suppress(redis.RedisError, OSError):
                undo = r.pipeline(transaction=True)
                if entries:
                    undo.xdel(queue.jobs_stream(prefix), *entries)
                undo.delete(*(queue.job_key(job_id, prefix) for job_id in ids))
                undo.execute()
            for job_id in ids:
                with contextlib.suppress(OSError):
                    ledger.discard(job_id)
            raise
    return ids


def _queue_guard(r: redis.Redis, settings: AppSettings, adding: int) -> None:
    if int(r.xlen(queue.jobs_stream(settings.redis_prefix))) + adding > settings.queue_max_depth:
        raise ServiceUnavailable("the job queue is full; retry later", settings.retry_after_s, code="queue_full")


@router.post("/v1/sessions/{session_id}/reprocess", status_code=status.HTTP_202_ACCEPTED, response_model=JobAccepted)
def reprocess_session(
    body: ReprocessRequest,
    meta: IngestSession,
    principal: IngestPrincipal,
    store: Store,
    r: RedisClient,
    settings: AppSettings,
) -> JobAccepted:
    """Queue a reprocess of one session (a new results version; raw uploads untouched): 202 {"job"}."""
    options = validate_options(body.options.document(), store.calibration(meta.id))
    _check_reprocessable(store, meta)
    _queue_guard(r, settings, 1)
    (job_id,) = enqueue_jobs(r, settings.redis_prefix, principal, [meta.id], options, ledger=store.jobs)
    log.info("reprocess queued", extra={"session": meta.id, "method": options["method"]})
    return JobAccepted(job=job_id, session=meta.id, status_url=f"/v1/jobs/{job_id}")


@router.post("/v1/reprocess", status_code=status.HTTP_202_ACCEPTED, response_model=BatchAccepted)
def reprocess_batch(
    body: BatchReprocessRequest, principal: IngestPrincipal, store: Store, r: RedisClient, settings: AppSettings
) -> BatchAccepted:
    """Queue a reprocess of several sessions (admin, or the owner of every one; else 404 naming none)."""
    sessions = list(dict.fromkeys(body.sessions))  # de-duplicated, order kept
    metas = []
    for sid in sessions:
        if not isinstance(sid, str) or not _ID.match(sid):
            raise NotFound("no such session")
        metas.append(visible_session(store, principal, sid))
    checked = [validate_options(body.options.document(), store.calibration(m.id)) for m in metas]
    for m in metas:
        _check_reprocessable(store, m)
    _queue_guard(r, settings, len(metas))
    batch = uuid.uuid4().hex
    ids = enqueue_jobs(r, settings.redis_prefix, principal, sessions, checked[0], batch=batch, ledger=store.jobs)
    log.info("batch reprocess queued", extra={"frames": len(ids), "method": checked[0]["method"]})
    return BatchAccepted(batch=batch, jobs=ids, status_url=f"/v1/batches/{batch}")


ReadPrincipal = Depends(require_scope("ingest", "view"))


def _decode(raw: dict[Any, Any]) -> dict[str, str]:
    return {
        (k.decode() if isinstance(k, bytes) else k): (v.decode() if isinstance(v, bytes) else v) for k, v in raw.items()
    }


def _may_see(principal: Principal, owner: str) -> bool:
    return principal.is_admin or (
        principal.fingerprint is not None and hmac.compare_digest(principal.fingerprint, owner)
    )


def job_state(raw: dict[str, str], job_id: str) -> JobState:
    """Return the public state of a job from its hash."""

    def as_int(name: str) -> int:
        try:
            return int(float(raw.get(name) or 0))
        except ValueError:
            return 0

    done, total = as_int("done"), as_int("total")
    version = as_int("version") or None
    try:
        options = json.loads(raw.get("options") or "{}")
    except ValueError:
        options = {}
    created = raw.get("created")
    return JobState(
        id=job_id,
        state=raw.get("state") or "queued",
        session=raw.get("session", ""),
        version=version,
        done=done,
        total=total,
        progress=(min(1.0, done / total) if total > 0 else (1.0 if raw.get("state") == "done" else None)),
        error=raw.get("error") or None,
        created=float(created) if created else None,
        batch=raw.get("batch") or None,
        options=options if isinstance(options, dict) else {},
    )


@router.get("/v1/jobs/{job_id}", response_model=JobState)
def get_job(job_id: str, r: RedisClient, settings: AppSettings, principal: Principal = ReadPrincipal) -> JobState:
    """Return a job's state and progress (visible to the key that created it and to admin keys)."""
    raw = _decode(r.hgetall(queue.job_key(job_id, settings.redis_prefix))) if _ID.match(job_id) else {}
    if not raw or not _may_see(principal, raw.get("owner", "")):
        raise NotFound("no such job")
    return job_state(raw, job_id)


@router.get("/v1/batches/{batch_id}", response_model=BatchState)
def get_batch(batch_id: str, r: RedisClient, settings: AppSettings, principal: Principal = ReadPrincipal) -> BatchState:
    """Return a batch's jobs; its state is done when every job is done or failed, failed if any failed."""
    prefix = settings.redis_prefix
    raw = _decode(r.hgetall(queue.batch_key(batch_id, prefix))) if _ID.match(batch_id) else {}
    if not raw or not _may_see(principal, raw.get("owner", "")):
        raise NotFound("no such batch")
    ids = json.loads(raw.get("jobs") or "[]")
    pipe = r.pipeline(transaction=False)
    for job_id in ids:
        pipe.hgetall(queue.job_key(job_id, prefix))
    jobs = [job_state(_decode(h), job_id) for job_id, h in zip(ids, pipe.execute(), strict=True) if h]
    states = {j.state for j in jobs}
    if states <= {"done"}:
        overall = "done"
    elif states <= {"done", "failed"}:
        overall = "failed"
    elif states <= {"queued"}:
        overall = "queued"
    else:
        overall = "running"
    return BatchState(batch=batch_id, state=overall, jobs=jobs)
