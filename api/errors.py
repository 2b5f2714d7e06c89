"""Every error -> HTTP status mapping, in one place; every error body is {"error": {"code", "message"}}.

Malformed JSON (a request body or the `meta` form field that does not parse) is 400 "malformed_json";
well-formed JSON that breaks the schema is 422 "validation_error" (with "details": [{"field", "message"}],
never echoing the submitted values, which may be patient data).

Storage faults (ENOSPC, EDQUOT: "insufficient_storage"; EIO, EROFS: "storage_unavailable") are 503 with
Retry-After, not 507: spec §5 lists 503 as the "retry later" answer, every client (cli/client.py included)
already retries it, and a balancer reading /readyz (503 below the free-space floor) stops sending meanwhile.
Nothing partial is kept: the store's writers remove their temporary files when a write fails.

`RESPONSES` is the one table of documented error answers: routes state theirs in the OpenAPI schema from it.
"""

# ruff: noqa: N818  (the HTTP names NotFound, Conflict, ... read better than NotFoundError)
from __future__ import annotations

import errno
import logging
from typing import Any

import redis
from fastapi import FastAPI, HTTPException, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from services.core.inputs.calibration import CalibrationError
from services.core.inputs.image_header import BadImageError
from services.core.inputs.study import StudyContextError
from services.core.method_options import without_values
from services.jobs.job_records import OwnerQuotaError, QueueFullError
from services.jobs.quotas import KeyQuotaError
from services.log_format import failure_frames, failure_reason
from services.store.session_export import NotFinishedError
from services.store.storage import ConflictError, ImplausibleTimeError, SessionClosedError, SessionNotFoundError
from services.store.stored_report import BadReferenceError, NoPathYetError, NothingToCompareError

log = logging.getLogger("veinmosaic.api")


