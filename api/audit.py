"""Who did what to which session, when and from where: the API's side of the audit log (services/store/audit.py).

AuditMiddleware (pure ASGI) records every request to /v1/ and /viewer/ once its status is known and *before*
the answer leaves: if the record cannot be stored (a full disk) the client gets 503 instead of the answer, so
nothing is served or accepted without a trace. A record holds: ts (Unix s), actor ("key:" + 16 hex of an HMAC
of the key's fingerprint with the audit key (AuditLog.key_actor), never the key; "token:<session>" for a viewer
link; "anonymous"), action, route template, method, session id (a path parameter; never a label), status,
client address and request id.

Every write (POST, PUT, DELETE) is recorded. Reads and refused requests are coalesced: one record per
caller, action, session, status and client per `audit_coalesce_s` window (60 s by default), so a viewer
fetching hundreds of tiles leaves one "mosaic.view" record a minute, not hundreds of fsyncs.

A path parameter is never recorded raw: the session field holds the id only when it has the form of one (32
lowercase hex), else INVALID_ID. Requests refused before authentication (actor "anonymous") are coalesced per
client and status alone, whatever their route or session, so a flood of random URLs from one address writes
one record per status a window, not one per request.
"""

from __future__ import annotations

import logging
import re
import time
from typing import Any

import anyio.to_thread
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from api.auth import PRINCIPAL_KEY
from api.errors import STORAGE_ERRNOS, error_response
from services.log_format import request_id_var
from services.store.audit import AuditLog

log = logging.getLogger("veinmosaic.api")
AUDITED_PREFIXES = ("/v1/", "/viewer/")
S = "/v1/sessions/{session_id}"
ACTIONS: dict[tuple[str, str], str] = {
    ("POST", "/v1/sessions"): "session.create",
    ("GET", S): "session.read",
    ("POST", f"{S}/frames"): "frame.upload",
    ("POST", f"{S}/forces"): "forces.upload",
    ("POST", f"{S}/finish"): "session.finish",
    ("GET", f"{S}/path"): "path.export",
    ("GET", f"{S}/mosaic.json"): "mosaic.view",
    ("GET", f"{S}/mosaic.png"): "mosaic.export",
    ("GET", f"{S}/mosaic.dzi"): "mosaic.view",
    ("GET", f"{S}/mosaic_files/{{level}}/{{col}}_{{row}}.png"): "mosaic.view",
    ("GET", f"{S}/events"): "events.view",
    ("POST", f"{S}/reference"): "reference.upload",
    ("GET", f"{S}/report"): "report.read",
    ("GET", f"{S}/plots/{{name}}.png"): "report.read",
    ("POST", f"{S}/reprocess"): "reprocess",
    ("POST", f"{S}/send"): "pacs.send.request",
    ("GET", f"{S}/export.dcm"): "dicom.export",
    ("GET", f"{S}/sheet.{{fmt}}"): "report.export",
    ("POST", "/v1/reprocess"): "reprocess.batch",
    ("GET", "/v1/jobs/{job_id}"): "job.read",
    ("GET", "/v1/batches/{batch_id}"): "job.read",
    ("GET", "/viewer/{session_id}"): "viewer.open",
    ("GET", "/v1/audit"): "audit.read",
    ("GET", "/v1/audit/verify"): "audit.verify",
}
WRITE_METHODS = ("POST", "PUT", "PATCH", "DELETE")
_MAX_COALESCE_KEYS = 50_000
SESSION_ID_FORM = re.compile(r"^[0-9a-f]{32}$")  # what services.store.storage makes (uuid4 hex)
INVALID_ID = "(invalid)"  # recorded instead of a session path parameter that is not of that form


def recorded_session(value: object) -> str | None:
    """Return the session field of a record: the id if it has the form of one, INVALID_ID if not, None if absent."""
    if value is None:
        return None
    return value if isinstance(value, str) and SESSION_ID_FORM.match(value) else INVALID_ID


def coalesce_key(record: dict[str, Any]) -> tuple[str, ...]:
    """Return the coalescing key of a read or refused request: per client and status alone when anonymous."""
    if record["actor"] == "anonymous":
        return ("anonymous", str(record["status"]), str(record["client"]))
    return (record["actor"], record["action"], str(record["session"]), str(record["status"]), str(record["client"]))


def actor_of(scope: Scope, audit: AuditLog) -> str:
    """Return the audit actor of a request: the key's keyed id, the viewer token's session, or anonymous."""
    principal = scope.get(PRINCIPAL_KEY)
    if principal is None:
        return "anonymous"
    if principal.session_id is not None:
        return f"token:{principal.session_id}"
    return audit.key_actor(principal.fingerprint or "")


def action_of(method: str, route: str) -> str:
    """Return the action name of a route (for routes without one: "read" for GET, else "write")."""
    return ACTIONS.get((method, route)) or ("read" if method in ("GET", "HEAD") else "write")


class AuditMiddleware:
    """Pure ASGI: write the request's audit record before its answer is sent (503 if it cannot be written)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app
        self._recent: dict[tuple[str, ...], float] = {}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not scope.get("path", "").startswith(AUDITED_PREFIXES):
            await self.app(scope, receive, send)
            return
        state: dict[str, Any] = {"replaced": False}

        async def audited_send(message: Message) -> None:
            if state["replaced"]:
                return  # the app's own answer was replaced by a 503: drop the rest of it
            if message["type"] == "http.response.start":
                try:
                    await self._record(scope, int(message["status"]))
                except OSError as exc:
                    state["replaced"] = True
                    code, text = STORAGE_ERRNOS.get(exc.errno or 0, ("storage_unavailable", "retry later"))
                    log.error("audit record not written", extra={"route": code})
                    retry = {"Retry-After": str(scope["app"].state.settings.retry_after_s)}
                    response = error_response(503, code, f"the audit log cannot be written: {text}", retry)
                    await response(scope, receive, send)
                    return
            await send(message)

        await self.app(scope, receive, audited_send)

    async def _record(self, scope: Scope, status: int) -> None:
        app = scope.get("app")
        app_state = getattr(app, "state", None)
        audit: AuditLog | None = getattr(app_state, "audit", None)
        if audit is None:
            return
        method = str(scope.get("method", ""))
        route = getattr(scope.get("route"), "path", None) or "(unmatched)"
        params = scope.get("path_params") or {}
        client = scope.get("client")
        now = time.time()
        record = {
            "ts": round(now, 3),
            "actor": actor_of(scope, audit),
            "action": action_of(method, route),
            "route": route,
            "method": method,
            "session": recorded_session(params.get("session_id")),
            "status": status,
            "client": client[0] if client else None,
            "request_id": _request_id(scope),
        }
        key: tuple[str, ...] | None = None
        if not (method in WRITE_METHODS and 200 <= status < 300):
            key = coalesce_key(record)
            last = self._recent.get(key)
            if last is not None and now - last < float(app_state.settings.audit_coalesce_s):  # type: ignore[union-attr]
                return
            if len(self._recent) >= _MAX_COALESCE_KEYS:
                self._recent.clear()
            self._recent[key] = now  # before the write: concurrent requests with this key wait for no record
        try:
            await anyio.to_thread.run_sync(audit.append, record)
        except BaseException:
            if key is not None and self._recent.get(key) == now:
                del self._recent[key]  # not written: the next request of this key is recorded
            raise


def _request_id(scope: Scope) -> str | None:
    rid = request_id_var.get()
    return None if rid in (None, "-") else str(rid)
