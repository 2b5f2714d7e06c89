"""Uploads during a scan: frames (multipart image + meta) and force/IMU batches (spec §5).

A 2xx answer means the bytes are durable on disk (and, for frames, the job is on the queue).
"""

from __future__ import annotations

import json
import logging
from typing import Annotated

from fastapi import APIRouter, File, Form, Response, UploadFile, status
from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError

from api.deps import AppSettings, IngestSession, QueueGuard, RedisClient, Store
from api.errors import (
    BadRequest,
    Conflict,
    PayloadTooLarge,
    ServiceUnavailable,
    UnsupportedMediaType,
)
from api.schemas import ForceBatch, ForcesAccepted, FrameAccepted, FrameMeta
from services.core.inputs.image_header import check_frame_file, sniff_image
from services.jobs import queue, quotas

router = APIRouter(prefix="/v1/sessions", tags=["ingest"])
log = logging.getLogger("veinmosaic.api")


def parse_meta(raw: str) -> FrameMeta:
    """Return the validated `meta` form field; 400 if it is not JSON, 422 naming the field otherwise."""
    try:
        doc = json.loads(raw)
    except ValueError:
        raise BadRequest("meta: not valid JSON", code="malformed_json") from None
    try:
        return FrameMeta.model_validate(doc)
    except ValidationError as exc:
        errors = [{**e, "loc": ("meta", *e["loc"])} for e in exc.errors(include_input=False)]
        raise RequestValidationError(errors) from None


@router.post(
    "/{session_id}/frames",
    status_code=status.HTTP_202_ACCEPTED,
    response_model=FrameAccepted,
    responses={200: {"model": FrameAccepted, "description": "the same frame was already received (no-op)"}},
)
def upload_frame(
    session: IngestSession,
    image: Annotated[UploadFile, File(description="PNG, TIFF or JPEG; grayscale 8/16-bit")],
    meta: Annotated[str, Form(description='JSON {"seq": int, "t_s": float}')],
    store: Store,
    r: RedisClient,
    settings: AppSettings,
    guard: QueueGuard,
    response: Response,
) -> FrameAccepted:
    """Return the acceptance of one frame stored durably and queued: 202; the same frame again 200; other bytes 409.

    Nothing is decoded for a seq already stored (a duplicate or a 409 is decided by its digest) nor for a
    finished session (409); a new frame's header must state the calibrated size before it is decoded (422); a new
    frame beyond its key's quota of frames in this window is 429.
    """
    data = image.file.read(settings.max_frame_bytes + 1)
    if len(data) > settings.max_frame_bytes:
        raise PayloadTooLarge(f"image: larger than {settings.max_frame_bytes} bytes")
    ext = sniff_image(data)
    if ext is None:
        raise UnsupportedMediaType("image: expected a PNG, TIFF or JPEG file")
    frame = parse_meta(meta)
    prefix = settings.redis_prefix

    counted = None  # a new frame counts against its key's quota of frames (a re-sent one does not)
    if store.get_frame(session.id, frame.seq) is None:
        if not session.accepting_uploads or not store.get_meta(session.id).accepting_uploads:
            raise Conflict("session is finished; no more uploads are accepted", code="session_finished")
        check_frame_file(data, tuple(session.calibration["image_size"]), settings.max_frame_side)
        if guard.depth(r, prefix, settings.queue_max_depth) >= settings.queue_max_depth:
            raise ServiceUnavailable(
                "the processing queue is full; retry later", settings.retry_after_s, code="queue_full"
            )
        quota, window_s = settings.quota_frames_per_key, settings.quota_window_s
        counted = quotas.take(r, prefix, session.owner, "frames", quota, window_s)  # KeyQuotaError: 429 (api.errors)
    try:  # 409 on conflict or after finish, 409 implausible_timestamp; "duplicate" for the same bytes and t_s
        outcome = store.put_frame(session.id, frame.seq, frame.t_s, data, ext, max_span_s=settings.max_session_span_s)
    except BaseException:
        quotas.give_back(r, counted)
        raise
    # Idempotent: a frame stored by an earlier attempt whose enqueue failed is queued now, never twice.
    duplicate = outcome == "duplicate"
    if duplicate:  # stored by a concurrent request meanwhile: counted there
        quotas.give_back(r, counted)
    queue.enqueue_frame(r, session.id, frame.seq, prefix=prefix, count=None if duplicate else "uploads_total")
    if duplicate:
        response.status_code = status.HTTP_200_OK
        return FrameAccepted(seq=frame.seq, status="duplicate")
    guard.accepted(prefix)
    log.info("frame accepted", extra={"session": session.id, "seq": frame.seq, "bytes": len(data)})
    return FrameAccepted(seq=frame.seq, status="accepted")


@router.post("/{session_id}/forces", status_code=status.HTTP_202_ACCEPTED, response_model=ForcesAccepted)
def upload_forces(body: ForceBatch, session: IngestSession, store: Store, settings: AppSettings) -> ForcesAccepted:
    """Return the rows accepted of one force batch (and IMU rows) stored as received; batches may overlap, any order."""
    imu = body.imu or []
    if len(body.samples) + len(imu) > settings.max_force_samples:
        raise PayloadTooLarge(f"a batch holds at most {settings.max_force_samples} rows; split it")
    # 409 after finish, 409 implausible_timestamp when a time is far from the session's first ones
    store.put_forces(session.id, body.samples, imu, max_span_s=settings.max_session_span_s)
    return ForcesAccepted(accepted=len(body.samples), imu_accepted=len(imu))
