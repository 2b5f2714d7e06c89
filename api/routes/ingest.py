"""Uploads during a scan: frames (multipart image + meta) and force/IMU batches (spec §5).

A 2xx answer means the bytes are durable on disk (and, for frames, the job is on the queue).
"""

from __future__ import annotations

import json
import logging
import struct
import threading
import time
import zlib
from typing import Annotated

import cv2
import numpy as np
import redis
from fastapi import APIRouter, File, Form, Response, UploadFile, status
from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError

from api.deps import AppSettings, IngestSession, RedisClient, Store
from api.errors import (
    BadRequest,
    Conflict,
    PayloadTooLarge,
    ServiceUnavailable,
    UnsupportedMediaType,
    Validation,
)
from api.schemas import ForceBatch, ForcesAccepted, FrameAccepted, FrameMeta
from services.core.image_header import check_header, read_header
from services.jobs import queue

router = APIRouter(prefix="/v1/sessions", tags=["ingest"])
log = logging.getLogger("veinmosaic.api")


class DepthGuard:
    """The queue-full check, with at most one Redis round trip per `every_s` while the queue is under half full.

    Far from the limit, the depth last read plus the uploads this process accepted since is a safe upper
    bound for a short while (workers only shrink the queue); near the limit every upload reads it afresh.
    """

    def __init__(self, every_s: float = 0.25) -> None:
        self.every_s = every_s
        self._read: dict[str, tuple[float, int]] = {}  # prefix -> (when, depth)
        self._since: dict[str, int] = {}  # prefix -> jobs accepted since that read
        self._lock = threading.Lock()

    def depth(self, r: redis.Redis, prefix: str, limit: int) -> int:
        """Return the queue depth (fresh, or a bound from a recent read when far below `limit`)."""
        now = time.monotonic()
        with self._lock:
            when, depth = self._read.get(prefix, (-1e9, 0))
            bound = depth + self._since.get(prefix, 0)
            if now - when < self.every_s and 2 * bound < limit:
                return bound
        depth = queue.queue_depth(r, prefix=prefix)
        with self._lock:
            self._read[prefix], self._since[prefix] = (now, depth), 0
        return depth

    def accepted(self, prefix: str) -> None:
        """Count one more job this process put on `prefix`'s queue."""
        with self._lock:
            self._since[prefix] = self._since.get(prefix, 0) + 1


_depth_guard = DepthGuard()


def sniff_image(data: bytes) -> str | None:
    """Return "png", "tif" or "jpg" from the file's magic bytes, or None for anything else."""
    if data.startswith(b"\x89PNG\r\n\x1a\n"):
        return "png"
    if data[:4] in (b"II*\x00", b"MM\x00*"):
        return "tif"
    if data.startswith(b"\xff\xd8\xff"):
        return "jpg"
    return None


MAX_PNG_CHUNKS = 65_536  # encoders write 8-64 KiB data chunks: a frame under max_frame_bytes has far fewer


def png_complete(data: bytes) -> bool:
    """Return True if a PNG's chunks are all whole with matching CRCs, ending with IEND (no pixels decoded).

    At most MAX_PNG_CHUNKS chunks are walked: a file made of millions of tiny chunks costs no more than that.
    """
    pos, end = 8, len(data)
    view = memoryview(data)
    for _ in range(MAX_PNG_CHUNKS):
        if pos + 12 > end:
            return False
        (length,) = struct.unpack_from(">I", data, pos)
        stop = pos + 12 + length
        if stop > end:
            return False
        if zlib.crc32(view[pos + 4 : stop - 4]) != struct.unpack_from(">I", data, stop - 4)[0]:
            return False
        if view[pos + 4 : pos + 8] == b"IEND":
            return True
        pos = stop
    return False


