"""DICOMweb STOW-RS (PS3.18 10.5): every object in one multipart/related POST to <base>/studies, with httpx.

The answer is read per instance: the Store Instances Response's ReferencedSOPSequence (stored, possibly with
a warning) and FailedSOPSequence (refused, with a FailureReason). HTTP 200 means all stored, 202 some, 409
none; 408, 429 and 5xx are passing faults (PacsUnreachable); other 4xx refuse the request (PacsRejected).
"""

from __future__ import annotations

import time
import uuid
from collections.abc import Sequence
from typing import Any

import httpx

from services.pacs.destinations import DicomWebDestination
from services.pacs.objects import DicomObject
from services.pacs.outcome import PacsRejected, PacsUnreachable, SendOutcome, conclude

REFERENCED_SOP_SEQUENCE = "00081199"
FAILED_SOP_SEQUENCE = "00081198"
REFERENCED_SOP_INSTANCE_UID = "00081155"
FAILURE_REASON = "00081197"
_RETRY_STATUSES = frozenset({408, 429})
_REQUEST_REFUSED = {
    401: "the credentials were refused",
    403: "the credentials were refused",
    404: "no STOW-RS service at this URL",
    405: "no STOW-RS service at this URL",
    413: "the request is too large for this PACS",
    415: "the PACS does not accept application/dicom",
}


def multipart_body(objects: Sequence[DicomObject], boundary: str) -> bytes:
    """Return the multipart/related body: one application/dicom part per object."""
    chunks: list[bytes] = []
    for obj in objects:
        chunks += [f"--{boundary}\r\nContent-Type: application/dicom\r\n\r\n".encode(), obj.data, b"\r\n"]
    chunks.append(f"--{boundary}--\r\n".encode())
    return b"".join(chunks)


def stow(destination: DicomWebDestination, objects: Sequence[DicomObject], timeout_s: float) -> SendOutcome:
    """Return the per-instance outcome of storing `objects` by STOW-RS, or raise PacsUnreachable / PacsRejected."""
    started = time.monotonic()
    where = destination.describe()
    boundary = f"veinmosaic-{uuid.uuid4().hex}"
    headers = {
        **destination.headers,
        "Content-Type": f'multipart/related; type="application/dicom"; boundary={boundary}',
        "Accept": "application/dicom+json",
    }
    try:
        with httpx.Client(timeout=timeout_s, follow_redirects=False) as client:
            resp = client.post(destination.stow_url, content=multipart_body(objects, boundary), headers=headers)
    except httpx.TimeoutException:
        raise PacsUnreachable(f"{where}: no answer within {timeout_s:g} s") from None
    except httpx.TransportError as exc:  # refused, reset, DNS, TLS: its type only (its text may quote the URL)
        raise PacsUnreachable(f"{where}: cannot connect ({type(exc).__name__})") from None
    status = resp.status_code
    if status >= 500 or status in _RETRY_STATUSES:
        raise PacsUnreachable(f"{where}: HTTP {status} (a fault of the PACS or a proxy; worth retrying)")
    if status in _REQUEST_REFUSED or 300 <= status < 400 or status < 200:
        reason = _REQUEST_REFUSED.get(status, "unexpected answer to STOW-RS")
        raise PacsRejected(f"{where}: HTTP {status}: {reason}")
    results: dict[str, int | str] = _per_instance(resp)
    default: int | str = 0x0000 if status == 200 else f"HTTP {status} without a status for this instance"
    for obj in objects:
        results.setdefault(obj.sop_instance_uid, default)
    return conclude(where, objects, results, started)


def _per_instance(resp: httpx.Response) -> dict[str, int | str]:
    """Return {SOP Instance UID: status code} from a Store Instances Response (DICOM JSON); {} if none."""
    try:
        doc = resp.json()
    except ValueError:
        return {}
    if isinstance(doc, list) and len(doc) == 1:  # some servers wrap the one response data set in an array
        doc = doc[0]
    if not isinstance(doc, dict):
        return {}
    out: dict[str, int | str] = {}
    for item in _items(doc, REFERENCED_SOP_SEQUENCE):
        uid = _value(item, REFERENCED_SOP_INSTANCE_UID)
        if isinstance(uid, str):
            out[uid] = 0x0000  # stored; a WarningReason (coercion, elements discarded) does not undo that
    for item in _items(doc, FAILED_SOP_SEQUENCE):
        uid = _value(item, REFERENCED_SOP_INSTANCE_UID)
        if isinstance(uid, str):
            reason = _value(item, FAILURE_REASON)
            out[uid] = reason if isinstance(reason, int) else "refused without a failure reason"
    return out


def _items(doc: dict[str, Any], tag: str) -> list[dict[str, Any]]:
    element = doc.get(tag)
    values = element.get("Value") if isinstance(element, dict) else None
    return [v for v in values if isinstance(v, dict)] if isinstance(values, list) else []


def _value(item: dict[str, Any], tag: str) -> object:
    element = item.get(tag)
    values = element.get("Value") if isinstance(element, dict) else None
    return values[0] if isinstance(values, list) and values else None
