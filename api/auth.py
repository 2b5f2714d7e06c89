"""Bearer API keys with scopes, session ownership, and signed expiring view-only viewer tokens (spec §5).

Keys are held as sha256 fingerprints; the fingerprint is the session owner recorded in storage (never the
key). "admin" satisfies every scope and sees every session. A viewer token is
"<expiry unix s>.<urlsafe-b64 HMAC-SHA256(secret, 'view:' + session_id + ':' + expiry)>": view scope, one
session, accepted on GET view routes via ?token= or Authorization: Bearer.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
from collections.abc import Awaitable, Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from fastapi import Request

from api.errors import Forbidden, NotFound, Unauthorized
from services.storage import SessionMeta, SessionNotFoundError, SessionStore

PRINCIPAL_KEY = "veinmosaic.principal"  # where the caller's Principal is left in the ASGI scope (api.audit reads it)


@dataclass(frozen=True)
class Principal:
    """Who is calling: a key (fingerprint = sha256 hex of the key) or a viewer token bound to one session."""

    fingerprint: str | None
    scopes: frozenset[str]
    session_id: str | None = None  # set for viewer tokens only

    @property
    def is_admin(self) -> bool:
        """Return True for an admin key."""
        return "admin" in self.scopes

    def has_any(self, scopes: Iterable[str]) -> bool:
        """Return True if the principal holds one of `scopes` (admin holds all)."""
        return self.is_admin or bool(self.scopes.intersection(scopes))

    def can_see(self, meta: SessionMeta) -> bool:
        """Return True if this principal may see the session: its owner, an admin, or a token for it."""
        if self.session_id is not None:
            return self.session_id == meta.id
        return self.is_admin or (self.fingerprint is not None and hmac.compare_digest(self.fingerprint, meta.owner))


def fingerprint(key: str) -> str:
    """Return the sha256 hex digest of an API key (what storage records as owner)."""
    return hashlib.sha256(key.encode()).hexdigest()


def key_table(api_keys: Mapping[str, Iterable[str]]) -> dict[str, frozenset[str]]:
    """Return {fingerprint: scopes} for the configured keys."""
    return {fingerprint(k): frozenset(v) for k, v in api_keys.items()}


def _b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode()


def _mac(secret: bytes, session_id: str, expires: int) -> bytes:
    return hmac.new(secret, f"view:{session_id}:{expires}".encode(), hashlib.sha256).digest()


def make_viewer_token(secret: bytes, session_id: str, ttl_s: float, now: float) -> str:
    """Return a URL-safe view-only token for `session_id` valid until now + ttl_s (Unix seconds)."""
    expires = int(now + ttl_s)
    return f"{expires}.{_b64(_mac(secret, session_id, expires))}"


def viewer_token_expiry(token: str) -> int | None:
    """Return the token's expiry (Unix seconds) without verifying it, or None if malformed."""
    head, _, _ = token.partition(".")
    return int(head) if head.isdigit() and len(head) <= 12 else None


def verify_viewer_token(secret: bytes, token: str, session_id: str, now: float) -> bool:
    """Return True if `token` was made with `secret` for `session_id` and has not expired at `now`."""
    expires = viewer_token_expiry(token)
    if expires is None or now >= expires:
        return False
    expected = f"{expires}.{_b64(_mac(secret, session_id, expires))}"
    return hmac.compare_digest(expected.encode(), token.encode())


def bearer(request: Request) -> str | None:
    """Return the bearer credential of the Authorization header, or None."""
    header = request.headers.get("authorization", "")
    scheme, _, value = header.partition(" ")
    if scheme.lower() != "bearer":
        return None
    return value.strip() or None


def key_principal(request: Request) -> Principal | None:
    """Return the principal of a configured bearer key, or None when there is no (valid) key."""
    credential = bearer(request)
    if credential is None:
        return None
    fp = fingerprint(credential)
    scopes = request.app.state.keys.get(fp)
    return None if scopes is None else Principal(fingerprint=fp, scopes=scopes)


def remember(request: Request, principal: Principal) -> Principal:
    """Leave the caller's principal in the ASGI scope for the audit log (api.audit); return it."""
    request.scope[PRINCIPAL_KEY] = principal
    return principal


def require_scope(*scopes: str) -> Callable[[Request], Awaitable[Principal]]:
    """Return a dependency yielding the key principal holding one of `scopes` (401 no key, 403 no scope)."""

    async def dependency(request: Request) -> Principal:  # CPU only: no thread-pool hop
        principal = key_principal(request)
        if principal is None:
            raise Unauthorized()
        remember(request, principal)
        if not principal.has_any(scopes):
            raise Forbidden(f"this key lacks the {' or '.join(scopes)} scope")
        return principal

    return dependency


async def view_principal(request: Request, session_id: str) -> Principal:
    """Return a key principal with view/ingest scope, or a viewer-token principal for `session_id` (CPU only)."""
    principal = key_principal(request)
    if principal is not None:
        remember(request, principal)
        if not principal.has_any(("view", "ingest")):
            raise Forbidden("this key lacks the view scope")
        return principal
    for token in (request.query_params.get("token"), bearer(request)):
        if token and verify_viewer_token(request.app.state.token_secret, token, session_id, _now(request)):
            return remember(request, Principal(fingerprint=None, scopes=frozenset({"view"}), session_id=session_id))
    raise Unauthorized("a valid bearer key or an unexpired viewer token for this session is required")


def _now(request: Request) -> float:
    return request.app.state.clock()


def visible_session(store: SessionStore, principal: Principal, session_id: str) -> SessionMeta:
    """Return the session's metadata if `principal` may see it; 404 otherwise (existence never leaks)."""
    try:
        meta = store.get_meta(session_id)
    except SessionNotFoundError:
        raise NotFound("no such session") from None
    if not principal.can_see(meta):
        raise NotFound("no such session")
    return meta


SECURITY_SCHEMES: dict[str, dict[str, str]] = {
    "bearer": {"type": "http", "scheme": "bearer", "description": "an API key of VEINMOSAIC_API_KEYS"},
    "viewerToken": {
        "type": "apiKey",
        "in": "query",
        "name": "token",
        "description": "a signed, expiring, view-only token for one session (from POST /v1/sessions)",
    },
}


def document_security(schema: dict[str, Any]) -> dict[str, Any]:
    """State in an OpenAPI document which credential each operation takes: a bearer key on /v1/ and /viewer/
    routes, or a viewer token on the GET routes of one session (view_principal); none elsewhere."""
    schema.setdefault("components", {})["securitySchemes"] = SECURITY_SCHEMES
    for path, item in schema.get("paths", {}).items():
        for method, operation in item.items():
            if not isinstance(operation, dict) or not path.startswith(("/v1/", "/viewer/")):
                continue
            viewable = method == "get" and path.startswith(("/v1/sessions/{session_id}", "/viewer/{session_id}"))
            operation["security"] = [{"bearer": []}, {"viewerToken": []}] if viewable else [{"bearer": []}]
    return schema