def check_frame(data: bytes, size: tuple[int, int], max_side: int) -> None:
    """Raise 422 unless the header states a grayscale `size` (width, height) image and the file is whole.

    The header is read (Pillow, no decoding) first: a file claiming a huge or a colour image costs no memory.
    Then the file's completeness is checked without decoding its pixels (the costly part of an upload): a
    PNG's every chunk CRC and its IEND, a JPEG's end-of-image marker; a TIFF (rare) is decoded, bounded by
    the checked size. A whole file whose compressed pixels are still bad is the frame's own content: the
    worker rejects it (poison, status rejected), never as an infrastructure fault.
    """
    header = read_header(data)
    check_header(header, max_side, size)  # BadImageError -> 422 invalid_image
    if header.format == "png":
        ok = png_complete(data)
    elif header.format == "jpg":
        ok = data.rstrip(b"\0\r\n").endswith(b"\xff\xd9")
    else:
        try:
            img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        except cv2.error:  # over OpenCV's own pixel limit
            img = None
        ok = img is not None and img.ndim == 2 and img.dtype in (np.uint8, np.uint16)
        ok = ok and (img.shape[1], img.shape[0]) == tuple(size)
    if not ok:
        raise Validation("image: the file is corrupt or truncated", code="invalid_image")


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
    response: Response,
) -> FrameAccepted:
    """Store one frame durably and queue it: 202; the same frame again 200; other bytes for its seq 409.

    Nothing is decoded for a seq already stored (a duplicate or a 409 is decided by its digest) nor for a
    finished session (409); a new frame's header must state the calibrated size before it is decoded (422).
    """
    data = image.file.read(settings.max_frame_bytes + 1)
    if len(data) > settings.max_frame_bytes:
        raise PayloadTooLarge(f"image: larger than {settings.max_frame_bytes} bytes")
    ext = sniff_image(data)
    if ext is None:
        raise UnsupportedMediaType("image: expected a PNG, TIFF or JPEG file")
    frame = parse_meta(meta)
    prefix = settings.redis_prefix

    if store.get_frame(session.id, frame.seq) is None:
        if not session.accepting_uploads or not store.get_meta(session.id).accepting_uploads:
            raise Conflict("session is finished; no more uploads are accepted", code="session_finished")
        check_frame(data, tuple(session.calibration["image_size"]), settings.max_frame_side)
        if _depth_guard.depth(r, prefix, settings.queue_max_depth) >= settings.queue_max_depth:
            raise ServiceUnavailable(
                "the processing queue is full; retry later", settings.retry_after_s, code="queue_full"
            )
    # 409 on conflict or after finish, 409 implausible_timestamp; "duplicate" for the same bytes and t_s
    outcome = store.put_frame(session.id, frame.seq, frame.t_s, data, ext, max_span_s=settings.max_session_span_s)
    # Idempotent: a frame stored by an earlier attempt whose enqueue failed is queued now, never twice.
    duplicate = outcome == "duplicate"
    queue.enqueue_frame(r, session.id, frame.seq, prefix=prefix, count=None if duplicate else "uploads_total")
    if duplicate:
        response.status_code = status.HTTP_200_OK
        return FrameAccepted(seq=frame.seq, status="duplicate")
    _depth_guard.accepted(prefix)
    log.info("frame accepted", extra={"session": session.id, "seq": frame.seq, "bytes": len(data)})
    return FrameAccepted(seq=frame.seq, status="accepted")


@router.post("/{session_id}/forces", status_code=status.HTTP_202_ACCEPTED, response_model=ForcesAccepted)
def upload_forces(body: ForceBatch, session: IngestSession, store: Store, settings: AppSettings) -> ForcesAccepted:
    """Store one force batch (and IMU rows) as received; batches may overlap and come in any order."""
    imu = body.imu or []
    if len(body.samples) + len(imu) > settings.max_force_samples:
        raise PayloadTooLarge(f"a batch holds at most {settings.max_force_samples} rows; split it")
    # 409 after finish, 409 implausible_timestamp when a time is far from the session's first ones
    store.put_forces(session.id, body.samples, imu, max_span_s=settings.max_session_span_s)
    return ForcesAccepted(accepted=len(body.samples), imu_accepted=len(imu))
