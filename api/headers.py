"""Security headers on every answer: nosniff, a restrictive CSP on API answers, no caching of /v1/ by default.

SecurityHeadersMiddleware (pure ASGI, the outermost layer, so the request middleware's own 413/500 answers get
them too) adds, unless the answer already carries the header:

- `X-Content-Type-Options: nosniff` on every answer;
- `Content-Security-Policy: API_CSP` on every answer (no interactive API docs are served: api/routes/openapi.py):
  nothing an API answer holds may run script, load anything or be framed. The viewer page sets its own,
  self-only policy (api/routes/viewer.py), which is kept;
- `Cache-Control: private, no-store` on every /v1/ and /viewer/ answer whose route sets no Cache-Control
  (the session JSON with its study, job states, the audit log, error documents).
"""

from __future__ import annotations

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from api.caching import PRIVATE_NO_STORE

API_CSP = "default-src 'none'; frame-ancestors 'none'; base-uri 'none'; form-action 'none'"
PRIVATE_PREFIXES = ("/v1/", "/viewer/")


class SecurityHeadersMiddleware:
    """Pure ASGI: add nosniff, the API CSP and the default Cache-Control where the answer has none."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        path = str(scope.get("path", ""))
        added = [(b"x-content-type-options", b"nosniff"), (b"content-security-policy", API_CSP.encode())]
        if path.startswith(PRIVATE_PREFIXES):
            added.append((b"cache-control", PRIVATE_NO_STORE.encode()))

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", []))
                present = {name.lower() for name, _ in headers}
                message["headers"] = headers + [(name, value) for name, value in added if name not in present]
            await send(message)

        await self.app(scope, receive, send_with_headers)
