"""Session lifecycle: create (with calibration), read state, finish (spec §5)."""

from __future__ import annotations

import logging

from fastapi import APIRouter, Request, Response, status

from api.auth import make_viewer_token
from api.deps import (
    AppSettings,
    IngestPrincipal,
    IngestSession,
    RedisClient,
    Store,
    ViewPrincipal,
    ViewSession,
)
from api.errors import Validation
from api.results_access import Results, reprocess_running, resolve_version, session_extent
from api.schemas import Accepted, SessionCreate, SessionCreated, SessionState
from services.core.inputs.calibration import parse_calibration
from services.core.outputs.scan_quality import live_lag, scan_warnings, summarize_frames
from services.jobs import job_records as jobs
from services.jobs import queue, quotas

router = APIRouter(prefix="/v1/sessions", tags=["sessions"])
log = logging.getLogger("veinmosaic.api")


@router.post("", status_code=status.HTTP_201_CREATED, response_model=SessionCreated)
def create_session(
    body: SessionCreate,
    principal: IngestPrincipal,
    store: Store,
    r: RedisClient,
    settings: AppSettings,
    request: Request,
    response: Response,
) -> SessionCreated:
    """Return the session created (201), owned by the calling key; 422 naming the field for a bad calibration;
    429 when the key created its quota of sessions in this window."""
    width, height = body.calibration.image_size
    if max(width, height) > settings.max_frame_side:
        raise Validation(
            f"calibration: image_size: at most {settings.max_frame_side} pixels a side", code="invalid_calibration"
        )
    calibration = parse_calibration(body.calibration.document())  # CalibrationError: 422 invalid_calibration
    study = body.study.context() if body.study is not None else None  # StudyContextError: 422 invalid_study
    assert principal.fingerprint is not None
    counted = quotas.take(  # KeyQuotaError: 429 quota_exceeded with Retry-After (api/errors.py)
        r, settings.redis_prefix, principal.fingerprint, "sessions", settings.quota_sessions_per_key,
        settings.quota_window_s,
    )  # fmt: skip
    try:
        meta = store.create_session(principal.fingerprint, body.label, calibration, study=study)
    except BaseException:
        quotas.give_back(r, counted)
        raise
    now = request.app.state.clock()
    token = make_viewer_token(request.app.state.token_secrets, meta.id, settings.viewer_token_ttl_s, now)
    response.headers["Location"] = f"/v1/sessions/{meta.id}"
    log.info("session created", extra={"session": meta.id})
    return SessionCreated(
        id=meta.id,
        viewer_url=f"/viewer/{meta.id}?token={token}",
        viewer_token=token,
        viewer_token_expires=int(now + settings.viewer_token_ttl_s),
    )


@router.get("/{session_id}", response_model=SessionState)
def get_session(
    meta: ViewSession,
    principal: ViewPrincipal,
    store: Store,
    r: RedisClient,
    settings: AppSettings,
    results: Results,
) -> SessionState:
    """Return the session's status and frame counters (received from storage, processed/lost from workers)."""
    counters = queue.session_counters(r, meta.id, prefix=settings.redis_prefix)
    version = resolve_version(results, meta.id, None)
    rows = results.read_path(meta.id, version) if version is not None else None
    frames = summarize_frames(rows) if rows else None
    lag = live_lag(queue.recent_lags(r, meta.id, prefix=settings.redis_prefix)) if meta.status != "done" else None
    return SessionState(
        id=meta.id,
        status=meta.status,  # type: ignore[arg-type]
        label=meta.label if principal.session_id is None else None,  # viewer links never see the label
        study=meta.study if principal.session_id is None else None,  # nor the study context
        created=meta.created,
        finished=meta.finished_at is not None,
        frames_received=store.count_frames(meta.id),
        frames_processed=counters["processed"],
        frames_lost=counters["lost"],
        frames_rejected=frames.n_rejected if frames else 0,
        registered_fraction=frames.registered_fraction if frames else None,
        not_placed_reasons=frames.reasons if frames else {},
        warnings=scan_warnings(frames, meta.status, reprocess_running(results, meta.id), lag),
        lag=lag.to_dict() if lag is not None else None,
        extent=session_extent(results, meta.id),
        tissue=(results.read_mosaic_meta(meta.id, version) or {}).get("tissue") if version is not None else None,
    )


@router.post("/{session_id}/finish", status_code=status.HTTP_202_ACCEPTED, response_model=Accepted)
def finish_session(meta: IngestSession, store: Store, r: RedisClient, settings: AppSettings) -> Accepted:
    """Return the session's id and status (202) after recording that no more uploads come (idempotent).

    The finish marker is queued after the frame jobs; the first finish also queues a send to each auto-send PACS
    destination (the job waits until the session is done).
    """
    first = meta.finished_at is None
    meta = store.finish(meta.id)
    queue.enqueue_finish(r, meta.id, prefix=settings.redis_prefix)
    if first and settings.pacs_auto_send:
        for name in settings.pacs_auto_send:
            jobs.enqueue_jobs(
                r, settings.redis_prefix, meta.owner, [meta.id], {"destination": name}, ledger=store.jobs, kind="send",
                in_flight=settings.queue_jobs_in_flight,
            )  # fmt: skip
    log.info("session finished", extra={"session": meta.id, "frames": meta.frames_expected})
    return Accepted(id=meta.id, status=meta.status)
