"""The FastAPI application: lifespan (settings, Redis, SessionStore), routers, errors, JSON request logs.

Logs never carry patient data: one JSON line per request with the route *template*
(/v1/sessions/{session_id}), never the raw URL (whose ?token= is a credential), and never labels or
calibrations. Every response carries X-Request-ID (the client's, if it sent a sane one). Run uvicorn with
access_log=False: its access log prints raw URLs; create_app disables "uvicorn.access" for the same reason.
"""

from __future__ import annotations

import logging
import re
import time
import uuid
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from api.audit import AuditMiddleware
from api.auth import document_security, key_table
from api.errors import BodyTooLarge, add_exception_handlers, document_errors, escaped_error_response
from api.headers import SecurityHeadersMiddleware
from api.limits import StreamSlots
from api.openapi_links import add_links
from api.routes import ROUTERS
from api.routes.audit import router as audit_router
from api.routes.viewer import mount_static
from services.decoder_limits import set_decoder_limits
from services.jobs import queue
from services.jobs.redis_backend import close, connect
from services.log_format import configure_json_logging, failure_reason, request_id_var
from services.settings import Settings, get_settings
from services.store.audit import AuditLog
from services.store.secrets import audit_key_bytes, token_secrets
from services.store.storage import SessionStore

API_VERSION = "1.0.0"
log = logging.getLogger("veinmosaic.api")
_SANE_ID = re.compile(r"^[A-Za-z0-9._-]{1,64}$")


def configure_logging(level: str) -> None:
    """Send "veinmosaic" logs to stderr as JSON lines (idempotent); silence uvicorn's raw-URL access log."""
    configure_json_logging(level)
    logging.getLogger("uvicorn.access").disabled = True


class RequestContextMiddleware:
    """Pure ASGI: request id, body limits (413), one JSON log line per request, last-resort 500.

    The body limit is enforced on what is *read*, whatever the transfer encoding: a declared Content-Length
    over the limit is answered 413 before the app runs; otherwise every `http.request` message is counted as
    the app receives it, and the message that passes the limit raises BodyTooLarge (413) instead of being
    handed on — so a chunked body never costs more than the limit in memory, and the rest of it is never read
    (uvicorn closes the connection after the answer).
    """

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = {k.decode().lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
        incoming = headers.get("x-request-id", "")
        rid = incoming if _SANE_ID.match(incoming) else uuid.uuid4().hex
        token = request_id_var.set(rid)
        started = time.perf_counter()
        state: dict[str, Any] = {"status": 500, "started": False}

        async def send_with_id(message: Message) -> None:
            if message["type"] == "http.response.start":
                state["status"], state["started"] = message["status"], True
                message.setdefault("headers", [])
                message["headers"] = [*message["headers"], (b"x-request-id", rid.encode())]
            await send(message)

        limit = _body_limit(scope)
        received = 0

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if limit is not None and message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    raise BodyTooLarge(limit)
            return message

        try:
            length = headers.get("content-length", "")
            if limit is not None and length.isdigit() and int(length) > limit:
                raise BodyTooLarge(limit)
            await self.app(scope, limited_receive, send_with_id)
        except BodyTooLarge as exc:
            if not state["started"]:
                response = escaped_error_response(exc)
                await response(scope, receive, send_with_id)
        except Exception as exc:
            # frames and type names only (services.log_format.JsonFormatter): a library's message may quote a patient
            log.error("unhandled error: %s", failure_reason(exc), exc_info=exc)
            if not state["started"]:
                response = escaped_error_response(exc)
                await response(scope, receive, send_with_id)
        finally:
            route = scope.get("route")
            log.info(
                "request",
                extra={
                    "method": scope.get("method"),
                    "route": getattr(route, "path", "(unmatched)"),
                    "status": state["status"],
                    "duration_ms": round(1000 * (time.perf_counter() - started), 1),
                },
            )
            request_id_var.reset(token)


def _body_limit(scope: Scope) -> int | None:
    """Return the body limit of this request: a frame upload's image plus its form parts, else max_json_bytes."""
    app = scope.get("app")
    settings: Settings | None = getattr(getattr(app, "state", None), "settings", None)
    if settings is None:
        return None
    if scope.get("method") == "POST" and scope.get("path", "").endswith("/frames"):
        return settings.max_frame_bytes + 256 * 1024  # the image plus multipart headers and the meta part
    return settings.max_json_bytes


def create_app(settings: Settings | None = None) -> FastAPI:
    """Return the application; settings default to the environment, read once here (at start-up)."""
    s = settings if settings is not None else get_settings()
    set_decoder_limits(s.max_frame_side)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        configure_logging(s.log_level)
        s.data_dir.mkdir(parents=True, exist_ok=True)
        app.state.settings = s
        app.state.keys = key_table(s.api_keys)
        app.state.token_secrets = token_secrets(s)  # oldest first: the previous secrets still verify
        app.state.store = SessionStore(s.data_dir)
        app.state.audit = AuditLog(s.data_dir / "audit" / "audit.jsonl", audit_key_bytes(s), s.audit_max_bytes)
        app.state.redis = connect(s.redis_url, s.data_dir)
        try:
            queue.ensure_groups(app.state.redis, prefix=s.redis_prefix)
        except Exception:  # Redis may come up later; /readyz reports it meanwhile
            log.warning("could not create the consumer groups at start-up")
        log.info("started", extra={"route": "lifespan"})
        try:
            yield
        finally:
            hub = getattr(app.state, "event_hub", None)  # the event streams' shared reader (api.event_hub)
            if hub is not None:
                await hub.close()
            close(app.state.redis)
            app.state.audit.close()
            log.info("stopped", extra={"route": "lifespan"})

    app = FastAPI(
        title="veinmosaic",
        version=API_VERSION,
        summary="Force-rectified near-infrared vein mosaicking for a hand-held breast-scanning probe",
        lifespan=lifespan,
        # the document is served by api/routes/openapi.py (behind a key by default); Swagger UI and ReDoc load
        # their scripts from a CDN, so they are not served at all
        openapi_url=None,
        docs_url=None,
        redoc_url=None,
    )
    app.state.clock = time.time
    app.state.queue_guard = queue.DepthGuard()  # the uploads' queue-full check (api.deps.QueueGuard)
    app.state.stream_slots = StreamSlots()  # the open event streams (api.routes.events)
    add_exception_handlers(app)
    for router in ROUTERS:
        app.include_router(router)
    app.include_router(audit_router)
    mount_static(app, s)
    app.add_middleware(AuditMiddleware)  # inside RequestContextMiddleware: it sees the request id
    app.add_middleware(RequestContextMiddleware)
    app.add_middleware(SecurityHeadersMiddleware)  # outermost: the request middleware's own answers get them too
    generate = app.openapi

    def openapi() -> dict[str, Any]:
        """Return the OpenAPI document: every error status, the links between operations, the frame size cap."""
        if app.openapi_schema is None:
            schema = add_links(document_security(document_errors(generate())))
            side = schema["components"]["schemas"]["CalibrationDoc"]["properties"]["image_size"]
            for item in side["prefixItems"]:
                item["maximum"] = s.max_frame_side
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
    return app
