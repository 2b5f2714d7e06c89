"""Bearer API keys with scopes, session ownership, and signed expiring view-only viewer tokens (spec §5).

Keys are held as sha256 fingerprints; the fingerprint is the session owner recorded in storage (never the
key). "admin" satisfies every scope and sees every session. A viewer token is an itsdangerous URL-safe signed
payload {"sid": session id, "scope": "view", "exp": expiry in Unix s} (HMAC with the token secret, salted for
this one use): view scope, one session, until its expiry; accepted on GET view routes via ?token= or
Authorization: Bearer. The payload is signed, not encrypted: it holds the session id, which the URL holds anyway.
"""

from __future__ import annotations

import hashlib
import hmac
from collections.abc import Awaitable, Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from fastapi import Request
from itsdangerous import BadSignature, URLSafeSerializer

from api.errors import Forbidden, NotFound, Unauthorized
from api.limits import refuse_unauthenticated
from services.store.storage import SessionMeta, SessionStore

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


TOKEN_SALT = "veinmosaic.viewer-token"  # a signature made for another use of the same secret is not a token
MAX_TOKEN_CHARS = 512  # longer is never one of ours: refused before any signature work


def token_serializer(secrets: bytes | Sequence[bytes]) -> URLSafeSerializer:
    """Return the itsdangerous serializer of viewer tokens (SHA-256 HMAC, the viewer-token salt).

    secrets: one key, or the keys oldest first (rotation): itsdangerous signs with the last and verifies with any.
    """
    keys = [secrets] if isinstance(secrets, bytes) else list(secrets)
    return URLSafeSerializer(keys, salt=TOKEN_SALT, signer_kwargs={"digest_method": hashlib.sha256})


def make_viewer_token(secrets: bytes | Sequence[bytes], session_id: str, ttl_s: float, now: float) -> str:
    """Return a URL-safe view-only token for `session_id` valid until now + ttl_s (Unix seconds), signed with the
    newest secret."""
    token = token_serializer(secrets).dumps({"sid": session_id, "scope": "view", "exp": int(now + ttl_s)})
    return str(token)


def verify_viewer_token(secrets: bytes | Sequence[bytes], token: str, session_id: str, now: float) -> bool:
    """Return True if `token` was made with one of `secrets` for `session_id`, is view-only and has not expired."""
    if len(token) > MAX_TOKEN_CHARS:
        return False
    try:
        claims = token_serializer(secrets).loads(token)  # the signature is checked before the payload is decoded
    except BadSignature:
        return False
    if not isinstance(claims, dict) or claims.get("scope") != "view" or claims.get("sid") != session_id:
        return False
    expires = claims.get("exp")
    return isinstance(expires, int) and now < expires


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
    """Return the caller's principal, left in the ASGI scope for the audit log (api.audit)."""
    request.scope[PRINCIPAL_KEY] = principal
    return principal


def require_scope(*scopes: str) -> Callable[[Request], Awaitable[Principal]]:
    """Return a dependency yielding the key principal holding one of `scopes` (401 no key, 403 no scope)."""

    async def dependency(request: Request) -> Principal:  # CPU only: no thread-pool hop
        principal = key_principal(request)
        if principal is None:
            raise refuse_unauthenticated(request, Unauthorized())  # 429 when this client is over its limit
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
        if token and verify_viewer_token(request.app.state.token_secrets, token, session_id, _now(request)):
            return remember(request, Principal(fingerprint=None, scopes=frozenset({"view"}), session_id=session_id))
    refusal = Unauthorized("a valid bearer key or an unexpired viewer token for this session is required")
    raise refuse_unauthenticated(request, refusal)  # 429 when this client is over its limit


def _now(request: Request) -> float:
    return request.app.state.clock()


def visible_session(store: SessionStore, principal: Principal, session_id: str) -> SessionMeta:
    """Return the session's metadata if `principal` may see it; 404 otherwise (existence never leaks)."""
    meta = store.get_meta(session_id)  # SessionNotFoundError: 404 not_found "no such session" (api/errors.py)
    if not principal.can_see(meta):
        raise NotFound("no such session")  # the same answer as a missing session
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
    """Return the OpenAPI document `schema`, changed in place to state which credential each operation takes.

    A bearer key on /v1/ and /viewer/ routes, or a viewer token on the GET routes of one session
    (view_principal); none elsewhere.
    """
    schema.setdefault("components", {})["securitySchemes"] = SECURITY_SCHEMES
    for path, item in schema.get("paths", {}).items():
        for method, operation in item.items():
            if not isinstance(operation, dict) or not path.startswith(("/v1/", "/viewer/")):
                continue
            viewable = method == "get" and path.startswith(("/v1/sessions/{session_id}", "/viewer/{session_id}"))
            operation["security"] = [{"bearer": []}, {"viewerToken": []}] if viewable else [{"bearer": []}]
    return schema
