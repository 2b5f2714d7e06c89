"""Send jobs: a session's DICOM objects (each layer and the one-page report) to a PACS destination (spec §5).

Steps: read the job's destination, wait until the session is done, build the objects of its newest finished
results version (services.store.session_export: the same objects GET export.dcm serves), send them
(services.pacs), record the outcome in the job hash and the audit log. An unreachable PACS (refused, timed
out, 5xx, association rejected) is retried with exponential back-off up to `pacs_max_attempts` attempts; a
PACS that refuses the objects fails the job at once. Sending again stores the same instances: the objects'
UIDs come from the session's identity and content, so a retry or a second job never duplicates anything.

A job's error is shown to API clients (GET /v1/jobs/{id}): it names the destination by its configured name,
never its host, port or URL (those stay in the worker's log, for the operator).
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from urllib.parse import urlsplit

from services.jobs import job_records as jobs
from services.jobs import queue
from services.pacs.destinations import Destination, DicomWebDestination
from services.pacs.send import PacsRejected, PacsUnreachable, send_objects
from services.store.session_export import finished_version, session_objects
from services.store.storage import SessionNotFoundError
from workers.config import Context
from workers.publisher import Publisher
from workers.retry import Retry

log = logging.getLogger("veinmosaic.worker")


def _attempts(ctx: Context, job_id: str) -> int:
    return int(jobs.job_view(jobs.read_job(ctx.r, ctx.prefix, job_id), job_id)["attempts"])


def retry_delay_s(attempt: int, first_s: float, max_s: float) -> float:
    """Return the wait (s) before attempt `attempt + 1`: first_s doubled per attempt made, capped at max_s."""
    return float(min(max_s, first_s * 2 ** max(0, attempt - 1)))


def public_error(message: str, destination: Destination, name: str) -> str:
    """Return a send failure's message as a job shows it: the destination by `name`, without its address."""
    text = message.replace(destination.describe(), f"destination {name!r}")
    if isinstance(destination, DicomWebDestination):
        parts = urlsplit(destination.base_url)
        address = [destination.base_url, parts.netloc, parts.hostname or ""]
    else:
        address = [f"{destination.host}:{destination.port}", destination.host]
    for piece in address:
        if piece:
            text = text.replace(piece, "(the PACS)")
    return text[:300]


def handle_send(ctx: Context, fields: dict[str, str], heartbeat: Callable[[], None]) -> Retry | None:
    """Return a Retry (session not done yet, PACS unreachable) or None (done or failed) of one send job's attempt."""
    cfg, pub = ctx.config, Publisher(ctx)
    job_id, sid = fields.get("job", ""), fields.get("session", "")
    try:
        name = str(json.loads(fields.get("options") or "{}").get("destination") or "")
    except (ValueError, AttributeError):
        name = ""
    destination = cfg.pacs_destinations.get(name)
    if destination is None:
        ctx.update_job(job_id, state="failed", error="destination not configured on the worker")
        pub.audit_send(sid, job_id, name, "failed", 0)
        return None
    try:
        meta = ctx.store.get_meta(sid)
    except SessionNotFoundError:
        ctx.update_job(job_id, state="failed", error="no such session")
        return None
    version = finished_version(ctx.results, sid) if meta.status == "done" else None
    if version is None:
        if meta.status == "failed":
            ctx.update_job(job_id, state="failed", error="the session failed: no results to send")
            pub.audit_send(sid, job_id, name, "failed", 0)
            return None
        ctx.update_job(job_id, state="queued", error="waiting for the session's results")
        return Retry(cfg.pacs_wait_s, "session not done")
    attempt = _attempts(ctx, job_id) + 1
    ctx.update_job(job_id, state="running", version=version, attempts=attempt, error="", started=time.time())
    heartbeat()
    objects = session_objects(ctx.store, ctx.results, sid, version)
    ctx.update_job(job_id, total=len(objects), done=0)
    heartbeat()
    try:
        outcome = send_objects(destination, list(objects.values()), timeout_s=cfg.pacs_timeout_s)
    except PacsUnreachable as exc:
        if attempt >= cfg.pacs_max_attempts:
            error = f"destination unreachable after {attempt} attempts: {exc}"
            ctx.update_job(job_id, state="failed", error=public_error(error, destination, name))
            pub.audit_send(sid, job_id, name, "failed", 0, version)
            return None
        delay = retry_delay_s(attempt, cfg.pacs_retry_first_s, cfg.pacs_retry_max_s)
        error = f"destination unreachable ({exc}); retry in {delay:.1f} s"
        ctx.update_job(job_id, state="queued", error=public_error(error, destination, name))
        pub.audit_send(sid, job_id, name, "retry", 0, version)
        log.warning("PACS unreachable; send retried in %.1f s (attempt %d)", delay, attempt, extra={"session": sid})
        return Retry(delay, "PACS unreachable")
    except PacsRejected as exc:
        error = f"the destination refused the objects: {exc}"
        ctx.update_job(job_id, state="failed", error=public_error(error, destination, name))
        pub.audit_send(sid, job_id, name, "rejected", 0, version)
        return None
    if not outcome.ok:  # some objects stored, others refused (a retry would be refused again)
        refused = ", ".join(f"{uid}: {why}" for uid, why in outcome.failed.items())
        error = public_error(f"the destination refused {refused}", destination, name)
        ctx.update_job(job_id, state="failed", done=outcome.sent, error=error)
        pub.audit_send(sid, job_id, name, "partly rejected", outcome.sent, version)
        return None
    ctx.update_job(job_id, state="done", done=outcome.sent, finished=time.time())
    pub.audit_send(sid, job_id, name, "done", outcome.sent, version)
    queue.incr_metric(ctx.r, "pacs_sends_total", prefix=ctx.prefix)
    log.info("sent %d DICOM objects", outcome.sent, extra={"session": sid})
    return None
