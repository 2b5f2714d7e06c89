"""Uploads during a scan: frames (multipart image + meta) and force/IMU batches (spec §5).

A 2xx answer means the bytes are durable on disk (and, for frames, the job is on the queue).
"""

from __future__ import annotations

import json
import logging
import struct
from typing import Annotated

import cv2
import numpy as np
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
from api.routes.metrics import incr
from api.schemas import ForceBatch, ForcesAccepted, FrameAccepted, FrameMeta
from services import queue

router = APIRouter(prefix="/v1/sessions", tags=["ingest"])
log = logging.getLogger("veinmosaic.api")

_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def sniff_image(data: bytes) -> str | None:
    """Return "png", "tif" or "jpg" from the file's magic bytes, or None for anything else."""
    if data.startswith(b"\x89PNG\r\n\x1a\n"):
        return "png"
    if data[:4] in (b"II*\x00", b"MM\x00*"):
        return "tif"
    if data.startswith(b"\xff\xd8\xff"):
        return "jpg"
    return None


def header_size(data: bytes, ext: str) -> tuple[int, int]:
    """Return (width, height) in pixels from the image header, before decoding (no decompression bombs)."""
    try:
        if ext == "png":
            if data[12:16] != b"IHDR":
                raise ValueError
            return struct.unpack(">II", data[16:24])
        if ext == "jpg":
            i = 2
            while i + 4 <= len(data):
                if data[i] != 0xFF:
                    raise ValueError
                marker = data[i + 1]
                if marker == 0xFF or 0xD0 <= marker <= 0xD8 or marker == 0x01:
                    i += 1 if marker == 0xFF else 2
                    continue
                (length,) = struct.unpack(">H", data[i + 2 : i + 4])
                if marker in _SOF:
                    height, width = struct.unpack(">HH", data[i + 5 : i + 9])
                    return width, height
                i += 2 + length
            raise ValueError
        bo = "<" if data[:2] == b"II" else ">"
        (ifd,) = struct.unpack(bo + "I", data[4:8])
        (count,) = struct.unpack(bo + "H", data[ifd : ifd + 2])
        dims: dict[int, int] = {}
        for k in range(count):
            tag, typ, _, value = struct.unpack(bo + "HHI4s", data[ifd + 2 + 12 * k : ifd + 14 + 12 * k])
            if tag in (256, 257):
                dims[tag] = struct.unpack(bo + ("H" if typ == 3 else "I"), value[: 2 if typ == 3 else 4])[0]
        return dims[256], dims[257]
    except (ValueError, struct.error, KeyError, IndexError):
        raise Validation("image: the file is corrupt (unreadable header)", code="invalid_image") from None


def check_frame(data: bytes, ext: str, size: tuple[int, int]) -> None:
    """Raise 422 unless `data` decodes to a single-channel 8/16-bit image of `size` (width, height) pixels."""
    w, h = header_size(data, ext)
    if (w, h) != tuple(size):
        raise Validation(
            f"image: expected {size[0]}x{size[1]} pixels (calibration image_size), got {w}x{h}",
            code="invalid_image",
        )
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise Validation("image: the file is corrupt (cannot be decoded)", code="invalid_image")
    if img.ndim != 2:
        raise Validation(
            f"image: expected a single-channel (grayscale) image, got {img.shape[2]} channels",
            code="invalid_image",
        )
    if img.dtype not in (np.uint8, np.uint16):
        raise Validation(f"image: expected 8- or 16-bit pixels, got {img.dtype}", code="invalid_image")
    if (img.shape[1], img.shape[0]) != tuple(size):
        raise Validation(
            f"image: expected {size[0]}x{size[1]} pixels, got {img.shape[1]}x{img.shape[0]}",
            code="invalid_image",
        )


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
    """Store one frame durably and queue it: 202; the same frame again 200; other bytes for its seq 409."""
    data = image.file.read(settings.max_frame_bytes + 1)
    if len(data) > settings.max_frame_bytes:
        raise PayloadTooLarge(f"image: larger than {settings.max_frame_bytes} bytes")
    ext = sniff_image(data)
    if ext is None:
        raise UnsupportedMediaType("image: expected a PNG, TIFF or JPEG file")
    frame = parse_meta(meta)
    check_frame(data, ext, tuple(session.calibration["image_size"]))
    prefix = settings.redis_prefix

    if store.get_frame(session.id, frame.seq) is None:
        if not store.get_meta(session.id).accepting_uploads:
            raise Conflict("session is finished; no more uploads are accepted", code="session_finished")
        depth = queue.queue_depth(r, prefix=prefix)
        if depth >= settings.queue_max_depth:
            raise ServiceUnavailable(
                "the processing queue is full; retry later", settings.retry_after_s, code="queue_full"
            )
        outcome = store.put_frame(session.id, frame.seq, frame.t_s, data, ext)  # 409 on conflict
    else:
        outcome = store.put_frame(session.id, frame.seq, frame.t_s, data, ext)  # duplicate or 409
    # Idempotent: a frame stored by an earlier attempt whose enqueue failed is queued now, never twice.
    queue.enqueue_frame(r, session.id, frame.seq, prefix=prefix)
    if outcome == "duplicate":
        response.status_code = status.HTTP_200_OK
        return FrameAccepted(seq=frame.seq, status="duplicate")
    incr(r, prefix, "uploads_total")
    log.info("frame accepted", extra={"session": session.id, "seq": frame.seq, "bytes": len(data)})
    return FrameAccepted(seq=frame.seq, status="accepted")


@router.post("/{session_id}/forces", status_code=status.HTTP_202_ACCEPTED, response_model=ForcesAccepted)
def upload_forces(body: ForceBatch, session: IngestSession, store: Store, settings: AppSettings) -> ForcesAccepted:
    """Store one force batch (and IMU rows) as received; batches may overlap and come in any order."""
    imu = body.imu or []
    if len(body.samples) + len(imu) > settings.max_force_samples:
        raise PayloadTooLarge(f"a batch holds at most {settings.max_force_samples} rows; split it")
    store.put_forces(session.id, body.samples, imu)  # 409 after finish
    return ForcesAccepted(accepted=len(body.samples), imu_accepted=len(imu))