class APIError(Exception):
    """An error with a status, a stable machine code and a human message safe to show to the client."""

    status = 500
    code = "internal_error"

    def __init__(self, message: str, *, code: str | None = None, headers: dict[str, str] | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.code = code or self.code
        self.headers = headers or {}


class BadRequest(APIError):
    status, code = 400, "bad_request"


class Unauthorized(APIError):
    status, code = 401, "unauthorized"

    def __init__(self, message: str = "a valid bearer key or viewer token is required", **kw: Any) -> None:
        super().__init__(message, **kw)
        self.headers.setdefault("WWW-Authenticate", 'Bearer realm="veinmosaic"')


class Forbidden(APIError):
    status, code = 403, "forbidden"


class NotFound(APIError):
    status, code = 404, "not_found"


class Conflict(APIError):
    status, code = 409, "conflict"


class PayloadTooLarge(APIError):
    status, code = 413, "payload_too_large"


class UnsupportedMediaType(APIError):
    status, code = 415, "unsupported_media_type"


class Validation(APIError):
    status, code = 422, "validation_error"


class TooManyRequests(APIError):
    status, code = 429, "rate_limited"

    def __init__(self, message: str, retry_after_s: int = 1, **kw: Any) -> None:
        super().__init__(message, **kw)
        self.headers.setdefault("Retry-After", str(max(1, int(retry_after_s))))


class ServiceUnavailable(APIError):
    status, code = 503, "service_unavailable"

    def __init__(self, message: str, retry_after_s: int = 2, **kw: Any) -> None:
        super().__init__(message, **kw)
        self.headers.setdefault("Retry-After", str(int(retry_after_s)))


class BodyTooLarge(HTTPException):
    """Raised while a request body is read, as soon as it passes the route's limit (api.app's middleware).

    An HTTPException, so FastAPI's body parsing re-raises it instead of turning it into a 400.
    """

    def __init__(self, limit: int) -> None:
        super().__init__(413, f"request body larger than {limit} bytes")


# errno of a failed write -> (code, message): the data volume is full or failing; answered 503 + Retry-After
STORAGE_ERRNOS: dict[int, tuple[str, str]] = {
    errno.ENOSPC: ("insufficient_storage", "the data volume is full; retry later"),
    errno.EDQUOT: ("insufficient_storage", "the data volume's quota is exhausted; retry later"),
    errno.EIO: ("storage_unavailable", "the data volume failed a write; retry later"),
    errno.EROFS: ("storage_unavailable", "the data volume is read-only; retry later"),
}

# Exceptions raised below the web layer: (status, code, message shown; None = the exception's own message).
SERVICE_ERRORS: dict[type[Exception], tuple[int, str, str | None]] = {
    SessionNotFoundError: (404, "not_found", "no such session"),
    ConflictError: (409, "conflict", None),
    SessionClosedError: (409, "session_finished", None),
    ImplausibleTimeError: (409, "implausible_timestamp", None),
    CalibrationError: (422, "invalid_calibration", None),
    BadImageError: (422, "invalid_image", None),
    BadReferenceError: (422, "invalid_reference", None),
    NothingToCompareError: (422, "nothing_to_compare", None),
    NoPathYetError: (409, "not_ready", None),
    StudyContextError: (422, "invalid_study", None),
    NotFinishedError: (404, "not_ready", None),
    QueueFullError: (
        503,
        "queue_full",
        "the job queue is full; retry later",
    ),  # its message names the field, never the value
    OwnerQuotaError: (429, "quota_exceeded", None),  # its message names the quota
    KeyQuotaError: (429, "quota_exceeded", None),  # sessions or frames per window; Retry-After: the window's end
    redis.ConnectionError: (503, "queue_unavailable", "the job queue is unreachable; retry later"),
    redis.TimeoutError: (503, "queue_unavailable", "the job queue is unreachable; retry later"),
}
HTTP_CODES = {400: "bad_request", 404: "not_found", 405: "method_not_allowed", 413: "payload_too_large"}


def error_body(code: str, message: str, **extra: Any) -> dict[str, Any]:
    """Return the JSON error document of spec §5."""
    return {"error": {"code": code, "message": message, **extra}}


def error_response(
    status: int, code: str, message: str, headers: dict[str, str] | None = None, **extra: Any
) -> JSONResponse:
    """Return a JSONResponse with the error document."""
    return JSONResponse(error_body(code, message, **extra), status_code=status, headers=headers)


INTERNAL_ERROR_MESSAGE = "internal error; quote the X-Request-ID (it identifies the error in the logs)"


def escaped_error_response(exc: Exception) -> JSONResponse:
    """Return the answer to an exception that escaped the app into the request middleware: 413 or 500."""
    if isinstance(exc, BodyTooLarge):
        return error_response(413, "payload_too_large", str(exc.detail))
    return error_response(500, "internal_error", INTERNAL_ERROR_MESSAGE)


def _field(loc: tuple[Any, ...]) -> str:
    parts = [str(p) for p in loc]
    if parts and parts[0] in ("body", "query", "path", "header", "form"):
        parts = parts[1:]
    return ".".join(parts) or "body"


def validation_response(errors: list[dict[str, Any]]) -> JSONResponse:
    """Return 400 for unparseable JSON, else 422 naming every failing field (values never echoed).

    The code is "invalid_calibration" when every failing field is inside a calibration, "invalid_options"
    inside reprocess options (as their semantic checks answer), else "validation_error".
    """
    if any(e.get("type") == "json_invalid" for e in errors):
        return error_response(400, "malformed_json", "the request body is not valid JSON")
    details = [{"field": _field(tuple(e.get("loc", ()))), "message": str(e.get("msg", "invalid"))} for e in errors]
    message = "; ".join(f"{d['field']}: {d['message']}" for d in details) or "invalid request"
    return error_response(422, _validation_code(details), message, details=details)


# a 422 whose failing fields all lie in one part of a body is named after that part (as its semantic checks are)
_PART_CODES = (
    ("calibration", "invalid_calibration"),
    ("options.calibration", "invalid_calibration"),
    ("study", "invalid_study"),
)


def _validation_code(details: list[dict[str, str]]) -> str:
    if not details:
        return "validation_error"
    for prefix, code in _PART_CODES[::-1]:  # the longest prefix first
        if all(d["field"] == prefix or d["field"].startswith(prefix + ".") for d in details):
            return code
    if all(d["field"] == "options" or d["field"].startswith("options.") for d in details):
        return "invalid_options"
    return "validation_error"


def add_exception_handlers(app: FastAPI) -> None:
    """Register the handlers that turn every exception into the spec's error document."""

    async def api_error(request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, APIError)
        return error_response(exc.status, exc.code, exc.message, headers=exc.headers or None)

    async def service_error(request: Request, exc: Exception) -> JSONResponse:
        for cls in type(exc).__mro__:
            if cls in SERVICE_ERRORS:
                status, code, message = SERVICE_ERRORS[cls]
                break
        else:  # pragma: no cover - only registered classes reach this handler
            status, code, message = 500, "internal_error", "internal error"
        retry = status in RETRY_STATUSES
        retry_after = getattr(exc, "retry_after_s", None) or request.app.state.settings.retry_after_s
        headers = {"Retry-After": str(int(retry_after))} if retry else None
        if message is None:  # the exception's own message, less any submitted value it quotes
            message = f"calibration: {without_values(str(exc))}" if isinstance(exc, CalibrationError) else str(exc)
        return error_response(status, code, message, headers=headers)

    async def request_validation(request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, RequestValidationError)
        return validation_response(list(exc.errors()))

    async def http_error(request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, StarletteHTTPException)
        code = HTTP_CODES.get(exc.status_code, "http_error")
        message = exc.detail if isinstance(exc.detail, str) else "request failed"
        return error_response(exc.status_code, code, message, headers=getattr(exc, "headers", None))

    async def os_error(request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, OSError)
        known = STORAGE_ERRNOS.get(exc.errno or 0)
        if known is None:
            return await unhandled(request, exc)
        log.error("storage fault", extra={"route": errno.errorcode.get(exc.errno or 0, "?")})
        retry = str(request.app.state.settings.retry_after_s)
        return error_response(503, known[0], known[1], headers={"Retry-After": retry})

    async def unhandled(request: Request, exc: Exception) -> JSONResponse:
        log.error("unhandled error: %s\n%s", failure_reason(exc), failure_frames(exc))
        return error_response(500, "internal_error", INTERNAL_ERROR_MESSAGE)

    app.add_exception_handler(APIError, api_error)
    for cls in SERVICE_ERRORS:
        app.add_exception_handler(cls, service_error)
    app.add_exception_handler(RequestValidationError, request_validation)
    app.add_exception_handler(StarletteHTTPException, http_error)
    app.add_exception_handler(OSError, os_error)
    app.add_exception_handler(Exception, unhandled)


# ----- the documented answers of every route (OpenAPI `responses=`) ---------------------------------------------
ERROR_DESCRIPTIONS: dict[int, str] = {
    304: "not modified (If-None-Match matched the ETag)",
    400: "malformed JSON or request",
    401: "no valid bearer key (or viewer token)",
    403: "the key lacks the scope",
    404: "no such session (or not visible to this key), or nothing to serve yet",
    405: "method not allowed",
    409: "conflicts with the session's state (finished, different bytes for a seq, implausible time)",
    413: "request body larger than the limit",
    415: "unsupported media type",
    422: "the body or a parameter breaks the schema, or the content is invalid (the message names the field)",
    429: (
        "too many requests (a rate limit, or the key's quota of sessions, frames or queued jobs); retry after "
        "Retry-After"
    ),
    503: (
        "unavailable, retry after Retry-After seconds: Redis down, queue full, or the data volume full (ENOSPC, "
        "EDQUOT: code insufficient_storage) or failing (EIO, EROFS: storage_unavailable); nothing was stored. "
        "A full disk is 503 rather than 507: spec §5 lists 503 as the retry-later answer and clients retry it"
    ),
}
# statuses whose answers carry Retry-After (seconds)
RETRY_AFTER_HEADER: dict[str, Any] = {
    "Retry-After": {"description": "seconds to wait before retrying", "schema": {"type": "integer", "minimum": 1}}
}
RETRY_STATUSES = (429, 503)
ERROR_SCHEMA: dict[str, Any] = {
    "type": "object",
    "required": ["error"],
    "properties": {
        "error": {
            "type": "object",
            "required": ["code", "message"],
            "properties": {"code": {"type": "string"}, "message": {"type": "string"}},
        }
    },
}
# every route can answer these: a body over the limit, a storage or Redis fault
COMMON_STATUSES = (413, 503)
_S = "/v1/sessions/{session_id}"
# What a route answers beyond the rules of `error_statuses` (its own conflicts, media types, lookups).
EXTRA_STATUSES: dict[tuple[str, str], tuple[int, ...]] = {
    ("post", f"{_S}/frames"): (409, 415),
    ("post", f"{_S}/forces"): (409,),
    ("post", f"{_S}/reference"): (409, 415),
    ("post", f"{_S}/reprocess"): (409,),
    ("post", f"{_S}/send"): (409,),
    ("post", "/v1/reprocess"): (404, 409),
}


def error_statuses(method: str, path: str, operation: dict[str, Any]) -> set[int]:
    """Return the error statuses an operation can answer: the common ones, 401/403 behind auth, 404 with path
    parameters, 422 with parameters or a body, 400 with a body (malformed JSON), plus EXTRA_STATUSES."""
    statuses = set(COMMON_STATUSES)
    if path.startswith(("/v1/", "/viewer/")):
        statuses |= {401, 403, 429}  # 429: too many requests without a valid credential (api.limits)
    params = operation.get("parameters") or []
    if any(p.get("in") == "path" for p in params):
        statuses.add(404)
    if params or "requestBody" in operation:
        statuses.add(422)
    if "requestBody" in operation:
        statuses.add(400)
    statuses |= set(EXTRA_STATUSES.get((method, path), ()))
    return statuses


def document_errors(schema: dict[str, Any]) -> dict[str, Any]:
    """State in an OpenAPI document every error status of every operation, with the error body's schema."""
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    components["Error"] = ERROR_SCHEMA
    components.pop("HTTPValidationError", None)
    components.pop("ValidationError", None)
    ref = {"$ref": "#/components/schemas/Error"}
    for path, item in schema.get("paths", {}).items():
        for method, operation in item.items():
            if not isinstance(operation, dict) or "responses" not in operation:
                continue
            answers = operation["responses"]
            for status in sorted(error_statuses(method, path, operation)):
                entry = answers.setdefault(str(status), {"description": ERROR_DESCRIPTIONS[status]})
                entry["content"] = {"application/json": {"schema": ref}}
                if status in RETRY_STATUSES:
                    entry["headers"] = RETRY_AFTER_HEADER
    return schema
